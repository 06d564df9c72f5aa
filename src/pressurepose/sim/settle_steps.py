"""Sim #1's stepping: one MuJoCo episode per body, a pool of slots stepped in lockstep, the
mattress forces of all running bodies at once (`sim.settle`)."""

from __future__ import annotations

import time

import numpy as np
import torch

from pressurepose.bed import BedShape
from pressurepose.body.capsules import (
    CAPSULE_JOINTS,
    CAPSULE_NAMES,
    HINGE_JOINTS,
    CapsuleBody,
)
from pressurepose.body.params import R_SUPINE, BodyParams, root_matrix
from pressurepose.body.rotations import (
    matrix_to_axis_angle,
    quaternion_to_axis_angle,
)
from pressurepose.mat import MatSpec
from pressurepose.sim.capsule_foundation import CapsuleFoundation, hold_roll_torque
from pressurepose.sim.fixed_order import matvec3, sq_norm3, sum_last
from pressurepose.sim.mattress import GRAVITY_M_S2, MattressParams
from pressurepose.sim.mjcf import axis_angle_quats, build_mjcf, matrix_quat, quat_to_matrix
from pressurepose.sim.settle_config import (
    PELVIS,
    REASON_ENERGY,
    REASON_FELL,
    REASON_NONFINITE,
    REASON_OFF_BED,
    REASON_SANK,
    REASON_TIMEOUT,
    EpisodeOutcome,
    SettleConfig,
)


