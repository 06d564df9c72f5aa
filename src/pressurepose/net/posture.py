"""A posture readout: which way the body lies (supine, left or right lateral, prone), read by
one linear layer after a strong dropout from the heatmap network's pooled bottleneck features
(`NetConfig.posture_head`, `train --posture-weight` / `--posture-only`).

Why: the posture a heatmap network's *body* lies in follows from which side of the mat it
localises each left and right joint on - a fine decision that real frames tip from one epoch to
the next (docs/network.md, "The real-data curve of one line"). A classifier of the four
postures sees the coarse picture only. Its labels come from the true joints (the training
targets hold no root rotation after the shift and mirror augmentations): the roll of the body
about the bed's long axis, roll = atan2(left_z, front_z) with left = the hips' and shoulders'
left-minus-right and front = left x (neck - pelvis), the body's axes as `eval.real.roll_deg`
reads them from a root rotation (x left, y head, z front), with its thresholds (|roll| <= 45 deg
supine, >= 135 prone, else left below 0 and right above).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from pressurepose.body.joints import J24_MIRROR
from pressurepose.body.params import root_roll

POSTURES = ("supine", "left", "right", "prone")
MIRRORED = (0, 2, 1, 3)  # the posture of the mirrored body: left and right swapped
LABEL_SMOOTHING = 0.1
_PELVIS, _L_HIP, _R_HIP, _NECK, _L_SHOULDER, _R_SHOULDER = 0, 1, 2, 12, 16, 17


def roll_from_root(root_rotation: torch.Tensor) -> torch.Tensor:
    """(B, 3) root rotations -> (B,) roll (deg) of the body about the bed's long axis: the
    heights of the body's left and front axes in the mat frame are its sine and cosine,
    whatever the yaw (`eval.real` reads PmatData's postures with it)."""
    return torch.rad2deg(root_roll(root_rotation))


def roll_from_joints(joints: torch.Tensor) -> torch.Tensor:
    """(B, 24, 3) J24 joints, mat frame (z up) -> (B,) roll (deg) about the bed's long axis."""
    left = joints[:, _L_HIP] - joints[:, _R_HIP] + joints[:, _L_SHOULDER] - joints[:, _R_SHOULDER]
    front = torch.linalg.cross(left, joints[:, _NECK] - joints[:, _PELVIS])
    left, front = F.normalize(left, dim=-1), F.normalize(front, dim=-1)
    return torch.rad2deg(torch.atan2(left[:, 2], front[:, 2]))


def posture_index(roll_deg: torch.Tensor) -> torch.Tensor:
    """(B,) roll (deg) -> (B,) index into POSTURES."""
    a = roll_deg.abs()
    side = torch.where(roll_deg < 0, 1, 2)
    return torch.where(a <= 45, 0, torch.where(a >= 135, 3, side)).long()


class PostureHead(nn.Module):
    """(B, F) pooled features -> (B, 4) logits over POSTURES."""

    def __init__(self, features: int, dropout: float = 0.5) -> None:
        super().__init__()
        self.layers = nn.Sequential(nn.Dropout(dropout), nn.Linear(features, len(POSTURES)))

    def forward(self, pooled: torch.Tensor) -> torch.Tensor:
        return self.layers(pooled)


def posture_loss(logits: torch.Tensor, joints: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    """Cross-entropy (label smoothing 0.1) of the posture logits (B, 4) against the posture of
    the true joints (B, 24, 3), and the share read right."""
    target = posture_index(roll_from_joints(joints.to(logits)))
    loss = F.cross_entropy(logits, target, label_smoothing=LABEL_SMOOTHING)
    right = (logits.detach().argmax(-1) == target).float().mean()
    return loss, {"posture": float(loss.detach()), "posture_accuracy": float(right)}


def mirrored_logits(logits: torch.Tensor) -> torch.Tensor:
    """The logits of the mirror image's reading, as a reading of the original body."""
    return logits[:, list(MIRRORED)]


def to_swap(body_roll_deg: torch.Tensor, posture_logits: torch.Tensor) -> torch.Tensor:
    """(B,) bool: where the body's posture and the readout's differ by left and right alone
    (supine and prone, or the two sides): the same joint positions with left and right joints
    exchanged are a body in the readout's posture (`NetConfig.posture_consistent`)."""
    body = posture_index(body_roll_deg)
    read = posture_logits.argmax(-1)
    return (body != read) & (body + read == len(POSTURES) - 1)  # supine 0 + prone 3, left 1 + right 2


def swapped_sides(joints: torch.Tensor) -> torch.Tensor:
    """(B, 24, ...) per-joint values with left and right joints exchanged, positions kept."""
    return joints[:, list(J24_MIRROR)]


__all__ = [
    "POSTURES",
    "PostureHead",
    "mirrored_logits",
    "posture_index",
    "posture_loss",
    "roll_from_joints",
    "roll_from_root",
    "swapped_sides",
    "to_swap",
]
