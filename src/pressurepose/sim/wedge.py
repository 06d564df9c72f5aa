"""A positioning wedge under a tilted body's back, in the articulated rest (`sim.articulated`;
docs/physics.md "Wedge").

Turning a person 20-40 deg toward a side and propping the back with a foam wedge is how nurses
offload the sacrum (the "30 deg tilt"); PmatData's group E records it (one or two wedges, 20
or 40 deg). Real frames of it show the body between supine and side-lying plus a broad, flat,
evenly loaded patch beside the back - the wedge's base on the mat. The wedge here:

- footprint: a rectangle on the mattress (on the mat), `length_m` along the bed centred between
  the shoulders' and the hips' midpoints, from `inner_m` beyond the trunk's midline toward its
  raised side (the side of the higher shoulder) to `base_m` further out; placed from the pose
  the rest starts in (the wedge is pushed in under the turned body);
- shape: its top rises from its thin edge at the body's tilt - the thickness at distance u from
  the thin edge is u tan(tilt), the tilt read from the starting pose's roll (`tilt_of`) - so
  a body turned by that angle leans on its slope;
- mechanics: a linear layer of modulus E, i.e. a per-cell stiffness E / t (Pa/m) in series
  with the tissue and the mattress, its top t above the mattress top (`sim.pillow.layer_in_series`,
  the pillow's layer with a thickness per cell);
- what the mat reads under it: the block's base pressure (`rigid_base`). A foam block 30 cm wide
  bends far less than the mattress under it compresses, so its base sinks as a plane: on an
  elastic bed the base pressure is then affine in position, with the force and moments of the
  load on its top - the broad, flat patch real frames show beside a tilted back.

Left out: the wedge's weight (~0.5 kg); in the rest itself each cell's load goes through the
wedge and the mattress in series, as if the block's cells were free to sink apart (the rigid
base is what the mat reads, not what the body rests on); the base lifting off where the plane
would pull (clipped at 0, the force kept); a wedge reaching beyond the mattress's edge (its part
there is lost and the base's force goes onto the part on the grid: 17.5% of 80 sampled tilted
bodies have more than 5% of the wedge beyond it, docs/physics.md "Wedge").
"""

from __future__ import annotations

import dataclasses
import math

import torch

from pressurepose.body.joints import joint_index
from pressurepose.errors import UserError

SHOULDERS = (joint_index("left_shoulder"), joint_index("right_shoulder"))
HIPS = (joint_index("left_hip"), joint_index("right_hip"))
MIN_TILT_RAD = math.radians(5.0)  # a body turned less needs no wedge
MAX_TILT_RAD = math.radians(60.0)  # wedges are not made steeper


@dataclasses.dataclass(frozen=True)
class Wedge:
    """A wedge's size and material (module doc); its slope is each body's tilt (`tilt_of`)."""

    modulus_pa: float = 30000.0
    """E (Pa): the stiffness per cell is E / thickness (firm polyurethane foam)."""
    length_m: float = 0.55
    """Along the bed."""
    base_m: float = 0.30
    """Across the bed, from the thin edge to the thick one."""
    inner_m: float = 0.0
    """The thin edge lies this far beyond the trunk's midline, toward the raised side."""

    def __post_init__(self) -> None:
        for name in ("modulus_pa", "length_m", "base_m"):
            if not float(getattr(self, name)) > 0:
                raise UserError(f"Wedge.{name} must be > 0, got {getattr(self, name)!r}")
        if not math.isfinite(self.inner_m):
            raise UserError(f"Wedge.inner_m must be finite, got {self.inner_m!r}")


def tilt_of(roll: torch.Tensor) -> torch.Tensor:
    """(B,) roll (rad, `body.params.root_roll`) -> each body's wedge slope (rad): its turn from
    supine, 0 below MIN_TILT_RAD or beyond a side (|roll| > 90 deg: lying on a side or face down
    needs no wedge), at most MAX_TILT_RAD."""
    tilt = roll.abs()
    return torch.where((tilt >= MIN_TILT_RAD) & (tilt <= math.pi / 2), tilt.clamp(max=MAX_TILT_RAD), 0.0 * tilt)


