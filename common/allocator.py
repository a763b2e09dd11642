"""Process-wide memory allocator setting for the pipeline's long-running processes.

A service handles megabyte-sized arrays for every frame (float images, pyramids, decoded JPEGs).
glibc's default malloc gives blocks that large back to the kernel when they are freed (``munmap``, or
trimming the heap top), so the next frame's arrays fault their pages in again, each one zeroed by the
kernel: on a virtual machine that system time exceeded the arithmetic it fed. ``retain_freed_memory``
keeps freed blocks in the process for reuse instead. Resident memory then stays at the process's
high-water mark rather than following each frame's allocations down and up again.
"""
from __future__ import annotations

import ctypes
import ctypes.util

M_TRIM_THRESHOLD = -1     # glibc mallopt parameters (malloc.h)
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024    # blocks up to this size come from the heap (glibc's dynamic maximum)
TRIM_THRESHOLD_BYTES = 1024 * 1024 * 1024  # free space kept at the heap's top before any is returned


def retain_freed_memory() -> bool:
    """Ask glibc to keep freed blocks up to 32 MB for reuse (no per-frame page faults). True when set;
    False where the C library is not glibc (nothing changes there)."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
