"""An air mattress's support for the articulated sim #2: soft tissue in series with air tubes
that share one pressure (docs/physics.md, "Air support").

Per grid cell the body's tissue (modulus k_t, Pa/m) presses on the tubes' top; the air inside
is at one gauge pressure P for the whole mattress (connected tubes), so a cell whose tissue
would press harder than P pushes the top down by u = w - P / k_t and carries P, and any other
cell carries its tissue's k_t w (w: the cell's total compression). The tubes' top travels at
most T (`thickness_m`) before the body meets the base beneath (bottoming out): there u = T and
the tissue alone carries k_t (w - T) >= P. The air is compressed by the volume the body
displaces, V = A sum u: P = P0 + kappa V (P0 the inflation pressure, kappa the air's volume
stiffness). With u = clamp(w - P / k_t, 0, T) the stored energy is

    E(w) = max_P [ sum_i A psi_P(w_i) - (P - P0)^2 / (2 kappa) ],
    psi_P(w) = k_t (w - u)^2 / 2 + P u,

convex in w (a maximum over P of functions convex in w: p = k_t (w - u) never falls as w
grows); the maximising P solves A sum u(P) = (P - P0) / kappa (decreasing in P: a safeguarded
Newton on it, exact once the cells' states stop changing). Its gradient is A p_i, and its
Hessian A k_t on the cells the tissue carries alone (below P or bottomed) plus a rank-one term
beta 1_D 1_D^T on the cells D that press the air, beta = kappa A^2 / (1 + kappa A sum_D 1 /
k_t): a cell pressed deeper raises the pressure under every such cell.
"""

from __future__ import annotations

import torch

from pressurepose.sim.mattress import MattressParams

# Newton steps on the pressure at most (it converges in a few; the cap only guards).
_MAX_PRESSURE_STEPS = 50


class AirLaw:
    """The air support of B bodies' cells (module doc). tissue: (B, K) or a number (Pa/m);
    area: a cell's area (m^2). `__call__(w)` gives, like `SeriesLaw`, the cells' pressure (Pa),
    their own dp/dw (Pa/m: k_t on the cells the tissue carries, 0 on the displaced ones) and
    psi per unit area; `pressure`, `beta` and `displaced` of the last call complete it."""

    coupled = True

    def __init__(self, mp: MattressParams, tissue: float | torch.Tensor | None, area: float):
        if tissue is None:
            raise ValueError("the air support needs a tissue modulus (the tissue carries the cells below P)")
        self.p0 = float(mp.air_pressure_pa)
        self.kappa = float(mp.air_stiffness_pa_per_m3)
        self.travel = float(mp.thickness_m)
        self.kt = tissue
        self.area = area
        self.inv_kt = 1.0 / tissue
        self.pressure = self.beta = self.displaced = None

    def take(self, idx: torch.Tensor, cells: int | None = None) -> AirLaw:
        """The law of the bodies `idx` (their first `cells` cells if given)."""
        out = object.__new__(AirLaw)
        out.__dict__.update(
            {
                n: v[..., :cells][idx] if isinstance(v, torch.Tensor) and n in ("kt", "inv_kt") else v
                for n, v in self.__dict__.items()
            }
        )
        out.pressure = out.beta = out.displaced = None
        return out

    def solve(self, w: torch.Tensor) -> torch.Tensor:
        """The air pressure (B,) Pa for the cells' compressions w (B, K) (module doc): Newton on
        the decreasing F(P) = A sum u(P) - (P - P0) / kappa inside a bracket [lo, hi] that it
        keeps (a step leaving it bisects). A body stops at its own last step, whatever the others
        in its batch still need."""
        inv_kt = torch.as_tensor(self.inv_kt, dtype=w.dtype, device=w.device).expand_as(w)
        lo = torch.full_like(w[:, 0], self.p0)  # F(P0) >= 0
        hi = self.p0 + self.kappa * self.area * w.clamp(max=self.travel).sum(1)  # F(hi) <= 0
        P = lo.clone()
        settled = torch.zeros_like(P, dtype=torch.bool)
        for _ in range(_MAX_PRESSURE_STEPS):
            u = (w - P[:, None] * inv_kt).clamp(0.0, self.travel)
            F = self.area * u.sum(1) - (P - self.p0) / self.kappa
            lo = torch.where(F >= 0, P, lo)
            hi = torch.where(F <= 0, P, hi)
            D = (u > 0) & (u < self.travel)
            slope = self.area * torch.where(D, inv_kt, 0.0).sum(1) + 1.0 / self.kappa
            nxt = P + F / slope
            nxt = torch.where((nxt < lo) | (nxt > hi), 0.5 * (lo + hi), nxt)
            small = (nxt - P).abs() <= 1e-12 * P.abs().clamp(min=1.0)
            P = torch.where(settled, P, nxt)
            settled = settled | small
            if bool(settled.all()):
                break
        return P

    def __call__(self, w: torch.Tensor):
        P = self.solve(w)[:, None]
        kt = torch.as_tensor(self.kt, dtype=w.dtype, device=w.device).expand_as(w)
        u = (w - P / kt).clamp(0.0, self.travel)
        D = (u > 0) & (u < self.travel)  # the cells that press the air (not bottomed)
        p = kt * (w - u)
        dp = torch.where(D, 0.0, kt)  # (the caller zeroes it off contact, as for `SeriesLaw`)
        psi = 0.5 * p * (w - u) + P * u
        S = torch.where(D, 1.0 / kt, 0.0).sum(1)
        self.pressure, self.displaced = P[:, 0], D
        self.beta = self.kappa * self.area**2 / (1.0 + self.kappa * self.area * S)
        return p, dp, psi

    def bed_share(self, w: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """How far the tubes' top went down (m) under cells at compression w carrying p: u, at
        most the travel (a bottomed cell's p / k_t leaves it exactly there, up to round-off)."""
        kt = torch.as_tensor(self.kt, dtype=w.dtype, device=w.device)
        return (w - p / kt).clamp(0.0, self.travel)

    def energy(self, w: torch.Tensor) -> torch.Tensor:
        """psi per unit area (B, K), as `__call__` gives it (the air's own term: `air_energy`)."""
        return self(w)[2]

    def air_energy(self) -> torch.Tensor:
        """(B,) the air's term -(P - P0)^2 / (2 kappa) of the last call (J)."""
        return -((self.pressure - self.p0) ** 2) / (2 * self.kappa)


__all__ = ["AirLaw"]
