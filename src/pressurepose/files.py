"""Writing outputs so that a partial file never sits under a final name; reading the JSON
files users hand us with one clear message when they are missing or broken."""

from __future__ import annotations

import json
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


def read_json(path: str | os.PathLike, what: str, hint: str = ""):
    """The decoded JSON of a user's file; ValueError "<what> <path> does not exist" or
    "... is not readable JSON (<why>)<hint>" instead of a traceback."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"{what} {path} does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{what} {path} is not readable JSON ({exc}){hint}") from None


def read_npy(path: str | os.PathLike, missing: str = "", what: str = "array"):
    """The numeric array of a user's .npy file, never unpickled; ValueError `missing` (default
    "no file <path>") when absent, or one line naming the file when it is unreadable, pickled or
    not a numeric `what` - instead of a traceback."""
    import numpy as np

    path = Path(path)
    try:
        arr = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise ValueError(missing or f"no file {path}") from None
    except (OSError, ValueError, EOFError) as exc:
        raise ValueError(f"{path} is not a readable .npy: not a numpy array file without pickles ({exc})") from None
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "fiu":
        raise ValueError(f"{path} must hold a numeric {what}, got {getattr(arr, 'dtype', type(arr).__name__)}")
    return arr
