"""Initial pose sampling (seed A.1): stratified rejection sampling of resting poses.

For each sample: draw the shape, the root (roll, yaw, shift) and, once, the cell each limb
must reach; then draw joint angles limb by limb until the distal joint lands in its cell (and
over the bed, crossed, ... as the partition asks) with the limb's capsules clear of the torso,
the head and the limbs placed before it. A limb that finds no such draw within
`max_limb_draws` draws fails the attempt; after `max_failures` failures (or at once when no
draw even reached the cell) the shape and root are drawn again, a limb that blocked
CELL_REDRAW_AFTER shapes gets a new cell, and after `max_shapes` shapes the sample gives up
with an error naming the partition - never an endless loop.

Determinism: every sample owns a random generator seeded from (seed, partition, gender,
over_bed, index) and draws from it in a fixed pattern that depends only on its own outcomes,
so a sample is the same whether it is drawn alone or in a batch of any size: the capsule
geometry is fitted in float64 and rounded to 1 nm, so batched round-off cannot change a
decision or a recorded number.

Speed: all samples of a batch advance together. Capsules are fitted for all new shapes at
once (body/capsules.py). Each limb's draws are tested in windows of several rounds: a float32
screen of every draw that is looser than the real conditions (it never drops a draw they
accept), the exact float64 tests for the few survivors, then self-collisions in draw order;
the generator is wound back to the end of the winning round, so windows change nothing but
the speed.

Raised bed (the half_sitting partition): each sample also draws the head-of-bed angle (once,
with its cells); with each shape and root comes the pitch at which that trunk rests on both
bed sections (`sampling.sitting.trunk_pitch`). Limbs are drawn in the trunk's frame as
usual, but the legs' cells, heights and bed outline are measured in the bed's frame turned
back by the pitch, so they hold for the legs on the flat foot section after the body is
turned up rigidly (`sit_up`: joint angles, limits and self-collisions unchanged). The sat-up
pose is then checked for what turning can change: the over-bed rule in the bed's surface
coordinates, and that the trunk, not a hand or a heel, rests on the bed (within
SEAT_TOLERANCE_M); a failure counts as a failed attempt (`sit_up_rejections`).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import zlib

import numpy as np
import torch

from pressurepose.bed import BedShape
from pressurepose.body.capsules import CAPSULES, Capsules, capsule_clearance, collision_pairs, fit_capsules
from pressurepose.body.joints import J24_NAMES, NUM_POSE_JOINTS
from pressurepose.body.kinematics import forward_kinematics, pose_in_mat
from pressurepose.body.limits import JointLimits
from pressurepose.body.model import BodyModel
from pressurepose.body.params import BodyParams, root_matrix
from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.sampling.partitions import (
    ARM_CELLS,
    HEIGHT_TOLERANCE_M,
    LEG_CELLS,
    Partition,
    SamplingConfig,
    limb_cells,
)
from pressurepose.sampling.shapes import draw_shape, shape_bounds
from pressurepose.sampling.sitting import HIP_JOINTS, fold_params, pitch_matrix, sit_up, trunk_pitch

_J = J24_NAMES.index
_D = math.pi / 180

# Joint-angle sampling ranges (REFERENCE.md, degrees, left side; the right side mirrors:
# (x, y, z) -> (x, -y, -z)). The shoulder triple is split 1/3 collar, 2/3 shoulder.
HIP_DEG = ((-90.0, 17.8), (-33.7, 32.6), (-30.5, 38.6))
KNEE_DEG = (-1.3, 139.9)   # about x
SHOULDER_DEG = ((-88.9, 81.4), (-140.7, 43.7), (-90.0, 80.4))
ELBOW_DEG = (-147.3, 2.8)  # about y
GEOMETRY_QUANTUM_M = 1e-9
FIRST_ROUND, LARGEST_ROUND = 64, 4096  # joint-angle draws per round, per limb and sample

LIMBS = ("left_leg", "right_leg", "left_arm", "right_arm")  # the order limbs are drawn in
_TORSO_JOINTS = tuple(_J(n) for n in ("pelvis", "spine1", "spine2", "spine3", "neck", "head"))
REJECTION_KEYS = ("limb_draws_rejected", "limb_failures", "collisions", "shape_resamples", "cell_redraws",
                  "sit_up_rejections")
# Sitting up on a raised bed: the trunk must rest on the bed, not be propped up by a hand or a
# heel by more than a lying body may be (its distal joints lie up to HEIGHT_TOLERANCE_M below
# their proximal joints); sim #1 lets it down.
SEAT_TOLERANCE_M = HEIGHT_TOLERANCE_M
# A limb whose cell had no solution for this many shapes gets a new cell: over the bed, a cell
# can lie off the mattress for nearly every body (a straight arm held out sideways); the seed
# clips such cells, the original redrew them.
CELL_REDRAW_AFTER = 2


def _mirror(ranges, side):
    if side == "left":
        return ranges
    (xl, xh), (yl, yh), (zl, zh) = ranges
    return ((xl, xh), (-yh, -yl), (-zh, -zl))


@dataclasses.dataclass(frozen=True)
class _Limb:
    name: str
    side: str
    chain: tuple[int, ...]      # J24 joints from the limb's root to its tip (root's parent has identity)
    proximal: int               # J24 joint the cell is measured from
    distal: int                 # J24 joint that must reach the cell
    over_bed: tuple[int, ...]   # joints that must lie over the mattress
    low: np.ndarray             # (k,) sampling range of the drawn angles, radians
    high: np.ndarray


def _limbs(limits: JointLimits) -> dict[str, _Limb]:
    out = {}
    for side in ("left", "right"):
        hip = _mirror(HIP_DEG, side)
        knee = KNEE_DEG
        low = [r[0] * _D for r in hip] + [knee[0] * _D]
        high = [r[1] * _D for r in hip] + [knee[1] * _D]
        bounds = [limits.bounds_of(f"{side}_hip")[k] for k in range(3)] + [limits.bounds_of(f"{side}_knee")[0]]
        low, high = _intersect(low, high, bounds)
        out[f"{side}_leg"] = _Limb(
            f"{side}_leg", side, (_J(f"{side}_hip"), _J(f"{side}_knee"), _J(f"{side}_ankle"), _J(f"{side}_foot")),
            _J(f"{side}_hip"), _J(f"{side}_ankle"),
            (_J(f"{side}_knee"), _J(f"{side}_ankle"), _J(f"{side}_foot")), low, high)
        sh = _mirror(SHOULDER_DEG, side)
        el = ELBOW_DEG if side == "left" else (-ELBOW_DEG[1], -ELBOW_DEG[0])
        low = [r[0] * _D for r in sh] + [el[0] * _D]
        high = [r[1] * _D for r in sh] + [el[1] * _D]
        # The shoulder triple is split 1/3 : 2/3 onto collar and shoulder, whose limits are
        # the same split of these ranges; intersect through the shoulder's share.
        sb = limits.bounds_of(f"{side}_shoulder") * 1.5
        bounds = [sb[k] for k in range(3)] + [limits.bounds_of(f"{side}_elbow")[1]]
        low, high = _intersect(low, high, bounds)
        out[f"{side}_arm"] = _Limb(
            f"{side}_arm", side,
            (_J(f"{side}_collar"), _J(f"{side}_shoulder"), _J(f"{side}_elbow"), _J(f"{side}_wrist"), _J(f"{side}_hand")),
            _J(f"{side}_shoulder"), _J(f"{side}_wrist"),
            (_J(f"{side}_elbow"), _J(f"{side}_wrist"), _J(f"{side}_hand")), low, high)
    return out


def _intersect(low, high, bounds):
    lo = np.array([max(a, float(b[0])) for a, b in zip(low, bounds)])
    hi = np.array([min(a, float(b[1])) for a, b in zip(high, bounds)])
    # float32 limit tables round: stay a hair inside so every drawn angle passes `contains`.
    span = hi - lo
    return lo + 1e-6 * span, hi - 1e-6 * span


def limb_pose(limb: _Limb, angles: torch.Tensor) -> torch.Tensor:
    """(..., k) drawn angles of a limb -> (..., len(chain) - 1 or so, 3) axis-angle of the
    rotating joints of its chain, in chain order (legs: hip, knee; arms: collar, shoulder,
    elbow)."""
    z = torch.zeros_like(angles[..., 0])
    if limb.name.endswith("leg"):
        hip = angles[..., :3]
        knee = torch.stack([angles[..., 3], z, z], -1)
        return torch.stack([hip, knee], -2)
    total = angles[..., :3]
    elbow = torch.stack([z, angles[..., 3], z], -1)
    return torch.stack([total / 3, total * (2 / 3), elbow], -2)


def _rotation_matrix(aa: torch.Tensor) -> torch.Tensor:
    """(N, 3) rotation vectors -> (N, 3, 3): I + a K + b K^2 with K^2 = k k^T - |k|^2 I,
    a = sin(t)/t, b = (1 - cos t)/t^2 from the half angle (stable at t -> 0)."""
    theta2 = (aa * aa).sum(-1)
    half = theta2.clamp_min(torch.finfo(aa.dtype).tiny).sqrt() * 0.5
    sinc = torch.sin(half) / half
    a, b = sinc * torch.cos(half), 0.5 * sinc * sinc
    x, y, z = aa.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).view(-1, 3, 3)
    eye = torch.eye(3, dtype=aa.dtype)
    return eye + a[:, None, None] * K + b[:, None, None] * (aa[:, :, None] * aa[:, None, :] - theta2[:, None, None] * eye)


def _rotating_joints(limb: _Limb) -> tuple[int, ...]:
    return limb.chain[:2] if limb.name.endswith("leg") else limb.chain[:3]


# --- limb geometry, elementwise ---------------------------------------------------------------
# A vector is a tuple of three tensors (x, y, z) of one broadcast shape: every operation is
# elementwise on contiguous arrays, so each draw's numbers depend on its own inputs only.
Vec = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def _rodrigues(k: Vec):
    """Rotation vectors k -> what `_rotate` needs: R(k) v = v + a (k x v) + b (k (k.v) - |k|^2 v),
    a = sin(t)/t, b = (1 - cos t)/t^2, written with the half angle (stable at t -> 0)."""
    theta2 = k[0] * k[0] + k[1] * k[1] + k[2] * k[2]
    half = theta2.clamp_min(torch.finfo(theta2.dtype).tiny).sqrt() * 0.5
    sinc = torch.sin(half) / half
    return k, theta2, sinc * torch.cos(half), 0.5 * sinc * sinc


def _rotate(rod, v: Vec) -> Vec:
    k, theta2, a, b = rod
    dot = k[0] * v[0] + k[1] * v[1] + k[2] * v[2]
    cross = (k[1] * v[2] - k[2] * v[1], k[2] * v[0] - k[0] * v[2], k[0] * v[1] - k[1] * v[0])
    return tuple(v[i] + a * cross[i] + b * (k[i] * dot - theta2 * v[i]) for i in range(3))


def _apply_hinge(limb: _Limb, angle: torch.Tensor, v: Vec) -> Vec:
    """v turned by the knee (about x) or elbow (about y) angle."""
    c, s = torch.cos(angle), torch.sin(angle)
    if limb.name.endswith("leg"):  # about x
        return (v[0], c * v[1] - s * v[2], s * v[1] + c * v[2])
    return (c * v[0] + s * v[2], v[1], c * v[2] - s * v[0])  # about y


def _add(a: Vec, b: Vec) -> Vec:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def _dot(a: Vec, b: Vec) -> torch.Tensor:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cols(x: torch.Tensor) -> Vec:
    """(..., 3) -> three (..., 1) column tensors (broadcast against (..., M) draws)."""
    return tuple(x[..., i:i + 1] for i in range(3))


def _split(x: torch.Tensor) -> Vec:
    return tuple(x[..., i] for i in range(3))


@dataclasses.dataclass
class InitialPoses:
    """A batch of sampled initial poses (float64) with their provenance."""

    params: BodyParams                 # shape, root (mat frame; lowest capsule point on z = 0), pose
    joints: torch.Tensor               # (B, 24, 3) J24 in the mat frame
    index: np.ndarray                  # (B,) sample index within (seed, partition, gender, over_bed)
    cells: np.ndarray                  # (B, 4) target cell of left leg, right leg, left arm, right arm
    root_draw: np.ndarray              # (B, 4) drawn roll, yaw (rad), shift along, across (m)
    head_angle_deg: np.ndarray         # (B,) head-of-bed angle the pose rests on (0: flat bed)
    rejections: dict[str, np.ndarray]  # REJECTION_KEYS -> (B,) counts
    config: SamplingConfig
    backend: str

    @property
    def batch_size(self) -> int:
        return int(self.index.shape[0])

    def beds(self) -> list[BedShape]:
        """The bed each sample rests on (what sim #1 and sim #2 must be given)."""
        return [BedShape(float(a)) for a in self.head_angle_deg]

    @classmethod
    def cat(cls, parts: list[InitialPoses]) -> InitialPoses:
        """One InitialPoses from several of the same config, in order."""
        first = parts[0]
        return cls(
            params=BodyParams.cat([p.params for p in parts]), joints=torch.cat([p.joints for p in parts]),
            index=np.concatenate([p.index for p in parts]), cells=np.concatenate([p.cells for p in parts]),
            root_draw=np.concatenate([p.root_draw for p in parts]),
            head_angle_deg=np.concatenate([p.head_angle_deg for p in parts]),
            rejections={k: np.concatenate([p.rejections[k] for p in parts]) for k in REJECTION_KEYS},
            config=first.config, backend=first.backend,
        )


class UnreachableConstraints(UserError):
    """Raised when a sample cannot satisfy its partition within the attempt limits."""


@dataclasses.dataclass
class _State:
    index: int
    rng: np.random.Generator
    cells: np.ndarray                  # (4,)
    shape: np.ndarray | None = None
    root: np.ndarray | None = None     # roll, yaw, shift_x, shift_y
    failures: int = 0
    shapes: int = 0
    angles: dict = dataclasses.field(default_factory=dict)
    counts: dict = dataclasses.field(default_factory=lambda: dict.fromkeys(REJECTION_KEYS, 0))
    # Derived from the shape and root by PoseSampler._prepare (None until then).
    rest: torch.Tensor | None = None   # (24, 3) T-pose joints, body axes
    caps: tuple | None = None          # capsule start (20, 3), end (20, 3), radius (20,) at rest
    root_aa: torch.Tensor | None = None
    frame: torch.Tensor | None = None  # (4, 3): bed 'along' and 'up' axes (roll only), mat x and y axes, in body axes
    shift: torch.Tensor | None = None  # pelvis (x, y, 0) in the mat frame
    lengths: tuple[float, float] = (0.0, 0.0)  # leg (hip-knee-ankle), arm (shoulder-elbow-wrist)
    unreachable: str | None = None     # a limb whose conditions had no solution in a whole budget
    failed_limb: str | None = None     # the limb that failed the last attempt
    blocked: dict = dataclasses.field(default_factory=dict)  # limb -> shapes it blocked since its last cell
    given_up: dict = dataclasses.field(default_factory=dict)  # limb -> cells it was redrawn away from
    placed: tuple | None = None        # capsule start, end (20, 3) of the accepted pose
    head_angle: float = 0.0            # head-of-bed angle (deg), drawn with the cells
    pitch: torch.Tensor | None = None  # (1,) rad the trunk turns up by on a raised bed
    leg_frame: torch.Tensor | None = None  # (4, 3) `frame` for the legs (turned back by the pitch)
    leg_shift: torch.Tensor | None = None  # (3,) `shift` for the legs (the pelvis once turned)
    sat: BodyParams | None = None      # the sat-up pose on a raised bed (batch of 1)


class _Attempt:
    """The samples of one pose attempt as stacked tensors (row r = states[r])."""

    def __init__(self, states: list[_State]) -> None:
        self.states = states
        self.rest = torch.stack([st.rest for st in states])            # (P, 24, 3)
        self.start0 = torch.stack([st.caps[0] for st in states])       # (P, 20, 3) at rest
        self.end0 = torch.stack([st.caps[1] for st in states])
        self.radius = torch.stack([st.caps[2] for st in states])       # (P, 20)
        self.a = self.start0.clone()  # placed so far (spine at zero: torso at rest)
        self.b = self.end0.clone()
        self.frame = torch.stack([st.frame for st in states])          # (P, 4, 3)
        self.shift = torch.stack([st.shift for st in states])          # (P, 3)
        self.leg_frame = torch.stack([st.leg_frame for st in states])  # (P, 4, 3)
        self.leg_shift = torch.stack([st.leg_shift for st in states])  # (P, 3)
        self.lengths = torch.tensor([st.lengths for st in states], dtype=torch.float64)  # (P, 2)
        self.cells = torch.from_numpy(np.stack([st.cells for st in states]))  # (P, 4)
        self.left_ankle_x = torch.zeros(len(states), dtype=torch.float64)


def sample_key(config: SamplingConfig, index: int) -> list[int]:
    """The entropy a sample's generator is seeded from."""
    return [int(config.seed), zlib.crc32(config.partition.encode()), int(config.gender == "female"),
            int(config.over_bed), int(index)]


def root_axis_angle(roll: float, yaw: float) -> np.ndarray:
    """Axis-angle (3,) of Rz(yaw) Rx(roll) (roll about the bed's long axis, then yaw in the bed
    plane), from the quaternion product in scalar float64 arithmetic (bit-identical whatever
    else is computed alongside)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    w, v = cy * cr, np.array([cy * sr, sy * sr, sy * cr])
    if w < 0:
        w, v = -w, -v
    n = math.sqrt(float(v @ v))
    if n < 1e-12:
        return 2.0 * v / w
    return v * (2.0 * math.atan2(n, w) / n)


# Rows of the per-sample frame: body axes -> bed 'along' (toward the foot) and 'up' after the
# roll only, and the mat's x and y axes after roll and yaw.
_ALONG, _UP, _MAT_X, _MAT_Y = range(4)
# The float32 screen of every draw is looser than the exact tests by this much (its round-off
# is < 1e-6 m), so it never drops a draw they would accept: samples stay exact and
# batch-independent.
PREFILTER_MARGIN_M = 1e-4
# Elements per temporary of the screen: samples x draws chunks that stay in the CPU cache.
_SCREEN_ELEMENTS = 1 << 16
# Draws tested at once (pending samples x rounds of a window): ~4 ms of work, so that the fixed
# cost of a window (~3 ms of small tensor operations) stays a small share.
_WINDOW_DRAWS = 1 << 16


class PoseSampler:
    """Draws initial poses for one SamplingConfig with one body model.

    >>> sampler = PoseSampler(model, SamplingConfig(partition="supine", gender="male"))
    >>> poses = sampler.sample(range(100))
    """

    def __init__(self, model: BodyModel, config: SamplingConfig, mat: MatSpec | None = None,
                 partition: Partition | None = None) -> None:
        """`partition` overrides the named preset of `config` (for experiments)."""
        if not isinstance(config, SamplingConfig):
            raise ValueError(f"expected a SamplingConfig, got {type(config).__name__}")
        self.model = model
        self.config = config
        self.part = partition or config.spec
        self.mat = mat or MatSpec()
        gender = getattr(model, "gender", None)
        if model.name == "smpl" and gender not in (None, "neutral", config.gender):
            raise UserError(
                f"the SMPL model is {gender} but the sampling asks for {config.gender}; "
                f"load the {config.gender} SMPL model or the neutral one"
            )
        self.shape_low, self.shape_high = shape_bounds(model.name, config.gender, model.shape_names)
        self.leg_cells, self.arm_cells = limb_cells(self.part, config.over_bed)
        self.limits = JointLimits.default(torch.float64)
        self.limbs = _limbs(self.limits)
        self.pairs = collision_pairs(self.part.checked_capsules)
        # Capsules each limb moves, and the checked pairs its draws are tested on: those
        # between its capsules and the torso, the head or a limb drawn before it.
        self._limb_capsules, self._limb_pairs = {}, {}
        placed = {i for i, c in enumerate(CAPSULES) if c.joint in _TORSO_JOINTS}
        for name in LIMBS:
            mine = [i for i, c in enumerate(CAPSULES) if c.joint in self.limbs[name].chain]
            self._limb_capsules[name] = mine
            known = placed | set(mine)
            keep = [k for k, (i, j) in enumerate(self.pairs.tolist())
                    if (i in mine and j in known) or (j in mine and i in known)]
            self._limb_pairs[name] = self.pairs[keep]
            placed |= set(mine)
        (self.x_lo, self.x_hi), (self.y_lo, self.y_hi) = self.mat.mattress_bounds_m
        self.centre = np.array([(self.x_lo + self.x_hi) / 2, (self.y_lo + self.y_hi) / 2])
        self._round_ends = _draw_schedule(config.max_limb_draws)

    # --- public -------------------------------------------------------------------------
    def sample(self, indices) -> InitialPoses:
        """Initial poses for the given sample indices (any iterable of ints >= 0)."""
        indices = [int(i) for i in indices]
        if not indices:
            raise ValueError("no sample indices given")
        if min(indices) < 0:
            raise ValueError("sample indices must be >= 0")
        states = [self._new_state(i) for i in indices]
        self._advance(states)
        return self._collect(states)

    def _advance(self, states: list[_State]) -> None:
        """Attempts until every sample has a pose (or one gives up: UnreachableConstraints)."""
        pending = list(states)
        while pending:
            for st in pending:
                if st.shape is None:
                    self._draw_shape_and_root(st)
            self._prepare(pending)
            # Inference mode: less overhead per tensor operation. Only here: libraries that
            # cache tensors (roma, in the capsule fit) must not cache inference tensors.
            with torch.inference_mode():
                self._draw_limbs(pending)
                if self.part.raised:
                    self._sit_up([st for st in pending if len(st.angles) == len(LIMBS)])
            still = []
            for st in pending:
                if len(st.angles) == len(LIMBS):
                    continue
                st.failures += 1
                last = st.failed_limb  # None: the pose failed when sat up
                if st.failures > self.config.max_failures or st.unreachable is not None:
                    # This shape is given up; a limb that blocked CELL_REDRAW_AFTER shapes
                    # gets a new cell.
                    st.blocked[last] = st.blocked.get(last, 0) + 1
                    if last is not None and st.blocked[last] >= CELL_REDRAW_AFTER:
                        # A new cell, not one that already blocked this limb (unless all did).
                        slot = LIMBS.index(last)
                        given_up = st.given_up.setdefault(last, set())
                        given_up.add(int(st.cells[slot]))
                        cells = self.leg_cells if last.endswith("leg") else self.arm_cells
                        left = [c for c in cells if c not in given_up] or list(cells)
                        st.cells[slot] = st.rng.choice(np.array(left))
                        st.blocked[last] = 0
                        st.counts["cell_redraws"] += 1
                    st.shapes += 1
                    st.counts["shape_resamples"] += 1
                    if st.shapes >= self.config.max_shapes:
                        raise UnreachableConstraints(
                            f"sample {st.index} of partition {self.config.partition!r} "
                            f"({self.config.gender}, over_bed={self.config.over_bed}) found no valid pose "
                            f"after {self.config.max_shapes} shapes x {self.config.max_failures + 1} attempts; "
                            f"its constraints are unreachable with these settings "
                            f"(raise max_shapes or max_limb_draws, or use another partition); "
                            + (f"last blocked: {last} in cell {st.cells[LIMBS.index(last)]}" if last is not None
                               else "the last pose failed when sat up on the raised bed")
                        )
                    st.shape = None
                    st.failures = 0
                    st.unreachable = None
                still.append(st)
            pending = still

    # --- steps --------------------------------------------------------------------------
    def _new_state(self, index: int) -> _State:
        rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(sample_key(self.config, index))))
        legs = rng.choice(np.array(self.leg_cells), size=2)
        arms = rng.choice(np.array(self.arm_cells), size=2)
        st = _State(index=index, rng=rng, cells=np.concatenate([legs, arms]))
        if self.part.raised:  # once per sample, like the cells (flat partitions draw nothing more)
            st.head_angle = float(rng.choice(np.array(self.part.head_angles_deg)))
        return st

    def _draw_shape_and_root(self, st: _State) -> None:
        st.shape = draw_shape(st.rng, self.shape_low, self.shape_high)
        p = self.part
        roll = st.rng.uniform(*p.roll)
        if p.either_side and st.rng.random() < 0.5:  # drawn only by such partitions: the others' streams stay
            roll = -roll
        st.root = np.array([roll, st.rng.uniform(*p.yaw), st.rng.uniform(*p.shift_x), st.rng.uniform(*p.shift_y)])
        st.rest = None

    def _prepare(self, states: list[_State]) -> None:
        """Rest joints, capsules and root transforms for samples with a new shape."""
        need = [st for st in states if st.rest is None]
        if not need:
            return
        model = self._fit_model()
        shape = torch.tensor(np.stack([st.shape for st in need]), dtype=torch.float64, device=model.device)
        with torch.no_grad():
            caps = fit_capsules(model, shape)
        # Rounded to 1 nm: float64 round-off of a batched fit (~1e-16 m) can then never make
        # a sample depend on the batch it was drawn in.
        q = lambda x: (x.cpu() / GEOMETRY_QUANTUM_M).round() * GEOMETRY_QUANTUM_M  # noqa: E731
        rest, start, end, radius = q(caps.rest), q(caps.start), q(caps.end), q(caps.radius)
        root = np.stack([st.root for st in need])
        root_aa = torch.from_numpy(np.stack([root_axis_angle(r[0], r[1]) for r in root]))
        zeros = np.zeros(len(need))
        R_roll = root_matrix(torch.from_numpy(np.stack([root[:, 0], zeros, zeros], -1)))  # body -> bed axes
        R_root = root_matrix(root_aa)  # body axes -> mat frame
        frame = torch.stack([R_roll[:, 0], R_roll[:, 2], R_root[:, 0], R_root[:, 1]], 1)
        shift = torch.from_numpy(np.stack([self.centre[0] + root[:, 2], self.centre[1] + root[:, 3], zeros], -1))
        if self.part.raised:  # shift_x places the hips' midpoint relative to the hinge
            hips = (R_root @ rest[:, list(HIP_JOINTS)].mean(1)[..., None])[..., 0]
            shift[:, 0] = BedShape().hinge_x(self.mat) + torch.from_numpy(root[:, 2]) - hips[:, 0]
        def seg(a, b):  # written out: the same bits whatever the batch
            d = rest[:, a] - rest[:, b]
            return (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]).sqrt()

        leg = seg(_J("left_hip"), _J("left_knee")) + seg(_J("left_knee"), _J("left_ankle"))
        arm = seg(_J("left_shoulder"), _J("left_elbow")) + seg(_J("left_elbow"), _J("left_wrist"))
        for i, st in enumerate(need):
            st.rest = rest[i]
            st.caps = (start[i], end[i], radius[i])
            st.root_aa = root_aa[i]
            st.frame = frame[i]
            st.shift = shift[i]
            st.leg_frame, st.leg_shift = frame[i], shift[i]
            if self.part.raised:
                self._pitch(st, root_aa[i:i + 1])
            st.lengths = (float(leg[i]), float(arm[i]))

    def _pitch(self, st: _State, root_aa: torch.Tensor) -> None:
        """The pitch this trunk sits up by on its bed, and the legs' frame and pelvis turned
        back by it (one sample at a time: never batch-dependent)."""
        caps, lying = _lying(st, root_aa, torch.zeros(1, NUM_POSE_JOINTS, 3, dtype=torch.float64))
        st.pitch = trunk_pitch(caps, lying, BedShape(st.head_angle), self.mat)
        # A body-axes vector v of the turned body points along Q v in the lying frame, so the
        # bed axes f seen from the lying frame are Q^T f: rows f^T Q.
        st.leg_frame = st.frame @ pitch_matrix(root_aa, st.pitch)[0]
        st.leg_shift = fold_params(lying, caps.rest, st.pitch, keep_thighs=False).root_translation[0]

    def _fit_model(self) -> BodyModel:
        """The body model in float64 on the CPU (a copy if the given one is not)."""
        if getattr(self, "_model64", None) is None:
            m = self.model
            with torch.inference_mode(False):  # a plain model, whatever mode we are called in
                self._model64 = m if (m.dtype == torch.float64 and m.device.type == "cpu") else \
                    copy.deepcopy(m).to(dtype=torch.float64, device="cpu")
        return self._model64

    def _draw_limbs(self, states: list[_State]) -> None:
        """One pose attempt: limbs in a fixed order, each drawn until it reaches its cell
        without touching what is already placed (torso, head, earlier limbs)."""
        for st in states:
            st.angles = {}
        batch = _Attempt(states)
        rows = torch.arange(len(states))
        for name in LIMBS:
            rows = self._rounds(batch, rows, self.limbs[name])
        for r in rows.tolist():
            batch.states[r].placed = (batch.a[r], batch.b[r])

    def _rounds(self, batch: _Attempt, rows: torch.Tensor, limb: _Limb) -> torch.Tensor:
        """Draw angles for `limb` until each sample (attempt rows `rows`) has a draw that meets
        every condition; returns the rows that got one (the others have failed this attempt).

        Draws come in rounds of growing size (64, 128, ... 4096) up to `max_limb_draws`, so
        common cells cost one small round and rare ones (a foot near the buttocks) still get
        thousands of tries; the first draw that passes everything wins, and the sample's
        generator has then used up exactly the rounds up to the winner's. For speed, several
        rounds are drawn and tested at once (a window: few pending samples, many rounds) and
        the generator is wound back to the end of the winner's round: the outcome is the same
        as drawing round by round. Each draw is first screened by a cheap float32 test that
        is looser than the real conditions by PREFILTER_MARGIN_M (so it never drops a draw
        they accept); survivors are tested exactly (float64), then for self-collisions."""
        pending, done = rows, []
        reachable = torch.zeros(len(batch.states), dtype=torch.bool)
        ctx = self._limb_context(batch, limb)
        ends = self._round_ends
        start, j = 0, 0
        while pending.numel() and j < len(ends):
            # A window: the rounds from `start` on that keep pending x draws within
            # _WINDOW_DRAWS (at least one round), so few pending samples take few windows.
            P = pending.numel()
            while j + 1 < len(ends) and P * (ends[j + 1] - start) <= _WINDOW_DRAWS:
                j += 1
            stop = int(ends[j])
            W = stop - start
            step = max(1, _WINDOW_DRAWS // W)
            won = [self._window(batch, ctx, pending[lo:lo + step], limb, start, W, reachable, done)
                   for lo in range(0, P, step)]
            pending = pending[~torch.cat(won)]
            start, j = stop, j + 1
        for r in pending.tolist():  # budget exhausted: this attempt fails
            st = batch.states[r]
            st.counts["limb_failures"] += 1
            st.failed_limb = limb.name
            # No draw met even the cell and bed conditions: other limbs cannot help (unless
            # the condition depends on them, as crossing does), only a new shape and root.
            if not reachable[r] and not (self.part.crossed_legs and limb.name == "right_leg"):
                st.unreachable = limb.name
        return torch.cat(done).sort().values if done else rows[:0]

    def _window(self, batch, ctx, pending, limb, start, W, reachable, done) -> torch.Tensor:
        """Draws start .. start + W (whole rounds) of each pending row; returns which rows
        found a winner."""
        P = pending.numel()
        ends = self._round_ends
        states = [batch.states[r] for r in pending.tolist()]
        one_round = int(np.searchsorted(ends, start, side="right")) == int(np.searchsorted(ends, start + W - 1, side="right"))
        saved = None if one_round else [st.rng.bit_generator.state for st in states]
        u = np.empty((P, W, limb.low.shape[0]))
        for p, st in enumerate(states):
            st.rng.random(out=u[p])
        u = torch.from_numpy(u)
        # 1. Screen every draw (float32, conservative).
        p_idx, k_idx = self._screen(ctx, pending, limb, u)
        # 2. The survivors exactly: cell, height, partition conditions, bed outline. Their
        # angles low + span * random = rng.uniform(low, high), bit for bit.
        angles = torch.from_numpy(limb.low) + torch.from_numpy(limb.high - limb.low) * u[p_idx, k_idx]
        if self.part.straight_limbs:
            angles[:, 3] = 0.0
        rows_s = pending[p_idx]
        geo, pos, caps_ab = self._limb_survivors(ctx, rows_s, limb, angles)
        p_idx, k_idx, rows_s, pos, angles = p_idx[geo], k_idx[geo], rows_s[geo], pos[geo], angles[geo]
        caps_ab = (caps_ab[0][geo], caps_ab[1][geo])
        # 3. Self-collision, in draw order: each sample's first 4 geometric draws, then (for
        # the samples without a free one yet) the next 32, 256, ... until one is free.
        reachable[rows_s] = True
        first = torch.full((P,), W, dtype=torch.long)
        if p_idx.numel():
            count = torch.bincount(p_idx, minlength=P)
            rank = torch.arange(p_idx.numel()) - (count.cumsum(0) - count)[p_idx]  # within its sample
            lo, width, top = 0, 4, int(rank.max())
            while lo <= top:
                sel = ((rank >= lo) & (rank < lo + width) & (first[p_idx] == W)).nonzero()[:, 0]
                if sel.numel():
                    free = self._collision_free(batch, rows_s[sel], limb, (caps_ab[0][sel], caps_ab[1][sel]))
                    first.scatter_reduce_(0, p_idx[sel][free], k_idx[sel][free], "amin")
                lo, width = lo + width, 8 * width
        before = k_idx < first[p_idx]  # geometric draws before the winner: all collided
        collided = torch.bincount(p_idx[before], minlength=P)
        rejected = first - collided
        for st, rej, col in zip(states, rejected.tolist(), collided.tolist()):
            st.counts["limb_draws_rejected"] += rej
            st.counts["collisions"] += col
        won = first < W
        if won.any():
            win = (k_idx == first[p_idx]).nonzero()[:, 0]  # one survivor per winning sample
            r = rows_s[win]
            caps = self._limb_capsules[limb.name]
            batch.a[r[:, None], caps] = caps_ab[0][win]
            batch.b[r[:, None], caps] = caps_ab[1][win]
            if limb.name == "left_leg":
                batch.left_ankle_x[r] = pos[win, -2, 0]
            for rr, pp, kk, ang in zip(r.tolist(), p_idx[win].tolist(), k_idx[win].tolist(), angles[win]):
                st = batch.states[rr]
                st.angles[limb.name] = ang
                # Wind the generator back to the end of the winner's round.
                used = int(ends[np.searchsorted(ends, start + kk, side="right")]) - start
                if used < W:  # (never in a one-round window)
                    st.rng.bit_generator.state = saved[pp]
                    st.rng.random(used * limb.low.shape[0])
            done.append(r)
        return won

    def _limb_context(self, batch: _Attempt, limb: _Limb) -> dict:
        """Per-row constants of the attempt for one limb (every row; windows index them)."""
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
        caps = self._limb_capsules[limb.name]
        rj = rest[:, [CAPSULES[k].joint for k in caps]]
        ci = {j: i for i, j in enumerate(chain)}
        # Screen (float32, loosened by the margin).
        reach_off = (offsets[:, 0], offsets[:, 1]) if leg else (offsets[:, 1], offsets[:, 2])
        # Legs are measured against the bed as they will lie once a raised-bed body sits up.
        frame, shift = (batch.leg_frame, batch.leg_shift) if leg else (batch.frame, batch.shift)
        ctx = dict(
            o1=reach_off[0].to(f32), o2=reach_off[1].to(f32), frame32=frame.to(f32),
            lo32=(lo - m).to(f32), hi32=(hi + m).to(f32), prox32=rest[:, limb.proximal].to(f32),
            shift32=shift.to(f32),
            # bed-outline slack: the margin (legs), or the collar's reach per radian (arms)
            slack32=(torch.full_like(cell, m) if leg else offsets[:, 0].norm(dim=-1) / 3).to(f32),
            left_ankle32=(batch.left_ankle_x - m).to(f32),
            # Exact tests (float64).
            offsets=offsets, root=rest[:, chain[0]], frame=frame, shift=shift,
            cell=batch.cells[:, slot], length=batch.lengths[:, 0 if leg else 1],
            left_ankle=batch.left_ankle_x,
            local=torch.cat([batch.start0[:, caps] - rj, batch.end0[:, caps] - rj], 1),  # (R, 2c, 3)
            cap_joints=[ci[CAPSULES[k].joint] for k in caps] * 2,
            over_bed=[ci[j] for j in limb.over_bed], distal=ci[limb.distal], proximal=ci[limb.proximal],
        )
        return ctx

    def _screen(self, ctx: dict, pending: torch.Tensor, limb: _Limb, u: torch.Tensor):
        """(p, k) of the draws that may meet the conditions, from the uniform numbers u (P, M, 4)
        the angles are made of: first the distal joint's cell and height above the bed (bed
        axes after the roll) for every draw, then for those left crossing and, over the bed,
        the distal joint's position - all loosened by PREFILTER_MARGIN_M (float32 round-off is
        < 1e-6 m), and for arms by how far the collar's third of the rotation can move the
        shoulder (at most |angle| / 3 x the collar-shoulder distance)."""
        P, M = u.shape[:2]
        leg = limb.name.endswith("leg")
        m = PREFILTER_MARGIN_M
        f32 = torch.float32
        low = torch.from_numpy(limb.low).to(f32)
        span = torch.from_numpy(limb.high - limb.low).to(f32)
        ps, ks = [], []
        step = max(1, _SCREEN_ELEMENTS // M)
        for lo in range(0, P, step):
            rows = pending[lo:lo + step]
            x = u[lo:lo + step].permute(2, 0, 1).to(f32, memory_format=torch.contiguous_format)  # (4, p, M)
            rot = _rodrigues(tuple(low[i] + span[i] * x[i] for i in range(3)))
            o2 = _cols(ctx["o2"][rows])
            if not self.part.straight_limbs:
                o2 = _apply_hinge(limb, low[3] + span[3] * x[3], o2)
            reach = _rotate(rot, _add(_cols(ctx["o1"][rows]), o2))
            frame = ctx["frame32"][rows]
            up = _dot(reach, _cols(frame[:, _UP]))
            along = _dot(reach, _cols(frame[:, _ALONG]))
            ok = up.abs() <= HEIGHT_TOLERANCE_M + m
            ok &= (along >= ctx["lo32"][rows, None]) & (along < ctx["hi32"][rows, None])
            if not leg and self.part.hands_behind_head:
                ok &= up <= m  # no higher than the shoulder
            idx = ok.nonzero()
            p, k = idx[:, 0], idx[:, 1]
            crossed = leg and self.part.crossed_legs
            if crossed or self.config.over_bed:
                # The same draws' distal joint, for those left.
                r = rows[p]
                dist = _add(_split(ctx["prox32"][r]), tuple(c.expand(ok.shape)[p, k] for c in reach))
                keep = torch.ones_like(p, dtype=torch.bool)
                if crossed:
                    if limb.side == "left":
                        keep &= dist[0] < m
                    else:
                        keep &= dist[0] > ctx["left_ankle32"][r]
                if self.config.over_bed:
                    slack = ctx["slack32"][r]
                    if not leg:
                        slack = slack * rot[1][p, k].sqrt() + m
                    fr, shift = ctx["frame32"][r], ctx["shift32"][r]
                    wx = _dot(_split(fr[:, _MAT_X]), dist) + shift[:, 0]
                    wy = _dot(_split(fr[:, _MAT_Y]), dist) + shift[:, 1]
                    keep &= (wx > self.x_lo - slack) & (wx < self.x_hi + slack)
                    keep &= (wy > self.y_lo - slack) & (wy < self.y_hi + slack)
                p, k = p[keep], k[keep]
            ps.append(p + lo)
            ks.append(k)
        return torch.cat(ps), torch.cat(ks)

    def _limb_survivors(self, ctx: dict, rows: torch.Tensor, limb: _Limb, angles: torch.Tensor):
        """For N draws (rows (N,), angles (N, 4)) that passed the screen: whether they meet
        every condition (N,) - cell, height, the partition's conditions, the bed outline - the
        chain joints' positions (N, n, 3) in body axes and the limb's capsule end points
        ((N, c, 3), (N, c, 3))."""
        leg = limb.name.endswith("leg")
        c, s = torch.cos(angles[:, 3]), torch.sin(angles[:, 3])
        one, zero = torch.ones_like(c), torch.zeros_like(c)
        if leg:  # knee about x
            hinge = torch.stack([one, zero, zero, zero, c, -s, zero, s, c], -1).view(-1, 3, 3)
        else:  # elbow about y
            hinge = torch.stack([c, zero, s, zero, one, zero, -s, zero, c], -1).view(-1, 3, 3)
        R = _rotation_matrix(angles[:, :3])
        lower = R @ hinge
        # World rotation of each chain joint (and the capsule riding it).
        if leg:  # hip, knee, ankle, foot
            rots = torch.stack([R, lower, lower, lower], 1)
        else:  # collar (1/3 of the rotation), shoulder, elbow, wrist, hand
            rots = torch.stack([_rotation_matrix(angles[:, :3] / 3), R, lower, lower, lower], 1)
        steps = (rots[:, :-1] @ ctx["offsets"][rows, ..., None])[..., 0]
        pos = torch.cat([ctx["root"][rows, None], steps], 1).cumsum(1)  # (N, n, 3)
        # Cell and height in the bed's axes after the roll only: 'along' is the body's long
        # axis and 'up' the height above the bed, whatever the yaw (a yawed body keeps its cells).
        frame = ctx["frame"][rows]
        dist, prox = pos[:, ctx["distal"]], pos[:, ctx["proximal"]]
        reach = dist - prox
        up = (reach * frame[:, _UP]).sum(-1)
        along = (reach * frame[:, _ALONG]).sum(-1)  # toward the foot
        ok = up.abs() <= HEIGHT_TOLERANCE_M
        cell, length = ctx["cell"][rows], ctx["length"][rows]
        if leg:
            ok &= (along >= 0) & (_leg_cell(along, length) == cell)
            if self.part.crossed_legs:
                # Feet crossed: the left ankle lies on the right of the right ankle (body x =
                # the subject's left). The left leg, drawn first, crosses the midline; the
                # right ankle must then stay on its left.
                ok &= (dist[:, 0] < 0) if limb.side == "left" else (ctx["left_ankle"][rows] < dist[:, 0])
        else:
            ok &= _arm_cell(-along, length) == cell
            if self.part.hands_behind_head:
                # Behind the head: the wrist between the midline and its shoulder, no higher
                # than the shoulder (it lies under the head).
                ok &= (dist[:, 0].abs() < prox[:, 0].abs()) & (up <= 0)
        if self.config.over_bed:
            bed = pos[:, ctx["over_bed"]]  # (N, k, 3)
            shift = ctx["shift"][rows]
            x = (bed * frame[:, None, _MAT_X]).sum(-1) + shift[:, None, 0]
            y = (bed * frame[:, None, _MAT_Y]).sum(-1) + shift[:, None, 1]
            ok &= ((x > self.x_lo) & (x < self.x_hi) & (y > self.y_lo) & (y < self.y_hi)).all(-1)
        # Capsule end points: joint position + the joint's rotation of the rest offset.
        cj = ctx["cap_joints"]
        ab = (rots[:, cj] @ ctx["local"][rows, ..., None])[..., 0] + pos[:, cj]
        c2 = len(cj) // 2
        return ok, pos, (ab[:, :c2], ab[:, c2:])

    def _collision_free(self, batch: _Attempt, rows: torch.Tensor, limb: _Limb, ends) -> torch.Tensor:
        """(N,) whether each draw's capsules clear the capsules already placed (checked pairs)."""
        pairs = self._limb_pairs[limb.name]
        if rows.numel() == 0 or pairs.numel() == 0:
            return torch.ones(rows.shape[0], dtype=torch.bool)
        caps = self._limb_capsules[limb.name]
        a, b = batch.a[rows], batch.b[rows]
        a[:, caps], b[:, caps] = ends
        return (capsule_clearance(a, b, batch.radius[rows], pairs) >= 0).all(-1)

    def _pose(self, states: list[_State]) -> torch.Tensor:
        """(B, 23, 3) pose of the drawn limb angles (torso at rest)."""
        pose = torch.zeros(len(states), NUM_POSE_JOINTS, 3, dtype=torch.float64)
        for name in LIMBS:
            lb = self.limbs[name]
            aa = limb_pose(lb, torch.stack([st.angles[name] for st in states]))  # (B, r, 3)
            for i, j in enumerate(_rotating_joints(lb)):
                pose[:, j - 1] = aa[:, i]
        return pose

    def _sit_up(self, states: list[_State]) -> None:
        """Turn each fully drawn pose up onto its raised bed and check what turning changes; a
        pose that fails loses its limbs (a failed attempt). One sample at a time: its numbers
        then never depend on the batch."""
        (x_lo, x_hi), (y_lo, y_hi) = self.mat.mattress_bounds_m
        over_bed = sorted({j for lb in self.limbs.values() for j in lb.over_bed})
        for st in states:
            bed = BedShape(st.head_angle)
            caps, lying = _lying(st, st.root_aa[None], self._pose([st]))
            sat, seat = sit_up(caps, lying, bed, self.mat, pitch=st.pitch, keep_thighs=False)
            ok = float(seat[0]) <= SEAT_TOLERANCE_M
            if ok and self.config.over_bed:
                _, joints = pose_in_mat(caps.rest, sat)
                s_y = bed.to_surface(joints[0, over_bed], self.mat)
                ok = bool(((s_y[:, 0] > x_lo) & (s_y[:, 0] < x_hi) & (s_y[:, 1] > y_lo) & (s_y[:, 1] < y_hi)).all())
            if ok:
                st.sat = sat
            else:
                st.angles = {}
                st.sat = None
                st.failed_limb = None
                st.counts["sit_up_rejections"] += 1

    def _collect(self, states: list[_State]) -> InitialPoses:
        pose = self._pose(states)
        shape = torch.tensor(np.stack([st.shape for st in states]), dtype=torch.float64)
        root_aa = torch.stack([st.root_aa for st in states])
        R = root_matrix(root_aa)
        # Pelvis height: the lowest capsule surface touches the undeformed mattress top.
        # (Element-wise products, not a batched matmul, then rounded to 1 nm: the result
        # must not depend on the batch size, to the last bit.)
        up = R[:, None, 2, :]  # the mat's z axis in body coordinates
        za = (torch.stack([st.placed[0] for st in states]) * up).sum(-1)
        zb = (torch.stack([st.placed[1] for st in states]) * up).sum(-1)
        radius = torch.stack([st.caps[2] for st in states])
        lowest = (torch.minimum(za, zb) - radius).amin(-1)
        trans = torch.stack([st.shift for st in states])
        trans[:, 2] = -(lowest / GEOMETRY_QUANTUM_M).round() * GEOMETRY_QUANTUM_M
        for i, st in enumerate(states):
            if st.sat is not None:  # sat up on a raised bed (placed there by sit_up)
                root_aa[i], trans[i], pose[i] = st.sat.root_rotation[0], st.sat.root_translation[0], st.sat.pose[0]
        R = root_matrix(root_aa)
        params = BodyParams(shape=shape, root_rotation=root_aa, root_translation=trans, pose=pose)
        _, joints = forward_kinematics(torch.stack([st.rest for st in states]), pose, R)
        return InitialPoses(
            params=params,
            joints=joints + trans[:, None],
            index=np.array([st.index for st in states], dtype=np.int64),
            cells=np.stack([st.cells for st in states]).astype(np.int64),
            root_draw=np.stack([st.root for st in states]),
            head_angle_deg=np.array([st.head_angle for st in states], dtype=np.float64),
            rejections={k: np.array([st.counts[k] for st in states], dtype=np.int64) for k in REJECTION_KEYS},
            config=self.config,
            backend=self.model.name,
        )


