"""Samples through the whole generator: initial pose -> sim #1 -> sim #2 -> sensor, labels.

`simulate_poses` is the pipeline dataset generation, training on the fly, `pressurepose
simulate` and `pressurepose realism` run (the command's files: `commands.simulate`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Literal

import numpy as np
import torch

from pressurepose.bed import BedShape
from pressurepose.body.model import BodyModel
from pressurepose.body.params import BodyParams
from pressurepose.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.sampling.partitions import get_partition
from pressurepose.sim.foundation import simulate_pressure
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.reading import taxel_pressure
from pressurepose.sim.sensor import label_maps, sensing_area, taxel_reading
from pressurepose.sim.settle import as_float64
from pressurepose.sim.settle import settle as settle_bodies
from pressurepose.sim.settle_config import SettleConfig

if TYPE_CHECKING:
    from pressurepose.sim.articulated import ArticulatedConfig


@dataclasses.dataclass
class SimulatedSamples:
    """B samples after both simulations. Rejected samples carry a reason and zero images."""

    params: BodyParams  # resting pose (sim #1, then sim #2's shift and tilt on the root)
    vertices: torch.Tensor  # (B, V, 3) mesh at rest, mat frame
    joints: torch.Tensor  # (B, 24, 3) J24 at rest, mat frame
    pressure_mmhg: torch.Tensor  # (B, 64, 27) sensor reading
    depth_mm: torch.Tensor  # (B, 64, 27) Q
    contact: torch.Tensor  # (B, 64, 27) C
    mass_kg: torch.Tensor  # (B,)
    height_m: torch.Tensor  # (B,) `BodyModel.measure` of the shape, with the mass
    reason: list[str]  # "" = accepted
    settle_steps: np.ndarray
    settle_ms: np.ndarray
    press_ms: float  # sim #2 wall time for the batch
    sink_m: np.ndarray  # sim #2 deepest compression
    head_angle_deg: np.ndarray  # (B,) the bed each sample rests on (0: flat)


SETTLE_ENGINES = ("articulated", "mujoco")
"""The generator's settling engines; the first is the default (docs/physics.md)."""


def default_mattress(settle: str, sim2: str | None = None) -> MattressParams:
    """The bed a settling engine uses unless told otherwise: the articulated rest's is the sponge
    preset (fitted to PmatData with it, docs/realism.md); the rigid rest's (MuJoCo followed by
    the rigid sim #2) the class defaults (its own calibration, docs/calibration.md)."""
    if settle == "articulated" or sim2 == "articulated":
        return MattressParams.preset("sponge")
    return MattressParams()


def settle_config_for(partition: str) -> SettleConfig:
    """Sim #1's settings for a sampling partition (its trunk roll hold; else the defaults)."""

    return SettleConfig(hold_roll_m=get_partition(partition).hold_roll_m)


def articulated_config_for(partition: str) -> ArticulatedConfig:
    """The articulated rest's settings for a sampling partition (the same trunk roll hold as
    sim #1's, `settle_config_for`; the `tilted` partition's wedges, `sim.wedge`)."""
    from pressurepose.sim.articulated import ArticulatedConfig
    from pressurepose.sim.wedge import Wedge

    spec = get_partition(partition)
    return ArticulatedConfig(hold_roll_m=spec.hold_roll_m, wedge=Wedge() if spec.wedge else None)


def simulate_poses(
    model: BodyModel,
    params: BodyParams,
    mattress: MattressParams | None = None,
    mat: MatSpec | None = None,
    seed: int = 0,
    bed: BedShape | Sequence[BedShape] | None = None,
    settle_config: SettleConfig | None = None,
    settle: Literal["mujoco", "articulated", "none"] = "mujoco",
    sim2: Literal["rigid", "articulated"] = "rigid",
    articulated: ArticulatedConfig | None = None,
    pillow_m: torch.Tensor | None = None,
) -> SimulatedSamples:
    """Settle (sim #1), press (sim #2), read (sensor) and label B initial poses on a flat bed,
    a bent one (`bed`), or one bed per sample (a sequence of B, e.g. `InitialPoses.beds()`:
    samples on the same bed are simulated together, results come back in input order).
    `settle_config`: sim #1's settings (default `SettleConfig()`; `settle_config_for` gives a
    partition's). `settle="none"` skips sim #1 (the poses rest as drawn); `sim2`: the whole mesh
    at rigid rest, or every body part on its own contact (`sim.articulated`, on flat and raised
    beds, `sim.raised`). `settle="articulated"`: one mechanics - the articulated rest settles
    the drawn pose itself (joint springs, self-contact, the soft bed; no MuJoCo) and its field
    is the image, whatever `sim2` says. `pillow_m` (B,): a pillow of this thickness (m, 0:
    none) under each head in the articulated rest on a flat bed (`sim.pillow`; the rigid rest
    and raised beds have none)."""
    if settle not in ("mujoco", "articulated", "none") or sim2 not in ("rigid", "articulated"):
        raise ValueError(
            f"settle must be 'mujoco', 'articulated' or 'none' and sim2 'rigid' or 'articulated', "
            f"got {settle!r}, {sim2!r}"
        )
    options = {"settle": settle, "sim2": sim2, "articulated": articulated}
    mattress = mattress or MattressParams()
    if pillow_m is not None:
        pillow_m = torch.as_tensor(pillow_m, dtype=torch.float64).reshape(-1)
        if pillow_m.shape[0] != params.batch_size:
            raise UserError(
                f"pillow_m must hold one thickness per sample ({params.batch_size}), got {pillow_m.shape[0]}"
            )
    mat = mat or MatSpec()
    if bed is None or isinstance(bed, BedShape):
        return _simulate_one_bed(
            model, params, mattress, mat, seed, bed or BedShape(), settle_config, pillow_m=pillow_m, **options
        )
    beds = list(bed)
    if len(beds) != params.batch_size or not all(isinstance(b, BedShape) for b in beds):
        raise UserError(
            f"bed must be one BedShape or a sequence of {params.batch_size} (one per sample), got {len(beds)} items"
        )
    groups: dict[BedShape, list[int]] = {}
    for i, b in enumerate(beds):
        groups.setdefault(b, []).append(i)
    if len(groups) == 1:
        return _simulate_one_bed(
            model, params, mattress, mat, seed, beds[0], settle_config, pillow_m=pillow_m, **options
        )
    parts, order = [], []
    for k, (b, rows) in enumerate(groups.items()):
        idx = torch.tensor(rows)
        part_pillow = None if pillow_m is None else pillow_m[idx]
        parts.append(
            _simulate_one_bed(
                model,
                params.index(idx),
                mattress,
                mat,
                seed + 7919 * k,
                b,
                settle_config,
                pillow_m=part_pillow,
                **options,
            )
        )
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
        params=params,
        vertices=cat_t("vertices"),
        joints=cat_t("joints"),
        pressure_mmhg=cat_t("pressure_mmhg"),
        depth_mm=cat_t("depth_mm"),
        contact=cat_t("contact"),
        mass_kg=cat_t("mass_kg"),
        height_m=cat_t("height_m"),
        reason=[reason[i] for i in back.tolist()],
        settle_steps=cat_n("settle_steps"),
        settle_ms=cat_n("settle_ms"),
        press_ms=sum(p.press_ms for p in parts),
        sink_m=cat_n("sink_m"),
        head_angle_deg=cat_n("head_angle_deg"),
    )


