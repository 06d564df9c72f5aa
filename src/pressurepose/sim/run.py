"""One sample through the whole generator: initial pose -> sim #1 -> sim #2 -> sensor, labels.

`simulate_poses` is the pipeline `pressurepose simulate` (and dataset generation) runs;
`run_simulate` is the CLI's quick look at one sample: sample.npz (no pickles), simulate.json
and simulate.png (pressure image, depth map, the body at rest).
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
import torch

from pressurepose.body.model import BodyModel
from pressurepose.body.params import BodyParams
from pressurepose.errors import UserError
from pressurepose.files import atomic_write
from pressurepose.mat import MatSpec
from pressurepose.bed import BedShape
from pressurepose.sim.mattress import MattressParams

if TYPE_CHECKING:
    from pressurepose.sim.articulated import ArticulatedConfig
    from pressurepose.sim.settle import SettleConfig


@dataclasses.dataclass
class SimulatedSamples:
    """B samples after both simulations. Rejected samples carry a reason and zero images."""

    params: BodyParams             # resting pose (sim #1, then sim #2's shift and tilt on the root)
    vertices: torch.Tensor         # (B, V, 3) mesh at rest, mat frame
    joints: torch.Tensor           # (B, 24, 3) J24 at rest, mat frame
    pressure_mmhg: torch.Tensor    # (B, 64, 27) sensor reading
    depth_mm: torch.Tensor         # (B, 64, 27) Q
    contact: torch.Tensor          # (B, 64, 27) C
    mass_kg: torch.Tensor          # (B,)
    reason: list[str]              # "" = accepted
    settle_steps: np.ndarray
    settle_ms: np.ndarray
    press_ms: float                # sim #2 wall time for the batch
    sink_m: np.ndarray             # sim #2 deepest compression
    head_angle_deg: np.ndarray     # (B,) the bed each sample rests on (0: flat)


def settle_config_for(partition: str) -> SettleConfig:
    """Sim #1's settings for a sampling partition (its trunk roll hold; else the defaults)."""
    from pressurepose.sampling.partitions import get_partition
    from pressurepose.sim.settle import SettleConfig

    return SettleConfig(hold_roll_m=get_partition(partition).hold_roll_m)


def simulate_poses(model: BodyModel, params: BodyParams, mattress: MattressParams | None = None,
                   mat: MatSpec | None = None, seed: int = 0,
                   bed: BedShape | Sequence[BedShape] | None = None,
                   settle_config: SettleConfig | None = None,
                   settle: Literal["mujoco", "articulated", "none"] = "mujoco",
                   sim2: Literal["rigid", "articulated"] = "rigid",
                   articulated: ArticulatedConfig | None = None) -> SimulatedSamples:
    """Settle (sim #1), press (sim #2), read (sensor) and label B initial poses on a flat bed,
    a bent one (`bed`), or one bed per sample (a sequence of B, e.g. `InitialPoses.beds()`:
    samples on the same bed are simulated together, results come back in input order).
    `settle_config`: sim #1's settings (default `SettleConfig()`; `settle_config_for` gives a
    partition's). `settle="none"` skips sim #1 (the poses rest as drawn); `sim2`: the whole mesh
    at rigid rest, or every body part on its own contact (`sim.articulated`; on flat beds,
    raised beds keep the rigid rest). `settle="articulated"`: one mechanics - the articulated
    rest settles the drawn pose itself (joint springs, self-contact, the soft bed; no MuJoCo)
    and its field is the image, whatever `sim2` says; raised beds fall back to MuJoCo and the
    rigid rest."""
    if settle not in ("mujoco", "articulated", "none") or sim2 not in ("rigid", "articulated"):
        raise ValueError(f"settle must be 'mujoco', 'articulated' or 'none' and sim2 'rigid' or 'articulated', "
                         f"got {settle!r}, {sim2!r}")
    options = {"settle": settle, "sim2": sim2, "articulated": articulated}
    mattress = mattress or MattressParams()
    mat = mat or MatSpec()
    if bed is None or isinstance(bed, BedShape):
        return _simulate_one_bed(model, params, mattress, mat, seed, bed or BedShape(), settle_config, **options)
    beds = list(bed)
    if len(beds) != params.batch_size or not all(isinstance(b, BedShape) for b in beds):
        raise UserError(f"bed must be one BedShape or a sequence of {params.batch_size} (one per sample), "
                         f"got {len(beds)} items")
    groups: dict[BedShape, list[int]] = {}
    for i, b in enumerate(beds):
        groups.setdefault(b, []).append(i)
    if len(groups) == 1:
        return _simulate_one_bed(model, params, mattress, mat, seed, beds[0], settle_config, **options)
    parts, order = [], []
    for k, (b, rows) in enumerate(groups.items()):
        parts.append(_simulate_one_bed(model, params.index(torch.tensor(rows)), mattress, mat, seed + 7919 * k, b,
                                       settle_config, **options))
        order += rows
    back = torch.from_numpy(np.argsort(np.array(order)))
    return _concat(parts, back)


