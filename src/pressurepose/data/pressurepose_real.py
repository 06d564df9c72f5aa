"""Import the original PressurePose real dataset (Clever et al. 2020; Harvard Dataverse
doi:10.7910/DVN/KOA4ML) into one predict-ready .npz with the participants' point clouds.

Layout of the release (its download script and readers, docs/real_data.md): one folder per
participant, S103 ... S196 (20 participants), each holding three Python 2 pickles:

- `participant_info_red.p`: a dict with `gender` ('f' or 'm'), `height_in` (inches),
  `weight_lbs` (pounds) and the pose lists `prescribed_pose_type`, `p_select_pose_type`;
- `prescribed.p` (48 prescribed poses) and `p_select.p` (5 participant-selected poses): dicts
  of per-frame lists - `images` (64 x 27 = 1,728 taxels, row 0 at the head end, the same
  orientation as the synthetic images), `pc` (the Kinect point cloud of the person, (P, 3) m,
  white bed-sheet points filtered out), `pose_type`, `pmat_corners`, `RGB`, `depth`.

The pickles are read by `importer.load_restricted` (numpy arrays and plain containers only).
The clouds are stored in the release's frame: axis 0 along the bed from the FOOT end, axis 1
across the bed from the column-0 side, axis 2 pointing DOWN (the Kinect hangs at -1.66 m);
`CloudFrame` maps them into our mat frame (x from the head, z up, z = 0 mattress top) - its
numbers are read from the release's renderer, not measured (see docs/real_data.md).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Literal

import numpy as np

from pressurepose.data.importer import load_restricted
from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.units import GRAVITY_M_S2, MMHG_PA

log = logging.getLogger(__name__)

ROWS, COLS = 64, 27
INCH_M = 0.0254
POUND_KG = 0.45359237
POSE_SETS = ("prescribed", "p_select")
INFO_FILE = "participant_info_red.p"
BEDSHEET_FACTOR = 4.0  # the release multiplies real images by 4 ("because we used a sheet on the bed")
# Taxel area used when a frame is scaled to the participant's weight.
TAXEL_AREA_M2 = MatSpec().taxel_area_m2
PressureScale = Literal["release", "weight", "stored"]


@dataclasses.dataclass(frozen=True)
class CloudFrame:
    """Where the release's cloud frame sits in our mat frame (all in metres):
    x_mat = head_x_m - p0, y_mat = p1 - col0_y_m, z_mat = mattress_z_m - p2.

    Defaults from the release's renderer (lib_pyrender_br.get_3D_pmat_markers): taxel row j
    drawn at p0 = (64 - j) * 0.0286 * 1.04 (so the head edge of row 0 at 1.904 m), column i at
    p1 = i * 0.0286, the mat surface at p2 = 0.075 with the camera at p2 = -1.66."""

    head_x_m: float = 64 * 0.0286 * 1.04
    """Cloud frame: the head edge of the sensing area along the cloud's axis 0 (m)."""
    col0_y_m: float = 0.0
    """Cloud frame: the column-0 edge along the cloud's axis 1 (m)."""
    mattress_z_m: float = 0.075
    """Cloud frame: the mattress top along the cloud's (downward) axis 2 (m)."""

    def to_mat(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64)
        return np.stack([self.head_x_m - p[:, 0], p[:, 1] - self.col0_y_m, self.mattress_z_m - p[:, 2]], 1)


def _load_dict(path: Path, what: str) -> dict:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise UserError(f"no {what} at {path}") from None
    doc = load_restricted(data, path)  # a UserError naming the file
    if not isinstance(doc, dict):
        raise UserError(f"{path}: expected a dict ({what}), got {type(doc).__name__}")
    return {(k.decode("latin1") if isinstance(k, bytes) else str(k)): v for k, v in doc.items()}


def _text(v) -> str:
    return v.decode("latin1") if isinstance(v, bytes) else str(v)


