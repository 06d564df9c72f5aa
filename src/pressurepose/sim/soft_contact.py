"""Soft contact of the articulated sim #2: which surface point of the body rests on each grid
cell, and the law of soft tissue in series with the foam."""

from __future__ import annotations

import torch

from pressurepose.maps import EMPTY_HEIGHT_M, grid_origin, grid_shape
from pressurepose.mat import MatSpec
from pressurepose.sim.mattress import MattressParams


def lowest_points(
    points: torch.Tensor, labels: torch.Tensor, mat: MatSpec, sub: int, values: torch.Tensor | None = None
):
    """Lowest point height (B, C) and its part (B, C) per covered grid cell (flattened);
    cells with no point hold EMPTY_HEIGHT_M and part 0. With `values` (B, P), also the lowest
    point's value per cell (else None)."""
    B = points.shape[0]
    nr, nc = grid_shape(mat, sub, True)
    x0, y0 = grid_origin(mat, True)
    r = torch.floor((points[..., 0] - x0) * (sub / mat.pitch_row_m)).long()
    c = torch.floor((points[..., 1] - y0) * (sub / mat.pitch_col_m)).long()
    inside = (r >= 0) & (r < nr) & (c >= 0) & (c < nc)
    flat = torch.where(inside, r * nc + c, nr * nc)
    z = points[..., 2].clamp(max=EMPTY_HEIGHT_M)
    h = torch.full((B, nr * nc + 1), EMPTY_HEIGHT_M, dtype=points.dtype, device=points.device)
    h = h.scatter_reduce(1, flat, z, "amin", include_self=True)
    lowest = (z == h.gather(1, flat)) & inside
    part = torch.zeros(B, nr * nc + 1, dtype=torch.long, device=points.device)
    target = torch.where(lowest, flat, nr * nc)
    part = part.scatter(1, target, labels[None].expand(B, -1))
    if values is None:
        return h[:, :-1], part[:, :-1], None
    value = torch.ones_like(h).scatter(1, target, values)
    return h[:, :-1], part[:, :-1], value[:, :-1]


class SeriesLaw:
    """Soft tissue (linear, modulus k_t in Pa/m) in series with the foam (p = k1 u + k3 u^3):
    for a total compression w (m), the pressure p (Pa), dp/dw (Pa/m) and the stored energy per
    unit area (J/m^2). The split w = u + p / k_t has u as the root of a cubic (the function
    u + p(u)/k_t is increasing: one root, in closed form below). tissue: a number or a tensor
    broadcasting with w (its per-cell constants are computed once here); None: the foam alone."""

    def __init__(self, mp: MattressParams, tissue_pa_per_m: float | torch.Tensor | None):
        self.k1, self.k3, self.kt = mp.k1_pa_per_m, mp.k3_pa_per_m3, tissue_pa_per_m
        if tissue_pa_per_m is None:
            return
        # The foam's share u solves a u^3 + b u = w with a = k3 / k_t, b = 1 + k1 / k_t > 0: one
        # real root, u = 2 s sinh(asinh(w / (2 a s^3)) / 3) with s^2 = b / (3 a) (exact, stable
        # at w = 0).
        kt = tissue_pa_per_m
        self.inv_b = kt / (kt + self.k1)  # 1 / b
        self.half_inv_kt = 0.5 / kt
        if self.k3 > 0:
            a = self.k3 / kt
            s = ((1 + self.k1 / kt) / (3 * a)) ** 0.5
            self.two_s = 2 * s
            self.scale = 1 / (2 * a * s**3)

    def __call__(self, w: torch.Tensor):
        k1, k3 = self.k1, self.k3
        if self.kt is None:
            w2 = w * w
            return w * (k1 + k3 * w2), k1 + 3 * k3 * w2, w2 * (0.5 * k1 + 0.25 * k3 * w2)
        u = self.two_s * torch.sinh(torch.asinh(w * self.scale) / 3) if k3 > 0 else w * self.inv_b
        u2 = u * u
        p = u * (k1 + k3 * u2)
        kf = k1 + 3 * k3 * u2
        # dp/dw = kf kt / (kf + kt); stored energy: the foam's and the tissue's p^2 / (2 kt).
        return p, kf / (1 + kf * 2 * self.half_inv_kt), u2 * (0.5 * k1 + 0.25 * k3 * u2) + p * p * self.half_inv_kt


def series_law(w: torch.Tensor, mp: MattressParams, tissue_pa_per_m: float | torch.Tensor | None):
    """`SeriesLaw(mp, tissue_pa_per_m)(w)`: pressure (Pa), dp/dw (Pa/m) and stored energy per
    unit area (J/m^2) of the tissue in series with the foam at total compression w (m)."""
    return SeriesLaw(mp, tissue_pa_per_m)(w)


__all__ = ["SeriesLaw", "lowest_points", "series_law"]
