"""Sim #1's settings, result and rejection reasons (`sim.settle`)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from pressurepose.body.capsules import (
    CAPSULE_NAMES,
)
from pressurepose.body.params import BodyParams
from pressurepose.errors import UserError

REASON_TIMEOUT = "did not settle within the step limit"
REASON_NONFINITE = "non-finite state"
REASON_SANK = "sank through the mattress"
REASON_FELL = "fell off the bed"
REASON_ENERGY = "energy grew (unstable)"
REASON_OFF_BED = "body outside the bed"
SETTLE_REASONS = (REASON_TIMEOUT, REASON_NONFINITE, REASON_SANK, REASON_FELL, REASON_ENERGY, REASON_OFF_BED)

PELVIS = CAPSULE_NAMES.index("pelvis")
TRUNK = [CAPSULE_NAMES.index(n) for n in ("pelvis", "spine1", "spine2", "spine3")]
SIM_VOLUME_POINTS = 2048  # capsule volumes for masses: <= 0.3% from 8192 points, a quarter of the cost
V_STICK = 0.02  # m/s: below this sliding speed Coulomb friction becomes a (stiff) damper
# Static friction: a tangential spring per capsule and bed section from where the capsule
# stuck (its force accumulates -k v dt at the centre of pressure), k = STICK_STIFFNESS x the
# capsule's effective mass / dt^2 (omega dt ~ 0.45: stable in the explicit step), capped at
# mu N (beyond, the anchor is dragged along: slip). Without it, the damper alone lets any
# sustained push along the bed creep at F 2 dt / m_eff (a body on a raised head section slid
# 0.2-0.5 m toward the foot).
STICK_STIFFNESS = 0.2


@dataclasses.dataclass
class EpisodeOutcome:
    """How one body's settling episode ended (`settle_steps.run_batch`): the reason ("" = at
    rest), step counts, the largest capsule speed (m/s) and acceleration (m/s^2) at the end,
    the deepest sink (m), wall time per body (ms) and the resting (root rotation, root
    translation, pose), or None when the state is not kept."""

    reason: str = ""
    steps: int = 0
    touch_step: int = -1
    max_speed: float = math.inf
    max_accel: float = math.inf
    sink: float = 0.0
    wall_ms: float = 0.0
    rest: tuple | None = None


@dataclasses.dataclass(frozen=True)
class SettleConfig:
    timestep_s: float = 0.0103  # the seed's DART step
    max_steps: int = 2000
    zero_velocity_every_s: float = 4 * 0.0103  # the seed's 4 DART steps
    speed_tol_m_s: float = 0.05
    accel_tol_m_s2: float = 0.5
    drop_height_m: float = 0.02
    min_steps_after_touch: int = 8
    grid_sub: int = 1  # foundation nodes per taxel side (sim #1's grid)
    # Trunk roll held (0: off, the seed's passive body): a torque about the bed's long axis
    # on the trunk capsules pulls the pelvis's roll back to its initial value, stiffness
    # hold_roll_m x the body's weight (N m/rad), damping that stiffness x hold_time_s - the
    # muscle tone that keeps a person on a side with straight legs, where a passive body rolls
    # onto its front or back. Only sim #1 uses it; sim #2 rests the settled mesh passively.
    hold_roll_m: float = 0.0
    hold_time_s: float = 0.1

    def __post_init__(self) -> None:
        if not (self.timestep_s > 0 and math.isfinite(self.timestep_s)):
            raise UserError(f"timestep_s must be > 0, got {self.timestep_s}")
        for name in ("max_steps", "grid_sub"):
            if int(getattr(self, name)) < 1:
                raise UserError(f"SettleConfig.{name} must be >= 1")
        for name in ("hold_roll_m", "hold_time_s"):
            v = getattr(self, name)
            if not (v >= 0 and math.isfinite(v)):
                raise UserError(f"SettleConfig.{name} must be finite and >= 0, got {v}")


@dataclasses.dataclass
class SettleResult:
    """Sim #1 for B bodies. `params` is the resting pose (float64); unsettled samples keep
    their last state there and carry a reason."""

    params: BodyParams
    ok: np.ndarray  # (B,) bool
    reason: list[str]  # (B,) "" when settled
    steps: np.ndarray  # (B,) steps simulated
    touch_step: np.ndarray  # (B,) step the pelvis touched (-1: never)
    max_speed: np.ndarray  # (B,) at the end, m/s
    max_accel: np.ndarray  # (B,) at the end, m/s^2
    sink_m: np.ndarray  # (B,) deepest foundation compression at the end
    wall_ms: np.ndarray  # (B,) time taken
