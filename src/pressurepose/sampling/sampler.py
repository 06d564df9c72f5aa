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

Speed: all samples of a batch advance together - shapes, capsules and the limb forward
kinematics of every candidate draw are batched tensors.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import zlib

import numpy as np
import torch

from pressurepose.body.capsules import CAPSULES, capsule_clearance, collision_pairs, fit_capsules
from pressurepose.body.joints import J24_NAMES, NUM_POSE_JOINTS
from pressurepose.body.kinematics import forward_kinematics
from pressurepose.body.limits import JointLimits
from pressurepose.body.model import BodyModel
from pressurepose.body.params import BodyParams, root_matrix
from pressurepose.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from pressurepose.mat import MatSpec
from pressurepose.sampling.partitions import HEIGHT_TOLERANCE_M, LEG_CELLS, Partition, SamplingConfig
from pressurepose.sampling.shapes import draw_shape, shape_bounds

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
REJECTION_KEYS = ("limb_draws_rejected", "limb_failures", "collisions", "shape_resamples", "cell_redraws")
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


def _rotating_joints(limb: _Limb) -> tuple[int, ...]:
    return limb.chain[:2] if limb.name.endswith("leg") else limb.chain[:3]


def _chain_fk(limb: _Limb, rest: torch.Tensor, rot_local: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World rotations (..., n, 3, 3) and positions (..., n, 3) of a limb's chain joints in body
    axes, for local rotations (..., r, 3, 3) of its rotating joints, the rest of the body at
    zero pose (the limb's root hangs off an unrotated pelvis or spine).

    rest: (..., 24, 3) rest joints, broadcast against the leading dims."""
    lead = rot_local.shape[:-3]
    n_rot = rot_local.shape[-3]
    chain = limb.chain
    pos = [rest[..., chain[0], :].expand(lead + (3,))]
    R = rot_local[..., 0, :, :]
    rots = [R]
    for i in range(1, len(chain)):
        offset = rest[..., chain[i], :] - rest[..., chain[i - 1], :]
        pos.append(pos[-1] + (R @ offset.expand(lead + (3,))[..., None])[..., 0])
        if i < n_rot:
            R = R @ rot_local[..., i, :, :]
        rots.append(R)
    return torch.stack(rots, -3), torch.stack(pos, -2)


@dataclasses.dataclass
class InitialPoses:
    """A batch of sampled initial poses (float64) with their provenance."""

    params: BodyParams                 # shape, root (mat frame; lowest capsule point on z = 0), pose
    joints: torch.Tensor               # (B, 24, 3) J24 in the mat frame
    index: np.ndarray                  # (B,) sample index within (seed, partition, gender, over_bed)
    cells: np.ndarray                  # (B, 4) target cell of left leg, right leg, left arm, right arm
    root_draw: np.ndarray              # (B, 4) drawn roll, yaw (rad), shift along, across (m)
    rejections: dict[str, np.ndarray]  # REJECTION_KEYS -> (B,) counts
    config: SamplingConfig
    backend: str

    @property
    def batch_size(self) -> int:
        return int(self.index.shape[0])


class UnreachableConstraints(ValueError):
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
    R_root: torch.Tensor | None = None  # body axes -> mat frame
    R_roll: torch.Tensor | None = None  # body axes -> mat frame axes, roll only (no yaw)
    unreachable: str | None = None     # a limb whose conditions had no solution in a whole budget
    failed_limb: str | None = None     # the limb that failed the last attempt
    blocked: dict = dataclasses.field(default_factory=dict)  # limb -> shapes it blocked since its last cell
    shift: torch.Tensor | None = None  # pelvis (x, y, 0) in the mat frame
    leg_length: float = 0.0
    arm_length: float = 0.0
    # The current attempt: accepted limb draws, their chain joints, all capsules placed so far.
    chains: dict = dataclasses.field(default_factory=dict)
    placed: tuple | None = None


def sample_key(config: SamplingConfig, index: int) -> list[int]:
    """The entropy a sample's generator is seeded from."""
    return [int(config.seed), zlib.crc32(config.partition.encode()), int(config.gender == "female"),
            int(config.over_bed), int(index)]


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
            raise ValueError(
                f"the SMPL model is {gender} but the sampling asks for {config.gender}; "
                f"load the {config.gender} SMPL model or the neutral one"
            )
        self.shape_low, self.shape_high = shape_bounds(model.name, config.gender, model.shape_names)
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

    # --- public -------------------------------------------------------------------------
    def sample(self, indices) -> InitialPoses:
        """Initial poses for the given sample indices (any iterable of ints >= 0)."""
        indices = [int(i) for i in indices]
        if not indices:
            raise ValueError("no sample indices given")
        if min(indices) < 0:
            raise ValueError("sample indices must be >= 0")
        states = [self._new_state(i) for i in indices]
        pending = list(states)
        while pending:
            for st in pending:
                if st.shape is None:
                    self._draw_shape_and_root(st)
            self._prepare(pending)
            self._draw_limbs(pending)
            still = []
            for st in pending:
                if len(st.angles) == len(LIMBS):
                    continue
                st.failures += 1
                last = st.failed_limb
                if st.failures > self.config.max_failures or st.unreachable is not None:
                    # This shape is given up; a limb that blocked CELL_REDRAW_AFTER shapes
                    # gets a new cell.
                    st.blocked[last] = st.blocked.get(last, 0) + 1
                    if st.blocked[last] >= CELL_REDRAW_AFTER:
                        cells = self.part.leg_cells if last.endswith("leg") else self.part.arm_cells
                        st.cells[LIMBS.index(last)] = st.rng.choice(np.array(cells))
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
                            f"last blocked: {last} in cell {st.cells[LIMBS.index(last)]}"
                        )
                    st.shape = None
                    st.failures = 0
                    st.unreachable = None
                still.append(st)
            pending = still
        return self._collect(states)

    # --- steps --------------------------------------------------------------------------
    def _new_state(self, index: int) -> _State:
        rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(sample_key(self.config, index))))
        legs = rng.choice(np.array(self.part.leg_cells), size=2)
        arms = rng.choice(np.array(self.part.arm_cells), size=2)
        return _State(index=index, rng=rng, cells=np.concatenate([legs, arms]))

    def _draw_shape_and_root(self, st: _State) -> None:
        st.shape = draw_shape(st.rng, self.shape_low, self.shape_high)
        p = self.part
        st.root = np.array([
            st.rng.uniform(*p.roll), st.rng.uniform(*p.yaw), st.rng.uniform(*p.shift_x), st.rng.uniform(*p.shift_y)])
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
        for i, st in enumerate(need):
            st.rest = rest[i]
            st.caps = (start[i], end[i], radius[i])
            roll, yaw = float(st.root[0]), float(st.root[1])
            # Roll about the bed's long axis, then yaw in the bed plane.
            Rx, Rz = axis_angle_to_matrix(torch.tensor([[roll, 0.0, 0.0], [0.0, 0.0, yaw]], dtype=torch.float64))
            st.root_aa = matrix_to_axis_angle(Rz @ Rx)
            st.R_root = root_matrix(st.root_aa[None])[0]  # body axes -> mat frame
            st.R_roll = root_matrix(torch.tensor([[roll, 0.0, 0.0]], dtype=torch.float64))[0]
            st.shift = torch.tensor([self.centre[0] + st.root[2], self.centre[1] + st.root[3], 0.0], dtype=torch.float64)
            lengths = lambda a, b, c: float((rest[i, a] - rest[i, b]).norm() + (rest[i, b] - rest[i, c]).norm())  # noqa: E731
            st.leg_length = lengths(_J("left_hip"), _J("left_knee"), _J("left_ankle"))
            st.arm_length = lengths(_J("left_shoulder"), _J("left_elbow"), _J("left_wrist"))

    def _fit_model(self) -> BodyModel:
        """The body model in float64 on the CPU (a copy if the given one is not)."""
        if getattr(self, "_model64", None) is None:
            m = self.model
            self._model64 = m if (m.dtype == torch.float64 and m.device.type == "cpu") else \
                copy.deepcopy(m).to(dtype=torch.float64, device="cpu")
        return self._model64

    def _draw_limbs(self, states: list[_State]) -> None:
        """One pose attempt: limbs in a fixed order, each drawn until it reaches its cell
        without touching what is already placed (torso, head, earlier limbs)."""
        for st in states:
            st.angles, st.chains = {}, {}
            st.placed = (st.caps[0].clone(), st.caps[1].clone())  # spine at zero: torso at rest
        active = list(states)
        for name in LIMBS:
            active = self._rounds(active, self.limbs[name])

    def _rounds(self, states: list[_State], limb: _Limb) -> list[_State]:
        """Draw angles for `limb` until each sample has a draw that meets every condition;
        returns the samples that got one (the others have failed this attempt).

        Draws come in rounds of growing size (64, 128, ... 4096) up to `max_limb_draws`, so
        common cells cost one small round and rare ones (a foot near the buttocks) still get
        thousands of tries; a sample's draws follow a fixed schedule, hence determinism."""
        pending, placed_ok = list(states), []
        reachable = set()
        drawn = 0
        size = FIRST_ROUND
        while pending and drawn < self.config.max_limb_draws:
            M = min(size, self.config.max_limb_draws - drawn)
            drawn += M
            size = min(2 * size, LARGEST_ROUND)
            angles = torch.tensor(np.stack([st.rng.uniform(limb.low, limb.high, size=(M, limb.low.shape[0]))
                                            for st in pending]))  # (P, M, 4)
            if self.part.straight_limbs:
                angles[..., 3] = 0.0
            geometric, rot, pos = self._limb_geometry(pending, limb, angles)
            free, ends = self._limb_collisions(pending, limb, geometric, rot, pos)
            good = geometric & free
            reachable.update(id(st) for p, st in enumerate(pending) if geometric[p].any())
            has = good.any(1)
            pick = good.int().argmax(1)
            still = []
            for p, st in enumerate(pending):
                k = int(pick[p]) if has[p] else M
                st.counts["limb_draws_rejected"] += int((~geometric[p, :k]).sum())
                st.counts["collisions"] += int((geometric[p, :k] & ~free[p, :k]).sum())
                if has[p]:
                    st.angles[limb.name] = angles[p, k]
                    st.chains[limb.name] = pos[p, k]
                    st.placed = ends[(p, k)]
                    placed_ok.append(st)
                else:
                    still.append(st)
            pending = still
        for st in pending:  # budget exhausted: this attempt fails
            st.counts["limb_failures"] += 1
            st.failed_limb = limb.name
            # No draw met even the cell and bed conditions: other limbs cannot help (unless
            # the condition depends on them, as crossing does), only a new shape and root.
            if id(st) not in reachable and not (self.part.crossed_legs and limb.name == "right_leg"):
                st.unreachable = limb.name
        return placed_ok

    def _limb_geometry(self, states: list[_State], limb: _Limb, angles: torch.Tensor):
        """For (P, M, 4) draws: whether each meets the cell, height, bed and crossing
        conditions (P, M), and the chain joints' world rotations and positions in body axes."""
        rest = torch.stack([st.rest for st in states])[:, None]        # (P, 1, 24, 3)
        rot, pos = _chain_fk(limb, rest, axis_angle_to_matrix(limb_pose(limb, angles)))
        # Cells and heights in the bed's axes after the roll only: "along" is the body's long
        # axis and z the height above the bed, whatever the yaw (a yawed body keeps its cells).
        R = torch.stack([st.R_roll for st in states])[:, None, None]    # (P, 1, 1, 3, 3)
        bed = (R @ pos[..., None])[..., 0]
        ci = {j: i for i, j in enumerate(limb.chain)}
        prox, dist = bed[:, :, ci[limb.proximal]], bed[:, :, ci[limb.distal]]
        ok = (dist[..., 2] - prox[..., 2]).abs() <= HEIGHT_TOLERANCE_M
        along = dist[..., 0] - prox[..., 0]  # toward the foot
        cell = torch.tensor([st.cells[LIMBS.index(limb.name)] for st in states])[:, None]
        if limb.name.endswith("leg"):
            L = torch.tensor([st.leg_length for st in states], dtype=torch.float64)[:, None]
            ok &= (along >= 0) & (_leg_cell(along, L) == cell)
            if self.part.crossed_legs:
                # Feet crossed: the left ankle lies on the right of the right ankle (body x =
                # the subject's left). The left leg, drawn first, crosses the midline; the
                # right ankle must then stay on its left.
                if limb.side == "left":
                    ok &= pos[:, :, ci[limb.distal], 0] < 0
                else:
                    left_ankle = torch.stack([st.chains["left_leg"][2, 0] for st in states])[:, None]
                    ok &= left_ankle < pos[:, :, ci[limb.distal], 0]
        else:
            A = torch.tensor([st.arm_length for st in states], dtype=torch.float64)[:, None]
            ok &= _arm_cell(-along, A) == cell
            if self.part.hands_behind_head:
                # Behind the head: the wrist between the midline and its shoulder, no higher
                # than the shoulder (it lies under the head).
                ok &= pos[:, :, ci[limb.distal], 0].abs() < pos[:, :, ci[limb.proximal], 0].abs()
                ok &= dist[..., 2] <= prox[..., 2]
        if self.config.over_bed:
            shift = torch.stack([st.shift for st in states])[:, None, None]
            R_root = torch.stack([st.R_root for st in states])[:, None, None]
            idx = [ci[j] for j in limb.over_bed]
            world = (R_root @ pos[:, :, idx, :, None])[..., 0] + shift
            x, y = world[..., 0], world[..., 1]
            ok &= ((x > self.x_lo) & (x < self.x_hi) & (y > self.y_lo) & (y < self.y_hi)).all(-1)
        return ok, rot, pos

    def _limb_collisions(self, states, limb, candidates, rot, pos):
        """Self-collision test of the draws flagged in `candidates` (P, M): whether each is
        free of the capsules already placed (P, M; True where not tested), and the placed
        capsule end points {(p, k): ((20, 3), (20, 3))} with the draw put in."""
        free = torch.ones_like(candidates)
        idx = candidates.nonzero()
        if idx.numel() == 0:
            return free, {}
        p, k = idx[:, 0], idx[:, 1]
        ci = {j: i for i, j in enumerate(limb.chain)}
        caps = self._limb_capsules[limb.name]
        jr = [ci[CAPSULES[c].joint] for c in caps]
        rest = torch.stack([st.rest for st in states])[p][:, [CAPSULES[c].joint for c in caps]]  # (N, c, 3)
        start0 = torch.stack([st.caps[0] for st in states])[p]        # (N, 20, 3)
        end0 = torch.stack([st.caps[1] for st in states])[p]
        Rj, pj = rot[p, k][:, jr], pos[p, k][:, jr]                   # (N, c, 3, 3), (N, c, 3)
        a = torch.stack([st.placed[0] for st in states])[p].clone()
        b = torch.stack([st.placed[1] for st in states])[p].clone()
        a[:, caps] = (Rj @ (start0[:, caps] - rest)[..., None])[..., 0] + pj
        b[:, caps] = (Rj @ (end0[:, caps] - rest)[..., None])[..., 0] + pj
        pairs = self._limb_pairs[limb.name]
        if pairs.numel():
            radius = torch.stack([st.caps[2] for st in states])[p]
            free[p, k] = (capsule_clearance(a, b, radius, pairs) >= 0).all(-1)
        ends = {(int(pi), int(ki)): (a[n], b[n]) for n, (pi, ki) in enumerate(zip(p, k))}
        return free, ends

    def _collect(self, states: list[_State]) -> InitialPoses:
        pose = torch.zeros(len(states), NUM_POSE_JOINTS, 3, dtype=torch.float64)
        for p, st in enumerate(states):
            for name in LIMBS:
                lb = self.limbs[name]
                for j, aa in zip(_rotating_joints(lb), limb_pose(lb, st.angles[name])):
                    pose[p, j - 1] = aa
        shape = torch.tensor(np.stack([st.shape for st in states]), dtype=torch.float64)
        root_aa = torch.stack([st.root_aa for st in states])
        R = root_matrix(root_aa)
        # Pelvis height: the lowest capsule surface touches the undeformed mattress top.
        # (Element-wise products, not a batched matmul: the result must not depend on the
        # batch size, to the last bit.)
        up = R[:, None, 2, :]  # the mat's z axis in body coordinates
        za = (torch.stack([st.placed[0] for st in states]) * up).sum(-1)
        zb = (torch.stack([st.placed[1] for st in states]) * up).sum(-1)
        radius = torch.stack([st.caps[2] for st in states])
        lowest = (torch.minimum(za, zb) - radius).amin(-1)
        trans = torch.stack([st.shift for st in states])
        trans[:, 2] = -(lowest / GEOMETRY_QUANTUM_M).round() * GEOMETRY_QUANTUM_M
        params = BodyParams(shape=shape, root_rotation=root_aa, root_translation=trans, pose=pose)
        _, joints = forward_kinematics(torch.stack([st.rest for st in states]), pose, R)
        return InitialPoses(
            params=params,
            joints=joints + trans[:, None],
            index=np.array([st.index for st in states], dtype=np.int64),
            cells=np.stack([st.cells for st in states]).astype(np.int64),
            root_draw=np.stack([st.root for st in states]),
            rejections={k: np.array([st.counts[k] for st in states], dtype=np.int64) for k in REJECTION_KEYS},
            config=self.config,
            backend=self.model.name,
        )


def _leg_cell(drop: torch.Tensor, L: torch.Tensor) -> torch.Tensor:
    """Leg cell 0..3 of an ankle `drop` below the hip (>= 0) in quarters of the leg length."""
    return (drop / (L / LEG_CELLS)).floor().clamp(0, LEG_CELLS - 1).long()


def _arm_cell(rise: torch.Tensor, A: torch.Tensor) -> torch.Tensor:
    """Arm cell 0..7 of a wrist `rise` toward the head from the shoulder: 0 = above 3A/4,
    3 = [0, A/4), 4 = [-A/4, 0), 7 = below -3A/4."""
    q = (rise / (A / 4)).floor().clamp(-4, 3).long()  # -4..3
    return 3 - q

