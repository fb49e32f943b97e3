"""`release_free_heap`: freed heap blocks stop counting in the resident memory."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

from pa_cli.runtime.heap import _malloc_trim, release_free_heap

BLOCK_FLOATS = 8_000  # 64 kB a block: below glibc's mmap threshold, so the blocks come from the heap
N_BLOCKS = 4_000  # 256 MB in all


def _resident_bytes() -> int:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


@pytest.mark.skipif(not sys.platform.startswith("linux") or _malloc_trim() is None, reason="glibc's malloc_trim")
def test_freed_heap_blocks_leave_the_resident_memory():
    blocks = [np.ones(BLOCK_FLOATS) for _ in range(N_BLOCKS)]  # written: resident
    pin = np.ones(BLOCK_FLOATS)  # allocated last, it keeps the heap from shrinking at its top by itself
    held = _resident_bytes()
    del blocks
    freed = _resident_bytes()
    assert release_free_heap()
    trimmed = _resident_bytes()
    size = N_BLOCKS * BLOCK_FLOATS * 8
    assert held - freed < size / 2  # freeing alone returned little
    assert freed - trimmed > size / 2  # the trim returned most of it
    assert pin.sum() == BLOCK_FLOATS