def thickness_map(wedge: Wedge, tilt: torch.Tensor, joints: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """(B, C) the wedge's thickness (m; 0 off its footprint) at cells centred at xy (C, 2), for
    bodies with joints (B, 24, 3) in the mat frame and slopes `tilt` (B,) rad (0: no wedge)."""
    shoulders, hips = joints[:, list(SHOULDERS)], joints[:, list(HIPS)]
    mid = 0.5 * (shoulders.mean(1) + hips.mean(1))  # (B, 3) the trunk's middle
    # The raised side: toward the higher shoulder, across the bed.
    high = torch.where((shoulders[:, 0, 2] >= shoulders[:, 1, 2])[:, None], shoulders[:, 0], shoulders[:, 1])
    side = torch.sign(high[:, 1] - mid[:, 1])
    side = torch.where(side == 0, torch.ones_like(side), side)
    u = (xy[None, :, 1] - mid[:, None, 1]) * side[:, None] - wedge.inner_m
    along = (xy[None, :, 0] - mid[:, None, 0]).abs() <= wedge.length_m / 2
    on = along & (u >= 0) & (u <= wedge.base_m)
    return torch.where(on, u * torch.tan(tilt)[:, None], torch.zeros_like(u))


def wedge_thickness(wedge: Wedge | None, roll: torch.Tensor, joints: torch.Tensor, grids, tissue, raised) -> tuple:
    """The rest's wedges: for each grid's cell centres (C, 2) in `grids` (None: no such grid) the
    (B, C) thickness map of bodies turned by `roll` (B,) rad - or None for every grid when there is
    no wedge or no body is turned enough (`tilt_of`). A wedge needs a flat bed (`raised` None) and
    the soft tissue (`tissue`, the surface points' modulus, not None) to rest on."""
    tilt = tilt_of(roll)
    if wedge is None or not bool(tilt.gt(0).any()):
        return tuple(None for _ in grids)
    if raised is not None:
        raise UserError("wedges lie on flat beds only; rest tilted bodies on a flat bed")
    if tissue is None:
        raise UserError("a wedge needs the soft tissue (MattressParams.tissue_pa_per_m > 0) to rest on")
    return tuple(None if xy is None else thickness_map(wedge, tilt, joints, xy) for xy in grids)


def rigid_base(pressure: torch.Tensor, on: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """What the mat reads (B, R, C) beneath the wedges: on each footprint `on` (B, R, C) the load
    replaced by the affine pressure a + b (x - xc) + c (y - yc) of the same force and first moments
    about the footprint's centroid (xc, yc) - a rigid base on an elastic bed - clipped at 0 and
    scaled back to the force; elsewhere, and for bodies without a footprint, unchanged. Cell
    centres x (R,), y (C,) in m."""
    w = on.to(pressure.dtype)
    load = pressure * w
    gx, gy = x[None, :, None].expand_as(w), y[None, None, :].expand_as(w)
    n = w.sum((1, 2))
    has = (n > 0) & (load.sum((1, 2)) > 0)
    n1 = n.clamp(min=1.0)
    dx = (gx - ((w * gx).sum((1, 2)) / n1)[:, None, None]) * w
    dy = (gy - ((w * gy).sum((1, 2)) / n1)[:, None, None]) * w
    basis = torch.stack([w, dx, dy], -1).flatten(1, 2)  # (B, R*C, 3)
    gram = basis.transpose(1, 2) @ basis
    # A footprint one cell wide has no moment about its long axis: a tiny ridge keeps it solvable.
    gram = gram + 1e-12 * gram.diagonal(dim1=1, dim2=2).amax(1).clamp(min=1.0)[:, None, None] * torch.eye(
        3, dtype=w.dtype, device=w.device
    )
    coef = torch.linalg.solve(gram, basis.transpose(1, 2) @ load.flatten(1)[..., None])
    base = (basis @ coef)[..., 0].view_as(w).clamp(min=0) * w
    base = base * (load.sum((1, 2)) / base.sum((1, 2)).clamp(min=1e-30))[:, None, None]
    return torch.where(has[:, None, None], pressure * (1 - w) + base, pressure)


__all__ = [
    "MAX_TILT_RAD",
    "MIN_TILT_RAD",
    "Wedge",
    "rigid_base",
    "thickness_map",
    "tilt_of",
    "wedge_thickness",
]
