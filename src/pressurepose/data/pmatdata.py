"""PmatData (PhysioNet) experiment II: real BT3510 frames, read and normalised.

Files hold 64 lines of 27 integers, raw uncalibrated units, row 0 at the FOOT end (README in
../shared/data/pmatdata). `read_frame` returns our convention (row 0 at the head). The raw
units are not pressures: `normalise` subtracts the frame's empty-taxel level, zeroes taxels
within `threshold` raw units of it (sensor noise), and scales the frame so its summed force
equals the subject's weight (sum p A = m g, with the dataset's A = 0.0286^2 m^2), in mmHg.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
from pathlib import Path

import numpy as np

from pressurepose.errors import UserError
from pressurepose.units import GRAVITY_M_S2, MMHG_PA

ROWS, COLS = 64, 27
PMAT_TAXEL_AREA_M2 = 0.0286**2


def read_frame(path: str | Path) -> np.ndarray:
    """(64, 27) float raw readings, row 0 at the head end."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise UserError(f"no PmatData frame at {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path} is not a readable PmatData text frame ({exc})") from None
    rows = [line.split() for line in text.strip().splitlines() if line.strip()]
    if len(rows) != ROWS or any(len(r) != COLS for r in rows):
        raise UserError(f"{path}: expected {ROWS} lines of {COLS} numbers, got {len(rows)} lines")
    try:
        raw = np.array(rows, dtype=np.float64)
    except ValueError:
        raise UserError(f"{path}: non-numeric values in a PmatData frame") from None
    if not np.isfinite(raw).all() or (raw < 0).any():
        raise UserError(f"{path}: readings must be finite and >= 0")
    return raw[::-1].copy()


