"""`pressurepose simulate`: one sample of a partition through both simulations, the CLI's quick
look: sample.npz (no pickles), simulate.json and simulate.png (pressure image, depth map, the
body at rest)."""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from pressurepose.bed import BedShape
from pressurepose.body import load_body_model
from pressurepose.commands.outputs import Written, flat_config
from pressurepose.errors import UserError
from pressurepose.files import atomic_write, write_text
from pressurepose.mat import MatSpec
from pressurepose.sampling.partitions import SamplingConfig
from pressurepose.sampling.sampler import PoseSampler
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.pillow import check_thickness
from pressurepose.sim.run import articulated_config_for, default_mattress, settle_config_for, simulate_poses
from pressurepose.viz.simulation import plot_sample


@dataclasses.dataclass(frozen=True)
class SimulateConfig:
    """Simulate one sample of a partition: both simulations, the image and a figure."""

    out: Path = Path("out/simulate")
    """Output folder (created)."""
    sampling: SamplingConfig = SamplingConfig(partition="supine")
    """Partition, gender, over_bed, seed and the sampler's attempt limits."""
    index: int = 0
    """Sample index: the sample is a function of (seed, partition, gender, over_bed, index)."""
    params: Path | None = None
    """Mattress/sensor parameter file (JSON from `pressurepose calibrate`); default: built-in."""
    head_angle_deg: float | None = None
    """Raise the head of the bed (0-70 degrees, hinge at sensing row 48 from the foot).
    Default: the bed the sample was drawn for (flat, or the half_sitting partition's angle)."""
    settle: Literal["articulated", "mujoco"] = "articulated"
    """How the pose comes to rest, as `generate --settle`: the articulated engine (default; the
    sponge bed) or MuJoCo then the rigid sim #2 (the class-default bed)."""
    pillow_m: float = 0.0
    """The head on a pillow of this free thickness (m; the articulated engine on a flat bed,
    `sim.pillow`, docs/physics.md "Pillow"); 0: none."""
    backend: Literal["anny", "smpl"] = "anny"
    smpl_dir: Path | None = None