class Episode:
    """One capsule body in MuJoCo: built, dropped, stepped until it rests or is rejected."""

    def __init__(
        self,
        body: CapsuleBody,
        i: int,
        params: BodyParams,
        mattress: MattressParams,
        mat: MatSpec,
        config: SettleConfig,
        bed: BedShape | None = None,
        pairs: list[tuple[int, int]] = (),
    ):
        import mujoco

        self.mj, self.config, self.mattress = mujoco, config, mattress
        m = self.model = mujoco.MjModel.from_xml_string(build_mjcf(body, i, config, pairs, mat, bed))
        d = self.data = mujoco.MjData(m)
        pose = params.pose[i].double()
        self.pose_in = pose
        q_pose = axis_angle_quats(pose.numpy())
        q_home = axis_angle_quats(body.home_pose[i].double().numpy())
        pose_np, home_np = pose.numpy(), body.home_pose[i].double().numpy()
        self.adr: dict[int, int] = {}
        for j in CAPSULE_JOINTS[1:]:
            adr = self.adr[j] = int(m.jnt_qposadr[m.joint(f"j{j}").id])
            if j in HINGE_JOINTS:
                axis = np.array(HINGE_JOINTS[j])
                d.qpos[adr] = float(pose_np[j - 1] @ axis)
                m.qpos_spring[adr] = float(home_np[j - 1] @ axis)
            else:
                d.qpos[adr : adr + 4] = q_pose[j - 1]
                m.qpos_spring[adr : adr + 4] = q_home[j - 1]
        d.qpos[0:3] = params.root_translation[i].double().numpy()
        d.qpos[3:7] = matrix_quat(root_matrix(params.root_rotation[i : i + 1].double())[0])
        self.body_ids = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n) for n in CAPSULE_NAMES])
        geom_ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n) for n in CAPSULE_NAMES]
        self.radius = np.array([m.geom_size[g][0] for g in geom_ids])
        la, lb = [], []
        for g in geom_ids:
            R = np.zeros(9)
            mujoco.mju_quat2Mat(R, m.geom_quat[g])
            half = m.geom_size[g][1] if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE else 0.0
            la.append(m.geom_pos[g] - half * R.reshape(3, 3)[:, 2])
            lb.append(m.geom_pos[g] + half * R.reshape(3, 3)[:, 2])
        self.loc_a, self.loc_b = np.array(la), np.array(lb)
        self.bed = bed or BedShape()
        # Lift along z until the lowest point is drop_height above the top (one step when flat;
        # on a raised bed, lifting changes the normal height by cos(angle), so repeat).
        for _ in range(3):
            mujoco.mj_forward(m, d)
            a, b = self.ends()
            n = self.bed.to_surface(torch.from_numpy(np.concatenate([a, b])), mat)[:, 2].numpy()
            lift = config.drop_height_m - float((np.minimum(n[: len(a)], n[len(a) :]) - self.radius).min())
            d.qpos[2] += lift
            if abs(lift) < 1e-9:
                break
        d.qvel[:] = 0.0
        mujoco.mj_forward(m, d)
        self.mat = mat
        self.mass = float(m.body_subtreemass[0])
        self.cap_mass = m.body_mass[self.body_ids].copy()
        self.cap_inertia = m.body_inertia[self.body_ids].min(1).copy()
        self.bounds = mat.mattress_bounds_m
        self.root_surface = self.bed.to_surface(torch.from_numpy(d.qpos[:3].copy()), mat).numpy()

    def ends(self) -> tuple[np.ndarray, np.ndarray]:
        d = self.data
        R = d.xmat[self.body_ids].reshape(-1, 3, 3)
        p = d.xpos[self.body_ids]
        return p + np.einsum("cij,cj->ci", R, self.loc_a), p + np.einsum("cij,cj->ci", R, self.loc_b)

    def resting_params(self, qpos: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(root_rotation (3,), root_translation (3,), pose (23, 3)) from a MuJoCo state."""
        q = torch.from_numpy(qpos.copy())
        R = quat_to_matrix(q[3:7])
        root_rot = matrix_to_axis_angle(R @ torch.tensor(R_SUPINE, dtype=torch.float64).T)
        pose = self.pose_in.clone()
        balls = [(j, adr) for j, adr in self.adr.items() if j not in HINGE_JOINTS]
        quats = torch.stack([q[adr : adr + 4] for _, adr in balls])
        vecs = quaternion_to_axis_angle(quats / quats.norm(dim=1, keepdim=True))
        for (j, _), v in zip(balls, vecs):
            pose[j - 1] = v
        for j, adr in self.adr.items():
            if j in HINGE_JOINTS:
                pose[j - 1] = float(q[adr]) * torch.tensor(HINGE_JOINTS[j], dtype=torch.float64)
        return root_rot, q[0:3].clone(), pose


class SlotPool:
    """Up to P episodes stepped in lockstep, each in its own MjData (mj_step1, forces,
    mj_step2), everything else vectorised over the running bodies: one call computes the
    mattress forces of all of them, and the state they need is gathered into (P, ...) arrays
    once per step. A slot whose body settles or is rejected takes the next body from the
    queue at once, so the per-step Python cost stays shared by P bodies. Each body keeps its
    own step count, so results do not depend on P or on which slot a body runs in.
    (`mujoco.batch.Batch` steps the same way in C, but measured ~40% slower per body-step
    here: it loads and saves each simulation's state around every call.)"""

    def __init__(
        self,
        make,
        n: int,
        mat: MatSpec,
        config: SettleConfig,
        mattress: MattressParams,
        bed: BedShape | None,
        size: int,
    ):
        import mujoco

        self.mj, self.config = mujoco, config
        self.make = make  # episode index -> Episode (built when started)
        self.eps: list[Episode | None] = [None] * n
        self.P = size
        self.C = len(CAPSULE_NAMES)
        self.found = CapsuleFoundation(mat, mattress, config.grid_sub, bed=bed)
        self.n_nodes = self.found.nr * self.found.nc
        self.body_ids = None
        P, C = size, self.C
        self.ep = np.full(P, -1)  # episode in each slot (-1: free)
        self.step = np.zeros(P, dtype=np.int64)  # steps this slot's body has taken
        self.touched = np.full(P, -1)
        self.prev_v = np.zeros((P, C, 3))
        self.e_ref = np.full(P, np.nan)
        self.speed = np.full(P, np.inf)
        self.accel = np.full(P, np.inf)
        self.sink = np.zeros(P)
        self.radius, self.mass, self.inertia = np.zeros((P, C)), np.ones((P, C)), np.ones((P, C))
        self.loc_a, self.loc_b = np.zeros((P, C, 3)), np.zeros((P, C, 3))
        self.weight = np.ones(P)
        self.stick = np.zeros((len(self.found._sections), P, C, 2))  # static-friction springs
        self.roll0 = np.tile(np.eye(3), (P, 1, 1))  # pelvis orientation at the drop (roll hold)
        # Per slot: model, data and views of the MjData arrays read every step (a view made
        # once costs nothing later; MjData's attribute access builds a new one each time).
        self.slot: list[tuple | None] = [None] * P

    def fill(self, slots: np.ndarray, episodes: list[int]) -> None:
        """Start built episodes in free slots (their MjData hold the dropped initial state)."""
        for s, k in zip(slots, episodes):
            ep = self.eps[k]
            self.ep[s] = k
            self.radius[s], self.mass[s], self.inertia[s] = ep.radius, ep.cap_mass, ep.cap_inertia
            self.loc_a[s], self.loc_b[s] = ep.loc_a, ep.loc_b
            self.weight[s] = ep.mass * GRAVITY_M_S2
            d = ep.data
            self.slot[s] = (
                ep.model,
                d,
                d.cvel,
                d.xipos,
                d.subtree_com[0],
                d.xmat,
                d.xpos,
                d.energy,
                d.xfrc_applied,
                d.qvel,
            )
            self.roll0[s] = d.xmat[ep.body_ids[PELVIS]].reshape(3, 3)
        self.step[slots] = 0
        self.touched[slots] = -1
        self.e_ref[slots] = np.nan
        self.speed[slots] = np.inf
        self.accel[slots] = np.inf
        self.sink[slots] = 0.0
        self.stick[:, slots] = 0.0


def run_batch(
    make,
    n: int,
    mat: MatSpec,
    config: SettleConfig,
    mattress: MattressParams,
    bed: BedShape | None = None,
    pool: int = 16,
) -> list[EpisodeOutcome]:
    """Settle episodes 0..n-1 (`make(k)` builds episode k) `pool` at a time (see `SlotPool`);
    an episode is built when a slot takes it and released when it is done, so memory is
    bounded by the pool. Returns per episode its statistics and its resting parameters
    ("rest": (root_rotation, root_translation, pose), None when non-finite)."""
    dt = config.timestep_s
    every = max(1, round(config.zero_velocity_every_s / dt))
    thickness = float(mattress.thickness_m)
    out = [EpisodeOutcome() for _ in range(n)]
    t0 = time.perf_counter()
    if n:
        p = SlotPool(make, n, mat, config, mattress, bed, min(pool, n))
        drive_pool(p, list(range(n)), out, every, thickness, dt)
    wall = (time.perf_counter() - t0) * 1e3 / max(n, 1)
    for o in out:
        o.wall_ms = wall
    return out


def drive_pool(
    p: SlotPool, queue: list[int], out: list[EpisodeOutcome], every: int, thickness: float, dt: float
) -> None:
    """The lockstep loop. Per step and running body, in this order: mj_step1; non-finite
    check; capsule speeds and accelerations; at rest?; mattress forces (from the current
    state); touch; mj_step2; velocity reset before the touch; energy, sinking and falling
    checks; step limit."""
    mj, config, C, found = p.mj, p.config, p.C, p.found
    eps = p.eps
    queue = list(queue)
    ids_body = p.body_ids
    # MuJoCo resets a state it finds non-finite or huge, with one of these warnings.
    bad_state = [mj.mjtWarning.mjWARN_BADQPOS, mj.mjtWarning.mjWARN_BADQVEL, mj.mjtWarning.mjWARN_BADQACC]

    def finish(slots, reason, keep_state=True):
        for s in slots:
            k = int(p.ep[s])
            ep, o = eps[k], out[k]
            if any(ep.data.warning[w].number for w in bad_state):
                reason, keep_state = REASON_NONFINITE, False
            o.reason = reason
            o.steps = int(p.step[s])
            o.touch_step = int(p.touched[s])
            o.max_speed, o.max_accel, o.sink = float(p.speed[s]), float(p.accel[s]), float(p.sink[s])
            o.rest = ep.resting_params(ep.data.qpos) if keep_state else None
            p.ep[s] = -1
            p.slot[s] = None
            eps[k] = None  # release the model and data

    def start(count):
        """Build the next episodes off the queue; those starting off the bed are done at once."""
        ready = []
        while queue and len(ready) < count:
            k = queue.pop(0)
            ep = eps[k] = p.make(k)
            (xr, xr1), (yr, yr1) = ep.bounds
            if not (xr <= ep.root_surface[0] <= xr1 and yr <= ep.root_surface[1] <= yr1):
                out[k].reason = REASON_OFF_BED
                out[k].rest = ep.resting_params(ep.data.qpos)
                eps[k] = None
                continue
            if p.body_ids is None:
                p.body_ids = ep.body_ids
            ready.append(k)
        return ready

    free = np.arange(p.P)
    while True:
        if len(free) and queue:
            ready = start(len(free))
            if ready:
                p.fill(free[: len(ready)], ready)
                ids_body = p.body_ids
        ids = np.flatnonzero(p.ep >= 0)
        if not len(ids):
            break
        slots = [p.slot[s] for s in ids]
        for sl in slots:
            mj.mj_step1(sl[0], sl[1])
        cv = np.array([sl[2] for sl in slots])[:, ids_body]  # (n, C, 6)
        xipos = np.array([sl[3] for sl in slots])[:, ids_body]  # (n, C, 3)
        com = np.array([sl[4] for sl in slots])  # (n, 3)
        finite = np.isfinite(cv).all((1, 2)) & np.isfinite(xipos).all((1, 2))
        if not finite.all():
            finish(ids[~finite], REASON_NONFINITE, keep_state=False)
            ids, cv, xipos, com = ids[finite], cv[finite], xipos[finite], com[finite]
            slots = [sl for sl, f in zip(slots, finite) if f]
        rel = xipos - com[:, None]
        om = cv[..., :3]
        v = cv[..., 3:] + np.stack(
            [
                om[..., 1] * rel[..., 2] - om[..., 2] * rel[..., 1],
                om[..., 2] * rel[..., 0] - om[..., 0] * rel[..., 2],
                om[..., 0] * rel[..., 1] - om[..., 1] * rel[..., 0],
            ],
            -1,
        )
        has_prev = p.step[ids] > 0
        speed = np.sqrt(sq_norm3(v)).max(1)
        accel = np.sqrt(sq_norm3(v - p.prev_v[ids])).max(1) / dt
        p.speed[ids] = np.where(has_prev, speed, p.speed[ids])
        p.accel[ids] = np.where(has_prev, accel, p.accel[ids])
        p.prev_v[ids] = v
        t = p.touched[ids]
        rest = (
            (t >= 0)
            & (p.step[ids] - t >= config.min_steps_after_touch)
            & (p.speed[ids] < config.speed_tol_m_s)
            & (p.accel[ids] < config.accel_tol_m_s2)
        )
        if rest.any():
            finish(ids[rest], "")
            keep = ~rest
            ids, cv, xipos, com = ids[keep], cv[keep], xipos[keep], com[keep]
            slots = [sl for sl, r in zip(slots, rest) if not r]
        n = len(ids)
        if n == 0:
            free = np.flatnonzero(p.ep < 0)
            continue
        # One force evaluation for every running body.
        R = np.array([sl[5] for sl in slots])[:, ids_body].reshape(n, C, 3, 3)
        pos = np.array([sl[6] for sl in slots])[:, ids_body]
        a = (pos + matvec3(R, p.loc_a[ids])).reshape(-1, 3)
        b = (pos + matvec3(R, p.loc_b[ids])).reshape(-1, 3)
        offset = np.repeat(np.arange(n) * p.n_nodes, C)
        stick = p.stick[:, ids].reshape(-1, n * C, 2)
        res = found.forces(
            a,
            b,
            p.radius[ids].ravel(),
            cv.reshape(-1, 6),
            np.repeat(com, C, axis=0),
            xipos.reshape(-1, 3),
            p.mass[ids].ravel(),
            p.inertia[ids].ravel(),
            offset,
            dt,
            stick,
        )
        p.stick[:, ids] = stick.reshape(-1, n, C, 2)
        if res is None:
            ft = np.zeros((n * C, 6))
            wmax = np.zeros(n)
            e_mat = np.zeros(n)
            pelvis = np.zeros(n, dtype=bool)
        else:
            ft, cap, w, energy = res
            body_of = cap // C
            wmax = np.zeros(n)
            np.maximum.at(wmax, body_of, w)
            e_mat = np.bincount(body_of, energy, minlength=n)
            pelvis = np.bincount(body_of, cap % C == PELVIS, minlength=n) > 0
        carried = sum_last(ft[:, 2].reshape(n, C)) >= 0.9 * p.weight[ids]
        t = p.touched[ids]
        touched = np.where((t < 0) & (pelvis | carried), p.step[ids], t)
        p.touched[ids] = touched
        energy = sum_last(np.array([sl[7] for sl in slots])) + e_mat
        ft = ft.reshape(n, C, 6)
        if config.hold_roll_m > 0:
            ft, e_hold = hold_roll_torque(ft, R[:, PELVIS], p.roll0[ids], cv, p.mass[ids], p.weight[ids], config)
            energy = energy + e_hold
        step = p.step[ids]
        reset = (touched < 0) & ((step + 1) % every == 0)
        for j, sl in enumerate(slots):
            sl[8][ids_body] = ft[j]
            mj.mj_step2(sl[0], sl[1])
            if reset[j]:
                sl[9][:] = 0.0
        p.step[ids] = step + 1
        p.sink[ids] = wmax
        # After the last velocity reset the system is passive: energy can only fall.
        on = touched >= 0
        e_ref = p.e_ref[ids]
        first = on & (np.isnan(e_ref) | (step - touched < 2))
        grew = on & ~first & (energy > e_ref + 1.0 + 0.05 * p.weight[ids] * (config.drop_height_m + 0.05))
        p.e_ref[ids] = np.where(first, np.where(np.isnan(e_ref), energy, np.minimum(e_ref, energy)), e_ref)
        finish(ids[grew], REASON_ENERGY)
        sank = ~grew & (wmax > thickness)
        finish(ids[sank], REASON_SANK)
        fell = ~grew & ~sank & (com[:, 2] < -thickness)
        finish(ids[fell], REASON_FELL)
        left = ~grew & ~sank & ~fell
        finish(ids[left & (step + 1 >= config.max_steps)], REASON_TIMEOUT)
        free = np.flatnonzero(p.ep < 0)
