"""The grid the articulated rest finds its contacts on (`sim.articulated`): cell centres, area,
the mattress top under each cell and the raised section's cells."""

from __future__ import annotations

import dataclasses

import torch

from pressurepose.maps import cell_centres, grid_shape
from pressurepose.mat import MatSpec
from pressurepose.sim.articulation import from_part_frames
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.pillow import in_series, layer_in_series
from pressurepose.sim.soft_contact import lowest_points


@dataclasses.dataclass
class ContactGrid:
    """One grid of the articulated rest's contacts (`build`) and the lowest points on it (`heights`)."""

    sub: int  # cells per taxel side
    X: torch.Tensor  # (nr, nc) cell centres along the bed (m)
    Y: torch.Tensor  # (nr, nc) across
    xy: torch.Tensor  # (C, 2)
    area: float  # m^2 per cell
    top: torch.Tensor | None  # (C,) the mattress top under each cell (air cells), None: flat
    head_cells: torch.Tensor | None  # (C,) bool: on the raised section (None: flat bed)
    nr: int
    nc: int
    mat: MatSpec

    def heights(
        self,
        local: torch.Tensor,
        labels: torch.Tensor,
        rot: torch.Tensor,
        joints: torch.Tensor,
        *,
        sag: torch.Tensor | None = None,
        tissue: torch.Tensor | None = None,
        raised=None,
        pillow: tuple | None = None,
        wedge: tuple | None = None,
    ):
        """The lowest surface point per cell at a posing (rot (B, 24, 3, 3), joints (B, 24, 3)):
        its height (B, C) above the mattress top, its part (B, C; on a raised bed + 24 on the
        head section, `raised` a `sim.raised.RaisedBed`) and the tissue modulus in series (B, C)
        or None. `local` (B, P, 3): the points in their parts' frames, `labels` (P,) their parts
        (sorted), `sag` and `tissue` (B, P) or None; `pillow` (thickness (B,), cells under it
        (B, C) or None, `sim.pillow.Pillow`): heights above the pillows' tops, through them in
        series (`sim.articulated`); `wedge` (thickness per cell (B, C) or None, `sim.wedge.Wedge`)
        likewise above and through a wedge."""
        pts = from_part_frames(local, labels, rot, joints)
        if sag is not None:  # the tissue hangs toward the bed, whatever the part's turn
            pts[..., 2] -= sag
        if raised is not None:  # heights along each section's normal, the cells by section
            pts = raised.to_surface(pts)
        h, part, cell_tissue = lowest_points(pts, labels, self.mat, self.sub, tissue)
        if raised is not None:
            part = raised.section_parts(part, self.head_cells)
        if self.top is not None:
            h = h - self.top  # heights above the (air cells') top, not above z = 0
        if pillow is not None and pillow[1] is not None:
            thickness, under, spec = pillow
            h = h - thickness[:, None] * under
            cell_tissue = in_series(cell_tissue, spec, thickness, under)
        if wedge is not None and wedge[0] is not None:
            thickness, spec = wedge
            h = h - thickness
            cell_tissue = layer_in_series(cell_tissue, spec.modulus_pa, thickness)
        return h, part, cell_tissue

    @classmethod
    def build(
        cls, mat: MatSpec, mp: MattressParams, sub: int, raised, dtype: torch.dtype, device: torch.device | str | None
    ) -> ContactGrid:
        """The covered grid of `sub` cells per taxel side; `raised` a `sim.raised.RaisedBed` or None."""
        X, Y = cell_centres(mat, sub, covered=True, dtype=dtype, device=device)
        xy = torch.stack([X.reshape(-1), Y.reshape(-1)], -1)
        nr, nc = grid_shape(mat, sub, True)
        return cls(
            sub=sub,
            X=X,
            Y=Y,
            xy=xy,
            area=mat.pitch_row_m * mat.pitch_col_m / sub**2,
            top=mp.top_height(xy[:, 0]) if mp.has_cells else None,
            head_cells=None if raised is None else raised.head_cells(xy[:, 0]),
            nr=nr,
            nc=nc,
            mat=mat,
        )


__all__ = ["ContactGrid"]