def _simulate_one_bed(
    model: BodyModel,
    params: BodyParams,
    mattress: MattressParams,
    mat: MatSpec,
    seed: int,
    bed: BedShape,
    settle_config: SettleConfig | None = None,
    settle: str = "mujoco",
    sim2: str = "rigid",
    articulated: ArticulatedConfig | None = None,
    pillow_m: torch.Tensor | None = None,
) -> SimulatedSamples:

    model64 = as_float64(model)
    B = params.batch_size
    if settle == "articulated":
        settle, sim2 = "none", "articulated"
    if settle == "mujoco":
        settled = settle_bodies(model64, params, mattress, mat, config=settle_config, bed=bed)
        rest, reason1, steps, settle_ms = settled.params, settled.reason, settled.steps, settled.wall_ms
    else:
        rest, reason1, steps, settle_ms = (
            params.to(dtype=torch.float64),
            [""] * B,
            np.zeros(B, dtype=np.int64),
            np.zeros(B),
        )
    measured = model64.measure(rest.shape)
    mass = measured.mass_kg
    t0 = time.perf_counter()
    if sim2 == "articulated":
        from pressurepose.sim.articulated import rest_articulated

        art = rest_articulated(
            model64, rest, mass, mattress, mat, articulated, pillow_m=pillow_m if bed.flat else None, bed=bed
        )
        pressure_pa, failure2, sink = (
            taxel_pressure(art.foundation_pa, mattress, mat, art.sub),
            art.failure,
            art.max_compression_m,
        )
        shifted, vertices, joints = art.params, art.vertices, art.joints
        # Its settling count: the re-posings, or outer + 1 for a body still moving at the cap
        # (such a body ran all `outer` of them).
        steps = (art.reposings + (~art.settled).long()).numpy()
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
    reason = [f"sim #1: {r1}" if r1 else (f"sim #2: {r2}" if r2 else "") for r1, r2 in zip(reason1, failure2)]
    bad = torch.tensor([bool(r) for r in reason])
    reading = torch.where(bad[:, None, None], torch.zeros_like(reading), reading)
    return SimulatedSamples(
        params=shifted,
        vertices=vertices.detach(),
        joints=joints.detach(),
        pressure_mmhg=reading,
        depth_mm=depth,
        contact=contact,
        mass_kg=mass,
        height_m=measured.height_m,
        reason=reason,
        settle_steps=steps,
        settle_ms=settle_ms,
        press_ms=press_ms,
        sink_m=sink.detach().numpy(),
        head_angle_deg=np.full(params.batch_size, float(bed.head_angle_deg)),
    )


def _apply_rest_to_root(params: BodyParams, pressed) -> BodyParams:
    """Sim #2 moved the rigid mesh by v -> R v + t; the same motion of the root (rotation on
    top of the supine reference, pelvis position) makes the parameters reproduce the mesh."""
    R, t = pressed.rotation.detach(), pressed.translation.detach()
    root = matrix_to_axis_angle(R @ axis_angle_to_matrix(params.root_rotation))
    pelvis = (R @ params.root_translation[..., None])[..., 0] + t
    return params.replace(root_rotation=root, root_translation=pelvis)


__all__ = [
    "SETTLE_ENGINES",
    "SimulatedSamples",
    "articulated_config_for",
    "default_mattress",
    "settle_config_for",
    "simulate_poses",
]
