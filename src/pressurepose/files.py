"""Writing outputs so that a partial file never sits under a final name.

Every output file of every command is written through `atomic_write` (or the helpers built on
it, `write_text` and `write_bytes`): the data goes to a temporary name in the same folder, then
is renamed, so a crash never leaves a partial file under the final name. A test greps src/ for
writes that bypass these helpers. Reading users' files is `pressurepose.validate`'s job."""

from __future__ import annotations

import os
from pathlib import Path


def atomic_write(path: Path, write) -> Path:
    """Write through `write(tmp_path)` to a temporary name in the same folder, then rename;
    the temporary file is removed if writing fails."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write `text` to `path` atomically."""
    return atomic_write(Path(path), lambda tmp: Path(tmp).write_text(text))


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write `data` to `path` atomically."""
    return atomic_write(Path(path), lambda tmp: Path(tmp).write_bytes(data))


def save_figure(fig, path, **kwargs):
    """`fig.savefig` to `path` atomically (format from the suffix unless given); a file-like
    `path` (an in-memory buffer) is written directly."""
    if not isinstance(path, (str, os.PathLike)):
        fig.savefig(path, **kwargs)
        return path
    path = Path(path)
    kwargs.setdefault("format", path.suffix.lstrip(".").lower() or "png")
    return atomic_write(path, lambda tmp: fig.savefig(tmp, **kwargs))
