"""The shard makers' allocator setting (`generate.allocator`): large temporaries stay on the
heap once it is set, it can be turned off, it is tried once per process and never raises."""

from __future__ import annotations

import ctypes
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

import pressurepose.generate.allocator as allocator

ALLOCATOR_FILE = Path(allocator.__file__)

# Run in a fresh interpreter (the setting is process-wide) that loads only allocator.py (ctypes,
# os, logging: no torch import whose own large blocks could move glibc's dynamic threshold).
# Prints what tune_allocator() returned (or "untuned") and how many mmapped blocks an 8 MiB
# malloc added (glibc's mallinfo2: hblks).
_PROBE = """
import ctypes, importlib.util, sys
spec = importlib.util.spec_from_file_location("allocator", sys.argv[2])
allocator = importlib.util.module_from_spec(spec)
spec.loader.exec_module(allocator)
names = "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost".split()
class Info(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in names]
libc = ctypes.CDLL(None)
libc.mallinfo2.restype = Info
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, (ctypes.c_size_t,)
libc.free.argtypes = (ctypes.c_void_p,)
print(allocator.tune_allocator() if sys.argv[1] == "tune" else "untuned")
before = libc.mallinfo2().hblks
block = libc.malloc(8 << 20)
print(libc.mallinfo2().hblks - before)
libc.free(block)
"""


def _glibc_with_mallinfo2() -> bool:
    try:
        libc = ctypes.CDLL(None)
        return bool(os.confstr("CS_GNU_LIBC_VERSION")) and hasattr(libc, "mallinfo2")
    except (AttributeError, ValueError, OSError):
        return False


def _probe(mode: str, **env_extra) -> list[str]:
    # glibc's own malloc tunables from the caller's environment would change the defaults.
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}
    env.pop(allocator.ENV, None)
    env.update(env_extra)
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, mode, str(ALLOCATOR_FILE)],
        capture_output=True,
        text=True,
        check=True,
        env=env,
        timeout=60,
    )
    return out.stdout.split()


glibc_only = pytest.mark.skipif(not _glibc_with_mallinfo2(), reason="glibc >= 2.33 (mallopt, mallinfo2) only")


@glibc_only
def test_tuned_allocator_keeps_large_temporaries_on_the_heap():
    assert _probe("plain") == ["untuned", "1"]  # glibc's default: a fresh mapping per 8 MiB block
    assert _probe("tune") == ["True", "0"]  # tuned: from the heap, no page-faulted mapping


@glibc_only
def test_allocator_tuning_can_be_turned_off():
    assert _probe("tune", **{allocator.ENV: "0"}) == ["False", "1"]


def _fresh_module(monkeypatch, cdll):
    """allocator.py loaded anew (its once-per-process state reset) with ctypes.CDLL replaced."""
    spec = importlib.util.spec_from_file_location("allocator_copy", ALLOCATOR_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    monkeypatch.setattr(module.ctypes, "CDLL", cdll)
    monkeypatch.setattr(module, "_glibc", lambda: True)
    monkeypatch.delenv(allocator.ENV, raising=False)
    return module


class _Mallopt:
    """A stand-in for libc's mallopt (ctypes functions take argtypes / restype)."""

    def __init__(self, answers):
        self.calls, self.answers = [], list(answers)

    def __call__(self, param, value):
        self.calls.append((param, value))
        return self.answers.pop(0)


class _Libc:
    def __init__(self, answers):
        self.mallopt = _Mallopt(answers)
        self.calls = self.mallopt.calls


def test_tune_allocator_sets_each_parameter_once_per_process(monkeypatch):
    libc = _Libc([1, 1, 1])
    mod = _fresh_module(monkeypatch, lambda name: libc)
    assert mod.tune_allocator() is True
    assert mod.tune_allocator() is True  # remembered: no second round of calls
    assert libc.calls == list(mod.SETTINGS)


def test_tune_allocator_reports_a_refused_setting_and_tries_the_others(monkeypatch):
    libc = _Libc([1, 0, 1])  # the trim threshold refused
    mod = _fresh_module(monkeypatch, lambda name: libc)
    assert mod.tune_allocator() is False
    assert len(libc.calls) == 3
    assert mod.tune_allocator() is False and len(libc.calls) == 3  # the failure is remembered too


def test_tune_allocator_never_raises_without_a_usable_libc(monkeypatch):
    def missing(name):
        raise OSError("no C library")

    mod = _fresh_module(monkeypatch, missing)
    assert mod.tune_allocator() is False
    mod = _fresh_module(monkeypatch, lambda name: object())  # no mallopt attribute
    assert mod.tune_allocator() is False


def test_the_shard_making_processes_tune_and_a_library_caller_does_not(monkeypatch):
    import torch

    from pressurepose.generate import run, worker

    calls = []
    monkeypatch.setattr(allocator, "tune_allocator", lambda: calls.append(1) or True)
    threads = torch.get_num_threads()
    try:
        run._init_worker(None)  # a pool worker's start
    finally:
        torch.set_num_threads(threads)
    assert calls == [1]
    assert "tune_allocator" not in vars(worker)  # make_shard (any caller's process) leaves it alone
