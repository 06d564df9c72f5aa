"""Sim #1: the capsulised body settles onto the mattress (MuJoCo).

The MJCF is built per body from its `CapsuleBody` (body/capsules.py): one MuJoCo body per
capsule on the J24 tree, placed in the T-pose with world-aligned frames (so a ball joint's
quaternion is exactly the J24 local rotation of BodyParams.pose), explicit masses and inertias,
ball joints with MuJoCo's native joint springs (`stiffness`, spring reference = the home pose
through `qpos_spring`) and damping, hinge knees and elbows, a free root. 55 DoF.

The mattress is not a MuJoCo contact: every step, sim #2's foundation law is applied to the
capsules (seed eq. 17's role - both simulations push back on a body the same way): over each
node of the covered grid, the compression w of the lowest capsule surface point below the
mattress top gives the force (k1 w + k3 w^3) A upwards, plus a damper (time constant
`damping_s` x the local stiffness) and regularised Coulomb friction (`friction`), applied to
that capsule at that point through `xfrc_applied` (on a raised bed, per bed section in its own
frame). MuJoCo's soft contacts would make the sinking depend on the number of contacts
(DESIGN.md); this does not. The mattress's sides are MuJoCo boxes, so limbs hanging over the
edge rest against them. Forces come from the current state (between mj_step1 and mj_step2).

Procedure (seed A.2): the body starts with its lowest capsule point `drop_height_m` above the
mattress; all velocities are zeroed every 4 steps until the buttocks (pelvis) capsule touches;
the body is at rest when the largest capsule speed < 0.05 m/s and acceleration < 0.5 m/s^2.
Rejected (with the reason) after `max_steps` steps, on a non-finite state, when a capsule sinks
through the mattress (compression beyond its thickness), when the body falls off the bed, or
when the total mechanical energy (kinetic + gravity + joint springs + mattress) grows, which
an integrator going unstable does and a passive system cannot.

Speed (docs/benchmarks.md): `settle` steps `batch` bodies together, each in its own MjData,
and a slot takes the next body as soon as its body is done, so the per-step Python cost is
always shared. The state every step needs is gathered into (P, ...) arrays from views made
once per body; the foundation forces of all running bodies are one vectorised call that
visits, per capsule and grid row, only the nodes within the horizontal reach of the capsule's
part below the top, computes one quadratic root (and one end sphere) per node, and picks the
lowest capsule per node with a scatter-min. Every body's numbers are its own, bit for bit:
results do not depend on `batch`, on the slot or on the other bodies (test). By
construction: MuJoCo steps each body in its own MjData; the batched force code uses only
elementwise operations (correctly rounded, so the same bits in any array), scatter-min/max,
and `np.bincount` sums, which add each capsule's nodes in the same order whatever comes
before or after them; every other sum and product is spelled out in a fixed order
(sim/fixed_order.py) - no `sum`, `einsum` or `@` over a batched array, whose rounding numpy
and BLAS may vary with the batch's size, alignment or the CPU. The capsule bodies are built
one body at a time for the same reason.
"""

from __future__ import annotations

import numpy as np
import torch

from pressurepose.bed import BedShape
from pressurepose.body.capsules import (
    CapsuleBody,
    build_capsule_body,
)
from pressurepose.body.model import BodyModel
from pressurepose.body.params import BodyParams
from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.mjcf import build_mjcf, initial_pairs
from pressurepose.sim.settle_config import (
    SETTLE_REASONS,
    SIM_VOLUME_POINTS,
    SettleConfig,
    SettleResult,
)
from pressurepose.sim.settle_steps import Episode, run_batch


def as_float64(model: BodyModel) -> BodyModel:
    """The model itself when float64, else a float64 copy (never converts the caller's)."""
    if model.dtype == torch.float64:
        return model
    import copy

    return copy.deepcopy(model).to(torch.float64)


def settle(
    model: BodyModel,
    params: BodyParams,
    mattress: MattressParams | None = None,
    mat: MatSpec | None = None,
    config: SettleConfig | None = None,
    body: CapsuleBody | None = None,
    batch: int = 16,
    bed: BedShape | None = None,
) -> SettleResult:
    """Settle B initial poses (BodyParams, mat frame) onto the mattress: one MuJoCo model per
    body, `batch` of them stepped together. A body's result depends on its own initial pose,
    shape (or capsule body) and bed only - not on `batch`, its slot or the other bodies - bit
    for bit, by construction (module docstring).

    `body` (the capsulised bodies of params.shape) is built body by body when not given
    (`build_capsule_body(..., one_by_one=True)`); a body built in a batch may differ in its
    last bits with the batch. Returns the resting poses and per-sample statistics; unsettled
    samples are flagged, never NaN.
    """
    mattress = mattress or MattressParams()
    mat = mat or MatSpec()
    config = config or SettleConfig()
    params = params.to(torch.float64)
    params.validate(model.shape_dim, torch.float64, params.shape.device)
    B = params.batch_size
    if body is None:
        body = build_capsule_body(as_float64(model), params.shape, volume_points=SIM_VOLUME_POINTS, one_by_one=True)
    if body.capsules.batch_size != B:
        raise UserError(f"capsule body batch ({body.capsules.batch_size}) != params batch ({B})")
    masses = body.mass_kg.sum(-1)
    if not torch.isfinite(masses).all() or bool((masses <= 0).any()):
        raise UserError("every body needs a finite mass > 0 (check the shape parameters)")
    root_rot = params.root_rotation.clone()
    root_t = params.root_translation.clone()
    pose = params.pose.clone()
    stats = {k: np.zeros(B) for k in ("steps", "touch_step", "max_speed", "max_accel", "sink", "wall_ms")}
    reasons = []
    pairs = initial_pairs(body, params) if B else []
    outs = run_batch(
        lambda i: Episode(body, i, params, mattress, mat, config, bed, pairs[i]),
        B,
        mat,
        config,
        mattress,
        bed,
        pool=batch,
    )
    for i, o in enumerate(outs):
        reasons.append(o.reason)
        for k in stats:
            stats[k][i] = getattr(o, k)
        if o.rest is not None:
            root_rot[i], root_t[i], pose[i] = o.rest
    return SettleResult(
        params=params.replace(root_rotation=root_rot, root_translation=root_t, pose=pose),
        ok=np.array([not r for r in reasons]),
        reason=reasons,
        steps=stats["steps"].astype(int),
        touch_step=stats["touch_step"].astype(int),
        max_speed=stats["max_speed"],
        max_accel=stats["max_accel"],
        sink_m=stats["sink"],
        wall_ms=stats["wall_ms"],
    )


__all__ = ["SETTLE_REASONS", "SettleConfig", "SettleResult", "as_float64", "build_mjcf", "settle"]
