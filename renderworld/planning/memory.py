"""Keep freed memory in the process for a planning loop (glibc's allocator; opt-in).

Every plan allocates and frees the same few hundred intermediate tensors. glibc hands blocks
above its mmap threshold (128 KiB at start) straight back to the operating system when they are
freed, and trims the heap top above 128 KiB, so the next plan takes the same memory again as
fresh pages, each one a page fault and a zeroed page: 1,300-2,600 minor faults per
trajectory-only plan of the mini token planner, 8-15 after this call (docs/planner.md). Raising
both thresholds keeps those blocks in the heap for reuse.

This is a process-wide allocator setting, so the planner never changes it by itself: call
:func:`retain_freed_memory` once at the start of a process that plans in a loop. Blocks larger
than the mmap threshold (e.g. Occ3D forecast decodes) are still returned at once.
"""

from __future__ import annotations

import ctypes
import ctypes.util

__all__ = ["retain_freed_memory"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: glibc's largest accepted mmap threshold on 64-bit systems (HEAP_MAX_SIZE / 2).
MAX_MMAP_THRESHOLD = 32 * 1024 * 1024


def retain_freed_memory(
    mmap_threshold: int = MAX_MMAP_THRESHOLD, trim_threshold: int = 512 * 1024 * 1024
) -> bool:
    """Raise glibc's mmap and trim thresholds so freed tensors stay in the heap.

    Args:
        mmap_threshold: bytes; blocks up to this size come from the heap (glibc accepts at
            most 32 MiB on 64-bit systems).
        trim_threshold: bytes of free heap top kept before memory is returned to the system.

    Returns:
        True when both were set; False where the C library has no ``mallopt`` (not glibc:
        musl, macOS, Windows), which changes nothing.

    Raises:
        ValueError: a threshold that is not a positive int, or an mmap threshold above 32 MiB.
    """
    for name, value in (("mmap_threshold", mmap_threshold), ("trim_threshold", trim_threshold)):
        if type(value) is not int or value <= 0:
            raise ValueError(f"{name}: expected a positive int (bytes), got {value!r}")
    if mmap_threshold > MAX_MMAP_THRESHOLD:
        raise ValueError(
            f"mmap_threshold: expected at most {MAX_MMAP_THRESHOLD} bytes (glibc's limit), "
            f"got {mmap_threshold}"
        )
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    ok = mallopt(_M_MMAP_THRESHOLD, mmap_threshold) == 1
    return ok and mallopt(_M_TRIM_THRESHOLD, min(trim_threshold, 2**31 - 1)) == 1