def run_simulate(cfg: SimulateConfig) -> Written:
    if cfg.index < 0:
        raise UserError(f"index must be >= 0, got {cfg.index}")
    check_thickness(cfg.pillow_m)
    if cfg.pillow_m > 0 and cfg.settle != "articulated":
        raise UserError("--pillow-m needs the articulated engine (--settle articulated, the default)")
    if cfg.sampling.spec.wedge and cfg.head_angle_deg:
        raise UserError(
            f"partition {cfg.sampling.partition} rests on wedges, which lie on flat beds only: leave out --head-angle-deg"
        )
    if cfg.sampling.spec.wedge and cfg.settle != "articulated":
        raise UserError(
            f"partition {cfg.sampling.partition} rests on wedges: it needs --settle articulated (the default)"
        )
    mattress = MattressParams.load(cfg.params) if cfg.params is not None else default_mattress(cfg.settle)
    options = {"model_dir": cfg.smpl_dir} if cfg.backend == "smpl" else {}
    model = load_body_model(cfg.backend, dtype=torch.float64, **options)
    sampling = cfg.sampling
    t0 = time.perf_counter()
    initial = PoseSampler(model, sampling).sample([cfg.index])
    t1 = time.perf_counter()
    bed = initial.beds()[0]
    if cfg.head_angle_deg is not None:
        if sampling.spec.raised and cfg.head_angle_deg != bed.head_angle_deg:
            raise UserError(
                f"partition {sampling.partition!r} sits sample {cfg.index} up on a bed raised "
                f"{bed.head_angle_deg:g} deg; leave out --head-angle-deg (or pick another index)"
            )
        bed = BedShape(cfg.head_angle_deg)
    if cfg.pillow_m > 0 and not bed.flat:
        raise UserError(
            f"--pillow-m: pillows lie on flat beds only, and this sample's bed is raised {bed.head_angle_deg:g} deg;"
            " leave out --pillow-m (or --head-angle-deg, or pick a flat partition)"
        )
    sim = simulate_poses(
        model,
        initial.params,
        mattress,
        seed=sampling.seed * 1_000_003 + cfg.index,
        bed=bed,
        settle_config=settle_config_for(sampling.partition),
        settle=cfg.settle,
        articulated=articulated_config_for(sampling.partition),
        pillow_m=torch.tensor([cfg.pillow_m]) if cfg.pillow_m > 0 else None,
    )
    t2 = time.perf_counter()
    cfg.out.mkdir(parents=True, exist_ok=True)
    reason = sim.reason[0]
    p = sim.pressure_mmhg[0].numpy()
    mat = MatSpec()
    record = {
        "command": "simulate",
        "config": flat_config(cfg),
        "mattress": mattress.to_dict(),
        "status": "rejected" if reason else "ok",
        "reason": reason,
        "mass_kg": round(float(sim.mass_kg[0]), 3),
        "settle_steps": int(sim.settle_steps[0]),
        "timing_ms": {
            "sample": round((t1 - t0) * 1e3, 1),
            "sim1": round(float(sim.settle_ms[0]), 1),
            "sim2": round(sim.press_ms, 1),
            "total": round((t2 - t0) * 1e3, 1),
        },
        "contact_area_m2": round(float((p > 0).sum() * mat.taxel_area_m2), 4),
        "mean_contact_pressure_mmhg": round(float(p[p > 0].mean()) if (p > 0).any() else 0.0, 2),
        "peak_pressure_mmhg": round(float(p.max()), 2),
        "sink_mm": round(float(sim.sink_m[0]) * 1e3, 1),
        "head_angle_deg": bed.head_angle_deg,
    }
    if sampling.spec.wedge:  # the wedge under the back (`sim.wedge`), sloped at the starting turn
        record["wedge"] = dataclasses.asdict(articulated_config_for(sampling.partition).wedge)
    paths = {}
    arrays = {
        "pressure_mmhg": p.astype(np.float32),
        "depth_mm": sim.depth_mm[0].numpy().astype(np.float32),
        "contact": sim.contact[0].numpy().astype(np.uint8),
        "shape": sim.params.shape[0].numpy(),
        "root_rotation": sim.params.root_rotation[0].numpy(),
        "root_translation": sim.params.root_translation[0].numpy(),
        "pose": sim.params.pose[0].numpy(),
        "joints": sim.joints[0].numpy(),
        "mass_kg": sim.mass_kg[:1].numpy(),
    }
    if not reason:
        paths["sample"] = atomic_write(cfg.out / "sample.npz", lambda tmp: np.savez_compressed(tmp, **arrays))
        title = (
            f"{sampling.partition}, {sampling.gender}, index {cfg.index}: {record['mass_kg']} kg, "
            f"area {record['contact_area_m2']} m^2, mean {record['mean_contact_pressure_mmhg']} mmHg, "
            f"peak {record['peak_pressure_mmhg']} mmHg"
        )
        profile = None
        if not bed.flat:
            (x0, x1), _ = mat.mattress_bounds_m
            s_pts = torch.tensor([[x0, 0.0, 0.0], [bed.hinge_x(mat), 0.0, 0.0], [x1, 0.0, 0.0]], dtype=torch.float64)
            profile = bed.to_world(s_pts, mat)[:, [0, 2]].numpy()
            title += f", head of the bed {bed.head_angle_deg:g} deg"
        paths["figure"] = plot_sample(
            cfg.out / "simulate.png", p, arrays["depth_mm"], sim.vertices[0].numpy(), title, bed_profile=profile
        )
    record["files"] = {k: v.name for k, v in paths.items()}
    paths["record"] = write_text(cfg.out / "simulate.json", json.dumps(record, indent=1))
    if reason:
        raise UserError(
            f"sample {cfg.index} of {sampling.partition}/{sampling.gender} was rejected ({reason}); "
            f"the generator skips such samples - try another --index (details in {paths['record']})"
        )
    return Written(paths, record)


def simulate(cfg: SimulateConfig) -> None:
    """Simulate one sample: initial pose, its rest on the bed (the articulated engine, or sim #1
    and sim #2 with --settle mujoco), sensor and label maps; writes sample.npz, simulate.json and
    simulate.png."""
    record = run_simulate(cfg).record
    print(
        f"{record['mass_kg']} kg: contact {record['contact_area_m2']} m^2, mean "
        f"{record['mean_contact_pressure_mmhg']} mmHg, peak {record['peak_pressure_mmhg']} mmHg, "
        + (
            f"sim #1 {record['timing_ms']['sim1']} ms ({record['settle_steps']} steps), "
            if record["timing_ms"]["sim1"]
            else f"articulated rest ({record['settle_steps']} re-posings), "
        )
        + f"sim #2 {record['timing_ms']['sim2']} ms -> {cfg.out}"
    )


__all__ = ["SimulateConfig", "run_simulate", "simulate"]
