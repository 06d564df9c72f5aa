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
    point's value per cell (else None). The points beyond the grid fall into a one-cell frame
    around it (dropped at the end); one scatter finds each cell's lowest point (its index), its
    part and value are read per cell (the point written last wins a tie, as before)."""
    B, P = points.shape[:2]
    nr, nc = grid_shape(mat, sub, True)
    x0, y0 = grid_origin(mat, True)
    row = (points[..., 0] - x0).mul_(sub / mat.pitch_row_m).floor_().clamp_(-1, nr).add_(1)
    col = (points[..., 1] - y0).mul_(sub / mat.pitch_col_m).floor_().clamp_(-1, nc).add_(1)
    flat = row.mul_(nc + 2).add_(col).long()  # in the framed (nr + 2, nc + 2) grid
    del row, col
    z = points[..., 2].clamp(max=EMPTY_HEIGHT_M)
    h = torch.full((B, (nr + 2) * (nc + 2)), EMPTY_HEIGHT_M, dtype=points.dtype, device=points.device)
    h.scatter_reduce_(1, flat, z, "amin", include_self=True)
    flat.masked_fill_(h.gather(1, flat) != z, 0)  # cell 0 (a frame corner) takes the others
    winner = torch.full_like(h, -1, dtype=torch.long)
    winner.scatter_(1, flat, torch.arange(P, device=points.device).expand(B, -1))

    def inner(t):
        return t.view(B, nr + 2, nc + 2)[:, 1:-1, 1:-1].reshape(B, nr * nc)

    h, winner = inner(h), inner(winner)
    empty = winner < 0
    winner = winner.clamp(min=0)
    part = labels[winner].masked_fill_(empty, 0)
    if values is None:
        return h, part, None
    return h, part, values.gather(1, winner).masked_fill_(empty, 1.0)


class SeriesLaw:
    """Soft tissue (linear, modulus k_t in Pa/m) in series with the foam (p = k1 u + k3 u^3):
    for a total compression w (m), the pressure p (Pa), dp/dw (Pa/m) and the stored energy per
    unit area (J/m^2). The split w = u + p / k_t has u as the root of a cubic (the function
    u + p(u)/k_t is increasing: one root, in closed form below). tissue: a number or a tensor
    broadcasting with w (its per-cell constants are computed once here); None: the foam alone.
    With the foam's densification (`MattressParams.densify_pa` P_d > 0; p gains P_d (u/T)^9),
    the cubic's root is the start of Newton's method on the convex, increasing
    u + p(u)/k_t - w, which it approaches from above, monotonically."""

    coupled = False  # each cell on its own (`sim.air_law.AirLaw` couples them)

    def __init__(self, mp: MattressParams, tissue_pa_per_m: float | torch.Tensor | None):
        self.k1, self.k3, self.kt = mp.k1_pa_per_m, mp.k3_pa_per_m3, tissue_pa_per_m
        self.thick = float(mp.thickness_m)
        self.dense = mp.densification if float(mp.densify_pa) > 0 else None  # (p, dp/du, energy) of u
        if tissue_pa_per_m is None:
            return
        # The foam's share u solves a u^3 + b u = w with a = k3 / k_t, b = 1 + k1 / k_t > 0: one
        # real root, u = 2 s sinh(asinh(w / (2 a s^3)) / 3) with s^2 = b / (3 a) (exact, stable
        # at w = 0).
        kt = tissue_pa_per_m
        self.inv_b = kt / (kt + self.k1)  # 1 / b
        self.half_inv_kt = 0.5 / kt
        self.inv_kt = 2 * self.half_inv_kt
        if self.k3 > 0:
            a = self.k3 / kt
            s = ((1 + self.k1 / kt) / (3 * a)) ** 0.5
            self.two_s = 2 * s
            self.scale = 1 / (2 * a * s**3)

    def take(self, idx: torch.Tensor, cells: int | None = None) -> SeriesLaw:
        """The law of the bodies `idx` (rows of per-cell constants, their first `cells` cells
        if given; numbers stay)."""
        out = object.__new__(SeriesLaw)
        out.__dict__.update(
            {n: v[..., :cells][idx] if isinstance(v, torch.Tensor) else v for n, v in self.__dict__.items()}
        )
        return out

    def __call__(self, w: torch.Tensor):
        k1, k3 = self.k1, self.k3
        if self.kt is None:
            w2 = w * w
            p, dp, e = w * (k1 + k3 * w2), k1 + 3 * k3 * w2, w2 * (0.5 * k1 + 0.25 * k3 * w2)
            if self.dense is not None:
                p_d, k_d, e_d = self.dense(w)
                p, dp, e = p + p_d, dp + k_d, e + e_d
            return p, dp, e
        u, u2, p = self._foam(w)
        kf = u2.mul(3 * k3).add_(k1)
        if self.dense is not None:
            kf = kf + self.dense(u)[1]
        # dp/dw = kf kt / (kf + kt); stored energy: the foam's and the tissue's p^2 / (2 kt).
        dp = kf.div_(kf.mul(self.inv_kt).add_(1))
        return p, dp, self._stored(u, u2, p)

    def bed_share(self, w: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """The foam's compression (m) of cells at total compression w carrying pressure p (the
        tissue's p / k_t taken off; without tissue, all of w)."""
        return w if self.kt is None else (w - p / self.kt).clamp(min=0)

    def energy(self, w: torch.Tensor) -> torch.Tensor:
        """The stored energy per unit area alone (J/m^2), as `__call__` gives it."""
        if self.kt is None:
            return self(w)[2]
        u, u2, p = self._foam(w)
        return self._stored(u, u2, p)

    def _foam(self, w):
        """The foam's compression u, u^2 and the pressure p (in-place chains: one temporary
        per result, the same operations in the same order as the formulas above)."""
        k1, k3 = self.k1, self.k3
        if k3 > 0:
            # asinh(x) = log1p(x + x^2 / (1 + sqrt(1 + x^2))) for x >= 0 (w >= 0): as accurate
            # (~2e-16 relative) and half the time of torch.asinh on a CPU.
            x = w * self.scale
            x2 = x * x
            u = x2.div_(x2.add(1).sqrt_() + 1).add_(x).log1p_().div_(3).sinh_().mul_(self.two_s)
        else:
            u = w * self.inv_b
        if self.dense is not None:  # Newton from the cubic's root, above the densified one
            kt = self.kt
            for _ in range(50):
                u2 = u * u
                p_d, k_d, _ = self.dense(u)
                g = u2.mul(k3).add(k1).mul(u).add(p_d).add(kt * u).sub(kt * w)
                step = g / (u2.mul(3 * k3).add(k1).add(k_d).add(kt))
                u = (u - step).clamp(min=0)
                if float(step.abs().max()) <= 1e-12 * self.thick:
                    break
        u2 = u * u
        p = u2.mul(k3).add_(k1).mul_(u)
        if self.dense is not None:
            p = p + self.dense(u)[0]
        return u, u2, p

    def _stored(self, u, u2, p):
        e = u2.mul(0.25 * self.k3).add_(0.5 * self.k1).mul_(u2).add_(p.mul(p).mul_(self.half_inv_kt))
        return e + self.dense(u)[2] if self.dense is not None else e


def series_law(w: torch.Tensor, mp: MattressParams, tissue_pa_per_m: float | torch.Tensor | None):
    """`SeriesLaw(mp, tissue_pa_per_m)(w)`: pressure (Pa), dp/dw (Pa/m) and stored energy per
    unit area (J/m^2) of the tissue in series with the foam at total compression w (m)."""
    return SeriesLaw(mp, tissue_pa_per_m)(w)


__all__ = ["SeriesLaw", "lowest_points", "series_law"]
