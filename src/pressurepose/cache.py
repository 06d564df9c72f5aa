"""The project cache directory (env PRESSUREPOSE_CACHE, else the platform's user cache dir)."""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
from pathlib import Path

import platformdirs

log = logging.getLogger(__name__)

ENV_VAR = "PRESSUREPOSE_CACHE"


def cache_dir() -> Path:
    """Root of everything pressurepose caches; created on first use."""
    path = Path(os.environ.get(ENV_VAR) or platformdirs.user_cache_dir("pressurepose"))
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RuntimeError(
            f"cannot create the cache directory {path} ({exc.strerror}); set {ENV_VAR} to a writable directory"
        ) from None
    return path


@contextlib.contextmanager
def file_lock(path: Path):
    """Exclusive inter-process lock on `path` (created if missing), so that only one
    process builds a cache entry while the others wait for it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
