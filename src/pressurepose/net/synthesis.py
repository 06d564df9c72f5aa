"""Analysis by synthesis: compare the input pressure image with the one sim #2 makes of the
estimated mesh (beyond the seed; issue 7).

`synthesis_loss` rests the estimated mesh on the mattress with sim #2
(`sim.foundation.simulate_pressure`, differentiable through the implicit function theorem),
reads it with the sensor model (`sim.sensor.taxel_reading`) and returns the mean absolute
difference between the two images, each scaled to a mean of 1 per taxel (the input's overall
level is unknown on real mats). Samples sim #2 cannot rest (no support, tipping over) are left
out of the mean. (A test-time `refine` that lowered this loss by Adam steps on the output
made MPJPE worse, 136 -> 149-234 mm, and was removed: docs/network.md.)
Costs one extra skinning pass for the mass and one sim #2 solve per step (~15 ms a sample).
"""

from __future__ import annotations

import torch

from pressurepose.net.model import Estimate, PressureNet
from pressurepose.sim.foundation import simulate_pressure
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.sensor import sensing_area, taxel_reading

TAXELS = 64 * 27


def _per_taxel_mean_one(p: torch.Tensor) -> torch.Tensor:
    return p * (TAXELS / p.sum((-2, -1), keepdim=True).clamp(min=1e-6))


def synthesised_pressure(
    net: PressureNet, est: Estimate, mattress: MattressParams | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, 64, 27) sensor reading (mmHg) sim #2 gives for the estimate's mesh, and (B,) bool
    whether sim #2 found a rest."""
    if est.vertices is None:
        raise ValueError("the estimate has no mesh; run the network with mesh=True")
    mattress = mattress or MattressParams()
    mass = net.body.measure(est.params.shape).mass_kg
    rest = simulate_pressure(est.vertices, net.faces, mass, mattress, net.mat, passes=1)
    reading = taxel_reading(sensing_area(rest.pressure_pa, net.mat), mattress, net.mat)
    return reading, rest.ok


def synthesis_loss(
    net: PressureNet, est: Estimate, pressure_mmhg: torch.Tensor, mattress: MattressParams | None = None
) -> torch.Tensor:
    """Scalar: mean |normalised input - normalised synthesised image| over the samples sim #2
    rests (0 with no gradient when none does)."""
    reading, ok = synthesised_pressure(net, est, mattress)
    diff = (_per_taxel_mean_one(reading) - _per_taxel_mean_one(pressure_mmhg.to(reading))).abs().mean((-2, -1))
    ok = ok.to(diff.device)
    if not bool(ok.any()):
        return diff.sum() * 0.0
    return diff[ok].mean()


__all__ = ["synthesis_loss", "synthesised_pressure"]