def read_participant_info(folder: Path) -> dict:
    """gender ('female'/'male'), height_m, mass_kg of one participant folder."""
    path = Path(folder) / INFO_FILE
    info = _load_dict(path, "participant info")
    missing = [k for k in ("gender", "height_in", "weight_lbs") if k not in info]
    if missing:
        raise UserError(f"{path}: missing keys {missing}; participant_info_red.p holds gender, height_in, weight_lbs")
    gender = {"f": "female", "female": "female", "m": "male", "male": "male"}.get(_text(info["gender"]).lower())
    if gender is None:
        raise UserError(f"{path}: gender must be 'f' or 'm', got {_text(info['gender'])!r}")
    try:
        height_in, weight_lbs = float(info["height_in"]), float(info["weight_lbs"])
    except (TypeError, ValueError):
        raise UserError(f"{path}: height_in and weight_lbs must be numbers") from None
    # Plausible adults only: a file in other units (cm, kg) fails here instead of downstream.
    if not (40 <= height_in <= 90 and 60 <= weight_lbs <= 500):
        raise UserError(
            f"{path}: height {height_in} in / weight {weight_lbs} lbs are not plausible (the release "
            "stores inches and pounds)"
        )
    return {"gender": gender, "height_m": height_in * INCH_M, "mass_kg": weight_lbs * POUND_KG}


def scale_images(images: np.ndarray, mode: PressureScale, mass_kg: float, max_mmhg: float = 100.0) -> np.ndarray:
    """Stored images (N, 64, 27) -> mmHg clipped at `max_mmhg`: 'release' x4 (the release's
    bed-sheet factor, onto the synthetic images' scale), 'weight' summed force = m g,
    'stored' as stored."""
    images = np.asarray(images, dtype=np.float64)
    if mode == "release":
        out = images * BEDSHEET_FACTOR
    elif mode == "weight":
        total = images.sum((1, 2), keepdims=True) * TAXEL_AREA_M2
        out = images * (mass_kg * GRAVITY_M_S2 / np.maximum(total, 1e-300)) / MMHG_PA
    elif mode == "stored":
        out = images
    else:
        raise UserError(f"pressure scale must be 'release', 'weight' or 'stored', got {mode!r}")
    return np.minimum(out, max_mmhg)


def read_pose_set(folder: Path, pose_set: str) -> dict:
    """images (N, 64, 27) as stored, clouds [N x (P, 3)] in the release's frame, pose types."""
    path = Path(folder) / f"{pose_set}.p"
    doc = _load_dict(path, f"{pose_set} poses")
    missing = [k for k in ("images", "pc") if k not in doc]
    if missing:
        raise UserError(
            f"{path}: missing keys {missing}; a PressurePose real file holds images, pc, pose_type, "
            "pmat_corners, RGB, depth"
        )
    frames, clouds = doc["images"], doc["pc"]
    if not isinstance(frames, (list, tuple, np.ndarray)) or not isinstance(clouds, (list, tuple)):
        raise UserError(f"{path}: 'images' and 'pc' must be per-frame lists")
    n = len(frames)
    if len(clouds) != n:
        raise UserError(f"{path}: 'pc' has {len(clouds)} entries but 'images' has {n}")
    images = np.zeros((n, ROWS, COLS))
    for i, f in enumerate(frames):
        try:
            a = np.asarray(f, dtype=np.float64)
        except (TypeError, ValueError):
            a = None
        if a is None or a.size != ROWS * COLS:
            raise UserError(
                f"{path}: image {i} is not {ROWS} x {COLS} = {ROWS * COLS} numbers "
                f"(got shape {None if a is None else a.shape})"
            )
        images[i] = a.reshape(ROWS, COLS)
    if not np.isfinite(images).all() or (images < 0).any():
        raise UserError(f"{path}: images must be finite and >= 0")
    empty = ~(images > 0).any((1, 2))
    if empty.any():
        raise UserError(f"{path}: image {int(np.argmax(empty))} is empty (no loaded taxel)")
    cloud_list = []
    for i, c in enumerate(clouds):
        try:
            a = np.asarray(c, dtype=np.float64)
        except (TypeError, ValueError):
            a = None
        if a is None or a.ndim != 2 or a.shape[1] != 3 or a.shape[0] == 0:
            raise UserError(
                f"{path}: point cloud {i} must be a non-empty (P, 3) array, got {None if a is None else a.shape}"
            )
        a = a[np.isfinite(a).all(1)]
        if a.shape[0] == 0:
            raise UserError(f"{path}: point cloud {i} has no finite points")
        cloud_list.append(a)
    pose_types = doc.get("pose_type")
    if pose_types is None or len(pose_types) != n:
        pose_types = [""] * n
    return {"images": images, "clouds": cloud_list, "pose_type": [_text(p) for p in pose_types]}


