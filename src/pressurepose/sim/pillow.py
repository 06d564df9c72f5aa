"""A pillow under the head, in the articulated rest (`sim.articulated`; docs/physics.md "Pillow").

Real in-bed recordings are made with the head on a pillow: PmatData's frames load a broad, low
patch at the head end (10-12 taxels across, 10-16 mmHg) where a head on the bare mattress
loads 5-6 taxels (docs/network.md "Real frames span the mat"). The pillow here is a soft,
thick layer lying on the mattress (on the mat) under each body's head:

- footprint: a rectangle on the mattress, from `past_neck_m` beyond the neck joint toward
  the head end, `length_m` long along the bed and `width_m` across, centred on the head (the
  covered grid clips it at the mattress's edges); placed from the pose the rest starts in;
- mechanics: a linear layer of free thickness t and material modulus E, i.e. a per-cell
  stiffness E / t (Pa/m) in series with the tissue and the mattress, its top t above the
  mattress top (a head on it sinks in, flexing the neck against its springs);
- what the mat reads under it: the load at the pillow's top spread by the layer over a
  Gaussian of sigma = `spread` x t (a load on a thick soft layer spreads over about its
  thickness), kept within the footprint with the force conserved.

What it leaves out: the pillow's own weight (~1 kg over its footprint, ~0.3 mmHg, below the
sensor's threshold), its bottoming (a 5 kg head on E = 3 kPa compresses a 10 cm pillow by
~5 cm), and its coupling to the mattress beneath (the mattress carries each cell's load as the
pillow's top does, not the spread one).
"""

from __future__ import annotations

import dataclasses

import torch

from pressurepose.body.joints import joint_index
from pressurepose.errors import UserError

HEAD, NECK = joint_index("head"), joint_index("neck")


@dataclasses.dataclass(frozen=True)
class Pillow:
    """A pillow's size and material (module doc); the thickness is per body (`rest_articulated`)."""

    modulus_pa: float = 3000.0
    """E (Pa): the stiffness per cell is E / thickness (a soft fibre or foam pillow)."""
    length_m: float = 0.45
    """Along the bed."""
    width_m: float = 0.65
    """Across the bed."""
    past_neck_m: float = 0.02
    """Its near edge lies this far beyond the neck joint, toward the head end."""
    spread: float = 0.5
    """sigma of the load's spread through the pillow, in pillow thicknesses."""

    def __post_init__(self) -> None:
        for name in ("modulus_pa", "length_m", "width_m", "spread"):
            if not float(getattr(self, name)) > 0:
                raise UserError(f"Pillow.{name} must be > 0, got {getattr(self, name)!r}")


PILLOW_THICKNESS_M = (0.05, 0.12)
"""The generator's pillows (`generate --pillow`): free thickness drawn uniformly in this range."""
MAX_THICKNESS_M = 0.3


def check_thickness(thickness_m: float) -> None:
    """UserError unless a pillow's thickness given on the command line lies in [0, MAX_THICKNESS_M]."""
    if not 0.0 <= thickness_m <= MAX_THICKNESS_M:
        raise UserError(f"pillow_m is a pillow's thickness in metres, in [0, {MAX_THICKNESS_M}]; got {thickness_m}")


def footprint(pillow: Pillow, joints: torch.Tensor, xy: torch.Tensor, thickness: torch.Tensor) -> torch.Tensor:
    """(B, C) bool: the cells (centres xy (C, 2)) under each body's pillow; joints (B, 24, 3) in
    the mat frame (the head end at smaller x); bodies of thickness 0 have none."""
    head, neck = joints[:, HEAD, :2], joints[:, NECK, :2]
    # Toward the head end along the bed: from the neck to the head (the bed's -x if level).
    d = torch.sign(head[:, 0] - neck[:, 0])
    d = torch.where(d == 0, -torch.ones_like(d), d)
    s = (xy[None, :, 0] - neck[:, None, 0]) * d[:, None]
    along = (s >= pillow.past_neck_m) & (s <= pillow.past_neck_m + pillow.length_m)
    across = (xy[None, :, 1] - head[:, None, 1]).abs() <= pillow.width_m / 2
    return along & across & (thickness[:, None] > 0)


def layer_in_series(tissue: torch.Tensor, modulus_pa: float, thickness: torch.Tensor) -> torch.Tensor:
    """The cells' tissue modulus (B, C) with a linear layer's E / t in series wherever its
    thickness (B, C) m is > 0 (a pillow here, `sim.wedge`'s wedge): two linear springs in series."""
    on = thickness > 0
    k = modulus_pa / torch.where(on, thickness, torch.ones_like(thickness))
    return torch.where(on, 1.0 / (1.0 / tissue + 1.0 / k), tissue)


def in_series(tissue: torch.Tensor, pillow: Pillow, thickness: torch.Tensor, under: torch.Tensor) -> torch.Tensor:
    """The cells' tissue modulus (B, C) with the pillow's E / t in series where `under`."""
    return layer_in_series(tissue, pillow.modulus_pa, thickness[:, None] * under)


def spread_load(
    pressure: torch.Tensor,
    under: torch.Tensor,
    pillow: Pillow,
    thickness: torch.Tensor,
    x: torch.Tensor,
    y: torch.Tensor,
) -> torch.Tensor:
    """What the mat reads (B, R, C) beneath the pillows: the pressure on the footprint `under`
    (B, R, C) spread by a Gaussian of sigma = spread x thickness (B,) (cell centres x (R,) and
    y (C,), m), kept on the footprint and scaled to its force; elsewhere unchanged. Not
    `blur.gaussian_blur`: sigma here is in metres per body on a grid of unequal pitches, and each
    source cell's load is normalised over the whole grid, so a head at the mattress's edge keeps
    its force rather than losing it to the zero padding."""
    on = under.to(pressure.dtype)
    load = pressure * on
    sigma = (pillow.spread * thickness).clamp(min=1e-6)[:, None, None]
    gx = torch.exp(-0.5 * ((x[:, None] - x[None, :])[None] / sigma) ** 2)  # (B, R, R)
    gy = torch.exp(-0.5 * ((y[:, None] - y[None, :])[None] / sigma) ** 2)  # (B, C, C)
    gx = gx / gx.sum(1, keepdim=True)  # each source row's load kept (columns sum to 1)
    gy = gy / gy.sum(1, keepdim=True)
    spread = (gx @ load @ gy.transpose(1, 2)) * on
    scale = load.sum((1, 2), keepdim=True) / spread.sum((1, 2), keepdim=True).clamp(min=1e-30)
    has = (thickness > 0)[:, None, None] & (load.sum((1, 2), keepdim=True) > 0)
    return torch.where(has, pressure * (1 - on) + spread * scale, pressure)


__all__ = [
    "MAX_THICKNESS_M",
    "PILLOW_THICKNESS_M",
    "Pillow",
    "check_thickness",
    "footprint",
    "in_series",
    "layer_in_series",
    "spread_load",
]
