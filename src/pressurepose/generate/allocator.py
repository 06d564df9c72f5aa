"""The C allocator of a process that makes shards (`generate.worker.make_shard`).

The articulated rest allocates and frees temporaries of 1-32 MB hundreds of times per batch
(a batch's surface points, (B, 3, P) doubles, are ~31 MB). glibc's malloc serves blocks above
its mmap threshold from fresh mappings and gives the heap's free top back to the kernel beyond
its trim threshold, so every such temporary page-faults its memory in again, zero-filled.
Keeping them on the heap - the threshold at glibc's largest (32 MiB on 64-bit), the free top
kept up to 1 GiB, 64 MiB padding per heap growth - saves that kernel work: 2-5% of the rest's
CPU time (docs/benchmarks.md "Session 50"). PyTorch's own CPU tuning guide makes the same point
with other allocators (jemalloc, tcmalloc); this needs none. Peak memory stays the program's own
peak: freed memory is kept for reuse, not added to. A no-op off glibc, and with
PRESSUREPOSE_MALLOC_TUNING=0.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os

log = logging.getLogger(__name__)

# mallopt parameters (malloc.h) and the values set.
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
SETTINGS = ((_M_MMAP_THRESHOLD, 32 << 20), (_M_TRIM_THRESHOLD, 1 << 30), (_M_TOP_PAD, 64 << 20))

_done = False


def tune_allocator() -> bool:
    """Set glibc malloc's thresholds for this process once (module doc); True if set."""
    global _done
    if _done:
        return True
    if os.environ.get("PRESSUREPOSE_MALLOC_TUNING", "1") == "0":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (macOS, Windows, musl without mallopt)
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    ok = all(mallopt(param, value) == 1 for param, value in SETTINGS)
    if not ok:
        log.debug("mallopt refused a setting; the allocator keeps glibc's defaults for it")
    _done = ok
    return ok


__all__ = ["SETTINGS", "tune_allocator"]
