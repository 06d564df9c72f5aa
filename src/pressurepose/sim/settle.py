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
that capsule at that point through `xfrc_applied`. MuJoCo's soft contacts would make the
sinking depend on the number of contacts (DESIGN.md); this does not.

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
from pressurepose.sim.mattress import GRAVITY_M_S2, MattressParams

REASON_TIMEOUT = "did not settle within the step limit"
REASON_NONFINITE = "non-finite state"
REASON_SANK = "sank through the mattress"
REASON_FELL = "fell off the bed"
REASON_ENERGY = "energy grew (unstable)"
REASON_OFF_BED = "body outside the bed"
SETTLE_REASONS = (REASON_TIMEOUT, REASON_NONFINITE, REASON_SANK, REASON_FELL, REASON_ENERGY, REASON_OFF_BED)

PELVIS = CAPSULE_NAMES.index("pelvis")
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


def _walls(mat: MatSpec, top_m: float = -0.03, depth_m: float = 1.0, thick_m: float = 0.2) -> str:
    """The mattress's sides as MuJoCo boxes (the top is the foundation law): a limb hanging
    over the edge rests against the side instead of swinging in under the mattress top."""
    (x0, x1), (y0, y1) = mat.mattress_bounds_m
    hz = (depth_m + top_m) / 2  # the walls reach from -depth_m up to top_m
    zc = top_m - hz
    boxes = [
        (x0 - thick_m / 2, (y0 + y1) / 2, thick_m / 2, (y1 - y0) / 2 + thick_m),
        (x1 + thick_m / 2, (y0 + y1) / 2, thick_m / 2, (y1 - y0) / 2 + thick_m),
        ((x0 + x1) / 2, y0 - thick_m / 2, (x1 - x0) / 2, thick_m / 2),
        ((x0 + x1) / 2, y1 + thick_m / 2, (x1 - x0) / 2, thick_m / 2),
    ]
    return "\n".join(f'    <geom name="side{k}" type="box" pos="{cx:.6g} {cy:.6g} {zc:.6g}" size="{hx:.6g} {hy:.6g} {hz:.6g}" '
                     f'contype="1" conaffinity="0"/>' for k, (cx, cy, hx, hy) in enumerate(boxes))


