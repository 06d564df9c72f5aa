"""Shapes for people given by height and weight (real-data subjects, calibration studies).

`shape_for_height_mass` finds shape parameters whose standing height and mass (the body
model's own measurements) match the targets: Anny's height, weight and muscle phenotypes
(gender fixed, age that of an adult), SMPL's first two betas. Targets outside what the model
can represent come back as the closest body, with the residual reported.
"""

from __future__ import annotations

import torch

from pressurepose.body.model import BodyModel
from pressurepose.errors import UserError


def shape_for_height_mass(
    model: BodyModel, height_m, mass_kg, female: bool | float = 0.0, iterations: int = 60
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(B, S) shapes, and their (B,) heights (m) and masses (kg), closest to the targets."""
    height = torch.as_tensor(height_m, dtype=model.dtype).reshape(-1)
    mass = torch.as_tensor(mass_kg, dtype=model.dtype).reshape(-1)
    if height.shape != mass.shape:
        raise UserError("height_m and mass_kg need the same number of values")
    if not (torch.isfinite(height).all() and torch.isfinite(mass).all()) or (height <= 0).any() or (mass <= 0).any():
        raise UserError("height_m and mass_kg must be finite and > 0")
    B = height.shape[0]
    # The average adult of that gender, its size entries (`BodyModel.with_size`) fitted.
    base = model.average_shape(torch.full((B,), float(female), dtype=model.dtype, device=model.device)).detach()
    z = torch.zeros(B, model.size_dim, dtype=model.dtype, requires_grad=True)

    def make(z):
        return model.with_size(base, z)

    opt = torch.optim.LBFGS([z], lr=0.5, max_iter=iterations, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        m = model.measure(make(z))
        loss = (((m.height_m - height) / 0.01) ** 2 + ((m.mass_kg - mass) / 1.0) ** 2).sum() + 1e-3 * (z**2).sum()
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        shape = make(z)
        m = model.measure(shape)
    return shape.detach(), m.height_m, m.mass_kg
