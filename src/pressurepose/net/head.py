"""The network's flat output vector -> BodyParams: the one place it is unpacked (seed B.1).

Layout of the raw vector (B, D), D = S + 78 (Anny S = 6: 84; SMPL S = 10: 88):

    [ shape (S) | root translation (3) | root rotation, 6D (6) | joint angles (23 x 3) ]

Each block is scaled by the range of its parameters, as the seed normalises the output:
- shape: mid + half-width x tanh(raw), inside the sampling bounds (`BodyModel.
  shape_bounds`, both genders' union for Anny); a known gender replaces Anny's gender entry;
- root translation: an initial guess (pelvis over the middle of the mat, 0.1 m up) plus raw
  x the bed's half-size (m);
- root rotation: the continuous 6D representation (Zhou et al. 2019) - two columns of the
  rotation matrix, orthonormalised by Gram-Schmidt - offset so that raw = 0 is the supine
  reference; the released network used (cos, sin) per Euler angle, which is discontinuous in
  the rotation it describes;
- joint angles: mid + half-width x raw per axis, then the joint-limit tanh squash
  (`JointLimits.squash`, alpha = 1.2) keeps them inside the inflated limits.
Mod2's residuals are added to Mod1's raw vector before this unpacking.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import roma
import torch

from pressurepose.body import backend_class
from pressurepose.body.joints import NUM_POSE_JOINTS
from pressurepose.body.limits import ALPHA, JointLimits
from pressurepose.body.params import BodyParams
from pressurepose.body.rotations import matrix_to_axis_angle
from pressurepose.mat import MatSpec

ROOT_Z_GUESS_M = 0.10  # pelvis height of a supine adult resting on the mattress
ROT6D_IDENTITY = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)  # first two columns of I


@dataclasses.dataclass(frozen=True)
class OutputLayout:
    """Slices of the raw output vector (no magic offsets elsewhere)."""

    shape_dim: int

    @property
    def size(self) -> int:
        return self.shape_dim + 3 + 6 + NUM_POSE_JOINTS * 3

    def split(self, raw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(B, D) -> shape (B, S), translation (B, 3), rotation 6D (B, 6), pose (B, 23, 3)."""
        if raw.ndim != 2 or raw.shape[1] != self.size:
            raise ValueError(f"raw output must have shape (B, {self.size}), got {tuple(raw.shape)}")
        S = self.shape_dim
        return (raw[:, :S], raw[:, S : S + 3], raw[:, S + 3 : S + 9], raw[:, S + 9 :].reshape(-1, NUM_POSE_JOINTS, 3))


def rotation_6d_to_matrix(d6: torch.Tensor) -> torch.Tensor:
    """(..., 6) two 3-vectors -> (..., 3, 3) rotation whose first two columns they span
    (Gram-Schmidt, `roma.special_gramschmidt`)."""
    return roma.special_gramschmidt(torch.stack([d6[..., :3], d6[..., 3:]], -1), epsilon=1e-8)


def matrix_to_rotation_6d(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 6): the first two columns."""
    return torch.cat([R[..., :, 0], R[..., :, 1]], -1)


def union_shape_bounds(backend: str, shape_names: tuple[str, ...]) -> tuple[torch.Tensor, torch.Tensor]:
    """(S,) low and high of the shape sampling bounds over both genders (float64)."""
    bounds = backend_class(backend).shape_bounds
    (lo_f, hi_f), (lo_m, hi_m) = (bounds(g, shape_names) for g in ("female", "male"))
    return torch.as_tensor(np.minimum(lo_f, lo_m)).double(), torch.as_tensor(np.maximum(hi_f, hi_m)).double()


class ParamHead(torch.nn.Module):
    """Raw (B, D) -> BodyParams, with the limits as (non-persistent) buffers."""

    def __init__(
        self, backend: str, shape_names: tuple[str, ...], mat: MatSpec | None = None, alpha: float = ALPHA
    ) -> None:
        super().__init__()
        mat = mat or MatSpec()
        self.layout = OutputLayout(len(shape_names))
        self.alpha = alpha
        self.gender_index = shape_names.index("gender") if "gender" in shape_names else None
        low, high = union_shape_bounds(backend, shape_names)
        limits = JointLimits.default(torch.float64)
        cx, cy = mat.centre_m
        buffers = {
            "shape_mid": (low + high) / 2,
            "shape_half": (high - low) / 2,
            "pose_lower": limits.lower,
            "pose_upper": limits.upper,
            "root_guess": torch.tensor([cx, cy, ROOT_Z_GUESS_M], dtype=torch.float64),
            "root_half": torch.tensor([mat.sensing_length_m / 2, mat.sensing_width_m / 2, 0.1], dtype=torch.float64),
            "rot6d_identity": torch.tensor(ROT6D_IDENTITY, dtype=torch.float64),
        }
        for name, value in buffers.items():
            self.register_buffer(name, value.float(), persistent=False)

    @property
    def size(self) -> int:
        return self.layout.size

    def forward(self, raw: torch.Tensor, gender: torch.Tensor | None = None) -> BodyParams:
        """raw (B, D) -> BodyParams; gender (B,) in [0, 1] (1 female) replaces Anny's entry."""
        shape_raw, trans_raw, rot_raw, pose_raw = self.layout.split(raw)
        low, high = self.shape_mid - self.shape_half, self.shape_mid + self.shape_half
        # tanh reaches +-1 in float32; the clamp only absorbs the round-off of mid + half.
        shape = torch.minimum(torch.maximum(self.shape_mid + self.shape_half * torch.tanh(shape_raw), low), high)
        if gender is not None and self.gender_index is not None:
            g = gender.to(shape).reshape(-1, 1)
            shape = torch.cat([shape[:, : self.gender_index], g, shape[:, self.gender_index + 1 :]], 1)
        translation = self.root_guess + self.root_half * trans_raw
        R = rotation_6d_to_matrix(self.rot6d_identity + rot_raw)
        mid = (self.pose_lower + self.pose_upper) / 2
        half = (self.pose_upper - self.pose_lower) / 2
        limits = JointLimits(lower=self.pose_lower, upper=self.pose_upper)
        pose = limits.squash(mid + half * pose_raw, self.alpha)
        return BodyParams(shape=shape, root_rotation=matrix_to_axis_angle(R), root_translation=translation, pose=pose)

    def shape_scale(self) -> torch.Tensor:
        """(S,) standard deviation of each shape parameter under the uniform sampling bounds:
        the shape-error normaliser (the seed's 1.728 is that of betas on [-3, 3])."""
        return (2 * self.shape_half / 12**0.5).clamp(min=1e-3)


__all__ = ["OutputLayout", "ParamHead", "matrix_to_rotation_6d", "rotation_6d_to_matrix", "union_shape_bounds"]
