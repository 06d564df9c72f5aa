"""`pressurepose realism`: simulated pressure images against real frames of known posture,
height and weight (docs/realism.md).

Real frames: PmatData experiment II by default (flat bed: supine group B, right C, left D),
or any folder in its layout (`index.csv` with the columns file, subject, mattress, group,
index, posture, body_roll_deg, bed_incline_deg, height_cm, weight_kg; frames as text files of
64 lines of 27 raw readings, row 0 at the foot). Simulated: one body per real frame (Anny,
fitted to the subject's height and weight) in the posture's resting pose, lying where that
frame's load lay, through the generator's simulations. Writes report.md, report.json and figures (mean real vs mean
simulated image, profiles along and across the bed) to --out.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from pressurepose.commands.realism_report import bands_dict, markdown, set_dict
from pressurepose.commands.realism_tilted import load_tilted, tilted_rows
from pressurepose.errors import UserError
from pressurepose.eval import realism as R
from pressurepose.files import write_text

POSTURES = ("supine", "left", "right")
ROLL_RAD = {"supine": 0.0, "left": -math.pi / 2, "right": math.pi / 2}
SIDE_MARGIN_M = 0.20
# The side-lying resting pose (rad): the arms forward at about a right angle to the trunk with
# the elbows bent about a right angle (the common side-sleeping posture; the along-bed figure's
# sensitivity to this choice is in docs/realism.md), hips and knees bent.
SIDE_POSE = {"shoulder": 1.6, "elbow": 1.5, "hip": 0.6, "knee": 0.9}


@dataclasses.dataclass(frozen=True)
class RealismConfig:
    """Compare simulated images with real ones (docs/realism.md)."""

    out: Path = Path("out/realism")
    """Output folder (report.md, report.json, figures)."""
    real: Path = Path("pmatdata")
    """Folder of real frames in PmatData's layout; "pmatdata" = the packaged copy."""
    sim2: Literal["articulated", "rigid"] = "articulated"
    """Sim #2: every body part resting on its own contact, or the whole mesh as one rigid body."""
    settle: Literal["none", "mujoco"] = "none"
    """Sim #1 before sim #2 (MuJoCo settling of the capsule body) or none (the pose as drawn)."""
    params: Path | None = None
    """Mattress/sensor parameter file or preset (sponge, air) for every set; default: each real
    set's own mattress preset (articulated sim #2) or the built-in bed (rigid)."""
    threshold: float = 20.0
    """Noise threshold (raw units) of the real frames."""
    bed_width_cols: int = 37
    """Width of the simulated mattress in taxel columns (the mat's 27 centred on it): PmatData's
    bed is wider than its mat (side-lying subjects' knees reach the mat's edge); the
    generator's default is the seed's 33."""
    placement: Literal["real", "centre"] = "real"
    """Where the simulated bodies lie: one per real frame at that frame's centre of pressure and
    long-axis angle (the same scene), or all at the mat's centre, straight."""
    pillow_m: float = 0.0
    """Every simulated head on a pillow of this free thickness (m; `sim.pillow`, the articulated
    sim #2 only); 0: none."""
    match_floor: bool = False
    """Read the simulated images again as the real set's are: nothing below the set's lowest
    reading (`eval.realism.reading_floor`, 3.0-3.8 mmHg for PmatData), the force kept. Off (the
    default since session 44): the images as the generator writes them, read from the sensor's
    own floor (`MattressParams.floor_mmhg`: the presets' 3.31 / 3.61 mmHg, PmatData's), so the
    report judges what a network trains on (docs/realism.md "The sensor's floor in the generator")."""
    model: Path | None = Path("default")
    """Heatmap network that reads the real frames and their simulated twins: how sharply its heatmaps
    pin the head and torso on each (`eval.real.trunk_spread`; docs/network.md "How far to trust a
    joint"), the generator's realism through the estimator's eyes; "default" = the packaged model,
    None: skip."""
    raised: bool = True
    """Also the raised beds (PmatData group F, the head of the bed at 0-60 deg) against bodies
    half-sitting on them, with the articulated sim #2 (`commands.realism_raised`; ~60 s more)."""
    tilted: bool = True
    """Also the tilted bodies (PmatData group E, 20 or 40 deg on wedges or a pillow) against twins
    on the `tilted` partition's wedge, with the articulated sim #2 (`commands.realism_tilted`; ~90 s more)."""

    def __post_init__(self) -> None:
        from pressurepose.sim.pillow import check_thickness

        check_thickness(self.pillow_m)
        if self.pillow_m > 0 and self.sim2 != "articulated":
            raise UserError("--pillow-m needs the articulated sim #2 (--sim2 articulated, the default)")


