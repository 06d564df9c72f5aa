"""Import SLP pressure maps (Simultaneously-collected multimodal Lying Pose, Liu et al.,
Ostadabbas lab) onto our 64 x 27 grid, as one predict-ready .npz.

Layout (the dataset's reader `data/SLP_RD.py`, docs/real_data.md):
    danaLab/physiqueData.npy                        one row per subject (see `read_physique`)
    danaLab/00001/PMarray/{uncover,cover1,cover2}/000001.npy ... 000045.npy   (192, 84) arrays
    danaLab/00001/PMcali.npy                        (3, 45): per cover and frame, the factor
                                                    that maps PMarray to physical pressure
The mat is 1.92 x 0.84 m (1 cm pitch, BodyPressure's SLP loader); its rows run head to foot
as stored (both of the BodiesAtRest authors' SLP loaders use the rows unflipped on networks
with row 0 at the head). Each frame is oriented, calibrated (`calibration`), resampled onto
our grid by area (`data.real.resample_to_mat`: force kept where the mats overlap; the sensing
areas share their centre), and clipped at 100 mmHg.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Literal

import numpy as np

from pressurepose.data.real import orient, resample_to_mat
from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.units import GRAVITY_M_S2, MMHG_PA
from pressurepose.validate import read_npy

log = logging.getLogger(__name__)

COVERS = ("uncover", "cover1", "cover2")
SLP_SHAPE = (192, 84)
SLP_PITCH_M = 0.01
KPA_MMHG = 1000.0 / MMHG_PA
Calibration = Literal["weight", "pmcali"]


def read_physique(root: Path) -> np.ndarray:
    """(S, 3) gender (1 female, 0 male on our scale), height_m, mass_kg per subject (row s =
    subject s + 1) from physiqueData.npy. SLP_RD swaps the file's columns 0 and 2 and then
    reads weight (kg), height, gender (0 female, 1 male): the file holds gender, height (cm),
    weight (kg) in columns 0, 1, 2."""
    path = Path(root) / "physiqueData.npy"
    arr = read_npy(path, f"no physiqueData.npy in {root}; point at SLP's danaLab folder")
    if arr.ndim != 2 or arr.shape[1] < 3 or not np.issubdtype(arr.dtype, np.number):
        raise UserError(f"{path}: expected a numeric (subjects, >= 3) array, got {arr.dtype} {arr.shape}")
    gender, height_cm, mass_kg = arr[:, 0].astype(float), arr[:, 1].astype(float), arr[:, 2].astype(float)
    # The column order is read from SLP's reader, not from a data description: check it.
    if not (
        np.isin(gender, (0, 1)).all()
        and ((height_cm > 100) & (height_cm < 230)).all()
        and ((mass_kg > 25) & (mass_kg < 250)).all()
    ):
        raise UserError(
            f"{path}: columns 0-2 are not gender (0/1), height (cm), weight (kg) as SLP's reader "
            "implies; check the file"
        )
    return np.stack([1.0 - gender, height_cm / 100, mass_kg], 1)


def _subject_folders(root: Path, subjects: list[int] | None) -> list[tuple[int, Path]]:
    found = {int(p.name): p for p in root.iterdir() if p.is_dir() and re.fullmatch(r"\d{5}", p.name)}
    if subjects is not None:
        missing = [s for s in subjects if s not in found]
        if missing:
            raise UserError(f"no SLP subject folders {[f'{s:05d}' for s in missing]} under {root}")
        found = {s: found[s] for s in subjects}
    if not found:
        raise UserError(f"no subject folders (00001, ...) under {root}; point at SLP's danaLab folder")
    return sorted(found.items())


def read_pm(path: Path) -> np.ndarray:
    """One PMarray frame (192, 84), finite and >= 0."""
    arr = read_npy(path)
    if arr.shape != SLP_SHAPE or not np.issubdtype(arr.dtype, np.number):
        raise UserError(f"{path}: expected an SLP pressure map of shape {SLP_SHAPE}, got {arr.dtype} {arr.shape}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all() or (arr < 0).any():
        raise UserError(f"{path}: readings must be finite and >= 0")
    return arr


def read_calibration(folder: Path) -> np.ndarray:
    """(3, F) PMcali factors of one subject (covers in COVERS order)."""
    path = folder / "PMcali.npy"
    cali = read_npy(path, f"no PMcali.npy in {folder}; use --calibration weight")
    if cali.ndim != 2 or cali.shape[0] != len(COVERS) or not np.isfinite(cali).all() or (cali <= 0).any():
        raise UserError(f"{path}: expected positive factors of shape (3, frames), got {cali.shape}")
    return cali.astype(np.float64)


def frame_to_mat(
    pm: np.ndarray,
    mass_kg: float,
    calibration: Calibration,
    cali_factor: float | None = None,
    pitch_m: float = SLP_PITCH_M,
    head_row: str = "first",
    flip_columns: bool = False,
    mat: MatSpec | None = None,
) -> np.ndarray:
    """One SLP frame -> (64, 27) mmHg on our grid, clipped at the mat's maximum."""
    mat = mat or MatSpec()
    p = orient(pm, head_row, flip_columns)
    if calibration == "pmcali":
        p = resample_to_mat(p * cali_factor * KPA_MMHG, pitch_m, pitch_m, mat)
    elif calibration == "weight":
        p = resample_to_mat(p, pitch_m, pitch_m, mat)
        total = p.sum() * mat.pitch_row_m * mat.pitch_col_m
        if total <= 0:
            raise UserError("an SLP frame has no load on the BT3510 area")
        p = p * (mass_kg * GRAVITY_M_S2 / total) / MMHG_PA
    else:
        raise UserError(f"calibration must be 'weight' or 'pmcali', got {calibration!r}")
    return np.minimum(p, mat.max_pressure_mmhg)