def build_mjcf(body: CapsuleBody, i: int, config: SettleConfig, pairs: list[tuple[int, int]] = (),
               mat: MatSpec | None = None) -> str:
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
{_walls(mat) if mat is not None else ""}
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

    def __init__(self, mat: MatSpec, params: MattressParams, sub: int, max_extent_m: float):
        self.mat, self.params, self.sub = mat, params, sub
        self.hx, self.hy = mat.pitch_row_m / sub, mat.pitch_col_m / sub
        self.x0, self.y0 = -mat.border_head_foot_m, -mat.border_side_m
        self.nr, self.nc = mat.covered_rows * sub, mat.covered_cols * sub
        self.area = self.hx * self.hy
        self.wr = int(math.ceil(max_extent_m / self.hx)) + 2
        self.wc = int(math.ceil(max_extent_m / self.hy)) + 2
        self.k1, self.k3 = float(params.k1_pa_per_m), float(params.k3_pa_per_m3)
        self.nu, self.mu = float(params.damping_s), float(params.friction)
        self._ar = np.arange(self.wr)
        self._ac = np.arange(self.wc)

    def underside(self, a: np.ndarray, b: np.ndarray, r: np.ndarray):
        """Per capsule (C,) a window of nodes: global flat index (C, wr, wc) (-1 outside the
        grid), node x, y and the capsule's lowest surface height there (inf where none)."""
        lo = np.minimum(a[:, :2], b[:, :2]) - r[:, None]
        hi = np.maximum(a[:, :2], b[:, :2]) + r[:, None]
        i0 = np.floor((lo[:, 0] - self.x0) / self.hx).astype(np.int64)
        j0 = np.floor((lo[:, 1] - self.y0) / self.hy).astype(np.int64)
        # One window for all capsules: the largest current footprint.
        wr = min(self.wr, int((np.floor((hi[:, 0] - self.x0) / self.hx) - i0).max()) + 1)
        wc = min(self.wc, int((np.floor((hi[:, 1] - self.y0) / self.hy) - j0).max()) + 1)
        ii = i0[:, None, None] + np.arange(wr)[None, :, None]
        jj = j0[:, None, None] + np.arange(wc)[None, None, :]
        ii, jj = np.broadcast_arrays(ii, jj)
        x = self.x0 + (ii + 0.5) * self.hx
        y = self.y0 + (jj + 0.5) * self.hy
        inside = (ii >= 0) & (ii < self.nr) & (jj >= 0) & (jj < self.nc)
        flat = np.where(inside, ii * self.nc + jj, -1)
        # End spheres.
        z = np.full(x.shape, np.inf)
        for e in (a, b):
            d2 = (x - e[:, 0, None, None]) ** 2 + (y - e[:, 1, None, None]) ** 2
            r2 = r[:, None, None] ** 2
            zs = e[:, 2, None, None] - np.sqrt(np.maximum(r2 - d2, 0.0))
            z = np.where(d2 <= r2, np.minimum(z, zs), z)
        # Cylinder: lower root of |perp(p - a)|^2 = r^2 on the vertical line through the node.
        axis = b - a
        L = np.linalg.norm(axis, axis=1)
        u = axis / np.maximum(L, 1e-12)[:, None]
        d0x = x - a[:, 0, None, None]
        d0y = y - a[:, 1, None, None]
        d0z = -a[:, 2, None, None]
        ux, uy, uz = (u[:, k, None, None] for k in range(3))
        du = d0x * ux + d0y * uy + d0z * uz
        A = 1.0 - uz**2
        Bq = 2.0 * (d0z - du * uz)
        Cq = d0x**2 + d0y**2 + d0z**2 - du**2 - r[:, None, None] ** 2
        disc = Bq**2 - 4 * A * Cq
        ok = (A > 1e-9) & (disc >= 0)
        zc = (-Bq - np.sqrt(np.maximum(disc, 0.0))) / (2 * np.where(ok, A, 1.0))
        t = du + zc * uz
        ok &= (t >= 0) & (t <= L[:, None, None])
        z = np.where(ok, np.minimum(z, zc), z)
        return flat, x, y, z

    def apply(self, a, b, r, body_vel, com, xipos, mass, inertia, dt: float, pelvis: int):
        """Mattress forces on capsules with axis ends a, b (C, 3) and radii r (C,).

        body_vel: (C, 6) angular and linear velocity of each capsule's body, the linear part
        at the point `com` (3,) (MuJoCo's cvel convention); returns per-capsule force and
        torque about `xipos` are assembled by the caller from (cap, point, force)."""
        active = np.flatnonzero(np.minimum(a[:, 2], b[:, 2]) - r < 0.0)
        if active.size == 0:
            return None
        flat, x, y, z = self.underside(a[active], b[active], r[active])
        valid = (flat >= 0) & (z < 0.0)
        if not valid.any():
            return None
        cap = np.broadcast_to(active[:, None, None], z.shape)[valid]
        idx, zz = flat[valid], z[valid]
        px, py = x[valid], y[valid]
        # The lowest capsule over a node is the one the foam pushes on.
        order = np.lexsort((zz, idx))
        keep = order[np.r_[True, idx[order][1:] != idx[order][:-1]]]
        cap, zz, px, py = cap[keep], zz[keep], px[keep], py[keep]
        w = -zz
        point = np.stack([px, py, zz], 1)
        om, v = body_vel[cap, :3], body_vel[cap, 3:]
        arm = point - xipos[cap]
        vel = v + np.cross(om, point - com)
        C = a.shape[0]
        # The damper is taken implicitly per capsule (backward Euler: c -> c / (1 + c dt / m),
        # with the smallest inertia for the lever arms), so light capsules stay stable.
        c = self.nu * (self.k1 + 3.0 * self.k3 * w**2) * self.area
        c_lin = np.bincount(cap, c, minlength=C)
        c_rot = np.bincount(cap, c * (arm**2).sum(1), minlength=C)
        scale = 1.0 / (1.0 + dt * np.maximum(c_lin / mass, c_rot / inertia))
        fn = np.maximum((self.k1 * w + self.k3 * w**3) * self.area - scale[cap] * c * vel[:, 2], 0.0)
        force = np.zeros((fn.shape[0], 3))
        force[:, 2] = fn
        energy = float((self.k1 * w**2 / 2 + self.k3 * w**4 / 4).sum() * self.area)
        return cap, arm, vel, force, float(w.max()), bool((cap == pelvis).any()), energy


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
                 mat: MatSpec, config: SettleConfig):
        import mujoco

        self.mj, self.config, self.mattress = mujoco, config, mattress
        m = self.model = mujoco.MjModel.from_xml_string(build_mjcf(body, i, config, initial_pairs(body, i, params), mat))
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
        mujoco.mj_forward(m, d)
        a, b = self.ends()
        d.qpos[2] += config.drop_height_m - float((np.minimum(a[:, 2], b[:, 2]) - self.radius).min())
        d.qvel[:] = 0.0
        mujoco.mj_forward(m, d)
        extent = float(np.max(np.linalg.norm(self.loc_b - self.loc_a, axis=1) + 2 * self.radius))
        self.foundation = CapsuleFoundation(mat, mattress, config.grid_sub, extent)
        self.mass = float(m.body_subtreemass[0])
        self.cap_mass = m.body_mass[self.body_ids].copy()
        self.cap_inertia = m.body_inertia[self.body_ids].min(1).copy()
        self.bounds = mat.mattress_bounds_m

    def ends(self) -> tuple[np.ndarray, np.ndarray]:
        d = self.data
        R = d.xmat[self.body_ids].reshape(-1, 3, 3)
        p = d.xpos[self.body_ids]
        return p + np.einsum("cij,cj->ci", R, self.loc_a), p + np.einsum("cij,cj->ci", R, self.loc_b)

    def capsule_velocities(self) -> np.ndarray:
        """(C, 3) linear velocity of each capsule's centre of mass."""
        d = self.data
        cv = d.cvel[self.body_ids]
        return cv[:, 3:] + np.cross(cv[:, :3], d.xipos[self.body_ids] - d.subtree_com[0])

    def push(self) -> tuple[float, bool, float]:
        """Set xfrc_applied from the mattress; returns (max compression, pelvis in contact or
        the weight carried, mattress elastic energy)."""
        d = self.data
        d.xfrc_applied[:] = 0.0
        a, b = self.ends()
        out = self.foundation.apply(a, b, self.radius, d.cvel[self.body_ids], d.subtree_com[0],
                                    d.xipos[self.body_ids], self.cap_mass, self.cap_inertia,
                                    self.config.timestep_s, PELVIS)
        if out is None:
            return 0.0, False, 0.0
        cap, arm, vel, force, wmax, pelvis, energy = out
        C = len(self.body_ids)
        ft = np.zeros((C, 6))
        for k in range(3):
            ft[:, k] = np.bincount(cap, force[:, k], minlength=C)
        torque = np.cross(arm, force)
        for k in range(3):
            ft[:, 3 + k] = np.bincount(cap, torque[:, k], minlength=C)
        self._friction(cap, arm, vel, force[:, 2], ft)
        d.xfrc_applied[self.body_ids] = ft
        # "Touching" also when the mattress already carries the body (side-lying bodies rest
        # on shoulder and hip while the crosswise pelvis capsule stands upright).
        carried = float(ft[:, 2].sum()) >= 0.9 * self.mass * GRAVITY_M_S2
        return wmax, pelvis or carried, energy

    def _friction(self, cap, arm, vel, fn, ft) -> None:
        """Coulomb friction per capsule at its centre of pressure, regularised below
        V_STICK as a damper, and that damper taken implicitly (backward Euler on the capsule's
        effective mass at the point): it may stop a capsule within a step but never reverse
        it, so the explicit step stays stable for the lightest hand."""
        C = ft.shape[0]
        Fn = np.bincount(cap, fn, minlength=C)
        touching = Fn > 1e-9
        if not touching.any():
            return
        w = fn / np.maximum(Fn[cap], 1e-12)
        arm_c = np.stack([np.bincount(cap, w * arm[:, k], minlength=C) for k in range(3)], 1)
        vel_c = np.stack([np.bincount(cap, w * vel[:, k], minlength=C) for k in range(2)], 1)
        dt = self.config.timestep_s
        m_eff = 1.0 / (1.0 / self.cap_mass + (arm_c**2).sum(1) / self.cap_inertia)
        c = self.mattress.friction * Fn / V_STICK
        c_eff = c / (1.0 + 2.0 * c * dt / m_eff)  # at most half the one-step stopping damper
        speed = np.sqrt((vel_c**2).sum(1))
        mag = np.minimum(self.mattress.friction * Fn, c_eff * speed)
        f = -vel_c * (mag / np.maximum(speed, 1e-12))[:, None]
        force = np.concatenate([f, np.zeros((C, 1))], 1)
        ft[:, :3] += force
        ft[:, 3:] += np.cross(arm_c, force)

    def run(self) -> dict:
        mj, m, d, cfg = self.mj, self.model, self.data, self.config
        t0 = time.perf_counter()
        (xr, xr1), (yr, yr1) = self.bounds
        out = dict(reason="", steps=0, touch_step=-1, max_speed=np.inf, max_accel=np.inf, sink=0.0)
        if not (xr <= d.qpos[0] <= xr1 and yr <= d.qpos[1] <= yr1):
            out["reason"] = REASON_OFF_BED
            out["wall_ms"] = (time.perf_counter() - t0) * 1e3
            return out
        weight = self.mass * GRAVITY_M_S2
        tol_energy = 1.0 + 0.05 * weight * (cfg.drop_height_m + 0.05)
        e_ref = None
        prev_v = self.capsule_velocities()
        touched_at = -1
        every = max(1, round(cfg.zero_velocity_every_s / cfg.timestep_s))
        for step in range(cfg.max_steps):
            # Kinematics and velocities of the current state first (mj_step1), then the
            # mattress forces from them, then integration (mj_step2): forces from a stale
            # state would lag a step and pump energy into stiff contacts.
            mj.mj_step1(m, d)
            if not (np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()):
                out["reason"] = REASON_NONFINITE
                break
            v = self.capsule_velocities()
            speed = float(np.sqrt((v**2).sum(1)).max())
            accel = float(np.sqrt(((v - prev_v) ** 2).sum(1)).max() / cfg.timestep_s)
            prev_v = v
            if (touched_at >= 0 and step - touched_at >= cfg.min_steps_after_touch
                    and speed < cfg.speed_tol_m_s and accel < cfg.accel_tol_m_s2):
                break
            wmax, pelvis, e_mat = self.push()
            if touched_at < 0 and pelvis:
                touched_at = step
            out.update(max_speed=speed, max_accel=accel, sink=wmax)
            mj.mj_step2(m, d)
            out["steps"] = step + 1
            if touched_at < 0 and (step + 1) % every == 0:
                d.qvel[:] = 0.0
            energy = float(d.energy[0] + d.energy[1]) + e_mat
            if touched_at >= 0:
                # After the last velocity reset the system is passive: energy can only fall.
                e_ref = energy if e_ref is None else min(e_ref, energy) if step - touched_at < 2 else e_ref
                if energy > e_ref + tol_energy:
                    out["reason"] = REASON_ENERGY
                    break
            if wmax > float(self.mattress.thickness_m):
                out["reason"] = REASON_SANK
                break
            if d.subtree_com[0][2] < -float(self.mattress.thickness_m):
                out["reason"] = REASON_FELL
                break
        else:
            out["reason"] = REASON_TIMEOUT
        out["touch_step"] = touched_at
        out["wall_ms"] = (time.perf_counter() - t0) * 1e3
        return out

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


