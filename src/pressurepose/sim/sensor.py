"""The pressure mat's reading, and the ground-truth label maps for the network.

Sensor (seed A.4, REFERENCE.md): a taxel's mat layer compresses d = p / mat_stiffness (mm)
under the pressure p that sim #2 puts on it, and reads c0 + c1 d + c2 d^2 mmHg for d > 0 (0 for
d <= 0), clipped to [0, 100] (the BT3510 saturates at 100 mmHg). Optional Gaussian noise of
`noise_mmhg` on the loaded taxels, drawn from an explicit generator (reproducible), applied
before the clip, so readings stay in [0, 100] and unloaded taxels stay 0. Readings below the
sensor's floor (`MattressParams.floor_mmhg`, after the noise) read 0, as a real mat reports nothing
below its detection floor (docs/realism.md "The sensor's floor in the generator").

Label maps: Q (depth, mm) and C (contact) are `pressurepose.maps.depth_map` and
`contact_map` of the mesh at rest - the same functions the network's PMR calls.
"""

from __future__ import annotations

import torch

from pressurepose.bed import BedShape
from pressurepose.maps import contact_map, depth_map
from pressurepose.mat import MatSpec
from pressurepose.sim.mattress import MattressParams


def taxel_reading(
    pressure_pa: torch.Tensor,
    params: MattressParams | None = None,
    mat: MatSpec | None = None,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """(B, R, C) pressure in Pa -> (B, R, C) readings in mmHg in [0, max_pressure_mmhg].

    Negative or non-finite pressures are a caller error (ValueError)."""
    params = params or MattressParams()
    mat = mat or MatSpec()
    if not torch.isfinite(pressure_pa).all():
        raise ValueError("pressure contains NaN or infinite values")
    if bool((pressure_pa < 0).any()):
        raise ValueError(f"pressure must be >= 0 Pa (min {float(pressure_pa.min()):.3g})")
    d = pressure_pa / params.mat_stiffness_pa_per_mm
    loaded = d > 0
    reading = params.c0_mmhg + params.c1_mmhg_per_mm * d + params.c2_mmhg_per_mm2 * d**2
    if float(params.noise_mmhg) > 0:
        noise = torch.randn(reading.shape, generator=generator, dtype=reading.dtype, device="cpu").to(reading.device)
        reading = reading + params.noise_mmhg * noise
    if float(params.floor_mmhg) > 0:
        loaded = loaded & (reading >= params.floor_mmhg)
    reading = torch.where(loaded, reading, torch.zeros_like(reading))
    return reading.clamp(0.0, mat.max_pressure_mmhg)


def sensing_area(covered: torch.Tensor, mat: MatSpec | None = None) -> torch.Tensor:
    """(B, covered_rows, covered_cols) -> (B, rows, cols): the recorded inner taxels."""
    mat = mat or MatSpec()
    if covered.shape[-2:] != mat.covered_shape:
        raise ValueError(f"expected a covered grid {mat.covered_shape}, got {tuple(covered.shape[-2:])}")
    rs, cs = mat.sensing_slice()
    return covered[..., rs, cs]


def label_maps(
    vertices: torch.Tensor, faces: torch.Tensor, mat: MatSpec | None = None, bed: BedShape | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth map Q (mm, (B, rows, cols)) and contact map C of meshes at rest (world frame).
    On a bent bed, heights are measured along the mattress normal in surface coordinates
    (the mat follows the mattress)."""
    mat = mat or MatSpec()
    if bed is not None and not bed.flat:
        vertices = bed.to_surface(vertices, mat)
    q = depth_map(vertices, faces, mat)
    return q, contact_map(q)


__all__ = ["label_maps", "sensing_area", "taxel_reading"]
