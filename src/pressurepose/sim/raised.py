"""The articulated rest (`sim.articulated`) on a bed with its head section raised
(`bed.BedShape`, PmatData group F, the `half_sitting` partition).

The mattress top is two planes folded at the hinge line. Everything on it lives in surface
coordinates (s, y, n) (`BedShape.to_surface`: each point in the frame of the section on its
side of the plane bisecting the fold): a cell of the mat's grid lies at (s, y) on its section,
and a body point's height above it is its n. Per section the rest's linearisation keeps its
form: a rotation theta about the axis u through p moves a point's n by
theta (u' x (r' - p'))_n = theta (u'_s (y - p'_y) - u'_y (s - p'_s)), with u', p', r' the
axis, pivot and point in the section's frame - affine in the cell's (s, y) as on the flat bed,
with the section's own coefficients; the vertical shift dz moves n by dz cos(angle) on the
raised section. The cells of the raised section carry their part + 24 (`Linearised`'s
`section_a`), so each part has one set of moments per section.

What it leaves out: the foam is compressed along each section's normal, and the fold's cells
(within a cell of the hinge) belong to one section or the other; the body's horizontal place is
held (the rest has no horizontal DoF), so the sheet's friction holds whatever the raised
section's normal forces push toward the foot: the rest reports the friction ratio that needs
(`friction_ratio`) and a body needing more than the sheet's friction fails (`FAIL_SLIDES`).
Friction's anchors (`sim.friction`) stay horizontal (world x, y) on both sections: on the raised
section they also resist a part's motion along the normal (its sin(angle) share, up to mu N)
and hold only cos(angle) of a motion along the slope - a simplification that can move some load
between the sections.
"""

from __future__ import annotations

import math

import torch

from pressurepose.bed import BedShape
from pressurepose.body.joints import NUM_JOINTS
from pressurepose.mat import MatSpec


class RaisedBed:
    """The raised bed's geometry for the articulated rest (module doc)."""

    def __init__(self, bed: BedShape, mat: MatSpec, dtype, device):
        if bed.flat:
            raise ValueError("RaisedBed needs a raised head section (head_angle_deg > 0)")
        self.bed, self.mat = bed, mat
        self.angle = bed.angle_rad
        self.cos, self.sin = math.cos(self.angle), math.sin(self.angle)
        self.hinge_x = bed.hinge_x(mat)
        (R, _, _), _ = bed.sections(mat)
        self.R = torch.as_tensor(R, dtype=dtype, device=device)  # columns: t, y, n in world axes
        self.hinge = torch.tensor([self.hinge_x, 0.0, 0.0], dtype=dtype, device=device)

    def to_surface(self, points: torch.Tensor) -> torch.Tensor:
        return self.bed.to_surface(points, self.mat)

    def to_world(self, surface: torch.Tensor) -> torch.Tensor:
        return self.bed.to_world(surface, self.mat)

    def head_cells(self, s: torch.Tensor) -> torch.Tensor:
        """(C,) bool: the cells (centres at s along the bed) on the raised section."""
        return s < self.hinge_x

    def section_parts(self, part: torch.Tensor, head: torch.Tensor) -> torch.Tensor:
        """The cells' parts (B, C) as the linearisation counts them: + 24 on the raised section."""
        return part + NUM_JOINTS * head.to(part.dtype)

    def drop(self, points: torch.Tensor) -> torch.Tensor:
        """(B,) how far down each body moves to touch the bed: its least normal height, over
        cos(angle) on the raised section (a vertical shift moves n by that)."""
        surface = self.to_surface(points)
        n = surface[..., 2]
        n = torch.where(surface[..., 0] < self.hinge_x, n / self.cos, n)
        return n.amin(1)

    def section_a(self, flat_a: torch.Tensor, axes: torch.Tensor, pivots: torch.Tensor) -> torch.Tensor:
        """(B, N, 2, 3): each DoF's coefficients of a point's normal height over (1, s, y) on the
        raised section (index 1) and on the flat one (index 0: `flat_a`, the world's)."""
        u = axes @ self.R  # (B, N, 3): the axes in the raised section's (t, y, n) components
        p = (pivots - self.hinge) @ self.R + self.hinge  # the pivots' (s, y, n) as if on the raised section
        a = torch.stack([u[..., 1] * p[..., 0] - u[..., 0] * p[..., 1], -u[..., 1], u[..., 0]], -1)
        a[:, 0] = torch.tensor([self.cos, 0.0, 0.0], dtype=a.dtype, device=a.device)
        return torch.stack([flat_a, a], 2)

    @property
    def section_cos(self) -> tuple[float, float]:
        """The cosine of each section's slope (flat, raised): `Linearised(section_cos=...)`."""
        return (1.0, self.cos)

    def foot_push(self, part: torch.Tensor, force: torch.Tensor) -> torch.Tensor:
        """(B,) the horizontal push toward the foot of the raised section's normal forces."""
        return (force * (part >= NUM_JOINTS)).sum(1) * self.sin


def on_sheet(state, raised: RaisedBed | None):
    """`Linearised.contact_state` for `sim.friction`: the parts (0-23) and world contact points
    (on a raised bed the state's parts carry + 24 on the head section and its points lie in
    surface coordinates)."""
    if raised is None:
        return state
    part, xyz, force, stiffness = state
    return part % NUM_JOINTS, raised.to_world(xyz), force, stiffness


__all__ = ["RaisedBed", "on_sheet"]