def _concat(parts: list[SimulatedSamples], back: torch.Tensor) -> SimulatedSamples:
    """Samples of several bed groups, put back in input order (`back` indexes the
    concatenation)."""
    cat_t = lambda name: torch.cat([getattr(p, name) for p in parts])[back]  # noqa: E731
    cat_n = lambda name: np.concatenate([getattr(p, name) for p in parts])[back.numpy()]  # noqa: E731
    params = BodyParams.cat([p.params for p in parts]).index(back)
    reason = [r for p in parts for r in p.reason]
    return SimulatedSamples(
        params=params, vertices=cat_t("vertices"), joints=cat_t("joints"), pressure_mmhg=cat_t("pressure_mmhg"),
        depth_mm=cat_t("depth_mm"), contact=cat_t("contact"), mass_kg=cat_t("mass_kg"),
        reason=[reason[i] for i in back.tolist()], settle_steps=cat_n("settle_steps"), settle_ms=cat_n("settle_ms"),
        press_ms=sum(p.press_ms for p in parts), sink_m=cat_n("sink_m"), head_angle_deg=cat_n("head_angle_deg"),
    )


def _simulate_one_bed(model: BodyModel, params: BodyParams, mattress: MattressParams, mat: MatSpec,
                      seed: int, bed: BedShape, settle_config: SettleConfig | None = None, settle: str = "mujoco",
                      sim2: str = "rigid", articulated: ArticulatedConfig | None = None) -> SimulatedSamples:
    from pressurepose.sim.foundation import simulate_pressure, taxel_pressure
    from pressurepose.sim.sensor import label_maps, sensing_area, taxel_reading
    from pressurepose.sim.settle import as_float64, settle as settle_bodies

    model64 = as_float64(model)
    B = params.batch_size
    if settle == "articulated":
        settle, sim2 = ("none", "articulated") if bed.flat else ("mujoco", "rigid")
    if settle == "mujoco":
        settled = settle_bodies(model64, params, mattress, mat, config=settle_config, bed=bed)
        rest, reason1, steps, settle_ms = settled.params, settled.reason, settled.steps, settled.wall_ms
    else:
        rest, reason1, steps, settle_ms = params.to(dtype=torch.float64), [""] * B, np.zeros(B, dtype=np.int64), np.zeros(B)
    mass = model64.measure(rest.shape).mass_kg
    t0 = time.perf_counter()
    if sim2 == "articulated" and bed.flat:  # raised beds keep the rigid rest (docs/physics.md)
        from pressurepose.sim.articulated import rest_articulated

        art = rest_articulated(model64, rest, mass, mattress, mat, articulated)
        pressure_pa, failure2, sink = taxel_pressure(art.foundation_pa, mattress, mat, art.sub), art.failure, art.max_compression_m
        shifted, vertices, joints = art.params, art.vertices, art.joints
    else:
        out = model64(rest)
        pressed = simulate_pressure(out.vertices, out.faces, mass, mattress, mat, bed=bed)
        pressure_pa, failure2, sink = pressed.pressure_pa, pressed.failure, pressed.max_compression_m
        # Fold sim #2's rigid motion into the root so parameters reproduce the mesh; the
        # joints ride the same motion.
        shifted = _apply_rest_to_root(rest, pressed)
        R, t = pressed.rotation.detach(), pressed.translation.detach()
        vertices, joints = pressed.vertices.detach(), out.joints @ R.transpose(1, 2) + t[:, None]
    press_ms = (time.perf_counter() - t0) * 1e3
    gen = torch.Generator().manual_seed(seed)
    reading = taxel_reading(sensing_area(pressure_pa, mat).detach(), mattress, mat, generator=gen)
    depth, contact = label_maps(vertices.detach(), model64.faces, mat, bed)
    reason = [f"sim #1: {r1}" if r1 else (f"sim #2: {r2}" if r2 else "")
              for r1, r2 in zip(reason1, failure2)]
    bad = torch.tensor([bool(r) for r in reason])
    reading = torch.where(bad[:, None, None], torch.zeros_like(reading), reading)
    return SimulatedSamples(
        params=shifted, vertices=vertices.detach(), joints=joints.detach(), pressure_mmhg=reading,
        depth_mm=depth, contact=contact, mass_kg=mass, reason=reason, settle_steps=steps,
        settle_ms=settle_ms, press_ms=press_ms, sink_m=sink.detach().numpy(),
        head_angle_deg=np.full(params.batch_size, float(bed.head_angle_deg)),
    )


