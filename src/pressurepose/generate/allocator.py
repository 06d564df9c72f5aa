"""The C allocator of the processes that make shards: the pool and Ray workers and the
`pressurepose generate` command (not a library caller's own process).

The articulated rest allocates and frees temporaries of 1-32 MB hundreds of times per batch
(a batch's surface points, (B, 3, P) doubles, are ~31 MB). glibc's malloc serves blocks above
its mmap threshold from fresh mappings and gives the heap's free top back to the kernel beyond
its trim threshold, so every such temporary page-faults its memory in again, zero-filled.
Keeping them on the heap - the threshold at glibc's largest (32 MiB on 64-bit), the free top
kept up to 1 GiB, 64 MiB padding per heap growth - saves that kernel work: 2-3% of the rest's
CPU time in its benchmark (docs/benchmarks.md "Session 50"). PyTorch's CPU tuning
guide makes the same point with other allocators (jemalloc, tcmalloc); this needs none. The
cost: freed memory stays with the process for reuse (the paper preset's peak RSS grew by up to
0.1 GB, ~10%). A no-op off glibc, and with PRESSUREPOSE_MALLOC_TUNING=0.
"""

from __future__ import annotations

import ctypes
import logging
import os

log = logging.getLogger(__name__)

ENV = "PRESSUREPOSE_MALLOC_TUNING"
# mallopt parameters (malloc.h) and the values set.
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
SETTINGS = ((_M_MMAP_THRESHOLD, 32 << 20), (_M_TRIM_THRESHOLD, 1 << 30), (_M_TOP_PAD, 64 << 20))

_state: bool | None = None  # None: not tried yet in this process; else what the try gave


def _glibc() -> bool:
    try:
        return bool(os.confstr("CS_GNU_LIBC_VERSION"))
    except (AttributeError, ValueError, OSError):  # not POSIX, or not glibc
        return False


def tune_allocator() -> bool:
    """Set glibc malloc's thresholds for this process (module doc), once; True if every
    setting took. Never raises."""
    global _state
    if _state is not None:
        return _state
    _state = False
    if os.environ.get(ENV, "1") == "0" or not _glibc():
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the process's own C library
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    refused = [param for param, value in SETTINGS if mallopt(param, value) != 1]
    if refused:
        log.debug("mallopt refused parameters %s; those keep glibc's defaults", refused)
    _state = not refused
    return _state


__all__ = ["ENV", "SETTINGS", "tune_allocator"]
