"""PMR: pressure map reconstruction from an estimated mesh (seed B.1, Fig. 16).

Q-hat and C-hat are the generator's own label maps (`pressurepose.maps.depth_map` and
`contact_map`, which `sim.sensor.label_maps` calls for the ground truth), so the network's
reconstruction equals the labels on the same mesh by construction. Q-hat is differentiable in
the vertices' heights (a per-taxel minimum through `scatter_reduce`, gradcheck in the tests);
the released original cast vertices to integers, so no gradient flowed.

C-hat = (Q-hat < 0) is a step: its derivative is zero wherever it exists. So that the contact
loss can still move the mesh, `reconstruct_maps` returns C-hat with a straight-through
gradient: the value is the exact 0/1 map, the gradient that of sigmoid(-Q-hat / T), T =
`contact_softness_mm`.
"""

from __future__ import annotations

import dataclasses

import torch

from pressurepose.maps import EMPTY_HEIGHT_M, contact_map, depth_map
from pressurepose.mat import MatSpec

CONTACT_SOFTNESS_MM = 5.0


@dataclasses.dataclass(frozen=True)
class ReconstructedMaps:
    depth_mm: torch.Tensor  # (B, 64, 27) Q-hat: lowest surface point per taxel, mm, capped at +500
    contact: torch.Tensor  # (B, 64, 27) C-hat in {0, 1}, straight-through gradient


def reconstruct_maps(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    mat: MatSpec | None = None,
    contact_softness_mm: float = CONTACT_SOFTNESS_MM,
) -> ReconstructedMaps:
    """Q-hat and C-hat of meshes (B, V, 3) in the mat frame (m), faces (F, 3), flat bed."""
    mat = mat or MatSpec()
    depth = depth_map(vertices, faces, mat)
    hard = contact_map(depth)
    soft = torch.sigmoid(-depth / contact_softness_mm)
    return ReconstructedMaps(depth_mm=depth, contact=hard + (soft - soft.detach()))


EMPTY_DEPTH_MM = EMPTY_HEIGHT_M * 1000.0

__all__ = ["CONTACT_SOFTNESS_MM", "EMPTY_DEPTH_MM", "ReconstructedMaps", "reconstruct_maps"]