def participant_folders(src: str | Path) -> list[Path]:
    """The participant folders under `src` (or `src` itself when it is one)."""
    src = Path(src)
    if not src.is_dir():
        raise UserError(f"no folder at {src}; give the release's real/ folder or one participant's (S103, ...)")
    if (src / INFO_FILE).is_file():
        return [src]
    found = sorted(p for p in src.iterdir() if p.is_dir() and (p / INFO_FILE).is_file())
    if not found:
        raise UserError(f"no participant folders (with {INFO_FILE}) under {src}")
    return found


def import_pressurepose_real(
    src: str | Path,
    out: str | Path,
    pose_sets: tuple[str, ...] = POSE_SETS,
    pressure: PressureScale = "release",
    bed_angle_deg: float = 0.0,
    cloud_frame: CloudFrame | None = None,
) -> dict:
    """PressurePose real participants -> one .npz (no pickles inside):
    pressure_mmhg (N, 64, 27) float32, row 0 at the head, scaled by `pressure` and clipped at
    100 mmHg; per frame subject, pose_set, pose_type, index, gender, height_m, mass_kg,
    bed_angle_deg; the clouds in our mat frame concatenated as cloud_points (P, 3) float32 m
    with cloud_offsets (N + 1,) (frame i: cloud_points[cloud_offsets[i]:cloud_offsets[i + 1]])."""
    from pressurepose.files import atomic_write

    bad = [s for s in pose_sets if s not in POSE_SETS]
    if bad or not pose_sets:
        raise UserError(f"pose sets must be among {POSE_SETS}, got {list(pose_sets)}")
    if not np.isfinite(bed_angle_deg) or not 0 <= bed_angle_deg <= 90:
        raise UserError(f"bed angle must lie in [0, 90] degrees, got {bed_angle_deg}")
    frame = cloud_frame or CloudFrame()
    cols: dict[str, list] = {
        k: [] for k in ("pressure_mmhg", "subject", "pose_set", "pose_type", "index", "gender", "height_m", "mass_kg")
    }
    clouds = []
    folders = participant_folders(src)
    for folder in folders:
        info = read_participant_info(folder)
        for pose_set in pose_sets:
            if not (folder / f"{pose_set}.p").is_file():
                log.warning("%s has no %s.p: skipped", folder, pose_set)
                continue
            d = read_pose_set(folder, pose_set)
            n = len(d["images"])
            cols["pressure_mmhg"].append(scale_images(d["images"], pressure, info["mass_kg"]))
            cols["subject"] += [folder.name] * n
            cols["pose_set"] += [pose_set] * n
            cols["pose_type"] += d["pose_type"]
            cols["index"] += list(range(n))
            cols["gender"] += [info["gender"]] * n
            cols["height_m"] += [info["height_m"]] * n
            cols["mass_kg"] += [info["mass_kg"]] * n
            clouds += [frame.to_mat(c) for c in d["clouds"]]
    if not clouds:
        raise UserError(f"no frames of {list(pose_sets)} under {src}")
    counts = np.array([len(c) for c in clouds], dtype=np.int64)
    arrays = {
        "pressure_mmhg": np.concatenate(cols["pressure_mmhg"]).astype(np.float32),
        "subject": np.array(cols["subject"]),
        "pose_set": np.array(cols["pose_set"]),
        "pose_type": np.array(cols["pose_type"]),
        "index": np.array(cols["index"], dtype=np.int64),
        "gender": np.array(cols["gender"]),
        "height_m": np.array(cols["height_m"]),
        "mass_kg": np.array(cols["mass_kg"]),
        "bed_angle_deg": np.full(len(clouds), float(bed_angle_deg)),
        "cloud_points": np.concatenate(clouds).astype(np.float32),
        "cloud_offsets": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
    }
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, lambda tmp: np.savez_compressed(tmp, **arrays))
    return {
        "frames": len(clouds),
        "participants": len(set(cols["subject"])),
        "points": int(counts.sum()),
        "out": str(out),
    }


def cloud_of(arrays, i: int) -> np.ndarray:
    """Frame i's cloud (P, 3) from an imported file's cloud_points / cloud_offsets."""
    lo, hi = int(arrays["cloud_offsets"][i]), int(arrays["cloud_offsets"][i + 1])
    return np.asarray(arrays["cloud_points"][lo:hi])


__all__ = [
    "CloudFrame",
    "POSE_SETS",
    "cloud_of",
    "import_pressurepose_real",
    "participant_folders",
    "read_participant_info",
    "read_pose_set",
    "scale_images",
]