@dataclasses.dataclass(frozen=True)
class RealSubject:
    subject: int
    height_m: float
    mass_kg: float


def load_real(
    root: Path, threshold: float
) -> tuple[dict[tuple[str, str], tuple[np.ndarray, np.ndarray, np.ndarray]], list[RealSubject]]:
    """Real frames of the flat bed per (posture, mattress): images (N, 64, 27) mmHg, heights
    (N,) m and subject ids (N,); and the subjects."""
    from pressurepose.data.pmatdata import distinct_frames, load_images, load_index, subjects_of
    from pressurepose.samples import resolve_pmatdata

    root = resolve_pmatdata(root)
    records = [r for r in load_index(root) if r.bed_incline_deg == 0 and r.posture in POSTURES and r.group != "E"]
    records = distinct_frames(records)  # PmatData repeats subject 4's frames as subject 8's
    if not records:
        raise UserError(
            f"{root / 'index.csv'}: no flat-bed supine, left or right frames (columns posture, "
            "bed_incline_deg); see docs/realism.md for the format"
        )
    out = {}
    for posture in POSTURES:
        for mattress in sorted({r.mattress for r in records}):
            rs = [r for r in records if r.posture == posture and r.mattress == mattress]
            if rs:
                out[(posture, mattress)] = (
                    load_images(rs, threshold),
                    np.array([r.height_cm / 100 for r in rs]),
                    np.array([r.subject for r in rs]),
                )
    return out, [RealSubject(*s) for s in subjects_of(records)]


def resting_pose(posture: str, batch: int, side_pose: dict[str, float] | None = None) -> torch.Tensor:
    """(B, 23, 3) the report's pose: supine in the home pose (arms at the sides, legs
    straight); on a side with the hips bent 35 deg, the knees 50 deg, the arms forward ~90 deg and
    the elbows bent ~85 deg, as people lie on their side (PmatData groups C, D). `side_pose`:
    other side-lying angles (SIDE_POSE's keys, rad)."""
    from pressurepose.body.capsules import home_pose
    from pressurepose.body.joints import joint_index
    from pressurepose.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle

    pose = home_pose(batch)
    if posture == "supine":
        return pose
    angles = SIDE_POSE if side_pose is None else side_pose
    forward = axis_angle_to_matrix(torch.tensor([-angles["shoulder"], 0.0, 0.0], dtype=pose.dtype))
    for side, sign in (("left", -1.0), ("right", 1.0)):
        j = joint_index(f"{side}_shoulder") - 1
        pose[:, j] = matrix_to_axis_angle(forward @ axis_angle_to_matrix(pose[:, j]))
        pose[:, joint_index(f"{side}_elbow") - 1, 1] = sign * angles["elbow"]
        pose[:, joint_index(f"{side}_hip") - 1, 0] = -angles["hip"]
        pose[:, joint_index(f"{side}_knee") - 1, 0] = angles["knee"]
    return pose