def _apply_rest_to_root(params: BodyParams, pressed) -> BodyParams:
    """Sim #2 moved the rigid mesh by v -> R v + t; the same motion of the root (rotation on
    top of the supine reference, pelvis position) makes the parameters reproduce the mesh."""
    from pressurepose.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle

    R, t = pressed.rotation.detach(), pressed.translation.detach()
    root = matrix_to_axis_angle(R @ axis_angle_to_matrix(params.root_rotation))
    pelvis = (R @ params.root_translation[..., None])[..., 0] + t
    return params.replace(root_rotation=root, root_translation=pelvis)


@dataclasses.dataclass(frozen=True)
class SimulateConfig:
    """Simulate one sample of a partition: both simulations, the image and a figure."""

    out: Path = Path("out/simulate")
    """Output folder (created)."""
    partition: str = "supine"
    """general, supine, hands_behind_head, prone_hands_up, crossed_legs, straight_limbs,
    half_sitting (head of the bed raised 10-60 deg), lateral (on either side, legs drawn up) or
    lateral_straight (on either side, legs nearly straight; the trunk roll held in sim #1)."""
    gender: Literal["female", "male"] = "female"
    over_bed: bool = False
    seed: int = 0
    index: int = 0
    """Sample index: the sample is a function of (seed, partition, gender, over_bed, index)."""
    params: Path | None = None
    """Mattress/sensor parameter file (JSON from `pressurepose calibrate`); default: built-in."""
    head_angle_deg: float | None = None
    """Raise the head of the bed (0-70 degrees, hinge at sensing row 48 from the foot).
    Default: the bed the sample was drawn for (flat, or the half_sitting partition's angle)."""
    backend: Literal["anny", "smpl"] = "anny"
    smpl_dir: Path | None = None


