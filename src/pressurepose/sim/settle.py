"""Sim #1: the capsulised body settles onto the mattress (MuJoCo).

The MJCF is built per body from its `CapsuleBody` (body/capsules.py): one MuJoCo body per
capsule on the J24 tree, placed in the T-pose with world-aligned frames (so a ball joint's
quaternion is exactly the J24 local rotation of BodyParams.pose), explicit masses and inertias,
ball joints with MuJoCo's native joint springs (`stiffness`, spring reference = the home pose
through `qpos_spring`) and damping, hinge knees and elbows, a free root. 55 DoF.

The mattress is not a MuJoCo contact: every step, sim #2's foundation law is applied to the
capsules (seed eq. 17's role - both simulations push back on a body the same way): over each
node of the covered grid, the compression w of the lowest capsule surface point below the
mattress top gives the force (k1 w + k3 w^3) A upwards, plus a damper (time constant
`damping_s` x the local stiffness) and regularised Coulomb friction (`friction`), applied to
that capsule at that point through `xfrc_applied` (on a raised bed, per bed section in its own
frame). MuJoCo's soft contacts would make the sinking depend on the number of contacts
(DESIGN.md); this does not. The mattress's sides are MuJoCo boxes, so limbs hanging over the
edge rest against them. Forces come from the current state (between mj_step1 and mj_step2).

Procedure (seed A.2): the body starts with its lowest capsule point `drop_height_m` above the
mattress; all velocities are zeroed every 4 steps until the buttocks (pelvis) capsule touches;
the body is at rest when the largest capsule speed < 0.05 m/s and acceleration < 0.5 m/s^2.
Rejected (with the reason) after `max_steps` steps, on a non-finite state, when a capsule sinks
through the mattress (compression beyond its thickness), when the body falls off the bed, or
when the total mechanical energy (kinetic + gravity + joint springs + mattress) grows, which
an integrator going unstable does and a passive system cannot.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import torch

from pressurepose.body.capsules import (
    CAPSULE_JOINTS, CAPSULE_NAMES, CAPSULE_PARENTS, HINGE_JOINTS, CapsuleBody, Capsules, build_capsule_body,
    collision_pairs, segment_distance,
)
from pressurepose.body.model import BodyModel
from pressurepose.body.params import R_SUPINE, BodyParams, root_matrix
from pressurepose.body.rotations import (
    axis_angle_to_matrix, matrix_to_axis_angle, matrix_to_quaternion, quaternion_to_axis_angle,
)
from pressurepose.mat import MatSpec
from pressurepose.bed import BedShape
from pressurepose.sim.mattress import GRAVITY_M_S2, MattressParams

REASON_TIMEOUT = "did not settle within the step limit"
REASON_NONFINITE = "non-finite state"
REASON_SANK = "sank through the mattress"
REASON_FELL = "fell off the bed"
REASON_ENERGY = "energy grew (unstable)"
REASON_OFF_BED = "body outside the bed"
SETTLE_REASONS = (REASON_TIMEOUT, REASON_NONFINITE, REASON_SANK, REASON_FELL, REASON_ENERGY, REASON_OFF_BED)

PELVIS = CAPSULE_NAMES.index("pelvis")
SIM_VOLUME_POINTS = 2048  # capsule volumes for masses: <= 0.3% from 8192 points, a quarter of the cost
V_STICK = 0.02  # m/s: below this sliding speed Coulomb friction becomes a (stiff) damper


@dataclasses.dataclass(frozen=True)
class SettleConfig:
    timestep_s: float = 0.0103  # the seed's DART step
    max_steps: int = 2000
    zero_velocity_every_s: float = 4 * 0.0103  # the seed's 4 DART steps
    speed_tol_m_s: float = 0.05
    accel_tol_m_s2: float = 0.5
    drop_height_m: float = 0.02
    min_steps_after_touch: int = 8
    grid_sub: int = 1   # foundation nodes per taxel side (sim #1's grid)

    def __post_init__(self) -> None:
        if not (self.timestep_s > 0 and math.isfinite(self.timestep_s)):
            raise ValueError(f"timestep_s must be > 0, got {self.timestep_s}")
        for name in ("max_steps", "grid_sub"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"SettleConfig.{name} must be >= 1")


@dataclasses.dataclass
class SettleResult:
    """Sim #1 for B bodies. `params` is the resting pose (float64); unsettled samples keep
    their last state there and carry a reason."""

    params: BodyParams
    ok: np.ndarray            # (B,) bool
    reason: list[str]         # (B,) "" when settled
    steps: np.ndarray         # (B,) steps simulated
    touch_step: np.ndarray    # (B,) step the pelvis touched (-1: never)
    max_speed: np.ndarray     # (B,) at the end, m/s
    max_accel: np.ndarray     # (B,) at the end, m/s^2
    sink_m: np.ndarray        # (B,) deepest foundation compression at the end
    wall_ms: np.ndarray       # (B,) time taken


# --- MJCF -----------------------------------------------------------------------------------
def _fmt(v) -> str:
    return " ".join(f"{float(x):.9g}" for x in np.ravel(v))


def _walls(mat: MatSpec, bed: BedShape | None = None, top_m: float = -0.03, depth_m: float = 1.0,
           thick_m: float = 0.2) -> str:
    """The mattress's sides as MuJoCo boxes (the top is the foundation law): a limb hanging
    over the edge rests against the side instead of swinging in under the mattress top. On a
    bent bed each section has its own side walls (and end wall), in the section's frame."""
    bed = bed or BedShape()
    (x0, x1), (y0, y1) = mat.mattress_bounds_m
    hinge = np.array([bed.hinge_x(mat), 0.0, 0.0])
    hz = (depth_m + top_m) / 2  # the walls reach from -depth_m up to top_m (section frame)
    zc = top_m - hz
    lines = []
    for k, (R, s0, s1) in enumerate(bed.sections(mat)):
        a, b = max(x0, s0), min(x1, s1)
        boxes = [((a + b) / 2, y0 - thick_m / 2, (b - a) / 2, thick_m / 2),
                 ((a + b) / 2, y1 + thick_m / 2, (b - a) / 2, thick_m / 2)]
        if a == x0:
            boxes.append((x0 - thick_m / 2, (y0 + y1) / 2, thick_m / 2, (y1 - y0) / 2 + thick_m))
        if b == x1:
            boxes.append((x1 + thick_m / 2, (y0 + y1) / 2, thick_m / 2, (y1 - y0) / 2 + thick_m))
        quat = _quat(torch.from_numpy(R))
        for j, (cx, cy, hx, hy) in enumerate(boxes):
            pos = hinge + R @ (np.array([cx, cy, zc]) - hinge)
            lines.append(f'    <geom name="side{k}_{j}" type="box" pos="{_fmt(pos)}" quat="{_fmt(quat)}" '
                         f'size="{hx:.6g} {hy:.6g} {hz:.6g}" contype="1" conaffinity="0"/>')
    return "\n".join(lines)