def frame_placement(images: np.ndarray, pitch_row_m: float, pitch_col_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Centre of pressure (N, 2) (x along, y across, m, mat frame) and the angle (N,) rad of the
    load's long axis from the bed's axis (principal axis of the pressure's second moments)."""
    rows, cols = images.shape[1:]
    x = (np.arange(rows) + 0.5) * pitch_row_m
    y = (np.arange(cols) + 0.5) * pitch_col_m
    w = images / images.sum((1, 2), keepdims=True)
    cx = (w.sum(2) * x).sum(1)
    cy = (w.sum(1) * y).sum(1)
    dx, dy = x[None, :, None] - cx[:, None, None], y[None, None, :] - cy[:, None, None]
    sxx, syy, sxy = (w * dx**2).sum((1, 2)), (w * dy**2).sum((1, 2)), (w * dx * dy).sum((1, 2))
    return np.stack([cx, cy], 1), 0.5 * np.arctan2(2 * sxy, sxx - syy)


def set_mattress(cfg: RealismConfig, name: str | None, fixed=None):
    """The bed a real set's simulated bodies rest on: `fixed` (the caller's or --params's
    `MattressParams`) when given; else the articulated sim #2 on the set's mattress preset (air,
    sponge), the rigid one on the class defaults (its own fit)."""
    from pressurepose.sim.mattress import PRESETS, MattressParams

    if fixed is not None:
        return fixed
    if cfg.sim2 == "articulated" and name in PRESETS:
        return MattressParams.preset(name)
    return MattressParams()


def simulate_subjects(
    subjects: list[RealSubject], cfg: RealismConfig, mattress=None, articulated=None, scenes: dict | None = None
):
    """Side-lying bodies hold their trunk's roll (sampling.partitions.HOLD_ROLL_M, in both
    simulations), as the generator's `lateral_straight` partition does. Per posture (or per
    (posture, mattress) with `scenes`): sensor images (N, 64, 27) mmHg of the accepted bodies,
    their heights (N,), the rejection reasons, the seconds it took and how many of the accepted
    bodies were still moving when the articulated rest's re-posings ran out.
    `scenes[(posture, mattress)] = (subject ids (N,), centres (N, 2) m, angles (N,) rad)`: one
    body per real frame, its centre of mass over the frame's centre of pressure, turned by its
    angle; without it one body per subject at the mat's centre."""
    from pressurepose.body import load_body_model
    from pressurepose.body.fit_shape import shape_for_height_mass
    from pressurepose.body.params import BodyParams
    from pressurepose.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle
    from pressurepose.maps import mesh_centroid
    from pressurepose.mat import MatSpec
    from pressurepose.sampling.partitions import HOLD_ROLL_M
    from pressurepose.sim.articulated import ArticulatedConfig
    from pressurepose.sim.mattress import MattressParams
    from pressurepose.sim.run import simulate_poses
    from pressurepose.sim.settle_config import SettleConfig

    fixed = mattress or (MattressParams.load(cfg.params) if cfg.params else None)

    mat = MatSpec(covered_cols=cfg.bed_width_cols)
    model = load_body_model("anny", dtype=torch.float64)
    heights = torch.tensor([s.height_m for s in subjects], dtype=torch.float64)
    masses = torch.tensor([s.mass_kg for s in subjects], dtype=torch.float64)
    shapes, h, _ = shape_for_height_mass(model, heights, masses, female=0.0)
    row_of = {s.subject: i for i, s in enumerate(subjects)}
    if scenes is None:
        centre = np.array([[0.85, mat.sensing_width_m / 2]] * len(subjects))
        scenes = {
            (p, None): (np.array([s.subject for s in subjects]), centre, np.zeros(len(subjects))) for p in POSTURES
        }
    out = {}
    for (posture, mattress_name), (ids, centres, angles) in scenes.items():
        idx = torch.tensor([row_of[int(i)] for i in ids])
        B = len(idx)
        roll = axis_angle_to_matrix(torch.tensor([[ROLL_RAD[posture], 0.0, 0.0]] * B, dtype=torch.float64))
        yaw = axis_angle_to_matrix(torch.from_numpy(np.stack([np.zeros(B), np.zeros(B), angles], 1)))
        params = BodyParams.zeros(B, shapes[idx]).replace(
            pose=resting_pose(posture, B), root_rotation=matrix_to_axis_angle(yaw @ roll)
        )
        # The centre of mass over the target point (the rest keeps the horizontal placement).
        com = mesh_centroid(model(params).vertices, model.faces)
        # Real subjects lie up to 0.22 m off the mat's centre line; a side-lying body placed
        # that far out on the simulated mattress would hang its knees and arms over the edge
        # and roll off. Keep the centre of mass within SIDE_MARGIN_M of the centre line.
        target = torch.from_numpy(np.asarray(centres, dtype=np.float64)).clone()
        mid = mat.sensing_width_m / 2
        target[:, 1] = target[:, 1].clamp(mid - SIDE_MARGIN_M, mid + SIDE_MARGIN_M)
        params = params.replace(
            root_translation=torch.cat([target - com[:, :2], torch.full((B, 1), 0.3, dtype=torch.float64)], 1)
        )
        t0 = time.perf_counter()
        art = articulated or ArticulatedConfig()
        if posture != "supine" and art.hold_roll_m == 0:
            art = dataclasses.replace(art, hold_roll_m=HOLD_ROLL_M)
        settle_config = SettleConfig(hold_roll_m=HOLD_ROLL_M) if posture != "supine" else None
        sim = simulate_poses(
            model,
            params,
            set_mattress(cfg, mattress_name, fixed),
            mat,
            settle=cfg.settle,
            sim2=cfg.sim2,
            articulated=art,
            settle_config=settle_config,
            pillow_m=torch.full((B,), float(cfg.pillow_m)) if cfg.pillow_m > 0 else None,
        )
        ok = [i for i, r in enumerate(sim.reason) if not r]
        # The articulated rests the re-posings' cap ended with the body still moving (their
        # settle_steps are outer + 1; with sim #1 the steps are MuJoCo's, none counted).
        moving = int((sim.settle_steps[ok] > art.outer).sum()) if cfg.settle == "none" else 0
        out[(posture, mattress_name)] = (
            sim.pressure_mmhg[ok].numpy(),
            h.numpy()[idx.numpy()][ok],
            [r for r in sim.reason if r],
            time.perf_counter() - t0,
            moving,
        )
    return out


def real_scenes(real: dict, cfg: RealismConfig) -> dict | None:
    """The simulated scenes matching the real frames (`simulate_subjects`' scenes), or None for
    placement "centre"."""
    if cfg.placement == "centre":
        return None
    from pressurepose.mat import MatSpec

    mat = MatSpec()
    scenes = {}
    for key, (imgs, _, subj) in real.items():
        centres, angles = frame_placement(imgs, mat.pitch_row_m, mat.pitch_col_m)
        scenes[key] = (subj, centres, angles)
    return scenes


def _readers(model: Path | None):
    """(images (N, 64, 27) mmHg -> `eval.real.trunk_spread`, images -> the roll read (N,) deg) by
    the model, or (None, None) without one; a network without heatmaps is refused."""
    if model is None:
        return None, None
    from pressurepose.eval.real import read_bodies, trunk_spread
    from pressurepose.train.checkpoint import load_network

    net = load_network(model)[0]
    if net.config.arch != "heatmap" or net.config.height_weight:
        raise UserError(f"--model {model} must be a heatmap network without height and mass inputs (or None)")
    tensor = lambda images: torch.as_tensor(np.asarray(images), dtype=torch.float32)  # noqa: E731
    return lambda x: trunk_spread(net, tensor(x)), lambda x: read_bodies(net, tensor(x)).roll_deg.numpy()


def run_realism(cfg: RealismConfig) -> dict[str, Path]:
    from pressurepose.mat import MatSpec

    mat = MatSpec()
    real, subjects = load_real(cfg.real, cfg.threshold)
    spread, rolls = _readers(cfg.model)  # a bad --model or group E row stops the run before the simulations
    tilted_real = load_tilted(cfg.real, cfg.threshold) if cfg.tilted and cfg.sim2 == "articulated" else {}
    scenes = real_scenes(real, cfg)
    sims = simulate_subjects(subjects, cfg, scenes=scenes)
    pitch = (mat.pitch_row_m, mat.pitch_col_m)
    real_sets = {key: R.summarise(imgs, hts, *pitch) for key, (imgs, hts, _) in real.items()}
    rows, ceilings, figures = [], [], {}
    for posture in POSTURES:
        for (p, mattress), (imgs, hts, subj) in real.items():
            if p != posture:
                continue
            images, heights, reasons, seconds, moving = sims[(posture, mattress if scenes else None)]
            floor = R.reading_floor(imgs) if cfg.match_floor else 0.0
            if len(images) and floor > 0:
                images = R.read_with_floor(images, floor)
            sim_set = R.summarise(images, heights, *pitch) if len(images) else None
            real_set = real_sets[(p, mattress)]
            row = {
                "posture": posture,
                "mattress": mattress,
                "real": set_dict(real_set),
                "simulated": set_dict(sim_set) if sim_set else None,
                "rejected": reasons,
                "simulated_bodies": int(len(images)),
                "still_moving": moving,
                "floor_mmhg": round(floor, 2),
                "sim_seconds": round(seconds, 2),
            }
            if spread is not None:
                row["trunk_spread"] = {"real": spread(imgs), "simulated": spread(images)}
            if sim_set:
                row["comparison"] = dataclasses.asdict(R.compare(real_set, sim_set))
                figures[(posture, mattress)] = (real_set, sim_set)
                # Transverse bands at the pitch the real frames show (air cells, docs/realism.md).
                real_bands = R.fit_bands(imgs, pitch[0])
                sim_bands = R.fit_bands(images, pitch[0], real_bands.period_m)
                row["bands"] = {"real": bands_dict(real_bands), "simulated": bands_dict(sim_bands)}
            rows.append(row)
            # Ceiling: real against real, first half of the subjects against the second.
            ids = sorted(set(subj.tolist()))
            if len(ids) >= 2:
                a = np.isin(subj, ids[: len(ids) // 2])
                c = R.compare(R.summarise(imgs[a], hts[a], *pitch), R.summarise(imgs[~a], hts[~a], *pitch))
                ceilings.append(
                    {
                        "posture": posture,
                        "between": f"{mattress}: subjects {ids[: len(ids) // 2]} vs rest",
                        **dataclasses.asdict(c),
                    }
                )
        mats = sorted(m for (p, m) in real if p == posture)
        if len(mats) == 2:
            c = R.compare(real_sets[(posture, mats[0])], real_sets[(posture, mats[1])])
            ceilings.append({"posture": posture, "between": f"{mats[0]} vs {mats[1]}", **dataclasses.asdict(c)})
    raised = []
    if cfg.raised and cfg.sim2 == "articulated":
        from pressurepose.commands.realism_raised import load_raised, raised_rows

        raised = raised_rows(load_raised(cfg.real, cfg.threshold), cfg)
    tilted = tilted_rows(tilted_real, cfg, rolls) if tilted_real else []
    cfg.out.mkdir(parents=True, exist_ok=True)
    record = {
        "command": "realism",
        "config": {k: str(v) for k, v in dataclasses.asdict(cfg).items()},
        "rows": rows,
        "ceilings": ceilings,
        "raised": raised,
        "tilted": tilted,
    }
    paths = {"json": write_text(cfg.out / "report.json", json.dumps(record, indent=1))}
    paths["markdown"] = write_text(cfg.out / "report.md", markdown(record))
    from pressurepose.viz.realism import plot_realism

    for (posture, mattress), (a, b) in figures.items():
        paths[f"{posture}_{mattress}"] = plot_realism(
            cfg.out / f"realism_{posture}_{mattress}.png", a, b, f"{posture}, {mattress} mattress"
        )
    return paths


def realism(cfg: RealismConfig) -> None:
    """Simulated pressure images against real ones of known posture, height and weight (PmatData
    by default): area, pressure, coverage, profiles, load per region, the real-vs-real ceiling."""
    paths = run_realism(cfg)
    print(Path(paths["markdown"]).read_text())
    print(f"realism report: {paths['markdown']}")


__all__ = [
    "RealismConfig",
    "realism",
    "frame_placement",
    "load_real",
    "real_scenes",
    "resting_pose",
    "run_realism",
    "set_mattress",
    "simulate_subjects",
]
