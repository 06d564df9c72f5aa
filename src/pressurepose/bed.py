"""The bed's shape: flat, or with the head section raised at a hinge (seed A.2's sitting poses).

The mattress top, with the mat on it, is folded at a hinge across the bed: the foot section
stays flat (z = 0), the head section is rotated up by `head_angle_deg` about the hinge line.
The original bent at taxel row 48 counted from the foot (~1.37 m from the foot end of the
sensing area). Everything on the mattress is described in *surface* coordinates (s, y, n):
s along the mattress top (the flat bed's x, so taxel rows stay where they are on the mat),
y across, n along the local surface normal (n = 0 on the undeformed top). For a flat bed,
surface and world coordinates coincide.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from pressurepose.errors import UserError
from pressurepose.mat import MatSpec

MAX_HEAD_ANGLE_DEG = 70.0


@dataclasses.dataclass(frozen=True)
class BedShape:
    head_angle_deg: float = 0.0
    hinge_row_from_foot: int = 48

    def __post_init__(self) -> None:
        a = float(self.head_angle_deg)
        if not (math.isfinite(a) and 0.0 <= a <= MAX_HEAD_ANGLE_DEG):
            raise UserError(f"head_angle_deg must be in [0, {MAX_HEAD_ANGLE_DEG:g}], got {self.head_angle_deg}")
        if not (isinstance(self.hinge_row_from_foot, int) and 0 < self.hinge_row_from_foot < 200):
            raise UserError(f"hinge_row_from_foot must be a positive row count, got {self.hinge_row_from_foot}")

    @property
    def flat(self) -> bool:
        return self.head_angle_deg == 0.0

    @property
    def angle_rad(self) -> float:
        return math.radians(self.head_angle_deg)

    def hinge_x(self, mat: MatSpec) -> float:
        """s (= x of the flat bed, m) of the hinge line: rows counted from the foot end of the
        sensing area."""
        return (mat.rows - self.hinge_row_from_foot) * mat.pitch_row_m

    def sections(self, mat: MatSpec) -> list[tuple[np.ndarray, float, float]]:
        """[(R, s_min, s_max)] per section: R's columns are the section's tangent along s, y and
        its normal, in world axes; the section covers s_min <= s < s_max; both sections pass
        through the hinge point (hinge_x, 0, 0)."""
        if self.flat:
            return [(np.eye(3), -math.inf, math.inf)]
        xh, p = self.hinge_x(mat), self.angle_rad
        t = np.array([math.cos(p), 0.0, -math.sin(p)])
        nrm = np.array([math.sin(p), 0.0, math.cos(p)])
        return [(np.stack([t, np.array([0.0, 1.0, 0.0]), nrm], 1), -math.inf, xh), (np.eye(3), xh, math.inf)]

    def to_surface(self, points: torch.Tensor, mat: MatSpec) -> torch.Tensor:
        """World points (..., 3) -> surface coordinates (s, y, n); each point goes to the
        section on its side of the plane that bisects the fold."""
        if self.flat:
            return points
        hinge = torch.tensor([self.hinge_x(mat), 0.0, 0.0], dtype=points.dtype, device=points.device)
        (R_head, _, _), _ = self.sections(mat)
        head = (points - hinge) @ torch.as_tensor(R_head, dtype=points.dtype, device=points.device) + hinge
        p = self.angle_rad
        bis = torch.tensor([math.sin(p), 0.0, -(1.0 - math.cos(p))], dtype=points.dtype, device=points.device)
        on_foot = ((points - hinge) @ bis) >= 0
        return torch.where(on_foot[..., None], points, head)

    def to_world(self, surface: torch.Tensor, mat: MatSpec) -> torch.Tensor:
        """Surface coordinates (..., 3) -> world points (the section chosen by s)."""
        if self.flat:
            return surface
        hinge = torch.tensor([self.hinge_x(mat), 0.0, 0.0], dtype=surface.dtype, device=surface.device)
        (R_head, _, _), _ = self.sections(mat)
        head = (surface - hinge) @ torch.as_tensor(R_head, dtype=surface.dtype, device=surface.device).T + hinge
        return torch.where((surface[..., 0] < hinge[0])[..., None], head, surface)

    def frame_at(self, s: torch.Tensor, mat: MatSpec) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Per surface coordinate s (...): unit normal, unit tangent along s (towards the foot),
        both (..., 3) in world axes, and the world point of the undeformed top at (s, 0)."""
        zeros = torch.zeros_like(s)
        world = self.to_world(torch.stack([s, zeros, zeros], -1), mat)
        foot_n = torch.tensor([0.0, 0.0, 1.0], dtype=s.dtype, device=s.device).expand(*s.shape, 3)
        foot_t = torch.tensor([1.0, 0.0, 0.0], dtype=s.dtype, device=s.device).expand(*s.shape, 3)
        if self.flat:
            return foot_n, foot_t, world
        p = self.angle_rad
        head_n = torch.tensor([math.sin(p), 0.0, math.cos(p)], dtype=s.dtype, device=s.device)
        head_t = torch.tensor([math.cos(p), 0.0, -math.sin(p)], dtype=s.dtype, device=s.device)
        in_head = (s < self.hinge_x(mat))[..., None]
        return torch.where(in_head, head_n, foot_n), torch.where(in_head, head_t, foot_t), world


__all__ = ["BedShape", "MAX_HEAD_ANGLE_DEG"]
