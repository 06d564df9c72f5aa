"""The one layer where files users hand us are read and checked.

Every reader of a user's file goes through these helpers, so a bad file gives one line that
names the file, the field and what was expected (a `UserError`), never a traceback:
- `read_json`, `read_json_object`, `read_jsonl`, `read_npy`: decoding (missing, unreadable,
  not JSON, pickled arrays);
- `field`: one field of a decoded record, of the expected kind (`KINDS`);
- `inside`: a path recorded in a file, confined to its folder (no absolute paths, no `..`
  escaping it, no symlink leading out);
- `resolve_recorded`: a path a report or run recorded as typed, found again from elsewhere;
- `check_tensor_shapes`: the tensors of a weights file against the network's;
- `BoundedUnpickler`: the base of the restricted unpicklers - no global outside an allow
  list, and no allocation beyond what the file's size can need (`budget`).
Schemas (which fields a manifest or a run config has) live with their formats; the checks
live here.
"""

from __future__ import annotations

import json
import math
import os
import pickle
from pathlib import Path
from typing import Any

from pressurepose.errors import UserError


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def read_json(path: str | os.PathLike, what: str, hint: str = "") -> Any:
    """The decoded JSON of a user's file; UserError "<what> <path> does not exist" or
    "... is not readable JSON (<why>)<hint>" instead of a traceback."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"{what} {path} does not exist") from None
    except IsADirectoryError:
        raise UserError(f"{what} {path} is a folder, not a file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise UserError(f"{what} {path} is not readable JSON ({exc}){hint}") from None


def read_json_object(path: str | os.PathLike, what: str, hint: str = "") -> dict:
    """`read_json`, and the top level must be a JSON object."""
    doc = read_json(path, what, hint)
    if not isinstance(doc, dict):
        raise UserError(f"{what} {path}: expected a JSON object at the top level, got {type(doc).__name__}{hint}")
    return doc


def read_jsonl(path: str | os.PathLike, what: str, hint: str = "") -> list[dict]:
    """The JSON objects of a JSON-lines file (blank lines skipped); [] when it is absent."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        return []
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{what} {path} is not readable ({exc}){hint}") from None
    rows = []
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except (json.JSONDecodeError, RecursionError) as exc:
            raise UserError(f"{what} {path}: line {number} is not readable JSON ({exc}){hint}") from None
        if not isinstance(row, dict):
            raise UserError(f"{what} {path}: line {number}: expected a JSON object, got {type(row).__name__}{hint}")
        rows.append(row)
    return rows


def read_npy(path: str | os.PathLike, missing: str = "", what: str = "array"):
    """The numeric array of a user's .npy file, never unpickled; UserError `missing` (default
    "no file <path>") when absent, or one line naming the file when it is unreadable, pickled or
    not a numeric `what`."""
    import numpy as np

    path = Path(path)
    try:
        arr = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise UserError(missing or f"no file {path}") from None
    except Exception as exc:  # noqa: BLE001 - numpy's header parser raises SyntaxError, TokenError... on garbage
        raise UserError(f"{path} is not a readable .npy: not a numpy array file without pickles ({exc})") from None
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "fiu":
        raise UserError(f"{path} must hold a numeric {what}, got {getattr(arr, 'dtype', type(arr).__name__)}")
    return arr


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return (_is_int(v) or isinstance(v, float)) and math.isfinite(v) and abs(v) < 1e300


KINDS = {
    "str": ("a string", lambda v: isinstance(v, str)),
    "name": ("a non-empty string", lambda v: isinstance(v, str) and bool(v.strip())),
    "bool": ("true or false", lambda v: isinstance(v, bool)),
    "int": ("an integer", _is_int),
    "count": ("an integer >= 0", lambda v: _is_int(v) and v >= 0),
    "number": ("a finite number", _is_number),
    "dict": ("a JSON object", lambda v: isinstance(v, dict)),
    "list": ("a JSON list", lambda v: isinstance(v, list)),
    "sha256": (
        "a sha256 (64 hex digits)",
        lambda v: isinstance(v, str) and len(v) == 64 and all(c in "0123456789abcdef" for c in v),
    ),
}


def field(doc: Any, key: str, kind: str, path: str | os.PathLike, where: str = "", hint: str = "") -> Any:
    """doc[key], which must be of `kind` (see KINDS); UserError "<path>: field <where><key>
    must be <kind>, got <value>" when it is absent or of another kind."""
    expected, ok = KINDS[kind]
    name = f"{where}{key}"
    if not isinstance(doc, dict):
        raise UserError(
            f"{path}: {where.rstrip('.[]') or 'the record'} must be a JSON object, got {type(doc).__name__}{hint}"
        )
    if key not in doc:
        raise UserError(f"{path}: field {name!r} is missing; expected {expected}{hint}")
    value = doc[key]
    if not ok(value):
        raise UserError(f"{path}: field {name!r} must be {expected}, got {_short(value)}{hint}")
    return value


def inside(root: str | os.PathLike, relative: Any, path: str | os.PathLike, name: str) -> Path:
    """root / relative, refused unless it is a relative path that stays inside root (after
    resolving `..` and symlinks): a file's records can never point us at other files."""
    if not isinstance(relative, str) or not relative or "\x00" in relative:
        raise UserError(f"{path}: field {name!r} must be a relative path inside {root}, got {_short(relative)}")
    rel = Path(relative)
    base = Path(root).resolve()
    target = (base / rel).resolve()
    if rel.is_absolute() or ".." in rel.parts or not target.is_relative_to(base) or target == base:
        raise UserError(f"{path}: field {name!r} must be a relative path inside {root}, got {relative!r}")
    return Path(root) / rel


