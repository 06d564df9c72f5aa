"""Writing outputs so that a partial file never sits under a final name."""

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
