"""J24 joint limits and the tanh squash that keeps angles inside them (seed B.1).

Bounds are per axis of the axis-angle vector, in radians, in SMPL's body axes relative to
the T-pose - the convention of BodyParams.pose on every backend, so the released SMPL values
(REFERENCE.md) apply without conversion. Mirroring across the sagittal plane maps a rotation
vector (x, y, z) to (x, -y, -z), so right-side bounds are the left ones with y and z negated
and swapped (the original's right-hip y range was empty by a typo; here it is derived).

Shoulders and collars have no released network bounds; we use the seed's sampling ranges
(shoulder roll x [-88.9, 81.4] deg, yaw y [-140.7, 43.7], pitch z [-90, 80.4] for the left
arm), split as the original split the rotation: 1/3 on the collar, 2/3 on the shoulder.
"""

from __future__ import annotations

import dataclasses
import math

import torch

from pressurepose.body.joints import J24_MIRROR, J24_NAMES, NUM_POSE_JOINTS
from pressurepose.constants import kept

ALPHA = 1.2  # seed B.1: bounds inflated by 20% so a straight knee is not at the tanh's edge

_D = math.pi / 180
# Left side and midline bounds: joint -> ((x_lo, x_hi), (y_lo, y_hi), (z_lo, z_hi)).
_EPS = (-0.01, 0.01)
_SHOULDER_DEG = ((-88.9, 81.4), (-140.7, 43.7), (-90.0, 80.4))
_LEFT_AND_MID: dict[str, tuple[tuple[float, float], ...]] = {
    "left_hip": ((-1.5794, 0.3098), (-0.5882, 0.5690), (-0.5323, 0.6737)),
    "left_knee": ((-0.0227, 2.4417), _EPS, _EPS),
    "left_ankle": ((-math.pi / 6, math.pi / 6),) * 3,
    "left_foot": (_EPS,) * 3,
    "left_collar": tuple((lo * _D / 3, hi * _D / 3) for lo, hi in _SHOULDER_DEG),
    "left_shoulder": tuple((lo * _D * 2 / 3, hi * _D * 2 / 3) for lo, hi in _SHOULDER_DEG),
    "left_elbow": (_EPS, (-2.5709, 0.048), _EPS),
    "left_wrist": ((-math.pi / 6, math.pi / 6),) * 3,
    "left_hand": (_EPS,) * 3,
}
for _name in ("spine1", "spine2", "spine3", "neck", "head"):
    _LEFT_AND_MID[_name] = ((-math.pi / 3, math.pi / 3), (-math.pi / 36, math.pi / 36), (-math.pi / 36, math.pi / 36))


def _mirrored(bounds: tuple[tuple[float, float], ...]) -> tuple[tuple[float, float], ...]:
    (xl, xh), (yl, yh), (zl, zh) = bounds
    return ((xl, xh), (-yh, -yl), (-zh, -zl))


def _table() -> torch.Tensor:
    table = torch.zeros(NUM_POSE_JOINTS, 3, 2, dtype=torch.float64)
    for j, name in enumerate(J24_NAMES[1:], start=1):
        if name in _LEFT_AND_MID:
            bounds = _LEFT_AND_MID[name]
        else:
            bounds = _mirrored(_LEFT_AND_MID[J24_NAMES[J24_MIRROR[j]]])
        table[j - 1] = torch.tensor(bounds, dtype=torch.float64)
    return table


_DEFAULTS: dict[tuple[torch.dtype, torch.device], JointLimits] = {}


@dataclasses.dataclass(frozen=True)
class JointLimits:
    """Per-axis bounds (23, 3) for joints 1..23 of J24 (the pose vector's layout), radians."""

    lower: torch.Tensor
    upper: torch.Tensor

    @classmethod
    def default(cls, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> JointLimits:
        """The table above in `dtype` on `device` (made once per pair and shared: read-only)."""

        def make() -> JointLimits:
            table = _table().to(dtype=dtype, device=device)
            return cls(lower=table[..., 0], upper=table[..., 1])

        return kept(_DEFAULTS, (dtype, torch.device(device)), make)

    def bounds_of(self, joint: str) -> torch.Tensor:
        """(3, 2) [lo, hi] per axis of one joint by J24 name."""
        if joint not in J24_NAMES[1:]:
            raise ValueError(f"unknown joint name {joint!r}; expected one of {', '.join(J24_NAMES[1:])}")
        j = J24_NAMES.index(joint) - 1
        return torch.stack([self.lower[j], self.upper[j]], -1)

    def contains(self, pose: torch.Tensor) -> torch.Tensor:
        """(B,) whether every angle of (B, 23, 3) poses lies within the (uninflated) bounds."""
        _check_pose(pose)
        return ((pose >= self.lower) & (pose <= self.upper)).flatten(1).all(-1)

    def squash(self, pose: torch.Tensor, alpha: float = ALPHA) -> torch.Tensor:
        """Soft limit (seed B.1): a' = tanh((a - m) 2 / w) w / 2 + m, w = alpha (hi - lo).

        Maps any real (B, 23, 3) into the bounds inflated by `alpha` about their midpoint m,
        strictly monotone, identity-like (slope 1) at m.
        """
        _check_pose(pose)
        mid, width = self._mid_width(pose, alpha)
        return torch.tanh((pose - mid) * 2 / width) * width / 2 + mid

    def unsquash(self, squashed: torch.Tensor, alpha: float = ALPHA) -> torch.Tensor:
        """Inverse of `squash`; ValueError if a value lies outside the inflated bounds."""
        _check_pose(squashed)
        mid, width = self._mid_width(squashed, alpha)
        u = (squashed - mid) * 2 / width
        if (u.abs() >= 1).any():
            raise ValueError("unsquash: some angles lie outside the inflated joint limits")
        return torch.atanh(u) * width / 2 + mid

    def _mid_width(self, like: torch.Tensor, alpha: float) -> tuple[torch.Tensor, torch.Tensor]:
        if not alpha > 0:
            raise ValueError(f"alpha must be > 0, got {alpha}")
        lower = self.lower.to(like)
        upper = self.upper.to(like)
        return (lower + upper) / 2, alpha * (upper - lower)


def _check_pose(pose: torch.Tensor) -> None:
    if pose.ndim < 2 or tuple(pose.shape[-2:]) != (NUM_POSE_JOINTS, 3):
        raise ValueError(f"pose must have shape (B, {NUM_POSE_JOINTS}, 3), got {tuple(pose.shape)}")