def resolve_recorded(recorded: str | None, near: str | os.PathLike) -> Path | None:
    """A path recorded in a report or run (as the user typed it, maybe relative to the folder
    the command ran in): as given, else relative to the record's folder `near` or its parents;
    None when none of them exists."""
    if not recorded or not isinstance(recorded, str):
        return None
    p, near = Path(recorded), Path(near)
    candidates = [p] if p.is_absolute() else [Path.cwd() / p, near / p, near.parent / p, near.parent.parent / p]
    return next((c for c in candidates if c.exists()), None)


def check_tensor_shapes(found: dict, expected: dict, path: str | os.PathLike, hint: str = "") -> None:
    """The tensors of a weights file must be the network's: same names, same shapes, finite."""
    missing = [k for k in expected if k not in found]
    unexpected = [k for k in found if k not in expected]
    if missing or unexpected:
        raise UserError(
            f"{path} does not match the network its metadata describes: missing tensors "
            f"{missing[:3]}, unexpected {unexpected[:3]}{hint}"
        )
    for name, want in expected.items():
        got = tuple(found[name].shape)
        if got != tuple(want):
            raise UserError(
                f"{path}: tensor {name!r} has shape {got}, expected {tuple(want)} for the network "
                f"its metadata describes{hint}"
            )
        tensor = found[name]
        if tensor.is_floating_point() and not bool(tensor.isfinite().all()):
            raise UserError(f"{path}: tensor {name!r} holds NaN or infinite values{hint}")


class BoundedUnpickler(pickle.Unpickler):
    """Base of the restricted unpicklers. `find_class` resolves a global only through
    `allowed()` (refusing any other), and every callable that allocates is wrapped so that
    no buffer or array beyond `budget` bytes is made: the pickled data of a real array is in
    the file, so nothing it can need exceeds the file's size. A file asking for more (a
    `bytearray(2**62)`) gets a UserError naming it, before memory is touched."""

    def __init__(self, file, budget: int, source: str | os.PathLike = "pickle", **kwargs) -> None:
        super().__init__(file, **kwargs)
        self.budget = int(budget)
        self.source = str(source)

    def allowed(self, module: str, name: str):
        """The object for a global the format needs, else None (refused)."""
        raise NotImplementedError

    def find_class(self, module: str, name: str):
        obj = self.allowed(module, name)
        if obj is None:
            raise UserError(
                f"{self.source}: refusing to load the global {module}.{name}: only numpy arrays "
                "and plain containers are allowed in this file (a pickle can run code when loaded)"
            )
        return self._bounded(obj)

    def check_allocation(self, nbytes: float, what: str) -> None:
        if not nbytes <= self.budget:
            raise UserError(
                f"{self.source}: asks for {what} of {nbytes:.3g} bytes, more than the file's "
                f"{self.budget} bytes can hold; not a valid file"
            )

    def _nbytes(self, shape, dtype) -> float:
        import numpy as np

        dims = (shape,) if _is_int(shape) else tuple(shape)
        if not all(_is_int(d) and d >= 0 for d in dims):
            raise UserError(f"{self.source}: an array shape {_short(shape)} is not a tuple of sizes >= 0")
        try:
            itemsize = np.dtype(dtype).itemsize
        except (TypeError, ValueError):
            raise UserError(f"{self.source}: an array dtype {_short(dtype)} is not a numpy dtype") from None
        return float(math.prod(dims)) * max(itemsize, 1)

    def _bounded(self, obj):
        import copyreg

        import numpy as np

        if obj is bytearray:

            def make_bytearray(*args):
                if args and _is_int(args[0]):
                    self.check_allocation(args[0], "a byte array")
                return bytearray(*args)

            return make_bytearray
        if obj is np.ndarray:

            class BoundedArray(np.ndarray):  # `ndarray(shape, dtype)` allocates: check first
                def __new__(cls, shape, dtype=float, *args, **kwargs):
                    self.check_allocation(self._nbytes(shape, dtype), "an array")
                    return np.ndarray.__new__(np.ndarray, shape, dtype, *args, **kwargs)

            return BoundedArray
        if getattr(obj, "__name__", "") == "_reconstruct" and "numpy" in getattr(obj, "__module__", ""):

            def reconstruct(cls, shape, dtype):
                self.check_allocation(self._nbytes(shape, dtype), "an array")
                if isinstance(cls, type) and issubclass(cls, np.ndarray):
                    cls = np.ndarray
                return obj(cls, shape, dtype)

            return reconstruct
        if obj is copyreg._reconstructor:

            def reconstructor(cls, base, state):
                if base is not object:  # base.__init__(state) could allocate anything
                    raise UserError(f"{self.source}: refusing copyreg._reconstructor on {_short(base)}")
                return obj(cls, base, state)

            return reconstructor
        if getattr(obj, "__name__", "") == "encode" and getattr(obj, "__module__", "") == "_codecs":

            def encode(text, encoding="utf-8", *args):
                if encoding not in ("latin1", "latin-1", "iso-8859-1"):
                    raise UserError(f"{self.source}: refusing _codecs.encode with encoding {_short(encoding)}")
                return obj(text, encoding)

            return encode
        return obj


__all__ = [
    "BoundedUnpickler",
    "KINDS",
    "check_tensor_shapes",
    "field",
    "inside",
    "read_json",
    "read_json_object",
    "read_jsonl",
    "read_npy",
]
