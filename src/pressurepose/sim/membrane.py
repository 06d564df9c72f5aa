"""The pressure mat as a tensioned membrane on the mattress: what it reads around a contact.

The mat and its cover lie on the foam under tension T (N/m). Where a body presses the mat into
the foam, the tension drags the mat down beyond the contact's edge, and the foam pushes back on
it there too: the mat reads a halo around every deep contact that the body itself does not
touch (PmatData's heads read 8-12 taxels wide at >= 3 mmHg where the skull loads 4-8 at >= 6
mmHg, docs/realism.md). Linearised about the foam's stiffness k (Pa/m), the mat's deflection u
under the body's pressure p_b obeys

    k u - T laplacian(u) = p_b,

and the foam's pressure on the mat, the reading, is p = k u: p_b screened over the length
lambda = sqrt(T / k) (`MattressParams.membrane_m`), p = (1 - lambda^2 laplacian)^-1 p_b. Its
kernel is K0(r / lambda) / (2 pi lambda^2): sharp at the centre (peaks stay, unlike a Gaussian
of the same reach) with exponential tails; it keeps the total force and the centre of pressure.
Solved exactly on the grid with the discrete Laplacian's Fourier symbol, the grid zero-padded by
`PAD_LENGTHS` lambda each side (the load that would leave the mat's edge is lost, as the
Gaussian spread's is).

Over an air mattress's tubes the foundation is not flat: its top lies s(x) >= 0 below the crests
(`MattressParams.top_height`), and a taut mat bridges the seams between the tubes. With the mat's
deflection u measured down from the crests, the foundation pushes back only where the mat reaches
it, k max(0, u - s), and

    k max(0, u - s) - T laplacian(u) = p_b,   i.e.   u = S(p_b / k + min(u, s)),

S the screening above. Repeating the right-hand side from u = 0 is gradient descent on a convex
energy preconditioned by (k - T laplacian), one screened solve per pass; Nesterov's momentum
(restarted whenever a step turns back) saves a few passes (18 against 20 to 1 Pa, 34 against 40
to 0.1 Pa on a body-sized load; 2 Pa from the solution). The reading k max(0, u - s) keeps the
total force (the Laplacian sums to zero). An unloaded mat reads nothing (u = 0 lies on the crests); a loaded one is pressed into the
seams only where the load is deep enough, so the crests read more and the seams less - the bands
of PmatData's air frames, which the flat model screens away. With s = 0 it is the flat model.
Its contrast falls as 1 / load (a heavier load fills the seams).

The other model of the tubes (`wave`; the air preset's since session 42): their stiffness under
the mat waves along the bed, k (1 + w(x)), stiffest on the crests. The mat, smooth over lambda,
presses every row alike and the stiffer rows push back harder: ((1 + w) - lambda^2 laplacian) v =
p_b, the reading (1 + w) v, solved as v = S(p_b - w v) (a contraction by max |w|). Its bands are
the same share of any load, as the real frames' are in every posture.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

PAD_LENGTHS = 6.0  # padding, in lambdas: the kernel falls to ~e^-6 there
SEAM_ITERATIONS = 80  # screened solves at most over a corrugated foundation
SEAM_TOL_PA = 3.0  # ... stopping once a pass moves no cell's reading more than this (Pa; 0.02 mmHg)


def membrane_spread(
    pressure: torch.Tensor,
    length_m,
    h_rows_m: float,
    h_cols_m: float,
    seams_m: Callable[[torch.Tensor], torch.Tensor] | None = None,
    support_pa_per_m: float = 0.0,
    wave: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> torch.Tensor:
    """(B, H, W) pressure on cells h_rows_m x h_cols_m -> the same grid read through a membrane
    of screening length `length_m` (m, a number or 0-d tensor; <= 0 returns the input).

    `seams_m`, if given, maps row positions (a float tensor of row indices; the padding's are < 0
    or >= H) to the foundation's depth below its crests there (m, >= 0), and `support_pa_per_m` > 0
    is the foundation's stiffness k under the mat: the mat bridges the seams (module doc).
    `wave`, if given (instead of seams), maps row positions to the relative change w of the
    foundation's stiffness there, k (1 + w) with |w| < 1: the smooth mat presses the stiffer rows
    harder (module doc)."""
    if seams_m is not None and wave is not None:
        raise ValueError("membrane_spread takes one model of the tubes under the mat: seams_m or wave, not both")
    lam = torch.as_tensor(length_m, dtype=pressure.dtype, device=pressure.device)
    reach = float(lam.detach())
    if not reach > 0:
        return pressure
    H, W = pressure.shape[-2:]
    pad_r = math.ceil(PAD_LENGTHS * reach / h_rows_m)
    pad_c = math.ceil(PAD_LENGTHS * reach / h_cols_m)
    n_r, n_c = H + 2 * pad_r, W + 2 * pad_c
    w_r = 2 * math.pi * torch.fft.fftfreq(n_r, dtype=pressure.dtype, device=pressure.device)
    w_c = 2 * math.pi * torch.fft.rfftfreq(n_c, dtype=pressure.dtype, device=pressure.device)
    # The 5-point Laplacian's symbol: -(4 / h^2) sin^2(w / 2) per axis.
    lap = (4 / h_rows_m**2) * torch.sin(w_r / 2)[:, None] ** 2 + (4 / h_cols_m**2) * torch.sin(w_c / 2)[None] ** 2
    symbol = 1 / (1 + lam**2 * lap)

    def screen(x: torch.Tensor) -> torch.Tensor:
        return torch.fft.irfft2(torch.fft.rfft2(x) * symbol, s=(n_r, n_c))

    padded = torch.nn.functional.pad(pressure, (pad_c, pad_c, pad_r, pad_r))
    if seams_m is None and wave is None:
        return screen(padded)[:, pad_r : pad_r + H, pad_c : pad_c + W].clamp(min=0)
    rows = torch.arange(-pad_r, H + pad_r, dtype=pressure.dtype, device=pressure.device)
    if seams_m is None:
        w = wave(rows)[:, None].expand(n_r, n_c)
        if not float(w.detach().abs().max()) < 1:
            raise ValueError("the foundation's stiffness wave must stay within (-1, 1) of its mean")
        v = screen(padded)  # ((1 + w) - lambda^2 laplacian) v = p as v = S(p - w v): contracts by max |w|
        for _ in range(SEAM_ITERATIONS):
            nxt = screen(padded - w * v)
            step = float((nxt - v).detach().abs().max())
            v = nxt
            if step < SEAM_TOL_PA:
                break
        out = (1 + w) * v
    else:
        if not float(support_pa_per_m) > 0:
            raise ValueError("a membrane over seams needs the foundation's stiffness support_pa_per_m > 0")
        s = seams_m(rows).clamp(min=0)[:, None].expand(n_r, n_c)
        k = support_pa_per_m
        load = screen(padded / k)  # the first pass from u = 0 (min(0, s) = 0)
        u = prev = load
        t = 1.0
        for _ in range(SEAM_ITERATIONS):  # Nesterov-accelerated passes, restarted when a step turns back
            t_next = (1 + math.sqrt(1 + 4 * t * t)) / 2
            nxt = load + screen(torch.minimum(u + (t - 1) / t_next * (u - prev), s))
            step = (nxt - u).detach()
            if float((step * (u - prev).detach()).sum()) < 0:
                t_next = 1.0
            prev, u, t = u, nxt, t_next
            if float(k * step.abs().max()) < SEAM_TOL_PA:
                break
        out = k * (u - s).clamp(min=0)
    return out[:, pad_r : pad_r + H, pad_c : pad_c + W].clamp(min=0)


__all__ = ["PAD_LENGTHS", "membrane_spread"]
