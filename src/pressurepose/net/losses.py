"""PressureNet's training losses (seed B.2, normalisers from REFERENCE.md).

Mod1: mean Euclidean error over the 24 joints / 0.1753 m + mean |shape error| / the shape
parameter's spread (the seed's 1.728 is the spread of betas on [-3, 3]; for Anny each
phenotype's standard deviation under the sampling bounds, `ParamHead.shape_scale`).
Mod2 adds 0.5 x MSE on the depth maps (mm) / 44.46^2 and 0.5 x L1 on the contact maps
/ 0.4428. The depth maps are compared capped at +DEPTH_CAP_MM: a taxel with no body above
holds +500 mm in Q (maps.EMPTY_HEIGHT_M), which would otherwise swamp the error of the taxels
that matter; with the cap, a limb floating over the wrong taxels is still pulled.
"""

from __future__ import annotations

import dataclasses

import torch

JOINT_SCALE_M = 0.1753
DEPTH_SCALE_MM = 44.46
CONTACT_SCALE = 0.4428
DEPTH_CAP_MM = 100.0


@dataclasses.dataclass(frozen=True)
class Targets:
    """Ground truth of a batch (mat frame, SI; maps as the generator writes them)."""

    joints: torch.Tensor  # (B, 24, 3) m
    shape: torch.Tensor  # (B, S)
    depth_mm: torch.Tensor | None = None  # (B, 64, 27)
    contact: torch.Tensor | None = None  # (B, 64, 27)


def joint_error_m(pred: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """(B, 24, 3) x 2 -> (B,) mean Euclidean joint error (m), i.e. per-sample MPJPE."""
    return (pred - true).norm(dim=-1).mean(-1)


def module_loss(
    joints: torch.Tensor,
    shape: torch.Tensor,
    targets: Targets,
    shape_scale: torch.Tensor,
    depth_mm: torch.Tensor | None = None,
    contact: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Scalar loss and its parts (floats, for logging). PMR terms when maps are given."""
    parts = {
        "joints": joint_error_m(joints, targets.joints).mean() / JOINT_SCALE_M,
        "shape": ((shape - targets.shape.to(shape)).abs() / shape_scale.to(shape)).mean(),
    }
    if depth_mm is not None:
        if targets.depth_mm is None or targets.contact is None:
            raise ValueError("the PMR losses need depth_mm and contact targets")
        cap = lambda q: q.clamp(max=DEPTH_CAP_MM)  # noqa: E731
        parts["depth"] = 0.5 * (cap(depth_mm) - cap(targets.depth_mm.to(depth_mm))).square().mean() / DEPTH_SCALE_MM**2
        parts["contact"] = 0.5 * (contact - targets.contact.to(contact)).abs().mean() / CONTACT_SCALE
    total = sum(parts.values())
    return total, {k: float(v.detach()) for k, v in parts.items()}


__all__ = [
    "CONTACT_SCALE",
    "DEPTH_CAP_MM",
    "DEPTH_SCALE_MM",
    "JOINT_SCALE_M",
    "Targets",
    "joint_error_m",
    "module_loss",
]
