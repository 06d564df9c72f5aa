"""Limbs of the pose sampler (seed A.1): joint-angle ranges per limb, the limb table built from
the joint limits, and elementwise limb geometry (vectors as tuples of three tensors)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from pressurepose.body.joints import J24_NAMES
from pressurepose.body.limits import JointLimits
from pressurepose.sampling.partitions import (
    LEG_CELLS,
)

J = J24_NAMES.index
DEG = math.pi / 180

# Joint-angle sampling ranges (REFERENCE.md, degrees, left side; the right side mirrors:
# (x, y, z) -> (x, -y, -z)). The shoulder triple is split 1/3 collar, 2/3 shoulder.
HIP_DEG = ((-90.0, 17.8), (-33.7, 32.6), (-30.5, 38.6))
KNEE_DEG = (-1.3, 139.9)  # about x
SHOULDER_DEG = ((-88.9, 81.4), (-140.7, 43.7), (-90.0, 80.4))
ELBOW_DEG = (-147.3, 2.8)  # about y
GEOMETRY_QUANTUM_M = 1e-9

LIMBS = ("left_leg", "right_leg", "left_arm", "right_arm")  # the order limbs are drawn in
TORSO_JOINTS = tuple(J(n) for n in ("pelvis", "spine1", "spine2", "spine3", "neck", "head"))


def _mirror(ranges, side):
    if side == "left":
        return ranges
    (xl, xh), (yl, yh), (zl, zh) = ranges
    return ((xl, xh), (-yh, -yl), (-zh, -zl))


@dataclasses.dataclass(frozen=True)
class Limb:
    name: str
    side: str
    chain: tuple[int, ...]  # J24 joints from the limb's root to its tip (root's parent has identity)
    proximal: int  # J24 joint the cell is measured from
    distal: int  # J24 joint that must reach the cell
    over_bed: tuple[int, ...]  # joints that must lie over the mattress
    low: np.ndarray  # (k,) sampling range of the drawn angles, radians
    high: np.ndarray


def limb_table(limits: JointLimits) -> dict[str, Limb]:
    out = {}
    for side in ("left", "right"):
        hip = _mirror(HIP_DEG, side)
        knee = KNEE_DEG
        low = [r[0] * DEG for r in hip] + [knee[0] * DEG]
        high = [r[1] * DEG for r in hip] + [knee[1] * DEG]
        bounds = [limits.bounds_of(f"{side}_hip")[k] for k in range(3)] + [limits.bounds_of(f"{side}_knee")[0]]
        low, high = _intersect(low, high, bounds)
        out[f"{side}_leg"] = Limb(
            f"{side}_leg",
            side,
            (J(f"{side}_hip"), J(f"{side}_knee"), J(f"{side}_ankle"), J(f"{side}_foot")),
            J(f"{side}_hip"),
            J(f"{side}_ankle"),
            (J(f"{side}_knee"), J(f"{side}_ankle"), J(f"{side}_foot")),
            low,
            high,
        )
        sh = _mirror(SHOULDER_DEG, side)
        el = ELBOW_DEG if side == "left" else (-ELBOW_DEG[1], -ELBOW_DEG[0])
        low = [r[0] * DEG for r in sh] + [el[0] * DEG]
        high = [r[1] * DEG for r in sh] + [el[1] * DEG]
        # The shoulder triple is split 1/3 : 2/3 onto collar and shoulder, whose limits are
        # the same split of these ranges; intersect through the shoulder's share.
        sb = limits.bounds_of(f"{side}_shoulder") * 1.5
        bounds = [sb[k] for k in range(3)] + [limits.bounds_of(f"{side}_elbow")[1]]
        low, high = _intersect(low, high, bounds)
        out[f"{side}_arm"] = Limb(
            f"{side}_arm",
            side,
            (J(f"{side}_collar"), J(f"{side}_shoulder"), J(f"{side}_elbow"), J(f"{side}_wrist"), J(f"{side}_hand")),
            J(f"{side}_shoulder"),
            J(f"{side}_wrist"),
            (J(f"{side}_elbow"), J(f"{side}_wrist"), J(f"{side}_hand")),
            low,
            high,
        )
    return out


def _intersect(low, high, bounds):
    lo = np.array([max(a, float(b[0])) for a, b in zip(low, bounds)])
    hi = np.array([min(a, float(b[1])) for a, b in zip(high, bounds)])
    # float32 limit tables round: stay a hair inside so every drawn angle passes `contains`.
    span = hi - lo
    return lo + 1e-6 * span, hi - 1e-6 * span


def limb_pose(limb: Limb, angles: torch.Tensor) -> torch.Tensor:
    """(..., k) drawn angles of a limb -> (..., len(chain) - 1 or so, 3) axis-angle of the
    rotating joints of its chain, in chain order (legs: hip, knee; arms: collar, shoulder,
    elbow)."""
    z = torch.zeros_like(angles[..., 0])
    if limb.name.endswith("leg"):
        hip = angles[..., :3]
        knee = torch.stack([angles[..., 3], z, z], -1)
        return torch.stack([hip, knee], -2)
    total = angles[..., :3]
    elbow = torch.stack([z, angles[..., 3], z], -1)
    return torch.stack([total / 3, total * (2 / 3), elbow], -2)


def rotating_joints(limb: Limb) -> tuple[int, ...]:
    return limb.chain[:2] if limb.name.endswith("leg") else limb.chain[:3]


# --- limb geometry, elementwise ---------------------------------------------------------------
# A vector is a tuple of three tensors (x, y, z) of one broadcast shape: every operation is
# elementwise on contiguous arrays, so each draw's numbers depend on its own inputs only. This
# is the float32 screen's layout (`LimbDraws._screen`), and why it keeps its own Rodrigues
# formula instead of roma: roma works on (..., 3) and (..., 4) tensors, and the same screen
# through `roma.rotvec_to_unitquat` and `roma.quat_action` took 13.9 ms instead of 2.3 ms for
# 16 x 4096 draws (one core). The exact float64 tests use roma (`body.rotations`).
Vec = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def rodrigues(k: Vec):
    """Rotation vectors k -> what `rotate` needs: R(k) v = v + a (k x v) + b (k (k.v) - |k|^2 v),
    a = sin(t)/t, b = (1 - cos t)/t^2, written with the half angle (stable at t -> 0)."""
    theta2 = k[0] * k[0] + k[1] * k[1] + k[2] * k[2]
    half = theta2.clamp_min(torch.finfo(theta2.dtype).tiny).sqrt() * 0.5
    sinc = torch.sin(half) / half
    return k, theta2, sinc * torch.cos(half), 0.5 * sinc * sinc


def rotate(rod, v: Vec) -> Vec:
    k, theta2, a, b = rod
    dot = k[0] * v[0] + k[1] * v[1] + k[2] * v[2]
    cross = (k[1] * v[2] - k[2] * v[1], k[2] * v[0] - k[0] * v[2], k[0] * v[1] - k[1] * v[0])
    return tuple(v[i] + a * cross[i] + b * (k[i] * dot - theta2 * v[i]) for i in range(3))


def apply_hinge(limb: Limb, angle: torch.Tensor, v: Vec) -> Vec:
    """v turned by the knee (about x) or elbow (about y) angle."""
    c, s = torch.cos(angle), torch.sin(angle)
    if limb.name.endswith("leg"):  # about x
        return (v[0], c * v[1] - s * v[2], s * v[1] + c * v[2])
    return (c * v[0] + s * v[2], v[1], c * v[2] - s * v[0])  # about y


def vadd(a: Vec, b: Vec) -> Vec:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def vdot(a: Vec, b: Vec) -> torch.Tensor:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def cols(x: torch.Tensor) -> Vec:
    """(..., 3) -> three (..., 1) column tensors (broadcast against (..., M) draws)."""
    return tuple(x[..., i : i + 1] for i in range(3))


def split_xyz(x: torch.Tensor) -> Vec:
    return tuple(x[..., i] for i in range(3))


def leg_cell(drop: torch.Tensor, L: torch.Tensor) -> torch.Tensor:
    """Leg cell 0..3 of an ankle `drop` below the hip (>= 0) in quarters of the leg length."""
    return (drop / (L / LEG_CELLS)).floor().clamp(0, LEG_CELLS - 1).long()


def arm_cell(rise: torch.Tensor, A: torch.Tensor) -> torch.Tensor:
    """Arm cell 0..7 of a wrist `rise` toward the head from the shoulder: 0 = above 3A/4,
    3 = [0, A/4), 4 = [-A/4, 0), 7 = below -3A/4."""
    q = (rise / (A / 4)).floor().clamp(-4, 3).long()  # -4..3
    return 3 - q


FIRST_ROUND, LARGEST_ROUND = 64, 4096  # joint-angle draws per round, per limb and sample


def draw_schedule(budget: int) -> np.ndarray:
    """Cumulative draw counts at the end of each round: 64, 128, ..., 4096, 4096, ... up to
    `budget`."""
    ends, drawn, size = [], 0, FIRST_ROUND
    while drawn < budget:
        drawn += min(size, budget - drawn)
        size = min(2 * size, LARGEST_ROUND)
        ends.append(drawn)
    return np.array(ends)
