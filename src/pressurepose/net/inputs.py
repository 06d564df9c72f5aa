"""Reading pressure images for `pressurepose predict`, checked before anything runs.

Accepted files (each gives one or more (64, 27) images in mmHg, row 0 at the head end):
- .npy: a (64, 27) or (N, 64, 27) array of mmHg (loaded without pickles);
- .npz: an array `pressure_mmhg` shaped as above (e.g. the training .npz format);
- .parquet: a dataset shard (its `pressure_mmhg` column);
- .csv / .txt: one frame as PmatData stores it: 64 lines of 27 numbers separated by spaces,
  commas or semicolons, row 0 at the FOOT end (flipped here). `text_units="raw"` (default)
  treats the numbers as PmatData's uncalibrated units: the empty-taxel level is removed and
  the frame scaled to the body's weight (`data.pmatdata.normalise`; the network normalises
  each image by its sum anyway, so the assumed mass changes only the 100 mmHg clip);
  `text_units="mmhg"` takes them as mmHg.
Every image must be finite, >= 0, not empty and at most MAX_PLAUSIBLE_MMHG (1000 mmHg; beyond
it only with `force`, and then clipped there); a shard inside a dataset folder must match its
recorded sha256. Any failure is a UserError naming the file.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Literal

import numpy as np

from pressurepose.errors import UserError

ROWS, COLS = 64, 27
# Plausibility bound on input pressures: a body at rest on a mattress presses a few tens of mmHg
# (peaks ~100-200 mmHg under bony points); 1000 mmHg (133 kPa) is beyond any reading of a
# person lying on a bed, so an image above it is taken as wrong units or a damaged file.
MAX_PLAUSIBLE_MMHG = 1000.0
SUFFIXES = (".npy", ".npz", ".parquet", ".csv", ".txt")


def read_pressure_file(
    path: str | Path, text_units: Literal["raw", "mmhg"] = "raw", mass_kg: float = 70.0, force: bool = False
) -> np.ndarray:
    """(N, 64, 27) float32 mmHg images of one file (see module doc). `force` accepts pressures
    above MAX_PLAUSIBLE_MMHG."""
    path = Path(path)
    if path.is_dir():
        raise UserError(f"{path}: is a folder; give pressure image files ({', '.join(SUFFIXES)})")
    if not path.is_file():
        raise UserError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise UserError(f"{path}: unsupported file type {suffix or '(none)'}; give {', '.join(SUFFIXES)} files")
    if path.stat().st_size == 0:
        raise UserError(f"{path}: the file is empty")
    if suffix == ".npy":
        images = _load_npy(path)
    elif suffix == ".npz":
        images = _load_npz(path)
    elif suffix == ".parquet":
        verify_dataset_shard(path)
        images = _load_parquet(path)
    else:
        images = _load_text(path, text_units, mass_kg)[None]
    return check_images(images, path, force)


def verify_dataset_shard(path: Path) -> None:
    """A shard inside a dataset folder (DATASET/shards/ID.parquet) is checked against its
    recorded sha256 - the manifest's record, else the shard's own record (shards/ID.json) -
    so a damaged copy is refused, as `info` refuses it, instead of being read silently."""
    from pressurepose.data.manifest import MANIFEST, load_manifest
    from pressurepose.data.shards import check_shard_record, verify_shard
    from pressurepose.validate import read_json

    root = path.parent.parent
    if (root / MANIFEST).is_file():
        for record in load_manifest(root, verify=False)["shards"]:
            if (root / record["file"]).resolve() == path.resolve():
                verify_shard(root, record)
                return
    sidecar = path.with_suffix(".json")
    if sidecar.is_file():
        record = check_shard_record(read_json(sidecar, "shard record"), sidecar, root)
        if (root / record["file"]).resolve() == path.resolve():
            verify_shard(root, record)


def check_images(images: np.ndarray, path: Path, force: bool = False) -> np.ndarray:
    """The images of a file as (N, 64, 27) float32 mmHg, checked: shape, numbers, finite, >= 0,
    not empty, and at most MAX_PLAUSIBLE_MMHG (unless `force`)."""
    shape = images.shape
    if images.ndim == 2:
        images = images[None]
    if images.ndim != 3 or images.shape[1:] != (ROWS, COLS):
        raise UserError(
            f"{path}: expected a ({ROWS}, {COLS}) pressure image or a stack (N, {ROWS}, {COLS}), got shape {shape}"
        )
    if images.shape[0] == 0:
        raise UserError(f"{path}: holds no images")
    if not np.issubdtype(images.dtype, np.number) or images.dtype == bool or images.dtype.kind == "c":
        raise UserError(f"{path}: not a pressure image (dtype {images.dtype})")
    values = images.astype(np.float64)  # check before the float32 cast (1e300 would overflow it)
    bad = ~np.isfinite(values).all((1, 2))
    if bad.any():
        raise UserError(f"{path}: image {int(np.argmax(bad))} contains NaN or infinite values")
    neg = (values < 0).any((1, 2))
    if neg.any():
        raise UserError(
            f"{path}: image {int(np.argmax(neg))} has negative pressures (min {values.min():.3g}); "
            "readings must be >= 0 mmHg"
        )
    empty = ~(values > 0).any((1, 2))
    if empty.any():
        raise UserError(f"{path}: image {int(np.argmax(empty))} is empty (no loaded taxel): nobody on the mat")
    high = (values > MAX_PLAUSIBLE_MMHG).any((1, 2))
    if high.any() and not force:
        raise UserError(
            f"{path}: image {int(np.argmax(high))} reads up to {values.max():.3g} mmHg, more than "
            f"{MAX_PLAUSIBLE_MMHG:g} mmHg (no body on a mattress presses that hard: wrong units?); "
            "pass --force to use it anyway (the network clips at 100 mmHg)"
        )
    if high.any():
        values = np.minimum(values, MAX_PLAUSIBLE_MMHG)  # forced: clipped, so the float32 cast stays finite
    return values.astype(np.float32)


def _load_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - numpy's header parser raises SyntaxError, TokenError... on garbage
        raise UserError(f"{path}: not a numpy array file without pickles ({exc})") from None


def _load_npz(path: Path) -> np.ndarray:
    try:
        with np.load(path, allow_pickle=False) as f:
            if "pressure_mmhg" not in f.files:
                raise UserError(f"{path}: no array 'pressure_mmhg' (holds {', '.join(f.files) or 'nothing'})")
            return f["pressure_mmhg"]
    except UserError:
        raise
    except Exception as exc:  # noqa: BLE001 - zipfile and numpy's header parser raise many types on garbage
        raise UserError(f"{path}: not a readable .npz file ({type(exc).__name__}: {exc})") from None


def _load_parquet(path: Path) -> np.ndarray:
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        raise UserError(f"{path}: reading dataset shards needs pyarrow (pip install pyarrow)") from None
    try:
        column = pq.read_table(path, columns=["pressure_mmhg"]).column("pressure_mmhg").combine_chunks()
    except (OSError, KeyError, pa.ArrowException) as exc:
        raise UserError(f"{path}: not a dataset shard with a pressure_mmhg column ({exc})") from None
    values = column.flatten().to_numpy(zero_copy_only=False) if len(column) else np.zeros(0, np.float32)
    if values.size != len(column) * ROWS * COLS:
        raise UserError(f"{path}: pressure_mmhg rows are not {ROWS} x {COLS} images")
    return values.reshape(len(column), ROWS, COLS)


def _load_text(path: Path, units: str, mass_kg: float) -> np.ndarray:
    from pressurepose.data.pmatdata import normalise

    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: not a text pressure frame ({exc})") from None
    rows = [re.split(r"[\s,;]+", line.strip()) for line in text.strip().splitlines() if line.strip()]
    if len(rows) != ROWS or any(len(r) != COLS for r in rows):
        counts = sorted({len(r) for r in rows})
        raise UserError(
            f"{path}: expected {ROWS} lines of {COLS} numbers (a PmatData frame), got {len(rows)} "
            f"lines of {counts} values"
        )
    try:
        raw = np.array(rows, dtype=np.float64)[::-1].copy()  # PmatData: row 0 at the foot end
    except ValueError:
        raise UserError(f"{path}: not a pressure frame (non-numeric values)") from None
    if units == "mmhg" or not np.isfinite(raw).all() or (raw < 0).any() or not (raw > 0).any():
        return raw  # check_images names the problem
    if units != "raw":
        raise UserError(f"text_units must be 'raw' or 'mmhg', got {units!r}")
    try:
        return normalise(raw, mass_kg)
    except ValueError as exc:
        raise UserError(f"{path}: {exc}") from None


__all__ = ["MAX_PLAUSIBLE_MMHG", "SUFFIXES", "check_images", "read_pressure_file", "verify_dataset_shard"]