def run_simulate(cfg: SimulateConfig) -> dict[str, Path]:
    from pressurepose.body import load_body_model
    from pressurepose.sampling.partitions import SamplingConfig
    from pressurepose.sampling.sampler import PoseSampler

    if cfg.index < 0:
        raise UserError(f"index must be >= 0, got {cfg.index}")
    mattress = MattressParams.load(cfg.params) if cfg.params is not None else MattressParams()
    options = {"model_dir": cfg.smpl_dir} if cfg.backend == "smpl" else {}
    model = load_body_model(cfg.backend, dtype=torch.float64, **options)
    sampling = SamplingConfig(partition=cfg.partition, gender=cfg.gender, over_bed=cfg.over_bed, seed=cfg.seed)
    t0 = time.perf_counter()
    initial = PoseSampler(model, sampling).sample([cfg.index])
    t1 = time.perf_counter()
    bed = initial.beds()[0]
    if cfg.head_angle_deg is not None:
        if sampling.spec.raised and cfg.head_angle_deg != bed.head_angle_deg:
            raise UserError(f"partition {cfg.partition!r} sits sample {cfg.index} up on a bed raised "
                             f"{bed.head_angle_deg:g} deg; leave out --head-angle-deg (or pick another index)")
        bed = BedShape(cfg.head_angle_deg)
    sim = simulate_poses(model, initial.params, mattress, seed=cfg.seed * 1_000_003 + cfg.index, bed=bed,
                         settle_config=settle_config_for(cfg.partition))
    t2 = time.perf_counter()
    cfg.out.mkdir(parents=True, exist_ok=True)
    reason = sim.reason[0]
    p = sim.pressure_mmhg[0].numpy()
    mat = MatSpec()
    record = {
        "command": "simulate",
        "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(cfg).items()},
        "mattress": mattress.to_dict(),
        "status": "rejected" if reason else "ok",
        "reason": reason,
        "mass_kg": round(float(sim.mass_kg[0]), 3),
        "settle_steps": int(sim.settle_steps[0]),
        "timing_ms": {"sample": round((t1 - t0) * 1e3, 1), "sim1": round(float(sim.settle_ms[0]), 1),
                      "sim2": round(sim.press_ms, 1), "total": round((t2 - t0) * 1e3, 1)},
        "contact_area_m2": round(float((p > 0).sum() * mat.taxel_area_m2), 4),
        "mean_contact_pressure_mmhg": round(float(p[p > 0].mean()) if (p > 0).any() else 0.0, 2),
        "peak_pressure_mmhg": round(float(p.max()), 2),
        "sink_mm": round(float(sim.sink_m[0]) * 1e3, 1),
        "head_angle_deg": bed.head_angle_deg,
    }
    paths = {}
    arrays = {
        "pressure_mmhg": p.astype(np.float32), "depth_mm": sim.depth_mm[0].numpy().astype(np.float32),
        "contact": sim.contact[0].numpy().astype(np.uint8), "shape": sim.params.shape[0].numpy(),
        "root_rotation": sim.params.root_rotation[0].numpy(), "root_translation": sim.params.root_translation[0].numpy(),
        "pose": sim.params.pose[0].numpy(), "joints": sim.joints[0].numpy(), "mass_kg": sim.mass_kg[:1].numpy(),
    }
    if not reason:
        paths["sample"] = atomic_write(cfg.out / "sample.npz", lambda tmp: np.savez_compressed(tmp, **arrays))
        from pressurepose.viz.simulation import plot_sample

        title = (f"{cfg.partition}, {cfg.gender}, index {cfg.index}: {record['mass_kg']} kg, "
                 f"area {record['contact_area_m2']} m^2, mean {record['mean_contact_pressure_mmhg']} mmHg, "
                 f"peak {record['peak_pressure_mmhg']} mmHg")
        profile = None
        if not bed.flat:
            (x0, x1), _ = mat.mattress_bounds_m
            s_pts = torch.tensor([[x0, 0.0, 0.0], [bed.hinge_x(mat), 0.0, 0.0], [x1, 0.0, 0.0]], dtype=torch.float64)
            profile = bed.to_world(s_pts, mat)[:, [0, 2]].numpy()
            title += f", head of the bed {bed.head_angle_deg:g} deg"
        paths["figure"] = plot_sample(cfg.out / "simulate.png", p, arrays["depth_mm"], sim.vertices[0].numpy(),
                                      title, bed_profile=profile)
    record["files"] = {k: v.name for k, v in paths.items()}
    paths["record"] = atomic_write(cfg.out / "simulate.json", lambda tmp: Path(tmp).write_text(json.dumps(record, indent=1)))
    if reason:
        raise UserError(f"sample {cfg.index} of {cfg.partition}/{cfg.gender} was rejected ({reason}); "
                         f"the generator skips such samples - try another --index (details in {paths['record']})")
    return paths



__all__ = ["SimulateConfig", "SimulatedSamples", "run_simulate", "settle_config_for", "simulate_poses"]
