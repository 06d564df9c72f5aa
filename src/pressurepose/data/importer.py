"""Import the original PressurePose synthetic files (Python 2 pickles) into our shard format.

The original release stores each partition file as a pickled dict of lists, one entry per
sample (keys: see ORIGINAL_KEYS). Pickles can run arbitrary code when loaded, so they are read
with `RestrictedUnpickler`, which resolves only the globals numpy needs to rebuild arrays and
scalars, plus plain containers; any other global (a class, a function such as os.system) is
refused with an error naming it, before anything runs.

What is converted is the storage, not the conventions: the original's mat frame, SMPL joints,
image orientation and units are kept as stored (docs/generation.md). Fields a file lacks are
filled with zeros and listed in the manifest under `import.missing`.
"""

from __future__ import annotations

import importlib
import io
import logging
import pickle
import re
from pathlib import Path

import numpy as np

from pressurepose.data.manifest import write_manifest
from pressurepose.data.schema import COLS, ROWS, SampleBatch, to_table
from pressurepose.data.shards import table_bytes, write_shard
from pressurepose.errors import UserError
from pressurepose.validate import BoundedUnpickler

log = logging.getLogger(__name__)

# Original key -> (our field, per-sample shape).
ORIGINAL_KEYS = {
    "images": ("pressure_mmhg", (ROWS, COLS)),
    "markers_xyz_m": ("joints_m", (24, 3)),
    "body_shape": ("shape", (10,)),
    "joint_angles": ("pose72", (72,)),  # root axis-angle (3) + 23 joints (69)
    "root_xyz_shift": ("root_translation", (3,)),
    "mesh_depth": ("depth_mm", (ROWS, COLS)),
    "mesh_contact": ("contact", (ROWS, COLS)),
    "body_mass": ("mass_kg", ()),
    "body_height": ("height_m", ()),
    "bed_angle_deg": ("head_angle_deg", ()),
}
REQUIRED = ("images", "markers_xyz_m", "body_shape", "joint_angles", "root_xyz_shift")


def _resolve(candidates: tuple[tuple[str, str], ...]):
    for module, name in candidates:
        try:
            return getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError):
            continue
    raise ImportError(f"none of {candidates} exists in this numpy")


# (module, name) in a pickle -> where this numpy keeps it (numpy 2 moved numpy.core to numpy._core).
_ALLOWED = {
    ("numpy.core.multiarray", "_reconstruct"): (
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "_reconstruct"),
    ),
    ("numpy._core.multiarray", "_reconstruct"): (
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "_reconstruct"),
    ),
    ("numpy.core.multiarray", "scalar"): (("numpy._core.multiarray", "scalar"), ("numpy.core.multiarray", "scalar")),
    ("numpy._core.multiarray", "scalar"): (("numpy._core.multiarray", "scalar"), ("numpy.core.multiarray", "scalar")),
    ("numpy.core.numeric", "_frombuffer"): (
        ("numpy._core.numeric", "_frombuffer"),
        ("numpy.core.numeric", "_frombuffer"),
    ),
    ("numpy._core.numeric", "_frombuffer"): (
        ("numpy._core.numeric", "_frombuffer"),
        ("numpy.core.numeric", "_frombuffer"),
    ),
    ("numpy", "ndarray"): (("numpy", "ndarray"),),
    ("numpy", "dtype"): (("numpy", "dtype"),),
    # Python 3 pickles bytes under protocol 2 as _codecs.encode(text, "latin1").
    ("_codecs", "encode"): (("_codecs", "encode"),),
}
_CONTAINERS = {"set", "frozenset", "list", "dict", "tuple", "complex", "bytearray"}


class RestrictedUnpickler(BoundedUnpickler):
    """Loads only numpy arrays/scalars/dtypes and plain containers; refuses any other global,
    and any allocation beyond the file's size (`validate.BoundedUnpickler`)."""

    def allowed(self, module: str, name: str):
        if (module, name) in _ALLOWED:
            return _resolve(_ALLOWED[(module, name)])
        if module in ("builtins", "__builtin__") and name in _CONTAINERS:
            return getattr(__import__("builtins"), name)
        return None


def load_restricted(data: bytes, source: str | Path = "pickle"):
    """Unpickle bytes with RestrictedUnpickler (Python 2 strings decoded as latin-1); any
    failure is a UserError naming `source`."""
    try:
        return RestrictedUnpickler(io.BytesIO(data), budget=len(data), source=source, encoding="latin1").load()
    except UserError:
        raise
    except (
        pickle.UnpicklingError,
        EOFError,
        ValueError,
        TypeError,
        IndexError,
        KeyError,
        AttributeError,
        OverflowError,
        MemoryError,
        RecursionError,
        UnicodeError,
    ) as exc:
        raise UserError(
            f"{source}: not a readable pickle ({type(exc).__name__}: {' '.join(str(exc).split())})"
        ) from None


def _leaves(value, limit: int) -> int:
    """Numbers in a nested list/tuple/array, counted up to `limit` + 1 (a pickle can share one
    list many times over, so a small file can describe a huge nest)."""
    count, stack = 0, [value]
    while stack and count <= limit:
        v = stack.pop()
        if isinstance(v, np.ndarray):
            count += v.size
        elif isinstance(v, (list, tuple)):
            stack.extend(v)
        else:
            count += 1
    return count


def _text(key) -> str:
    return key.decode("latin1") if isinstance(key, bytes) else str(key)


_PARTITION_HINTS = (
    ("_xl_", "crossed_legs"),
    ("_sl_", "straight_limbs"),
    ("hbh", "hands_behind_head"),
    ("roll180", "prone_hands_up"),
    ("roll0", "supine"),
)