def empty_level(raw: np.ndarray) -> float:
    """Reading of an unloaded taxel: the median of the frame's lower half."""
    v = np.sort(raw.ravel())
    return float(np.median(v[: v.size // 2]))


def normalise(raw: np.ndarray, mass_kg: float, threshold: float = 10.0) -> np.ndarray:
    """Raw frame -> pressure in mmHg whose summed force equals m g (see module doc)."""
    if not mass_kg > 0:
        raise UserError(f"mass_kg must be > 0, got {mass_kg}")
    p = raw - empty_level(raw)
    p[p <= threshold] = 0.0
    total = p.sum() * PMAT_TAXEL_AREA_M2
    if total <= 0:
        raise UserError("frame has no loaded taxels")
    return p * (mass_kg * GRAVITY_M_S2 / total) / MMHG_PA


@dataclasses.dataclass(frozen=True)
class PmatRecord:
    path: Path
    subject: int
    mattress: str
    group: str
    index: int
    posture: str
    bed_incline_deg: float
    height_cm: float
    weight_kg: float
    # group E's roll toward `posture`'s side (20 or 40 deg, on wedges or a pillow); 0 where the
    # protocol gives none (groups B-D: flat supine and full lateral)
    body_roll_deg: float = 0.0


def load_index(root: str | Path) -> list[PmatRecord]:
    """Rows of PmatData's index.csv (paths made absolute); a row that cannot be read is a one-line
    UserError naming its line (a missing column, a number that is not one, a group F row without
    its bed angle)."""
    root = Path(root)
    path = root / "index.csv"
    if not path.is_file():
        raise UserError(f"no index.csv in {root}; point at the pmatdata folder")
    out = []
    with path.open() as fh:
        for line, row in enumerate(csv.DictReader(fh), start=2):
            try:
                out.append(_record(root, row))
            except KeyError as exc:
                raise UserError(f"{path}: line {line}: no column {exc.args[0]!r}; see the data README") from None
            except (ValueError, TypeError) as exc:
                raise UserError(f"{path}: line {line}: {exc}") from None
    return out


def _record(root: Path, row: dict) -> PmatRecord:
    if row["group"] == "F" and not (row["bed_incline_deg"] or "").strip():
        raise ValueError("a group F row (head of the bed raised) needs its bed_incline_deg")
    return PmatRecord(
        path=root / row["file"],
        subject=int(row["subject"]),
        mattress=row["mattress"],
        group=row["group"],
        index=int(row["index"]),
        posture=row["posture"],
        bed_incline_deg=float(row["bed_incline_deg"] or 0),
        body_roll_deg=float(row.get("body_roll_deg") or 0),
        height_cm=float(row["height_cm"]),
        weight_kg=float(row["weight_kg"]),
    )


def repeated_frames(records: list[PmatRecord]) -> list[tuple[PmatRecord, PmatRecord]]:
    """(repeat, original) pairs, in the records' order: records whose file holds byte for byte
    the same frame as another's; of each such group the original is the lowest-numbered subject's
    (then the first path). PmatData experiment II as published holds 52 of subject 8's 58 files as
    copies of subject 4's (all but the supine variants B1-B3 on each mattress; docs/real_data.md):
    a repeat is not a second measurement."""
    groups: dict[str, list[PmatRecord]] = {}
    digests = []
    for r in records:
        try:
            digest = hashlib.sha256(Path(r.path).read_bytes()).hexdigest()
        except FileNotFoundError:
            raise UserError(f"no PmatData frame at {r.path}") from None
        except OSError as exc:
            raise UserError(f"{r.path} is not a readable PmatData frame ({exc})") from None
        groups.setdefault(digest, []).append(r)
        digests.append(digest)
    first = {d: min(rs, key=lambda r: (r.subject, str(r.path))) for d, rs in groups.items()}
    return [(r, first[d]) for r, d in zip(records, digests) if first[d] is not r]


def distinct_frames(records: list[PmatRecord]) -> list[PmatRecord]:
    """`records` without the repeats `repeated_frames` finds (each frame once)."""
    repeats = {id(r) for r, _ in repeated_frames(records)}
    return [r for r in records if id(r) not in repeats]


def subjects_of(records: list[PmatRecord]) -> list[tuple[int, float, float]]:
    """The records' subjects, sorted: (subject, height m, mass kg) each."""
    return sorted({(r.subject, r.height_cm / 100, r.weight_kg) for r in records})


def load_images(records: list[PmatRecord], threshold: float = 20.0) -> np.ndarray:
    """(N, 64, 27) float32 mmHg images of index records, row 0 at the head: normalised as the
    data README says and clipped at the sensor model's 100 mmHg."""
    return np.stack([np.minimum(normalise(read_frame(r.path), r.weight_kg, threshold), 100.0) for r in records]).astype(
        np.float32
    )


def import_pmatdata(
    root: str | Path, out: str | Path, groups: str | None = None, mattress: str | None = None, threshold: float = 20.0
) -> dict:
    """PmatData frames -> one .npz in the project's image convention, ready for `predict`:
    pressure_mmhg (N, 64, 27) float32 (row 0 at the head; normalised as the README says and
    clipped at the sensor's 100 mmHg), with per frame: path, subject, mattress, group, index,
    posture, bed_incline_deg, body_roll_deg (group E's documented roll toward its posture's
    side, else 0), height_m, mass_kg (no pickles: strings as unicode arrays).
    groups: posture groups to keep (e.g. "BCD"; default all); mattress: air or sponge (default
    both). Returns counts."""
    from pressurepose.files import atomic_write
    from pressurepose.samples import resolve_pmatdata

    root = resolve_pmatdata(root)
    records = load_index(root)
    if groups is not None:
        records = [r for r in records if r.group in groups]
    if mattress is not None:
        if mattress not in ("air", "sponge"):
            raise UserError(f"mattress must be 'air' or 'sponge', got {mattress!r}")
        records = [r for r in records if r.mattress == mattress]
    if not records:
        raise UserError(f"no PmatData frames under {root} match groups={groups!r}, mattress={mattress!r}")
    arrays = {
        "pressure_mmhg": load_images(records, threshold),
        "path": np.array([str(r.path.relative_to(Path(root))) for r in records]),
        "subject": np.array([r.subject for r in records], dtype=np.int64),
        "mattress": np.array([r.mattress for r in records]),
        "group": np.array([r.group for r in records]),
        "index": np.array([r.index for r in records], dtype=np.int64),
        "posture": np.array([r.posture for r in records]),
        "bed_incline_deg": np.array([r.bed_incline_deg for r in records]),
        "body_roll_deg": np.array([r.body_roll_deg for r in records]),
        "height_m": np.array([r.height_cm / 100 for r in records]),
        "mass_kg": np.array([r.weight_kg for r in records]),
    }
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, lambda tmp: np.savez_compressed(tmp, **arrays))
    return {"frames": len(records), "subjects": len({r.subject for r in records}), "out": str(out)}


def frame_stats(p_mmhg: np.ndarray, taxel_area_m2: float = PMAT_TAXEL_AREA_M2) -> dict[str, float]:
    """Contact area (m^2), mean contact pressure and peak (mmHg) of one image."""
    loaded = p_mmhg > 0
    return {
        "area_m2": float(loaded.sum() * taxel_area_m2),
        "mean_mmhg": float(p_mmhg[loaded].mean()) if loaded.any() else 0.0,
        "peak_mmhg": float(p_mmhg.max()),
    }
