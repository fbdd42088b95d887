"""Let glibc keep freed large buffers in the heap, so each frame's big matrices reuse touched memory."""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

# mallopt() parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
# Above glibc's 32 MiB default cap: the score and patch matrices of a large view (N ~ 4400 source
# and M ~ 1900 target voxels) are ~35 MiB each.
_KEEP_BYTES = 256 * 1024 * 1024

_applied: bool | None = None


def reuse_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds once per process; True when in effect.

    By default glibc serves every block above a (dynamic, at most 32 MiB) threshold with a fresh
    mmap and unmaps it on free, so the score matrix, its exponentials and the patch matrices of
    every registration are page-faulted in anew: on a large view that costs more than the
    arithmetic (~30 ms of a ~120 ms matching stage). With the thresholds raised, freed blocks stay
    in the heap and the next registration reuses them; the arithmetic, and so every result, is
    unchanged. The price is that the process keeps its peak heap instead of returning it to the
    system. No-op (False) where the C library has no mallopt (not Linux/glibc).
    """
    global _applied
    if _applied is None:
        _applied = False
        if sys.platform.startswith("linux"):
            try:
                mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
            except (OSError, AttributeError):  # no libc by that name, or one without mallopt (musl)
                return False
            mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
            _applied = bool(mallopt(_M_MMAP_THRESHOLD, _KEEP_BYTES)) and bool(mallopt(_M_TRIM_THRESHOLD, _KEEP_BYTES))
    return _applied
