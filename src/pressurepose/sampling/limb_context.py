"""The per-row constants of a pose attempt for one limb (`sampling.limb_draws`): the float32
screen's bounds and the float64 exact tests' inputs, as named fields."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from pressurepose.body.capsules import CAPSULES
from pressurepose.sampling.attempt import Attempt
from pressurepose.sampling.limbs import LIMBS, Limb
from pressurepose.sampling.partitions import ARM_CELLS, LEG_CELLS

# The float32 screen of every draw is looser than the exact tests by this much (its round-off
# is < 1e-6 m), so it never drops a draw they would accept: samples stay exact and
# batch-independent.
PREFILTER_MARGIN_M = 1e-4


@dataclasses.dataclass
class LimbContext:
    """Rows are the attempt's samples (R); `*32` fields are the screen's (float32, loosened by
    PREFILTER_MARGIN_M), the others the exact tests' (float64)."""

    o1: torch.Tensor  # (R, 3) the two bone offsets the reach test rotates
    o2: torch.Tensor
    frame32: torch.Tensor
    lo32: torch.Tensor  # (R,) the target cell's bounds along the limb's axis
    hi32: torch.Tensor
    prox32: torch.Tensor  # (R, 3) the proximal joint
    shift32: torch.Tensor
    slack32: torch.Tensor  # (R,) bed-outline slack
    left_ankle32: torch.Tensor
    offsets: torch.Tensor  # (R, n - 1, 3) bone offsets along the chain
    root: torch.Tensor  # (R, 3) the chain's first joint
    frame: torch.Tensor
    shift: torch.Tensor
    cell: torch.Tensor  # (R,) target cell
    length: torch.Tensor  # (R,) limb length
    left_ankle: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor
    local: torch.Tensor  # (R, 2c, 3) the limb's capsule ends relative to their joints
    cap_joints: list[int]
    over_bed: list[int]
    distal: int
    proximal: int
    budget: torch.Tensor | None = None  # (R,) draws each row may make (set per phase)
    children: dict[int, tuple[np.random.Generator, object]] = dataclasses.field(default_factory=dict)
    """Per row over the bed: its own generator and reachable boxes (`sampling.support`)."""


def limb_context(batch: Attempt, limb: Limb, caps: list[int]) -> LimbContext:
    """Per-row constants of the attempt for one limb (every row; windows index them); `caps`
    the capsules the limb moves."""
    m = PREFILTER_MARGIN_M
    f32 = torch.float32
    leg = limb.name.endswith("leg")
    slot = LIMBS.index(limb.name)
    chain = list(limb.chain)
    rest = batch.rest
    offsets = rest[:, chain[1:]] - rest[:, chain[:-1]]  # (R, n - 1, 3)
    # 'along' bounds of each row's target cell (outer cells open-ended).
    cell = batch.cells[:, slot].to(torch.float64)
    inf = torch.full_like(cell, math.inf)
    if leg:
        q = batch.lengths[:, 0] / LEG_CELLS
        lo, hi = cell * q, torch.where(cell == LEG_CELLS - 1, inf, (cell + 1) * q)
        lo = lo.clamp_min(0.0)  # the ankle may not lie above its hip
    else:  # rise = -along in [(3 - cell) A/4, (4 - cell) A/4)
        q = batch.lengths[:, 1] / 4
        lo = torch.where(cell == 0, -inf, (cell - 4) * q)
        hi = torch.where(cell == ARM_CELLS - 1, inf, (cell - 3) * q)
    rj = rest[:, [CAPSULES[k].joint for k in caps]]
    ci = {j: i for i, j in enumerate(chain)}
    # Screen (float32, loosened by the margin).
    reach_off = (offsets[:, 0], offsets[:, 1]) if leg else (offsets[:, 1], offsets[:, 2])
    # Limbs are measured against the bed as they will lie once a raised-bed body sits up.
    frame, shift = (batch.leg_frame, batch.leg_shift) if leg else (batch.arm_frame, batch.arm_shift)
    return LimbContext(
        o1=reach_off[0].to(f32),
        o2=reach_off[1].to(f32),
        frame32=frame.to(f32),
        lo32=(lo - m).to(f32),
        hi32=(hi + m).to(f32),
        prox32=rest[:, limb.proximal].to(f32),
        shift32=shift.to(f32),
        # bed-outline slack: the margin (legs), or the collar's reach per radian (arms)
        slack32=(torch.full_like(cell, m) if leg else offsets[:, 0].norm(dim=-1) / 3).to(f32),
        left_ankle32=(batch.left_ankle_x - m).to(f32),
        # Exact tests (float64).
        offsets=offsets,
        root=rest[:, chain[0]],
        frame=frame,
        shift=shift,
        cell=batch.cells[:, slot],
        length=batch.lengths[:, 0 if leg else 1],
        left_ankle=batch.left_ankle_x,
        lo=lo,
        hi=hi,
        local=torch.cat([batch.start0[:, caps] - rj, batch.end0[:, caps] - rj], 1),  # (R, 2c, 3)
        cap_joints=[ci[CAPSULES[k].joint] for k in caps] * 2,
        over_bed=[ci[j] for j in limb.over_bed],
        distal=ci[limb.distal],
        proximal=ci[limb.proximal],
    )
