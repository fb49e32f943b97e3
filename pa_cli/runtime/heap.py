"""Hand the memory the C allocator holds free back to the operating system.

glibc's malloc keeps freed blocks for reuse; arrays below its mmap threshold (which grows to 32 MB as
large arrays are freed) come from that heap, and once freed their pages stay resident while other
blocks pin the heap around them: over the stages of a long run, gigabytes the process no longer uses.
`malloc_trim` returns those pages; where the C library has none (macOS, Windows, musl) nothing is done.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from collections.abc import Callable


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's `malloc_trim`, or None where the C library has none."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        return ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):
        return None


def release_free_heap() -> bool:
    """Return the free pages of the C heap to the operating system; False where that cannot be done."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True