def build_mjcf(body: CapsuleBody, i: int, config: SettleConfig, pairs: list[tuple[int, int]] = (),
               mat: MatSpec | None = None, bed: BedShape | None = None) -> str:
    """MJCF of capsule body `i` of `body` in its T-pose (body axes), free root; with `mat`,
    the mattress sides as walls."""
    caps = body.capsules
    rest = caps.rest[i].double().numpy()
    start, end = caps.start[i].double().numpy(), caps.end[i].double().numpy()
    radius = caps.radius[i].double().numpy()
    mass = body.mass_kg[i].double().numpy()
    inertia = body.inertia[i].double().numpy()
    stiff = body.stiffness[i].double().numpy()
    damp = body.damping[i].double().numpy()
    children: dict[int, list[int]] = {}
    for c, p in enumerate(CAPSULE_PARENTS):
        children.setdefault(p, []).append(c)

    def body_xml(c: int, indent: str) -> str:
        j = CAPSULE_JOINTS[c]
        p = CAPSULE_PARENTS[c]
        origin = rest[j]
        pos = origin - (rest[CAPSULE_JOINTS[p]] if p >= 0 else 0.0)
        a, b = start[c] - origin, end[c] - origin
        axis = b - a
        length = np.linalg.norm(axis)
        u = axis / length if length > 1e-9 else np.array([1.0, 0.0, 0.0])
        # Principal axes: capsule axis + two perpendiculars -> full inertia in the body frame.
        tmp = np.array([0.0, 0.0, 1.0]) if abs(u[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        v = np.cross(u, tmp); v /= np.linalg.norm(v)
        w = np.cross(u, v)
        Rm = np.stack([u, v, w], 1)
        I = Rm @ np.diag(inertia[c]) @ Rm.T
        full = [I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]]
        lines = [f'{indent}<body name="{CAPSULE_NAMES[c]}" pos="{_fmt(pos)}">']
        if p < 0:
            lines.append(f'{indent}  <freejoint name="root"/>')
        elif j in HINGE_JOINTS:
            lines.append(f'{indent}  <joint name="j{j}" type="hinge" axis="{_fmt(HINGE_JOINTS[j])}" '
                         f'stiffness="{stiff[j - 1]:.9g}" damping="{damp[j - 1]:.9g}" springref="0"/>')
        else:
            lines.append(f'{indent}  <joint name="j{j}" type="ball" stiffness="{stiff[j - 1]:.9g}" '
                         f'damping="{damp[j - 1]:.9g}"/>')
        lines.append(f'{indent}  <inertial pos="{_fmt((a + b) / 2)}" mass="{mass[c]:.9g}" fullinertia="{_fmt(full)}"/>')
        if length > 1e-9:
            lines.append(f'{indent}  <geom name="{CAPSULE_NAMES[c]}" type="capsule" size="{radius[c]:.9g}" fromto="{_fmt(np.concatenate([a, b]))}"/>')
        else:
            lines.append(f'{indent}  <geom name="{CAPSULE_NAMES[c]}" type="sphere" size="{radius[c]:.9g}" pos="{_fmt(a)}"/>')
        for ch in children.get(c, []):
            lines.append(body_xml(ch, indent + "  "))
        lines.append(f"{indent}</body>")
        return "\n".join(lines)

    pair_xml = "\n".join(f'    <pair geom1="{CAPSULE_NAMES[a]}" geom2="{CAPSULE_NAMES[b]}"/>' for a, b in pairs)
    return f"""<mujoco model="pressurepose_capsule_body">
  <option timestep="{config.timestep_s:.9g}" integrator="implicitfast" gravity="0 0 {-GRAVITY_M_S2}">
    <flag energy="enable"/>
  </option>
  <default><geom contype="0" conaffinity="1"/></default>
  <worldbody>
{_walls(mat, bed) if mat is not None else ""}
{body_xml(0, "    ")}
  </worldbody>
  <contact>
{pair_xml}
  </contact>
</mujoco>
"""


# --- the mattress acting on capsules --------------------------------------------------------
class CapsuleFoundation:
    """Sim #2's foundation law applied to capsules over a grid (numpy, per step)."""

    def __init__(self, mat: MatSpec, params: MattressParams, sub: int = 1, bed: BedShape | None = None):
        self.bed = bed or BedShape()
        self.hinge = np.array([self.bed.hinge_x(mat), 0.0, 0.0])
        self._sections = self.bed.sections(mat)
        self.hx, self.hy = mat.pitch_row_m / sub, mat.pitch_col_m / sub
        self.x0, self.y0 = -mat.border_head_foot_m, -mat.border_side_m
        self.nr, self.nc = mat.covered_rows * sub, mat.covered_cols * sub
        self.area = self.hx * self.hy
        self.k1, self.k3 = float(params.k1_pa_per_m), float(params.k3_pa_per_m3)
        self.nu, self.mu = float(params.damping_s), float(params.friction)

    def underside(self, a: np.ndarray, b: np.ndarray, r: np.ndarray, s_range=(-math.inf, math.inf)):
        """The nodes under C capsules (axis ends a, b (C, 3), radii r (C,)), each capsule's own
        footprint window, flattened: (capsule index, grid node index (-1 off the grid), node
        x, node y, the capsule's lowest surface height over the node (inf where none))."""
        lo = np.minimum(a[:, :2], b[:, :2]) - r[:, None]
        hi = np.maximum(a[:, :2], b[:, :2]) + r[:, None]
        i0 = np.floor((lo[:, 0] - self.x0) / self.hx).astype(np.int64)
        j0 = np.floor((lo[:, 1] - self.y0) / self.hy).astype(np.int64)
        nr = np.floor((hi[:, 0] - self.x0) / self.hx).astype(np.int64) - i0 + 1
        nc = np.floor((hi[:, 1] - self.y0) / self.hy).astype(np.int64) - j0 + 1
        size = nr * nc
        cap = np.repeat(np.arange(a.shape[0]), size)
        start = np.repeat(np.cumsum(size) - size, size)
        k = np.arange(cap.shape[0]) - start
        ii = i0[cap] + k // nc[cap]
        jj = j0[cap] + k % nc[cap]
        x = self.x0 + (ii + 0.5) * self.hx
        y = self.y0 + (jj + 0.5) * self.hy
        inside = (ii >= 0) & (ii < self.nr) & (jj >= 0) & (jj < self.nc) & (x >= s_range[0]) & (x < s_range[1])
        flat = np.where(inside, ii * self.nc + jj, -1)
        ax, ay, az = a[cap, 0], a[cap, 1], a[cap, 2]
        rc2 = r[cap] ** 2
        # End spheres.
        z = np.full(x.shape, np.inf)
        for ex, ey, ez in ((ax, ay, az), (b[cap, 0], b[cap, 1], b[cap, 2])):
            d2 = (x - ex) ** 2 + (y - ey) ** 2
            z = np.where(d2 <= rc2, np.minimum(z, ez - np.sqrt(np.maximum(rc2 - d2, 0.0))), z)
        # Cylinder: lower root of |perp(p - a)|^2 = r^2 on the vertical line through the node.
        axis = b - a
        L = np.sqrt((axis**2).sum(1))
        u = axis / np.maximum(L, 1e-12)[:, None]
        ux, uy, uz = u[cap, 0], u[cap, 1], u[cap, 2]
        d0x, d0y, d0z = x - ax, y - ay, -az
        du = d0x * ux + d0y * uy + d0z * uz
        A = 1.0 - uz**2
        Bq = 2.0 * (d0z - du * uz)
        Cq = d0x**2 + d0y**2 + d0z**2 - du**2 - rc2
        disc = Bq**2 - 4 * A * Cq
        ok = (A > 1e-9) & (disc >= 0)
        zc = (-Bq - np.sqrt(np.maximum(disc, 0.0))) / (2 * np.where(ok, A, 1.0))
        t = du + zc * uz
        ok &= (t >= 0) & (t <= L[cap])
        z = np.where(ok, np.minimum(z, zc), z)
        return cap, flat, x, y, z

    def forces(self, a, b, r, body_vel, com, xipos, mass, inertia, offset, dt: float):
        """Mattress forces on C capsules (of one or several bodies, stepped together), summed
        over the bed's sections (one when flat): each section is handled in its own frame,
        where its top is z = 0 (see `_forces_local`)."""
        if self.bed.flat:
            return self._forces_local(a, b, r, body_vel, com, xipos, mass, inertia, offset, dt)
        total, caps, ws, es = None, [], [], []
        for R, s0, s1 in self._sections:
            # Positions into the section's frame about the hinge; velocities just rotate.
            a_l, b_l, com_l, xi_l = ((p - self.hinge) @ R + self.hinge for p in (a, b, com, xipos))
            vel = np.concatenate([body_vel[:, :3] @ R, body_vel[:, 3:] @ R], 1)
            res = self._forces_local(a_l, b_l, r, vel, com_l, xi_l, mass, inertia, offset, dt, (s0, s1))
            if res is None:
                continue
            out, cap, w, energy = res
            out = np.concatenate([out[:, :3] @ R.T, out[:, 3:] @ R.T], 1)
            total = out if total is None else total + out
            caps.append(cap), ws.append(w), es.append(energy)
        if total is None:
            return None
        return total, np.concatenate(caps), np.concatenate(ws), np.concatenate(es)

    def _forces_local(self, a, b, r, body_vel, com, xipos, mass, inertia, offset, dt: float,
                      s_range=(-math.inf, math.inf)):
        """Mattress forces on C capsules in a frame where the (section's) top is z = 0.

        a, b: (C, 3) axis ends; r: (C,); body_vel: (C, 6) angular and linear velocity of
        each capsule's body, the linear part at the point com (C, 3) (MuJoCo's cvel);
        xipos, mass, inertia (smallest principal moment): (C, 3), (C,), (C,); offset: (C,)
        node-index offset of each capsule's body (bodies do not share nodes).
        Returns (C, 6) force and torque about xipos, and per loaded node its capsule,
        compression and elastic energy - or None when nothing touches."""
        C = a.shape[0]
        active = np.flatnonzero(np.minimum(a[:, 2], b[:, 2]) - r < 0.0)
        if active.size == 0:
            return None
        # Only the part of the axis lower than r can reach below the mattress top: clip the
        # capsule to it (exact for every point below z = 0; smaller node windows).
        aa, bb, rr = a[active], b[active], r[active]
        dz = bb[:, 2] - aa[:, 2]
        safe = np.where(np.abs(dz) > 1e-12, dz, 1.0)
        t_cut = np.clip((rr - aa[:, 2]) / safe, 0.0, 1.0)
        t0 = np.where(dz < -1e-12, t_cut, 0.0)
        t1 = np.where(dz > 1e-12, t_cut, 1.0)
        axis = bb - aa
        aa, bb = aa + t0[:, None] * axis, aa + t1[:, None] * axis
        local, flat, x, y, z = self.underside(aa, bb, rr, s_range)
        valid = (flat >= 0) & (z < 0.0)
        if not valid.any():
            return None
        cap = active[local[valid]]
        idx = flat[valid] + offset[cap]
        zz, px, py = z[valid], x[valid], y[valid]
        # The lowest capsule over a node is the one the foam pushes on.
        order = np.lexsort((zz, idx))
        keep = order[np.r_[True, idx[order][1:] != idx[order][:-1]]]
        cap, zz, px, py = cap[keep], zz[keep], px[keep], py[keep]
        w = -zz
        rel = np.stack([px, py, zz], 1) - com[cap]
        om, v = body_vel[cap, :3], body_vel[cap, 3:]
        vel = v + _cross(om, rel)
        arm = rel + (com - xipos)[cap]
        # The damper is taken implicitly per capsule (backward Euler: c -> c / (1 + c dt / m),
        # with the smallest inertia for the lever arms), so light capsules stay stable.
        c = self.nu * (self.k1 + 3.0 * self.k3 * w**2) * self.area
        arm2 = (arm**2).sum(1)
        c_lin = np.bincount(cap, c, minlength=C)
        c_rot = np.bincount(cap, c * arm2, minlength=C)
        scale = 1.0 / (1.0 + dt * np.maximum(c_lin / mass, c_rot / inertia))
        fn = np.maximum((self.k1 * w + self.k3 * w**3) * self.area - scale[cap] * c * vel[:, 2], 0.0)
        out = np.zeros((C, 6))
        out[:, 2] = np.bincount(cap, fn, minlength=C)
        out[:, 3] = np.bincount(cap, arm[:, 1] * fn, minlength=C)
        out[:, 4] = np.bincount(cap, -arm[:, 0] * fn, minlength=C)
        self._friction(out, cap, arm, vel, fn, mass, inertia, dt)
        energy = (self.k1 * w**2 / 2 + self.k3 * w**4 / 4) * self.area
        return out, cap, w, energy

    def _friction(self, out, cap, arm, vel, fn, mass, inertia, dt) -> None:
        """Coulomb friction per capsule at its centre of pressure, regularised below V_STICK
        as a damper taken implicitly on the capsule's effective mass at that point (at most
        half the damper that would stop it within one step): it never reverses a capsule,
        so the explicit step stays stable for the lightest hand."""
        C = out.shape[0]
        Fn = out[:, 2]
        touching = Fn > 1e-9
        if not touching.any():
            return
        wgt = fn / np.maximum(Fn[cap], 1e-12)
        arm_c = np.stack([np.bincount(cap, wgt * arm[:, k], minlength=C) for k in range(3)], 1)
        vel_c = np.stack([np.bincount(cap, wgt * vel[:, k], minlength=C) for k in range(2)], 1)
        m_eff = 1.0 / (1.0 / mass + (arm_c**2).sum(1) / inertia)
        c = self.mu * Fn / V_STICK
        c_eff = c / (1.0 + 2.0 * c * dt / m_eff)
        speed = np.sqrt((vel_c**2).sum(1))
        mag = np.minimum(self.mu * Fn, c_eff * speed)
        f = np.zeros((C, 3))
        f[:, :2] = -vel_c * (mag / np.maximum(speed, 1e-12))[:, None]
        out[:, :3] += f
        out[:, 3:] += _cross(arm_c, f)


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (N, 3) arrays (np.cross is slow on small arrays)."""
    return np.stack([u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1],
                     u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2],
                     u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]], 1)


def _quat(R: torch.Tensor) -> np.ndarray:
    return matrix_to_quaternion(R).double().numpy()


def initial_pairs(body: CapsuleBody, i: int, params: BodyParams) -> list[tuple[int, int]]:
    """The sampler's self-collision pairs (distal capsules vs non-adjacent ones) that are
    apart in the initial pose: MuJoCo keeps them apart while the body settles."""
    c = body.capsules
    caps = Capsules(c.start[i : i + 1], c.end[i : i + 1], c.radius[i : i + 1], c.rest[i : i + 1])
    a, b = caps.posed(params.pose[i : i + 1].to(caps.rest.dtype))
    pairs = collision_pairs()
    d = segment_distance(a[0][pairs[:, 0]], b[0][pairs[:, 0]], a[0][pairs[:, 1]], b[0][pairs[:, 1]])
    gap = d - caps.radius[0][pairs[:, 0]] - caps.radius[0][pairs[:, 1]]
    return [(int(p[0]), int(p[1])) for p, g in zip(pairs, gap) if float(g) > 0.0]


class _Episode:
    """One capsule body in MuJoCo: built, dropped, stepped until it rests or is rejected."""

    def __init__(self, body: CapsuleBody, i: int, params: BodyParams, mattress: MattressParams,
                 mat: MatSpec, config: SettleConfig, bed: BedShape | None = None):
        import mujoco

        self.mj, self.config, self.mattress = mujoco, config, mattress
        m = self.model = mujoco.MjModel.from_xml_string(build_mjcf(body, i, config, initial_pairs(body, i, params), mat, bed))
        d = self.data = mujoco.MjData(m)
        pose = params.pose[i].double()
        home = body.home_pose[i].double()
        self.pose_in = pose
        self.adr: dict[int, int] = {}
        for j in CAPSULE_JOINTS[1:]:
            jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"j{j}")
            adr = self.adr[j] = int(m.jnt_qposadr[jid])
            if j in HINGE_JOINTS:
                axis = torch.tensor(HINGE_JOINTS[j], dtype=torch.float64)
                d.qpos[adr] = float(pose[j - 1] @ axis)
                m.qpos_spring[adr] = float(home[j - 1] @ axis)
            else:
                d.qpos[adr : adr + 4] = _quat(axis_angle_to_matrix(pose[j - 1]))
                m.qpos_spring[adr : adr + 4] = _quat(axis_angle_to_matrix(home[j - 1]))
        d.qpos[0:3] = params.root_translation[i].double().numpy()
        d.qpos[3:7] = _quat(root_matrix(params.root_rotation[i : i + 1].double())[0])
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
            lift = config.drop_height_m - float((np.minimum(n[: len(a)], n[len(a):]) - self.radius).min())
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

    def capsule_velocities(self) -> np.ndarray:
        """(C, 3) linear velocity of each capsule's centre of mass."""
        d = self.data
        cv = d.cvel[self.body_ids]
        return cv[:, 3:] + _cross(cv[:, :3], d.xipos[self.body_ids] - d.subtree_com[0])

    def resting_params(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(root_rotation (3,), root_translation (3,), pose (23, 3)) from the MuJoCo state."""
        q = torch.from_numpy(self.data.qpos.copy())
        R = _quat_to_matrix(q[3:7])
        root_rot = matrix_to_axis_angle(R @ torch.tensor(R_SUPINE, dtype=torch.float64).T)
        pose = self.pose_in.clone()
        for j, adr in self.adr.items():
            if j in HINGE_JOINTS:
                pose[j - 1] = float(q[adr]) * torch.tensor(HINGE_JOINTS[j], dtype=torch.float64)
            else:
                pose[j - 1] = quaternion_to_axis_angle(q[adr : adr + 4] / q[adr : adr + 4].norm())
        return root_rot, q[0:3].clone(), pose


def _run_batch(eps: list[_Episode], config: SettleConfig, mattress: MattressParams,
               bed: BedShape | None = None) -> list[dict]:
    """Step several episodes in lockstep: MuJoCo steps each body, one vectorised call computes
    the mattress forces for all of them (the per-step Python cost is shared)."""
    import mujoco as mj

    E, C = len(eps), len(CAPSULE_NAMES)
    dt = config.timestep_s
    found = CapsuleFoundation(eps[0].mat, mattress, config.grid_sub, bed=bed)
    n_nodes = found.nr * found.nc
    every = max(1, round(config.zero_velocity_every_s / dt))
    out = [dict(reason="", steps=0, touch_step=-1, max_speed=np.inf, max_accel=np.inf, sink=0.0, wall_ms=0.0)
           for _ in eps]
    t0 = time.perf_counter()
    running = []
    for k, ep in enumerate(eps):
        (xr, xr1), (yr, yr1) = ep.bounds
        if not (xr <= ep.root_surface[0] <= xr1 and yr <= ep.root_surface[1] <= yr1):
            out[k]["reason"] = REASON_OFF_BED
        else:
            running.append(k)
    radius = np.concatenate([ep.radius for ep in eps])
    mass = np.concatenate([ep.cap_mass for ep in eps])
    inertia = np.concatenate([ep.cap_inertia for ep in eps])
    weight = np.array([ep.mass * GRAVITY_M_S2 for ep in eps])
    tol_energy = 1.0 + 0.05 * weight * (config.drop_height_m + 0.05)
    e_ref = np.full(E, np.nan)
    touched = np.full(E, -1)
    prev_v = [None] * E
    thickness = float(mattress.thickness_m)
    for step in range(config.max_steps):
        if not running:
            break
        alive = []
        for k in running:
            ep = eps[k]
            mj.mj_step1(ep.model, ep.data)
            d = ep.data
            if not (np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()):
                out[k]["reason"] = REASON_NONFINITE
                continue
            v = ep.capsule_velocities()
            if prev_v[k] is not None:
                out[k]["max_speed"] = float(np.sqrt((v**2).sum(1)).max())
                out[k]["max_accel"] = float(np.sqrt(((v - prev_v[k]) ** 2).sum(1)).max() / dt)
            prev_v[k] = v
            if (touched[k] >= 0 and step - touched[k] >= config.min_steps_after_touch
                    and out[k]["max_speed"] < config.speed_tol_m_s and out[k]["max_accel"] < config.accel_tol_m_s2):
                continue  # at rest
            alive.append(k)
        running = alive
        if not running:
            break
        # One force evaluation for every running body.
        idx = np.array(running)
        ends = [eps[k].ends() for k in running]
        a = np.concatenate([e[0] for e in ends])
        b = np.concatenate([e[1] for e in ends])
        sel = (idx[:, None] * C + np.arange(C)[None]).ravel()
        vel = np.concatenate([eps[k].data.cvel[eps[k].body_ids] for k in running])
        com = np.repeat(np.stack([eps[k].data.subtree_com[0] for k in running]), C, axis=0)
        xipos = np.concatenate([eps[k].data.xipos[eps[k].body_ids] for k in running])
        offset = np.repeat(np.arange(len(running)) * n_nodes, C)
        res = found.forces(a, b, radius[sel], vel, com, xipos, mass[sel], inertia[sel], offset, dt)
        n = len(running)
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
        carried = ft[:, 2].reshape(n, C).sum(1) >= 0.9 * weight[idx]
        alive = []
        for j, k in enumerate(running):
            ep, d, o = eps[k], eps[k].data, out[k]
            if touched[k] < 0 and (pelvis[j] or carried[j]):
                touched[k] = step
            d.xfrc_applied[ep.body_ids] = ft[j * C:(j + 1) * C]
            energy = float(d.energy[0] + d.energy[1]) + float(e_mat[j])
            mj.mj_step2(ep.model, d)
            o["steps"] = step + 1
            o["sink"] = float(wmax[j])
            if touched[k] < 0 and (step + 1) % every == 0:
                d.qvel[:] = 0.0
            if touched[k] >= 0:
                # After the last velocity reset the system is passive: energy can only fall.
                if np.isnan(e_ref[k]) or step - touched[k] < 2:
                    e_ref[k] = energy if np.isnan(e_ref[k]) else min(e_ref[k], energy)
                elif energy > e_ref[k] + tol_energy[k]:
                    o["reason"] = REASON_ENERGY
                    continue
            if wmax[j] > thickness:
                o["reason"] = REASON_SANK
                continue
            if d.subtree_com[0][2] < -thickness:
                o["reason"] = REASON_FELL
                continue
            alive.append(k)
        running = alive
    for k in running:
        out[k]["reason"] = REASON_TIMEOUT
    wall = (time.perf_counter() - t0) * 1e3 / max(E, 1)
    for k in range(E):
        out[k]["touch_step"] = int(touched[k])
        out[k]["wall_ms"] = wall
    return out


def as_float64(model: BodyModel) -> BodyModel:
    """The model itself when float64, else a float64 copy (never converts the caller's)."""
    if model.dtype == torch.float64:
        return model
    import copy

    return copy.deepcopy(model).to(torch.float64)


def _quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    q = q / q.norm()
    return axis_angle_to_matrix(quaternion_to_axis_angle(q))


def settle(model: BodyModel, params: BodyParams, mattress: MattressParams | None = None,
           mat: MatSpec | None = None, config: SettleConfig | None = None,
           body: CapsuleBody | None = None, batch: int = 16, bed: BedShape | None = None) -> SettleResult:
    """Settle B initial poses (BodyParams, mat frame) onto the mattress: one MuJoCo model per
    body, `batch` of them stepped together (results do not depend on `batch`).

    `body` (the capsulised bodies of params.shape) is built when not given. Returns the
    resting poses and per-sample statistics; unsettled samples are flagged, never NaN.
    """
    mattress = mattress or MattressParams()
    mat = mat or MatSpec()
    config = config or SettleConfig()
    params = params.to(torch.float64)
    params.validate(model.shape_dim, torch.float64, params.shape.device)
    B = params.batch_size
    if body is None:
        body = build_capsule_body(as_float64(model), params.shape, volume_points=SIM_VOLUME_POINTS)
    if body.capsules.batch_size != B:
        raise ValueError(f"capsule body batch ({body.capsules.batch_size}) != params batch ({B})")
    masses = body.mass_kg.sum(-1)
    if not torch.isfinite(masses).all() or bool((masses <= 0).any()):
        raise ValueError("every body needs a finite mass > 0 (check the shape parameters)")
    root_rot = params.root_rotation.clone()
    root_t = params.root_translation.clone()
    pose = params.pose.clone()
    stats = {k: np.zeros(B) for k in ("steps", "touch_step", "max_speed", "max_accel", "sink", "wall_ms")}
    reasons = []
    for lo in range(0, B, batch):
        t_build = time.perf_counter()
        eps = [_Episode(body, i, params, mattress, mat, config, bed) for i in range(lo, min(B, lo + batch))]
        build_ms = (time.perf_counter() - t_build) * 1e3 / len(eps)
        outs = _run_batch(eps, config, mattress, bed)
        for j, (ep, o) in enumerate(zip(eps, outs)):
            i = lo + j
            reasons.append(o["reason"])
            o["wall_ms"] += build_ms
            for k in stats:
                stats[k][i] = o[k]
            if o["reason"] != REASON_NONFINITE:
                root_rot[i], root_t[i], pose[i] = ep.resting_params()
    return SettleResult(
        params=params.replace(root_rotation=root_rot, root_translation=root_t, pose=pose),
        ok=np.array([not r for r in reasons]), reason=reasons, steps=stats["steps"].astype(int),
        touch_step=stats["touch_step"].astype(int), max_speed=stats["max_speed"],
        max_accel=stats["max_accel"], sink_m=stats["sink"], wall_ms=stats["wall_ms"],
    )


__all__ = ["SETTLE_REASONS", "SettleConfig", "SettleResult", "build_mjcf", "settle"]