def _quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    q = q / q.norm()
    return axis_angle_to_matrix(quaternion_to_axis_angle(q))


def settle(model: BodyModel, params: BodyParams, mattress: MattressParams | None = None,
           mat: MatSpec | None = None, config: SettleConfig | None = None,
           body: CapsuleBody | None = None) -> SettleResult:
    """Settle B initial poses (BodyParams, mat frame) onto the mattress, one MuJoCo run each.

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
        body = build_capsule_body(model.to(torch.float64) if model.dtype != torch.float64 else model, params.shape)
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
    for i in range(B):
        ep = _Episode(body, i, params, mattress, mat, config)
        out = ep.run()
        reasons.append(out["reason"])
        for k in stats:
            stats[k][i] = out[k]
        if out["reason"] != REASON_NONFINITE:
            root_rot[i], root_t[i], pose[i] = ep.resting_params()
    return SettleResult(
        params=params.replace(root_rotation=root_rot, root_translation=root_t, pose=pose),
        ok=np.array([not r for r in reasons]), reason=reasons, steps=stats["steps"].astype(int),
        touch_step=stats["touch_step"].astype(int), max_speed=stats["max_speed"],
        max_accel=stats["max_accel"], sink_m=stats["sink"], wall_ms=stats["wall_ms"],
    )


__all__ = ["SETTLE_REASONS", "SettleConfig", "SettleResult", "build_mjcf", "settle"]
