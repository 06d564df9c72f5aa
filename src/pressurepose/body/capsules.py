"""The capsulised body (seed A.1, A.2): 20 capsules on J24 for collisions and settling.

Layout (SMPLify's): one capsule per J24 part that moves on its own, riding that joint rigidly.
- Limbs, collars, neck and head: the axis runs from the joint to its child joint; the head,
  hands and feet, which end the chains, extend to the far end of their vertices (the feet
  also back to the heel).
- Torso (pelvis, spine1, spine2, spine3): the axis runs across the body (body x), centred on
  the part's vertices, as SMPLify does: a row of crosswise capsules gives the back its width,
  so a supine body rests stably instead of rolling on a line of spine capsules.
Each capsule is fitted per shape from the T-pose mesh: its vertices are those whose dominant
skinning part is the capsule's part, the radius is the median distance of the vertices in the
middle of the segment to the axis (robust to the joint regions shared with neighbours).

Volumes share overlapping space fractionally (seed A.2): a point inside n capsules counts 1/n
for each. `capsule_volumes(method="voxel")` is the seed's 2 mm voxelisation; the default
"qmc" integrates the same quantity on fixed Sobol points inside each capsule (exact capsule
volume times the mean of 1/n) and agrees with it within 1% (test) at a fraction of the cost.

Masses follow seed eq. 11-12: within a body segment R (trunk, head, thigh, ...), capsule c of a
body with shape beta gets m_c = m_g X_R,g V_c / V_R,g(average body). Departure: the masses are
then scaled by one factor so that they sum to the body model's mass (mesh volume x 980 kg/m^3),
the weight sim #2 presses into the mattress - both simulations must carry the same weight.
Inertia is analytic (uniform solid capsule). Joint stiffness is the seed's per-joint value times
m / 70.45 kg, damping 15 k, equilibrium = the home pose (arms at the sides, legs straight).

Modules: `capsule_layout` (layout, tables, home pose), `capsule_fit` (the fit),
`capsule_geometry` (distances), `capsule_volumes` (volumes); this module builds the physical
body and re-exports the others' public names.
"""

from __future__ import annotations

import dataclasses
import math

import torch

from pressurepose.body.capsule_fit import Capsules, fit_capsules
from pressurepose.body.capsule_geometry import capsule_clearance, point_segment_distance, segment_distance
from pressurepose.body.capsule_layout import (
    AVERAGE_MASS_KG,
    CAPSULE_JOINTS,
    CAPSULE_NAMES,
    CAPSULE_PARENTS,
    CAPSULES,
    CHAIN_JOINTS,
    DAMPING_RATIO,
    DISTAL_CAPSULES,
    HINGE_JOINTS,
    JOINT_STIFFNESS,
    NUM_CAPSULES,
    SEGMENT_FRACTIONS,
    STIFFNESS_REFERENCE_MASS_KG,
    CapsuleSpec,
    capsule_index,
    collision_pairs,
    home_pose,
)
from pressurepose.body.capsule_volumes import capsule_volumes, overlap_pairs
from pressurepose.body.joints import J24_NAMES, NUM_POSE_JOINTS
from pressurepose.body.model import BodyModel


# --- the physical body ----------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class CapsuleBody:
    """Everything sim #1 needs about B capsulised bodies (SI units, body axes, T-pose)."""

    capsules: Capsules
    volume_m3: torch.Tensor  # (B, 20) shared volume
    mass_kg: torch.Tensor  # (B, 20)
    inertia: torch.Tensor  # (B, 20, 3) principal moments about the centre (axis, perp, perp)
    stiffness: torch.Tensor  # (B, 23) N m / rad per J24 pose joint (0: not a chain joint)
    damping: torch.Tensor  # (B, 23) N m s / rad
    home_pose: torch.Tensor  # (B, 23, 3) spring equilibrium
    body_mass_kg: torch.Tensor  # (B,) = mass_kg.sum(-1)


def capsule_inertia(mass: torch.Tensor, radius: torch.Tensor, length: torch.Tensor) -> torch.Tensor:
    """(..., 3) principal moments (axial, transverse, transverse) of solid capsules of uniform
    density, about their centre: cylinder + two hemispherical caps."""
    vc = math.pi * radius**2 * length
    vs = 4.0 / 3.0 * math.pi * radius**3
    mc = mass * vc / (vc + vs)
    ms = mass - mc
    axial = mc * radius**2 / 2 + ms * 2 * radius**2 / 5
    perp = mc * (radius**2 / 4 + length**2 / 12) + ms * (2 * radius**2 / 5 + length**2 / 4 + 3 * length * radius / 8)
    return torch.stack([axial, perp, perp], -1)


