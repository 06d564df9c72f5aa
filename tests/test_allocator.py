"""The shard makers' allocator setting (`generate.allocator`): large temporaries stay on the
heap once it is set, and it can be turned off."""

from __future__ import annotations

import ctypes.util
import subprocess
import sys

import pytest

# Run in a fresh interpreter: the setting is process-wide. Prints how many mmapped blocks an
# 8 MiB malloc added (glibc's mallinfo2: hblks), with or without tune_allocator() first.
_PROBE = """
import ctypes, ctypes.util, sys
from pressurepose.generate.allocator import tune_allocator
names = "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost".split()
class Info(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in names]
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.mallinfo2.restype = Info
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, (ctypes.c_size_t,)
libc.free.argtypes = (ctypes.c_void_p,)
print(tune_allocator() if sys.argv[1] == "tune" else "untuned")
before = libc.mallinfo2().hblks
block = libc.malloc(8 << 20)
print(libc.mallinfo2().hblks - before)
libc.free(block)
"""


def _glibc_with_mallinfo2() -> bool:
    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        return hasattr(libc, "mallinfo2") and hasattr(libc, "mallopt")
    except OSError:
        return False


def _probe(mode: str, env: dict | None = None) -> list[str]:
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, mode], capture_output=True, text=True, check=True, env=env, timeout=120
    )
    return out.stdout.split()


@pytest.mark.skipif(not _glibc_with_mallinfo2(), reason="glibc >= 2.33 (mallopt, mallinfo2) only")
def test_tuned_allocator_keeps_large_temporaries_on_the_heap():
    assert _probe("plain") == ["untuned", "1"]  # glibc's default: a fresh mapping per 8 MiB block
    assert _probe("tune") == ["True", "0"]  # tuned: from the heap, no page-faulted mapping


@pytest.mark.skipif(not _glibc_with_mallinfo2(), reason="glibc >= 2.33 (mallopt, mallinfo2) only")
def test_allocator_tuning_can_be_turned_off():
    import os

    env = dict(os.environ, PRESSUREPOSE_MALLOC_TUNING="0")
    assert _probe("tune", env) == ["False", "1"]


def test_tune_allocator_is_idempotent():
    from pressurepose.generate.allocator import tune_allocator

    first = tune_allocator()
    assert tune_allocator() is first