def _lying(st: _State, root_aa: torch.Tensor, pose: torch.Tensor) -> tuple[Capsules, BodyParams]:
    """A sample's capsules and its pose lying flat (pelvis over the bed, height 0), batch of 1."""
    caps = Capsules(st.caps[0][None], st.caps[1][None], st.caps[2][None], st.rest[None])
    return caps, BodyParams(shape=torch.from_numpy(st.shape)[None], root_rotation=root_aa,
                            root_translation=st.shift[None].clone(), pose=pose)


def _draw_schedule(budget: int) -> np.ndarray:
    """Cumulative draw counts at the end of each round: 64, 128, ..., 4096, 4096, ... up to
    `budget`."""
    ends, drawn, size = [], 0, FIRST_ROUND
    while drawn < budget:
        drawn += min(size, budget - drawn)
        size = min(2 * size, LARGEST_ROUND)
        ends.append(drawn)
    return np.array(ends)


def _leg_cell(drop: torch.Tensor, L: torch.Tensor) -> torch.Tensor:
    """Leg cell 0..3 of an ankle `drop` below the hip (>= 0) in quarters of the leg length."""
    return (drop / (L / LEG_CELLS)).floor().clamp(0, LEG_CELLS - 1).long()


def _arm_cell(rise: torch.Tensor, A: torch.Tensor) -> torch.Tensor:
    """Arm cell 0..7 of a wrist `rise` toward the head from the shoulder: 0 = above 3A/4,
    3 = [0, A/4), 4 = [-A/4, 0), 7 = below -3A/4."""
    q = (rise / (A / 4)).floor().clamp(-4, 3).long()  # -4..3
    return 3 - q