def import_slp(
    root: str | Path,
    out: str | Path,
    covers: tuple[str, ...] = COVERS,
    subjects: list[int] | None = None,
    calibration: Calibration = "weight",
    pitch_m: float = SLP_PITCH_M,
    head_row: str = "first",
    flip_columns: bool = False,
) -> dict:
    """SLP danaLab pressure maps -> one .npz: pressure_mmhg (N, 64, 27) float32 (row 0 at the
    head), with per frame subject, cover, frame (1-based, as in the file names), gender
    ('female'/'male'), height_m, mass_kg, bed_angle_deg (0: SLP's bed was flat)."""
    from pressurepose.files import atomic_write

    root = Path(root)
    if not root.is_dir():
        raise UserError(f"no folder at {root}; point at SLP's danaLab folder")
    bad = [c for c in covers if c not in COVERS]
    if bad or not covers:
        raise UserError(f"covers must be among {COVERS}, got {list(covers)}")
    if calibration not in ("weight", "pmcali"):
        raise UserError(f"calibration must be 'weight' or 'pmcali', got {calibration!r}")
    if not pitch_m > 0:
        raise UserError(f"pitch must be > 0 m, got {pitch_m}")
    physique = read_physique(root)
    rows: dict[str, list] = {
        k: [] for k in ("pressure_mmhg", "subject", "cover", "frame", "gender", "height_m", "mass_kg")
    }
    for subject, folder in _subject_folders(root, subjects):
        if subject > len(physique):
            raise UserError(f"subject {subject:05d} has no row in physiqueData.npy ({len(physique)} rows)")
        gender, height_m, mass_kg = physique[subject - 1]
        cali = read_calibration(folder) if calibration == "pmcali" else None
        for c, cover in enumerate(COVERS):
            if cover not in covers:
                continue
            files = sorted((folder / "PMarray" / cover).glob("[0-9][0-9][0-9][0-9][0-9][0-9].npy"))
            if not files:
                log.warning("%s has no PMarray/%s frames", folder, cover)
            for f in files:
                k = int(f.stem)
                if cali is not None and k > cali.shape[1]:
                    raise UserError(f"{folder / 'PMcali.npy'} has {cali.shape[1]} frames; {f} needs frame {k}")
                try:
                    img = frame_to_mat(
                        read_pm(f),
                        mass_kg,
                        calibration,
                        None if cali is None else cali[c, k - 1],
                        pitch_m,
                        head_row,
                        flip_columns,
                    )
                except ValueError as exc:
                    msg = str(exc)
                    raise UserError(msg if msg.startswith(str(f)) else f"{f}: {msg}") from None
                rows["pressure_mmhg"].append(img)
                rows["subject"].append(subject)
                rows["cover"].append(cover)
                rows["frame"].append(k)
                rows["gender"].append("female" if gender > 0.5 else "male")
                rows["height_m"].append(height_m)
                rows["mass_kg"].append(mass_kg)
    if not rows["subject"]:
        raise UserError(f"no SLP frames of covers {list(covers)} under {root}")
    arrays = {
        "pressure_mmhg": np.stack(rows["pressure_mmhg"]).astype(np.float32),
        "subject": np.array(rows["subject"], dtype=np.int64),
        "cover": np.array(rows["cover"]),
        "frame": np.array(rows["frame"], dtype=np.int64),
        "gender": np.array(rows["gender"]),
        "height_m": np.array(rows["height_m"]),
        "mass_kg": np.array(rows["mass_kg"]),
        "bed_angle_deg": np.zeros(len(rows["subject"])),
    }
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, lambda tmp: np.savez_compressed(tmp, **arrays))
    return {"frames": len(rows["subject"]), "subjects": len(set(rows["subject"])), "out": str(out)}


__all__ = [
    "COVERS",
    "SLP_PITCH_M",
    "SLP_SHAPE",
    "frame_to_mat",
    "import_slp",
    "read_calibration",
    "read_physique",
    "read_pm",
]
