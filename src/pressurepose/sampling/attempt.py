"""The pose sampler's per-sample state and the stacked tensors of one pose attempt."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from pressurepose.body.params import BodyParams
from pressurepose.sampling.poses import REJECTION_KEYS

# Rows of the per-sample frame: body axes -> bed 'along' (toward the foot) and 'up' after the
# roll only, and the mat's x and y axes after roll and yaw.
ALONG, UP, MAT_X, MAT_Y = range(4)


@dataclasses.dataclass
class SampleState:
    index: int
    rng: np.random.Generator
    cells: np.ndarray  # (4,)
    shape: np.ndarray | None = None
    root: np.ndarray | None = None  # roll, yaw, shift_x, shift_y
    failures: int = 0
    shapes: int = 0
    angles: dict = dataclasses.field(default_factory=dict)
    counts: dict = dataclasses.field(default_factory=lambda: dict.fromkeys(REJECTION_KEYS, 0))
    # Derived from the shape and root by PoseSampler._prepare (None until then).
    rest: torch.Tensor | None = None  # (24, 3) T-pose joints, body axes
    caps: tuple | None = None  # capsule start (20, 3), end (20, 3), radius (20,) at rest
    root_aa: torch.Tensor | None = None
    frame: torch.Tensor | None = None  # (4, 3): bed 'along' and 'up' axes (roll only), mat x and y axes, in body axes
    shift: torch.Tensor | None = None  # pelvis (x, y, 0) in the mat frame
    lengths: tuple[float, float] = (0.0, 0.0)  # leg (hip-knee-ankle), arm (shoulder-elbow-wrist)
    unreachable: str | None = None  # a limb whose conditions had no solution in a whole budget
    failed_limb: str | None = None  # the limb that failed the last attempt
    blocked: dict = dataclasses.field(default_factory=dict)  # limb -> shapes it blocked since its last cell
    given_up: dict = dataclasses.field(default_factory=dict)  # limb -> cells it was redrawn away from
    placed: tuple | None = None  # capsule start, end (20, 3) of the accepted pose
    head_angle: float = 0.0  # head-of-bed angle (deg), drawn with the cells
    roll: float | None = None  # the root's roll, drawn with the first shape and kept (sampler)
    pitch: torch.Tensor | None = None  # (1,) rad the trunk turns up by on a raised bed
    leg_frame: torch.Tensor | None = None  # (4, 3) `frame` for the legs (turned back by the pitch)
    leg_shift: torch.Tensor | None = None  # (3,) `shift` for the legs (the pelvis once turned)
    # `frame` and `shift` for the arms: on a raised bed their mat-x row and shift give the head
    # section's surface coordinate once the body has sat up (`sitting.sit_up_frame`).
    arm_frame: torch.Tensor | None = None  # (4, 3)
    arm_shift: torch.Tensor | None = None  # (3,)
    sat: BodyParams | None = None  # the sat-up pose on a raised bed (batch of 1)
    support: dict = dataclasses.field(default_factory=dict)  # (limb, cell) -> reachable boxes (this shape)


class Attempt:
    """The samples of one pose attempt as stacked tensors (row r = states[r])."""

    def __init__(self, states: list[SampleState]) -> None:
        self.states = states
        self.rest = torch.stack([st.rest for st in states])  # (P, 24, 3)
        self.start0 = torch.stack([st.caps[0] for st in states])  # (P, 20, 3) at rest
        self.end0 = torch.stack([st.caps[1] for st in states])
        self.radius = torch.stack([st.caps[2] for st in states])  # (P, 20)
        self.a = self.start0.clone()  # placed so far (spine at zero: torso at rest)
        self.b = self.end0.clone()
        self.frame = torch.stack([st.frame for st in states])  # (P, 4, 3)
        self.shift = torch.stack([st.shift for st in states])  # (P, 3)
        self.leg_frame = torch.stack([st.leg_frame for st in states])  # (P, 4, 3)
        self.leg_shift = torch.stack([st.leg_shift for st in states])  # (P, 3)
        self.arm_frame = torch.stack([st.arm_frame for st in states])  # (P, 4, 3)
        self.arm_shift = torch.stack([st.arm_shift for st in states])  # (P, 3)
        self.lengths = torch.tensor([st.lengths for st in states], dtype=torch.float64)  # (P, 2)
        self.cells = torch.from_numpy(np.stack([st.cells for st in states]))  # (P, 4)
        self.left_ankle_x = torch.zeros(len(states), dtype=torch.float64)
