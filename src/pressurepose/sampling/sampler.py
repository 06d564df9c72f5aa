"""Initial pose sampling (seed A.1): stratified rejection sampling of resting poses.

For each sample: draw the shape, the root (roll, yaw, shift) and, once, the cell each limb
must reach; then draw joint angles limb by limb until the distal joint lands in its cell (and
over the bed, crossed, ... as the partition asks) with the limb's capsules clear of the torso,
the head and the limbs placed before it. A limb that finds no such draw within
`max_limb_draws` draws fails the attempt; after `max_failures` failures (over the bed at most
the partition's `over_bed_max_failures`), or at once when no draw even reached the cell, the
shape and root are drawn again, a limb that blocked CELL_REDRAW_AFTER shapes gets a new cell,
and after `max_shapes` shapes the sample gives up with an error naming the partition - never
an endless loop.

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
turned up rigidly (`sit_up`: joint angles, limits and self-collisions unchanged); over the bed
the arms' outline test is measured on the head section as they will lie (`sit_up_frame`,
a bound the check after sitting up implies). The sat-up
pose is then checked for what turning can change: the over-bed rule in the bed's surface
coordinates, and that the trunk, not a hand or a heel, rests on the bed (within
SEAT_TOLERANCE_M); a failure counts as a failed attempt (`sit_up_rejections`).

Modules: `sampler` (PoseSampler: states, shapes and roots, the result), `sitting_draws` (sitting
up on a raised bed), `limb_draws`
(the limb rounds: screen, exact tests, collisions), `limbs` (angle ranges, limb table, limb
geometry), `attempt` (per-sample state, one attempt's tensors), `poses` (InitialPoses, seeds),
`support` (over the bed: the angle boxes that may reach a limb's cell, drawn from after the
first rounds - the same law, far fewer draws).
"""

from __future__ import annotations

import copy

import numpy as np
import torch

from pressurepose.bed import BedShape
from pressurepose.body.capsules import CAPSULES, collision_pairs, fit_capsules
from pressurepose.body.joints import NUM_POSE_JOINTS
from pressurepose.body.kinematics import forward_kinematics
from pressurepose.body.limits import JointLimits
from pressurepose.body.model import BodyModel
from pressurepose.body.params import BodyParams, root_matrix
from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.sampling.attempt import SampleState
from pressurepose.sampling.limb_draws import LimbDraws
from pressurepose.sampling.limbs import (
    GEOMETRY_QUANTUM_M,
    LIMBS,
    TORSO_JOINTS,
    J,
    draw_schedule,
    limb_pose,
    limb_table,
    rotating_joints,
)
from pressurepose.sampling.partitions import (
    Partition,
    SamplingConfig,
    leg_cells_for_roll,
    limb_cells,
    max_failures,
)
from pressurepose.sampling.poses import (
    REJECTION_KEYS,
    InitialPoses,
    UnreachableConstraints,
    root_axis_angle,
    root_axis_angles,
    sample_key,
)
from pressurepose.sampling.shapes import draw_shape
from pressurepose.sampling.sitting import HIP_JOINTS
from pressurepose.sampling.sitting_draws import SittingDraws
from pressurepose.sampling.support import LimbGrid

# A limb whose cell had no solution for this many shapes gets a new cell: over the bed, a cell
# can lie off the mattress for nearly every body (a straight arm held out sideways); the seed
# clips such cells, the original redrew them.
CELL_REDRAW_AFTER = 2


