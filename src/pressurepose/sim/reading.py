"""What the pressure mat reads of the foundation's pressure (docs/physics.md "The mat's membrane"):
the cover's Gaussian spread (`MattressParams.spread_m`), the mat's membrane (`membrane_m`, over air
cells bridging their seams or pressing their stiffer crests harder, `sim.membrane`), then the mean
per taxel. Every sim #2 engine reads its images through `taxel_pressure`."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from pressurepose.blur import gaussian_blur
from pressurepose.maps import grid_origin
from pressurepose.mat import MatSpec
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.membrane import membrane_spread


def taxel_pressure(foundation_pa: torch.Tensor, params: MattressParams, mat: MatSpec, sub: int) -> torch.Tensor:
    """Foundation pressure on the covered grid's cells (B, rows*sub, cols*sub) -> per covered
    taxel (B, rows, cols) Pa: spread by the mat and cover (`spread_m`) and read through the mat's
    membrane (`membrane_m`, `sim.membrane`; over air cells bridging their seams when
    `membrane_support_pa_per_m` > 0, or pressing their stiffer crests harder when
    `membrane_wave` > 0), averaged per taxel."""
    h_cell = mat.pitch_row_m / sub
    w_cell = mat.pitch_col_m / sub
    spread = gaussian_blur(foundation_pa, params.spread_m / h_cell, params.spread_m / w_cell)
    seams = wave = None
    support = params.membrane_support_pa_per_m
    if params.has_cells:
        x0 = grid_origin(mat, covered=True)[0] + 0.5 * h_cell  # the first row's centre

        def along(rows):  # a row index (the membrane's padding included) -> x along the bed
            return x0 + rows * h_cell

        if float(support) > 0:  # the mat bridges the air tubes' seams

            def seams(rows):
                return -params.top_height(along(rows))

        elif float(params.membrane_wave) > 0:  # the tubes stiffer on their crests than in their seams

            def wave(rows):
                return params.tube_stiffness_wave(along(rows))

    spread = membrane_spread(spread, params.membrane_m, h_cell, w_cell, seams, support, wave)
    return F.avg_pool2d(spread[:, None], sub)[:, 0]


__all__ = ["taxel_pressure"]
