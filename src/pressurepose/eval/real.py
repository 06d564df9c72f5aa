"""The posture a body lies in, read from its root rotation (PmatData's labels: supine, left,
right lateral; `pressurepose evaluate-real`).

Posture from the root: the heights of the body's left and front axes in the mat frame give
the roll about the bed's long axis, roll = atan2(left_z, front_z) whatever the yaw (0 supine,
-90 deg on the left side, +90 deg on the right, +-180 prone; the convention of `sampling` and
`benchmarks/sim_realism.py`, which put PmatData's group D "left" at roll -90 deg).
|roll| <= 45 deg: supine; >= 135: prone; otherwise left or right by its sign.
"""

from __future__ import annotations

import torch

from pressurepose.body.params import root_matrix

POSTURES = ("supine", "left", "right", "prone")
GROUP_POSTURE = {"B": "supine", "C": "right", "D": "left"}  # PmatData groups (README)


def roll_deg(root_rotation: torch.Tensor) -> torch.Tensor:
    """(B,) roll (deg) of the body about the bed's long axis from root rotations (B, 3)."""
    R = root_matrix(root_rotation)  # body axes (x left, y head, z front) -> mat frame
    # Heights of the body's left and front axes: sin and cos of the roll, whatever the yaw.
    return torch.rad2deg(torch.atan2(R[:, 2, 0], R[:, 2, 2]))


def posture_of(roll: torch.Tensor) -> list[str]:
    out = []
    for r in roll.tolist():
        a = abs(r)
        out.append("supine" if a <= 45 else "prone" if a >= 135 else ("left" if r < 0 else "right"))
    return out


__all__ = ["GROUP_POSTURE", "POSTURES", "posture_of", "roll_deg"]