class PoseSampler(LimbDraws, SittingDraws):
    """Draws initial poses for one SamplingConfig with one body model.

    >>> sampler = PoseSampler(model, SamplingConfig(partition="supine", gender="male"))
    >>> poses = sampler.sample(range(100))
    """

    def __init__(
        self, model: BodyModel, config: SamplingConfig, mat: MatSpec | None = None, partition: Partition | None = None
    ) -> None:
        """`partition` overrides the named preset of `config` (for experiments)."""
        if not isinstance(config, SamplingConfig):
            raise ValueError(f"expected a SamplingConfig, got {type(config).__name__}")
        self.model = model
        self.config = config
        self.part = partition or config.spec
        self.mat = mat or MatSpec()
        if model.fixed_gender not in (None, config.gender):
            raise UserError(
                f"the {model.name} body model is {model.fixed_gender} but the sampling asks for "
                f"{config.gender}; load the {config.gender} model or the neutral one"
            )
        self.shape_low, self.shape_high = model.shape_bounds(config.gender, model.shape_names)
        self.shape_power = model.shape_powers(model.shape_names)
        self.leg_cells, self.arm_cells = limb_cells(self.part, config.over_bed)
        self.max_failures = max_failures(self.part, config)
        self.limits = JointLimits.default(torch.float64)
        self.limbs = limb_table(self.limits)
        self.pairs = collision_pairs(self.part.checked_capsules)
        # Capsules each limb moves, and the checked pairs its draws are tested on: those
        # between its capsules and the torso, the head or a limb drawn before it.
        self._limb_capsules, self._limb_pairs = {}, {}
        placed = {i for i, c in enumerate(CAPSULES) if c.joint in TORSO_JOINTS}
        for name in LIMBS:
            mine = [i for i, c in enumerate(CAPSULES) if c.joint in self.limbs[name].chain]
            self._limb_capsules[name] = mine
            known = placed | set(mine)
            keep = [
                k
                for k, (i, j) in enumerate(self.pairs.tolist())
                if (i in mine and j in known) or (j in mine and i in known)
            ]
            self._limb_pairs[name] = self.pairs[keep]
            placed |= set(mine)
        (self.x_lo, self.x_hi), (self.y_lo, self.y_hi) = self.mat.mattress_bounds_m
        self.centre = np.array([(self.x_lo + self.x_hi) / 2, (self.y_lo + self.y_hi) / 2])
        self._round_ends = draw_schedule(config.max_limb_draws)
        # Over the bed, limbs draw from the boxes that may reach their cell (sampling.support).
        self._grids = {n: LimbGrid(self.limbs[n], self.part.straight_limbs) for n in LIMBS} if config.over_bed else {}

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

    def _advance(self, states: list[SampleState]) -> None:
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
                if st.failures > self.max_failures or st.unreachable is not None:
                    # This shape is given up; a limb that blocked CELL_REDRAW_AFTER shapes
                    # gets a new cell.
                    st.blocked[last] = st.blocked.get(last, 0) + 1
                    if last is not None and st.blocked[last] >= CELL_REDRAW_AFTER:
                        # A new cell, not one that already blocked this limb (unless all did).
                        slot = LIMBS.index(last)
                        given_up = st.given_up.setdefault(last, set())
                        given_up.add(int(st.cells[slot]))
                        cells = self._leg_cells(st) if last.endswith("leg") else self.arm_cells
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
                            f"after {self.config.max_shapes} shapes x {self.max_failures + 1} attempts; "
                            f"its constraints are unreachable with these settings "
                            f"(raise max_shapes or max_limb_draws, or use another partition); "
                            + (
                                f"last blocked: {last} in cell {st.cells[LIMBS.index(last)]}"
                                if last is not None
                                else "the last pose failed when sat up on the raised bed"
                            )
                        )
                    st.shape = None
                    st.failures = 0
                    st.unreachable = None
                still.append(st)
            pending = still

    # --- steps --------------------------------------------------------------------------
    def _new_state(self, index: int) -> SampleState:
        rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(sample_key(self.config, index))))
        legs = rng.choice(np.array(self.leg_cells), size=2)
        arms = rng.choice(np.array(self.arm_cells), size=2)
        st = SampleState(index=index, rng=rng, cells=np.concatenate([legs, arms]))
        if self.part.raised:  # once per sample, like the cells (flat partitions draw nothing more)
            st.head_angle = float(rng.choice(np.array(self.part.head_angles_deg)))
        return st

    def _leg_cells(self, st: SampleState) -> tuple[int, ...]:
        """The cells a sample's legs may draw (`partitions.leg_cells_for_roll`, once rolled)."""
        return self.leg_cells if st.roll is None else leg_cells_for_roll(self.leg_cells, st.roll, self.config.over_bed)

    def _draw_shape_and_root(self, st: SampleState) -> None:
        st.shape = draw_shape(st.rng, self.shape_low, self.shape_high, self.shape_power)
        p = self.part
        roll = st.rng.uniform(*p.roll)
        if p.either_side and st.rng.random() < 0.5:  # drawn only by such partitions: the others' streams stay
            roll = -roll
        # The roll is the sample's, like its cells: drawn with the first shape, kept for the
        # next ones (the draws above still happen, so the stream is the same). Otherwise the
        # shapes that fail most - face-down bodies, whose legs cannot reach the cells near the
        # buttocks without kneeling - would be redrawn into other rolls.
        if st.roll is None:
            st.roll = roll
            # Face down, a leg can reach the cells near the buttocks only by kneeling (the knee
            # pressed into the bed, which `limb_draws` refuses): its cell is drawn again among
            # the far ones, from the sample's own stream.
            cells = self._leg_cells(st)
            for slot in (0, 1):
                if st.cells[slot] not in cells:
                    st.cells[slot] = st.rng.choice(np.array(cells))
        roll = st.roll
        st.root = np.array([roll, st.rng.uniform(*p.yaw), st.rng.uniform(*p.shift_x), st.rng.uniform(*p.shift_y)])
        st.rest = None
        st.support = {}

    def _prepare(self, states: list[SampleState]) -> None:
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
        root_aa = torch.from_numpy(root_axis_angles(root[:, 0], root[:, 1]))
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

        leg = seg(J("left_hip"), J("left_knee")) + seg(J("left_knee"), J("left_ankle"))
        arm = seg(J("left_shoulder"), J("left_elbow")) + seg(J("left_elbow"), J("left_wrist"))
        for i, st in enumerate(need):
            st.rest = rest[i]
            st.caps = (start[i], end[i], radius[i])
            st.root_aa = root_aa[i]
            st.frame = frame[i]
            st.shift = shift[i]
            st.leg_frame, st.leg_shift = frame[i], shift[i]
            st.arm_frame, st.arm_shift = frame[i], shift[i]
            if self.part.raised:
                self._pitch(st, root_aa[i : i + 1])
            st.lengths = (float(leg[i]), float(arm[i]))

    def _fit_model(self) -> BodyModel:
        """The body model in float64 on the CPU (a copy if the given one is not)."""
        if getattr(self, "_model64", None) is None:
            m = self.model
            with torch.inference_mode(False):  # a plain model, whatever mode we are called in
                self._model64 = (
                    m
                    if (m.dtype == torch.float64 and m.device.type == "cpu")
                    else copy.deepcopy(m).to(dtype=torch.float64, device="cpu")
                )
        return self._model64

    def _pose(self, states: list[SampleState]) -> torch.Tensor:
        """(B, 23, 3) pose of the drawn limb angles (torso at rest)."""
        pose = torch.zeros(len(states), NUM_POSE_JOINTS, 3, dtype=torch.float64)
        for name in LIMBS:
            lb = self.limbs[name]
            aa = limb_pose(lb, torch.stack([st.angles[name] for st in states]))  # (B, r, 3)
            for i, j in enumerate(rotating_joints(lb)):
                pose[:, j - 1] = aa[:, i]
        return pose

    def _collect(self, states: list[SampleState]) -> InitialPoses:
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


__all__ = ["InitialPoses", "PoseSampler", "UnreachableConstraints", "root_axis_angle", "sample_key"]