def _segment_table(female: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-capsule segment fraction X_R,g (B, 20) (blended by gender) and segment ids (20,)."""
    segments = sorted({c.segment for c in CAPSULES})
    seg_id = torch.tensor([segments.index(c.segment) for c in CAPSULES])
    f = torch.tensor(
        [SEGMENT_FRACTIONS["female"][c.segment] for c in CAPSULES], dtype=female.dtype, device=female.device
    )
    m = torch.tensor([SEGMENT_FRACTIONS["male"][c.segment] for c in CAPSULES], dtype=female.dtype, device=female.device)
    return female[:, None] * f + (1 - female[:, None]) * m, seg_id.to(female.device)


def build_capsule_body(
    model: BodyModel,
    shape: torch.Tensor,
    volume_method: str = "qmc",
    volume_points: int = 8192,
    one_by_one: bool = False,
) -> CapsuleBody:
    """Capsules, masses (seed eq. 11-12, summing to the body model's mass), inertia, joint
    stiffness and damping for (B, S) shapes. `volume_points`: Sobol points per capsule for the
    "qmc" shared volumes (2048 changes a capsule's volume by at most 0.3% against 8192 and
    costs a quarter; sim #1 uses it).

    one_by_one: build every body from its own shape alone (and the average body of each
    gender alone), so a body's numbers depend on its shape only. Batched, they also depend,
    in the last bits (~1e-16 relative), on the other shapes in the batch: torch picks matrix
    kernels by size. Sim #1 builds one by one (`settle`), ~2x the cost of a batched build."""
    model.validate_shape(shape)
    B = shape.shape[0]
    if not one_by_one or B == 0:
        return _build(model, shape, volume_method, volume_points, None)
    cache: dict = {}
    parts = [_build(model, shape[i : i + 1], volume_method, volume_points, cache) for i in range(B)]
    return _concat_bodies(parts)


def _build(
    model: BodyModel, shape: torch.Tensor, volume_method: str, volume_points: int, avg_cache: dict | None
) -> CapsuleBody:
    """build_capsule_body of a batch; avg_cache (one-by-one builds): the average bodies'
    capsule volumes by shape, each computed alone."""
    caps = fit_capsules(model, shape)
    volume = capsule_volumes(caps, method=volume_method, points=volume_points)
    female = model.female_fraction(shape)
    # The average person of the same gender (seed: beta = 0): the backend's default shape.
    average_shape = model.average_shape(female)
    # One average body per distinct gender (datasets use exactly 0 and 1), not one per body.
    unique, inverse = torch.unique(average_shape, dim=0, return_inverse=True)
    if avg_cache is None:
        avg_volume = capsule_volumes(fit_capsules(model, unique), method=volume_method, points=volume_points)
    else:
        rows = []
        for u in unique:
            key = tuple(u.tolist())
            if key not in avg_cache:
                avg_cache[key] = capsule_volumes(
                    fit_capsules(model, u[None]), method=volume_method, points=volume_points
                )[0]
            rows.append(avg_cache[key])
        avg_volume = torch.stack(rows)
    avg_volume = avg_volume[inverse]
    fraction, seg_id = _segment_table(female)
    # V_R,g of the average body: sum of its capsule volumes over each segment (per side for
    # limbs: a left and a right segment are separate parts, each with fraction X_R).
    side = torch.tensor(
        [0 if c.segment in ("trunk", "head") else (1 if c.name.startswith("left_") else 2) for c in CAPSULES],
        device=shape.device,
    )
    group = seg_id * 3 + side
    part_volume = torch.zeros(shape.shape[0], int(group.max()) + 1, dtype=volume.dtype, device=volume.device)
    part_volume.index_add_(1, group, avg_volume)
    raw = fraction * volume / part_volume[:, group]  # eq. 11-12 up to the factor m_g
    body_mass = model.measure(shape).mass_kg
    mass = raw * (body_mass / raw.sum(-1))[:, None]
    inertia = capsule_inertia(mass, caps.radius, caps.length)
    # Stiffness per J24 pose joint, scaled by the mass ratio; joints off the chain get 0.
    base = torch.zeros(NUM_POSE_JOINTS, dtype=shape.dtype, device=shape.device)
    for j in CHAIN_JOINTS:
        name = J24_NAMES[j].removeprefix("left_").removeprefix("right_")
        base[j - 1] = JOINT_STIFFNESS[name]
    stiffness = base[None] * (body_mass / STIFFNESS_REFERENCE_MASS_KG)[:, None]
    return CapsuleBody(
        capsules=caps,
        volume_m3=volume,
        mass_kg=mass,
        inertia=inertia,
        stiffness=stiffness,
        damping=DAMPING_RATIO * stiffness,
        home_pose=home_pose(shape.shape[0], shape.dtype, shape.device),
        body_mass_kg=mass.sum(-1),
    )


def _concat_bodies(parts: list[CapsuleBody]) -> CapsuleBody:
    def cat(objs):
        return type(objs[0])(
            **{
                f.name: cat([getattr(o, f.name) for o in objs])
                if dataclasses.is_dataclass(getattr(objs[0], f.name))
                else torch.cat([getattr(o, f.name) for o in objs])
                for f in dataclasses.fields(objs[0])
            }
        )

    return cat(parts)


__all__ = [
    "AVERAGE_MASS_KG",
    "CAPSULES",
    "CAPSULE_JOINTS",
    "CAPSULE_NAMES",
    "CAPSULE_PARENTS",
    "CHAIN_JOINTS",
    "DAMPING_RATIO",
    "DISTAL_CAPSULES",
    "HINGE_JOINTS",
    "JOINT_STIFFNESS",
    "NUM_CAPSULES",
    "SEGMENT_FRACTIONS",
    "STIFFNESS_REFERENCE_MASS_KG",
    "CapsuleBody",
    "CapsuleSpec",
    "Capsules",
    "build_capsule_body",
    "capsule_clearance",
    "capsule_index",
    "capsule_inertia",
    "capsule_volumes",
    "collision_pairs",
    "fit_capsules",
    "home_pose",
    "overlap_pairs",
    "point_segment_distance",
    "segment_distance",
]
