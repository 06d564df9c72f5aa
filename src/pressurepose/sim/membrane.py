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
"""

from __future__ import annotations

import math

import torch

PAD_LENGTHS = 6.0  # padding, in lambdas: the kernel falls to ~e^-6 there


def membrane_spread(pressure: torch.Tensor, length_m, h_rows_m: float, h_cols_m: float) -> torch.Tensor:
    """(B, H, W) pressure on cells h_rows_m x h_cols_m -> the same grid read through a membrane
    of screening length `length_m` (m, a number or 0-d tensor; <= 0 returns the input)."""
    lam = torch.as_tensor(length_m, dtype=pressure.dtype, device=pressure.device)
    reach = float(lam.detach())
    if not reach > 0:
        return pressure
    H, W = pressure.shape[-2:]
    pad_r = math.ceil(PAD_LENGTHS * reach / h_rows_m)
    pad_c = math.ceil(PAD_LENGTHS * reach / h_cols_m)
    n_r, n_c = H + 2 * pad_r, W + 2 * pad_c
    spec = torch.fft.rfft2(torch.nn.functional.pad(pressure, (pad_c, pad_c, pad_r, pad_r)))
    w_r = 2 * math.pi * torch.fft.fftfreq(n_r, dtype=pressure.dtype, device=pressure.device)
    w_c = 2 * math.pi * torch.fft.rfftfreq(n_c, dtype=pressure.dtype, device=pressure.device)
    # The 5-point Laplacian's symbol: -(4 / h^2) sin^2(w / 2) per axis.
    lap = (4 / h_rows_m**2) * torch.sin(w_r / 2)[:, None] ** 2 + (4 / h_cols_m**2) * torch.sin(w_c / 2)[None] ** 2
    out = torch.fft.irfft2(spec / (1 + lam**2 * lap), s=(n_r, n_c))
    return out[:, pad_r : pad_r + H, pad_c : pad_c + W].clamp(min=0)


__all__ = ["PAD_LENGTHS", "membrane_spread"]
