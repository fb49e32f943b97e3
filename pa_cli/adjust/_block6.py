"""The 6x6 block product C += alpha A B of the block factorisations, in explicit vector code.

numba compiles with LLVM's SLP vectoriser off (it was switched off for miscompilations, and it is
a process-wide setting), so a 6x6 product written as scalar loops runs one multiply and one add
per term. `nn6` is a numba intrinsic that emits the product directly as LLVM vector operations:
the six rows of B are loaded once as a 4-wide and a 2-wide vector each, and every row of C is
accumulated by fused multiply-adds of the broadcast entries alpha A[r, k] with them, then stored
once. FMA rounds once per term instead of twice; the result agrees with the scalar loops to the
last bits.

Contract: C and B are C-contiguous 6x6 float64 arrays (blocks of a C-ordered (n, 6, 6) array),
A is any 6x6 float64 array (a transposed view passes A^T B), and C shares no memory with A or B.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

BLOCK = 6
_F64 = ir.DoubleType()
_V4 = ir.VectorType(_F64, 4)
_V2 = ir.VectorType(_F64, 2)


def _load_vector(builder, row_pointer, start, vector_type):
    pointer = builder.gep(row_pointer, [ir.Constant(ir.IntType(64), start)])
    return builder.load(builder.bitcast(pointer, vector_type.as_pointer()), align=8)


def _store_vector(builder, value, row_pointer, start):
    pointer = builder.gep(row_pointer, [ir.Constant(ir.IntType(64), start)])
    builder.store(value, builder.bitcast(pointer, value.type.as_pointer()), align=8)


def _splat(builder, value, vector_type):
    width = vector_type.count
    first = builder.insert_element(ir.Constant(vector_type, ir.Undefined), value,
                                   ir.Constant(ir.IntType(32), 0))
    return builder.shuffle_vector(first, ir.Constant(vector_type, ir.Undefined),
                                  ir.Constant(ir.VectorType(ir.IntType(32), width), [0] * width))


def _multiply_add(builder, a, b, c):
    """a * b + c, flagged contractible: one fused multiply-add where the CPU has one."""
    return builder.fadd(builder.fmul(a, b, flags=("contract",)), c, flags=("contract",))


def _is_block(array_type, contiguous: bool) -> bool:
    return (isinstance(array_type, types.Array) and array_type.ndim == 2
            and array_type.dtype == types.float64 and (array_type.layout == "C" or not contiguous))


@intrinsic
def nn6(typingctx, C, A, B, alpha):
    """C += alpha A B for 6x6 float64 blocks (see the module docstring for the contract)."""
    if not (_is_block(C, True) and _is_block(A, False) and _is_block(B, True)
            and isinstance(alpha, types.Float)):
        return None

    def codegen(context, builder, signature, args):
        c_array = context.make_array(signature.args[0])(context, builder, args[0])
        a_array = context.make_array(signature.args[1])(context, builder, args[1])
        b_array = context.make_array(signature.args[2])(context, builder, args[2])
        scale = context.cast(builder, args[3], signature.args[3], types.float64)
        a_stride_row, a_stride_col = cgutils.unpack_tuple(builder, a_array.strides, 2)
        a_bytes = builder.bitcast(a_array.data, ir.IntType(8).as_pointer())
        b_rows = [(_load_vector(builder, b_array.data, BLOCK * k, _V4),
                   _load_vector(builder, b_array.data, BLOCK * k + 4, _V2)) for k in range(BLOCK)]
        for r in range(BLOCK):
            c4 = _load_vector(builder, c_array.data, BLOCK * r, _V4)
            c2 = _load_vector(builder, c_array.data, BLOCK * r + 4, _V2)
            row_offset = builder.mul(a_stride_row, ir.Constant(a_stride_row.type, r))
            for k in range(BLOCK):
                offset = builder.add(row_offset, builder.mul(a_stride_col, ir.Constant(a_stride_col.type, k)))
                entry_pointer = builder.bitcast(builder.gep(a_bytes, [offset]), _F64.as_pointer())
                entry = builder.fmul(scale, builder.load(entry_pointer, align=8))
                c4 = _multiply_add(builder, _splat(builder, entry, _V4), b_rows[k][0], c4)
                c2 = _multiply_add(builder, _splat(builder, entry, _V2), b_rows[k][1], c2)
            _store_vector(builder, c4, c_array.data, BLOCK * r)
            _store_vector(builder, c2, c_array.data, BLOCK * r + 4)
        return context.get_dummy_value()

    return types.void(C, A, B, alpha), codegen