def infer_labels(path: Path) -> dict:
    """split, gender and partition from an original file name like
    train_roll0_xl_f_lay_set2both_4000.p (None where the name says nothing)."""
    name = path.name.lower()
    split = "train" if name.startswith("train") else ("test" if name.startswith("test") else None)
    gender = "female" if re.search(r"(^|_)f(_|$)", name) else ("male" if re.search(r"(^|_)m(_|$)", name) else None)
    partition = next((p for hint, p in _PARTITION_HINTS if hint in name), None)
    return {"split": split, "gender": gender, "partition": partition}


def read_original(
    path: str | Path, split: str | None = None, gender: str | None = None, partition: str | None = None
) -> tuple[SampleBatch, list[str]]:
    """One original file -> (SampleBatch, original keys it lacked)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such file" + (" (a folder: give the .p files in it)" if path.is_dir() else ""))
    data = path.read_bytes()
    doc = load_restricted(data, path)
    if not isinstance(doc, dict):
        raise UserError(f"{path}: expected a dict of lists, got {type(doc).__name__}")
    doc = {_text(k): v for k, v in doc.items()}
    missing_required = [k for k in REQUIRED if k not in doc]
    if missing_required:
        raise UserError(
            f"{path}: missing keys {missing_required}; an original PressurePose file has {', '.join(ORIGINAL_KEYS)}"
        )
    labels = infer_labels(path)
    split, gender = split or labels["split"] or "train", gender or labels["gender"]
    partition = partition or labels["partition"] or "unknown"
    if gender not in ("female", "male"):
        raise UserError(f"{path}: cannot tell the gender from the file name; pass --gender female or male")
    if not isinstance(doc["images"], (list, tuple, np.ndarray)):
        raise UserError(f"{path}: key 'images' must be a list of images, got {type(doc['images']).__name__}")
    n = len(doc["images"])
    budget = len(data)  # numbers the file can hold: each takes at least one byte of it
    arrays, missing = {}, []
    for key, (field, shape) in ORIGINAL_KEYS.items():
        if key not in doc:
            missing.append(key)
            arrays[field] = np.zeros((n, *shape))
            continue
        values = doc[key]
        if not isinstance(values, (list, tuple, np.ndarray)):
            raise UserError(f"{path}: key {key!r} must be a list with one entry per image, got {type(values).__name__}")
        if len(values) != n:
            raise UserError(f"{path}: key {key!r} has {len(values)} entries but 'images' has {n}")
        size = n * int(np.prod(shape))
        if size > budget or _leaves(values, size) != size:
            raise UserError(
                f"{path}: key {key!r} entries are not numbers of shape {shape} (or the file asks for "
                f"more numbers than its {len(data)} bytes hold)"
            )
        try:
            a = np.asarray([np.asarray(v, dtype=np.float64).reshape(shape) for v in values]).reshape(n, *shape)
        except (ValueError, TypeError):
            raise UserError(f"{path}: key {key!r} entries are not numbers of shape {shape}") from None
        if not np.isfinite(a).all():
            raise UserError(f"{path}: key {key!r} holds NaN or infinite values")
        arrays[field] = a
    pose72 = arrays.pop("pose72")
    batch = SampleBatch(
        split=np.array([split] * n, dtype=object),
        partition=np.array([partition] * n, dtype=object),
        gender=np.array([gender] * n, dtype=object),
        over_bed=np.zeros(n, dtype=bool),
        index=np.arange(n, dtype=np.int64),
        pressure_mmhg=arrays["pressure_mmhg"].astype(np.float32),
        depth_mm=arrays["depth_mm"].astype(np.float32),
        contact=(arrays["contact"] > 0).astype(np.uint8),
        shape=arrays["shape"],
        root_rotation=pose72[:, :3],
        root_translation=arrays["root_translation"],
        pose=pose72[:, 3:].reshape(n, 23, 3),
        joints_m=arrays["joints_m"],
        mass_kg=arrays["mass_kg"],
        height_m=arrays["height_m"],
        head_angle_deg=arrays["head_angle_deg"],
        settle_steps=np.zeros(n, dtype=np.int32),
        sink_mm=np.zeros(n, dtype=np.float32),
    )
    return batch, missing


def import_original(
    paths: list[Path], out: Path, split: str | None = None, gender: str | None = None, partition: str | None = None
) -> Path:
    """Convert original files into a dataset folder (one shard per file); returns manifest path."""
    from pressurepose import __version__

    if not paths:
        raise UserError("give at least one original PressurePose file")
    out = Path(out)
    records, sources = [], []
    for k, path in enumerate(paths):
        batch, missing = read_original(path, split, gender, partition)
        if missing:
            log.warning("%s lacks %s: filled with zeros", path, ", ".join(missing))
        shard_id = f"import-{k:05d}-{re.sub(r'[^A-Za-z0-9_]+', '_', Path(path).stem)[:60]}"
        record = {
            "split": str(batch.split[0]),
            "partition": str(batch.partition[0]),
            "gender": str(batch.gender[0]),
            "over_bed": False,
            "number": k,
            "first_slot": 0,
            "count": len(batch),
            "candidates": len(batch),
            "rejections": {},
            "sampling_rejections": {},
        }
        records.append(write_shard(out, shard_id, table_bytes(to_table(batch)), record))
        sources.append({"file": str(path), "samples": len(batch), "missing": missing})
    header = {
        "pressurepose_version": __version__,
        "config": {"source": "original PressurePose pickles"},
        "import": {"files": sources, "conventions": "original (mat frame, SMPL joints, units as stored)"},
    }
    return write_manifest(out, header, records)


__all__ = [
    "ORIGINAL_KEYS",
    "RestrictedUnpickler",
    "import_original",
    "infer_labels",
    "load_restricted",
    "read_original",
]
