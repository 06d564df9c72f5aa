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

Speed (docs/benchmarks.md): `settle` steps `batch` bodies together, each in its own MjData,
and a slot takes the next body as soon as its body is done, so the per-step Python cost is
always shared. The state every step needs is gathered into (P, ...) arrays from views made
once per body; the foundation forces of all running bodies are one vectorised call that
visits, per capsule and grid row, only the nodes within the horizontal reach of the capsule's
part below the top, computes one quadratic root (and one end sphere) per node, and picks the
lowest capsule per node with a scatter-min. Every body's numbers are its own, bit for bit:
results do not depend on `batch`, on the slot or on the other bodies (test). By
construction: MuJoCo steps each body in its own MjData; the batched force code uses only
elementwise operations (correctly rounded, so the same bits in any array), scatter-min/max,
and `np.bincount` sums, which add each capsule's nodes in the same order whatever comes
before or after them; every other sum and product is spelled out in a fixed order
(sim/fixed_order.py) - no `sum`, `einsum` or `@` over a batched array, whose rounding numpy
and BLAS may vary with the batch's size, alignment or the CPU. The capsule bodies are built
one body at a time for the same reason.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import torch

from pressurepose.bed import BedShape
from pressurepose.body.capsules import (
    CAPSULE_JOINTS,
    CAPSULE_NAMES,
    CAPSULE_PARENTS,
    HINGE_JOINTS,
    CapsuleBody,
    build_capsule_body,
    collision_pairs,
    segment_distance,
)
from pressurepose.body.model import BodyModel
from pressurepose.body.params import R_SUPINE, BodyParams, root_matrix
from pressurepose.body.rotations import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    matrix_to_quaternion,
    quaternion_to_axis_angle,
)
from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.sim.fixed_order import atan2_each, matvec3, sq_norm3, sum_last
from pressurepose.sim.mattress import GRAVITY_M_S2, MattressParams

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


# --- MJCF -----------------------------------------------------------------------------------
def _fmt(v) -> str:
    return " ".join(f"{x:.9g}" for x in np.ravel(v).tolist())


def _walls(
    mat: MatSpec, bed: BedShape | None = None, top_m: float = -0.03, depth_m: float = 1.0, thick_m: float = 0.2
) -> str:
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
        boxes = [
            ((a + b) / 2, y0 - thick_m / 2, (b - a) / 2, thick_m / 2),
            ((a + b) / 2, y1 + thick_m / 2, (b - a) / 2, thick_m / 2),
        ]
        if a == x0:
            boxes.append((x0 - thick_m / 2, (y0 + y1) / 2, thick_m / 2, (y1 - y0) / 2 + thick_m))
        if b == x1:
            boxes.append((x1 + thick_m / 2, (y0 + y1) / 2, thick_m / 2, (y1 - y0) / 2 + thick_m))
        quat = _quat(torch.from_numpy(R))
        for j, (cx, cy, hx, hy) in enumerate(boxes):
            pos = hinge + R @ (np.array([cx, cy, zc]) - hinge)
            lines.append(
                f'    <geom name="side{k}_{j}" type="box" pos="{_fmt(pos)}" quat="{_fmt(quat)}" '
                f'size="{hx:.6g} {hy:.6g} {hz:.6g}" contype="1" conaffinity="0"/>'
            )
    return "\n".join(lines)


def build_mjcf(
    body: CapsuleBody,
    i: int,
    config: SettleConfig,
    pairs: list[tuple[int, int]] = (),
    mat: MatSpec | None = None,
    bed: BedShape | None = None,
) -> str:
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

    # All capsules at once: origins, axis ends in the body frame, full inertias.
    jc = np.array(CAPSULE_JOINTS)
    pc = np.array(CAPSULE_PARENTS)
    origin = rest[jc]
    rel_pos = origin - np.where((pc >= 0)[:, None], rest[jc[np.maximum(pc, 0)]], 0.0)
    a_all, b_all = start - origin, end - origin
    axis = b_all - a_all
    length = np.sqrt((axis**2).sum(1))
    u = np.where((length > 1e-9)[:, None], axis / np.maximum(length, 1e-12)[:, None], np.array([1.0, 0.0, 0.0]))
    # Principal axes: capsule axis + two perpendiculars -> full inertia in the body frame.
    tmp = np.where((np.abs(u[:, 2]) < 0.9)[:, None], np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    v = _cross(u, tmp)
    v /= np.sqrt((v**2).sum(1))[:, None]
    w = _cross(u, v)
    Rm = np.stack([u, v, w], 2)
    I_all = np.einsum("cik,ck,cjk->cij", Rm, inertia, Rm)
    full_all = I_all[:, [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]

    def body_xml(c: int, indent: str) -> str:
        j = CAPSULE_JOINTS[c]
        p = CAPSULE_PARENTS[c]
        pos, a, b, full = rel_pos[c], a_all[c], b_all[c], full_all[c]
        lines = [f'{indent}<body name="{CAPSULE_NAMES[c]}" pos="{_fmt(pos)}">']
        if p < 0:
            lines.append(f'{indent}  <freejoint name="root"/>')
        elif j in HINGE_JOINTS:
            lines.append(
                f'{indent}  <joint name="j{j}" type="hinge" axis="{_fmt(HINGE_JOINTS[j])}" '
                f'stiffness="{stiff[j - 1]:.9g}" damping="{damp[j - 1]:.9g}" springref="0"/>'
            )
        else:
            lines.append(
                f'{indent}  <joint name="j{j}" type="ball" stiffness="{stiff[j - 1]:.9g}" damping="{damp[j - 1]:.9g}"/>'
            )
        lines.append(f'{indent}  <inertial pos="{_fmt((a + b) / 2)}" mass="{mass[c]:.9g}" fullinertia="{_fmt(full)}"/>')
        if length[c] > 1e-9:
            lines.append(
                f'{indent}  <geom name="{CAPSULE_NAMES[c]}" type="capsule" size="{radius[c]:.9g}" fromto="{_fmt(np.concatenate([a, b]))}"/>'
            )
        else:
            lines.append(
                f'{indent}  <geom name="{CAPSULE_NAMES[c]}" type="sphere" size="{radius[c]:.9g}" pos="{_fmt(a)}"/>'
            )
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
        """The grid nodes over which C capsules (axis ends a, b (C, 3), radii r (C,)) reach
        below z = 0, flattened: (capsule index, grid node index, node x, node y, the capsule's
        lowest surface height over the node (< 0)); a node under two capsules appears twice.

        Each capsule visits the nodes of its own window: the box around its axis widened by
        the horizontal reach of its part below z = 0 (sqrt(r^2 - h^2) at the axis's lowest
        height h), clipped to the grid and to s_range. Over a node, the lowest point is the
        lower root of the infinite cylinder when that root falls between the ends; otherwise
        it lies on the end sphere on that side (the spheres lie inside the cylinder, so the
        line meets them after its lower root), or on the lower one for an upright capsule."""
        C = a.shape[0]
        h = np.maximum(np.minimum(a[:, 2], b[:, 2]), 0.0)
        reach = np.sqrt(np.maximum(r * r - h * h, 0.0))
        lo_x = np.minimum(a[:, 0], b[:, 0]) - reach
        hi_x = np.maximum(a[:, 0], b[:, 0]) + reach
        # Node i's centre is x0 + (i + 1/2) hx: the rows with centres in [lo_x, hi_x].
        i0 = np.maximum(np.ceil((lo_x - self.x0) / self.hx - 0.5), 0).astype(np.int64)
        i1 = np.minimum(np.floor((hi_x - self.x0) / self.hx - 0.5), self.nr - 1).astype(np.int64)
        nr = np.maximum(i1 - i0 + 1, 0)
        # Per (capsule, row): the axis points within `reach` of the row in x span an interval
        # of t; the footprint on the row lies within `reach` of their y range (exact bound,
        # and much narrower than the box for a capsule lying diagonally).
        rc = np.repeat(np.arange(C), nr)
        row = np.repeat(i0, nr) + np.arange(len(rc)) - np.repeat(np.cumsum(nr) - nr, nr)
        xr = self.x0 + (row + 0.5) * self.hx
        ax_, ay_ = a[rc, 0], a[rc, 1]
        ex, ey, rh = b[rc, 0] - ax_, b[rc, 1] - ay_, reach[rc]
        along = np.abs(ex) > 1e-12
        safe = np.where(along, ex, 1.0)
        t1, t2 = (xr - rh - ax_) / safe, (xr + rh - ax_) / safe
        tlo = np.where(along, np.clip(np.minimum(t1, t2), 0.0, 1.0), 0.0)
        thi = np.where(along, np.clip(np.maximum(t1, t2), 0.0, 1.0), 1.0)
        ylo = ay_ + np.minimum(tlo * ey, thi * ey) - rh
        yhi = ay_ + np.maximum(tlo * ey, thi * ey) + rh
        j0 = np.maximum(np.ceil((ylo - self.y0) / self.hy - 0.5), 0).astype(np.int64)
        j1 = np.minimum(np.floor((yhi - self.y0) / self.hy - 0.5), self.nc - 1).astype(np.int64)
        ncol = np.maximum(j1 - j0 + 1, 0)
        size = np.bincount(rc, ncol, minlength=C).astype(np.int64)  # candidates per capsule
        total = int(ncol.sum())
        if total == 0:
            e = np.zeros(0)
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), e, e, e
        cap = np.repeat(rc, ncol)
        ii = np.repeat(row, ncol)
        jj = np.repeat(j0, ncol) + np.arange(total) - np.repeat(np.cumsum(ncol) - ncol, ncol)
        x = self.x0 + (ii + 0.5) * self.hx
        y = self.y0 + (jj + 0.5) * self.hy
        # Per capsule: axis direction u, length L, A = 1 - uz^2 (the quadratic's leading term).
        axis = b - a
        L = np.sqrt(sq_norm3(axis))
        u = axis / np.maximum(L, 1e-12)[:, None]
        A = 1.0 - u[:, 2] ** 2
        upright = A <= 1e-9
        inv_A = 1.0 / np.where(upright, 1.0, A)
        ax, ay, az = a[:, 0], a[:, 1], a[:, 2]
        r2 = r * r

        def per(v):
            return np.repeat(v, size)

        dx, dy = x - per(ax), y - per(ay)
        uz = per(u[:, 2])
        # Lower root z of |(p - a) - ((p - a).u) u|^2 = r^2 on the vertical line through the node.
        du = dx * per(u[:, 0]) + dy * per(u[:, 1]) - per(az * u[:, 2])
        beta = -per(az) - du * uz
        cq = dx * dx + dy * dy + per(az * az - r2) - du * du
        disc = beta * beta - per(A) * cq
        zc = (-beta - np.sqrt(np.maximum(disc, 0.0))) * per(inv_A)
        t = du + zc * uz
        Lc = per(L)
        up = per(upright)
        on_cyl = (disc >= 0.0) & ~up & (t >= 0.0) & (t <= Lc)
        # End spheres: b where the root lies beyond b, or b is the lower end of an upright one.
        use_b = np.where(up, per(axis[:, 2] < 0.0), t > Lc)
        ex = dx - use_b * per(axis[:, 0])
        ey = dy - use_b * per(axis[:, 1])
        d2 = ex * ex + ey * ey
        rc2 = per(r2)
        sphere = (disc >= 0.0) | up
        zs = per(az) + use_b * per(axis[:, 2]) - np.sqrt(np.maximum(rc2 - d2, 0.0))
        z = np.where(on_cyl, zc, np.where(sphere & (d2 <= rc2), zs, np.inf))
        keep = z < 0.0
        if math.isfinite(s_range[0]) or math.isfinite(s_range[1]):
            keep &= (x >= s_range[0]) & (x < s_range[1])
        return cap[keep], (ii * self.nc + jj)[keep], x[keep], y[keep], z[keep]

    def forces(self, a, b, r, body_vel, com, xipos, mass, inertia, offset, dt: float, stick=None):
        """Mattress forces on C capsules (of one or several bodies, stepped together), summed
        over the bed's sections (one when flat): each section is handled in its own frame,
        where its top is z = 0 (see `_forces_local`). stick: (sections, C, 2) static-friction
        spring forces (section frames), updated in place (None: the damper alone)."""
        if self.bed.flat:
            st = None if stick is None else stick[0]
            res = self._forces_local(a, b, r, body_vel, com, xipos, mass, inertia, offset, dt, stick=st)
            if res is None and st is not None:
                st[:] = 0.0  # nothing touches: every anchor is released
            return res
        total, caps, ws, es = None, [], [], []
        for k, (R, s0, s1) in enumerate(self._sections):
            # Positions into the section's frame about the hinge; velocities just rotate.
            a_l, b_l, com_l, xi_l = (matvec3(R.T, p - self.hinge) + self.hinge for p in (a, b, com, xipos))
            vel = np.concatenate([matvec3(R.T, body_vel[:, :3]), matvec3(R.T, body_vel[:, 3:])], 1)
            st = None if stick is None else stick[k]
            res = self._forces_local(a_l, b_l, r, vel, com_l, xi_l, mass, inertia, offset, dt, (s0, s1), st)
            if res is None:
                if st is not None:
                    st[:] = 0.0  # nothing touches this section: every anchor is released
                continue
            out, cap, w, energy = res
            out = np.concatenate([matvec3(R, out[:, :3]), matvec3(R, out[:, 3:])], 1)
            total = out if total is None else total + out
            caps.append(cap), ws.append(w), es.append(energy)
        if total is None:
            return None
        return total, np.concatenate(caps), np.concatenate(ws), np.concatenate(es)

    def _forces_local(
        self, a, b, r, body_vel, com, xipos, mass, inertia, offset, dt: float, s_range=(-math.inf, math.inf), stick=None
    ):
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
        local, flat, px, py, zz = self.underside(aa, bb, rr, s_range)
        if local.size == 0:
            return None
        cap = active[local]
        idx = flat + offset[cap]
        # The lowest capsule over a node is the one the foam pushes on (a tie: the first).
        lowest = np.full(int(offset.max()) + self.nr * self.nc, np.inf)
        np.minimum.at(lowest, idx, zz)
        keep = np.flatnonzero(zz == lowest[idx])
        if np.bincount(idx[keep]).max() > 1:
            keep = np.sort(keep[np.unique(idx[keep], return_index=True)[1]])
        cap, zz, px, py = cap[keep], zz[keep], px[keep], py[keep]
        w = -zz
        # Per node: the lever from com, the body's velocity there, the lever from xipos.
        bv = body_vel[cap]
        rx, ry, rz = px - com[cap, 0], py - com[cap, 1], zz - com[cap, 2]
        vx = bv[:, 3] + bv[:, 1] * rz - bv[:, 2] * ry
        vy = bv[:, 4] + bv[:, 2] * rx - bv[:, 0] * rz
        vz = bv[:, 5] + bv[:, 0] * ry - bv[:, 1] * rx
        shift = (com - xipos)[cap]
        arm = np.stack([rx + shift[:, 0], ry + shift[:, 1], rz + shift[:, 2]], 1)
        # The damper is taken implicitly per capsule (backward Euler: c -> c / (1 + c dt / m),
        # with the smallest inertia for the lever arms), so light capsules stay stable.
        w2 = w * w
        c = self.nu * (self.k1 + 3.0 * self.k3 * w2) * self.area
        arm2 = sq_norm3(arm)
        c_lin = np.bincount(cap, c, minlength=C)
        c_rot = np.bincount(cap, c * arm2, minlength=C)
        scale = 1.0 / (1.0 + dt * np.maximum(c_lin / mass, c_rot / inertia))
        fn = np.maximum((self.k1 + self.k3 * w2) * w * self.area - scale[cap] * c * vz, 0.0)
        out = np.zeros((C, 6))
        out[:, 2] = np.bincount(cap, fn, minlength=C)
        out[:, 3] = np.bincount(cap, arm[:, 1] * fn, minlength=C)
        out[:, 4] = np.bincount(cap, -arm[:, 0] * fn, minlength=C)
        self._friction(out, cap, arm, vx, vy, fn, mass, inertia, dt, stick)
        energy = (self.k1 / 2 + self.k3 / 4 * w2) * w2 * self.area
        return out, cap, w, energy

    def _friction(self, out, cap, arm, vx, vy, fn, mass, inertia, dt, stick=None) -> None:
        """Coulomb friction per capsule at its centre of pressure: a damper, regularised below
        V_STICK and taken implicitly on the capsule's effective mass at that point (at most
        half the damper that would stop it within one step), plus the static-friction spring
        `stick` (C, 2) (see STICK_STIFFNESS; updated in place), the sum capped at mu N."""
        C = out.shape[0]
        Fn = out[:, 2]
        touching = Fn > 1e-9
        if stick is not None:
            stick[~touching] = 0.0  # contact lost: the anchor goes with it
        if not touching.any():
            return
        wgt = fn / np.maximum(Fn[cap], 1e-12)
        arm_c = np.stack([np.bincount(cap, wgt * arm[:, k], minlength=C) for k in range(3)], 1)
        vel_c = np.stack([np.bincount(cap, wgt * vx, minlength=C), np.bincount(cap, wgt * vy, minlength=C)], 1)
        m_eff = 1.0 / (1.0 / mass + sq_norm3(arm_c) / inertia)
        c = self.mu * Fn / V_STICK
        c_eff = c / (1.0 + 2.0 * c * dt / m_eff)
        speed = np.sqrt(vel_c[:, 0] * vel_c[:, 0] + vel_c[:, 1] * vel_c[:, 1])
        cap_n = self.mu * Fn
        f = np.zeros((C, 3))
        if stick is None:
            mag = np.minimum(cap_n, c_eff * speed)
            f[:, :2] = -vel_c * (mag / np.maximum(speed, 1e-12))[:, None]
        else:
            spring = stick - (STICK_STIFFNESS * m_eff / dt)[:, None] * vel_c  # -k v dt, k = kappa m / dt^2
            norm = np.sqrt(spring[:, 0] * spring[:, 0] + spring[:, 1] * spring[:, 1])
            spring *= np.minimum(1.0, cap_n / np.maximum(norm, 1e-12))[:, None]  # slip drags the anchor
            stick[:] = np.where(touching[:, None], spring, 0.0)
            total = stick - c_eff[:, None] * vel_c
            norm = np.sqrt(total[:, 0] * total[:, 0] + total[:, 1] * total[:, 1])
            f[:, :2] = total * np.minimum(1.0, cap_n / np.maximum(norm, 1e-12))[:, None]
        out[:, :3] += f
        out[:, 3:] += _cross(arm_c, f)


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (N, 3) arrays (np.cross is slow on small arrays)."""
    return np.stack(
        [
            u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1],
            u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2],
            u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0],
        ],
        1,
    )


def _axis_angle_quats(v: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) -> unit quaternions (N, 4) as (w, x, y, z), w >= 0 (for
    angles up to pi). Per body in numpy, so a body's numbers never depend on its batch."""
    theta = np.sqrt((v * v).sum(1))
    half = theta / 2
    # sin(theta / 2) / theta, with its series near 0 (where the axis is undefined).
    small = theta < 1e-6
    k = np.where(small, 0.5 - theta**2 / 48, np.sin(half) / np.where(small, 1.0, theta))
    q = np.concatenate([np.cos(half)[:, None], v * k[:, None]], 1)
    return np.where(q[:, :1] < 0, -q, q)


def _quat(R: torch.Tensor) -> np.ndarray:
    return matrix_to_quaternion(R).double().numpy()


def initial_pairs(body: CapsuleBody, params: BodyParams) -> list[list[tuple[int, int]]]:
    """Per body, the sampler's self-collision pairs (distal capsules vs non-adjacent ones)
    that are apart in the initial pose: MuJoCo keeps them apart while the body settles.
    Body by body (torch's batched kernels could move a gap's last bits with the batch)."""
    caps = body.capsules
    pairs = collision_pairs()
    p0, p1 = pairs[:, 0], pairs[:, 1]
    pl = [(int(x), int(y)) for x, y in pairs]
    out = []
    for i in range(caps.batch_size):
        one = dataclasses.replace(caps, **{f.name: getattr(caps, f.name)[i : i + 1] for f in dataclasses.fields(caps)})
        a, b = one.posed(params.pose[i : i + 1].to(caps.rest.dtype))
        d = segment_distance(a[:, p0], b[:, p0], a[:, p1], b[:, p1])
        gap = (d - one.radius[:, p0] - one.radius[:, p1])[0].numpy()
        out.append([pl[k] for k in np.flatnonzero(gap > 0.0)])
    return out


class _Episode:
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
        q_pose = _axis_angle_quats(pose.numpy())
        q_home = _axis_angle_quats(body.home_pose[i].double().numpy())
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
        R = _quat_to_matrix(q[3:7])
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


class _Pool:
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
        self.make = make  # episode index -> _Episode (built when started)
        self.eps: list[_Episode | None] = [None] * n
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


def _run_batch(
    make,
    n: int,
    mat: MatSpec,
    config: SettleConfig,
    mattress: MattressParams,
    bed: BedShape | None = None,
    pool: int = 16,
) -> list[dict]:
    """Settle episodes 0..n-1 (`make(k)` builds episode k) `pool` at a time (see `_Pool`);
    an episode is built when a slot takes it and released when it is done, so memory is
    bounded by the pool. Returns per episode its statistics and its resting parameters
    ("rest": (root_rotation, root_translation, pose), None when non-finite)."""
    dt = config.timestep_s
    every = max(1, round(config.zero_velocity_every_s / dt))
    thickness = float(mattress.thickness_m)
    out = [
        dict(reason="", steps=0, touch_step=-1, max_speed=np.inf, max_accel=np.inf, sink=0.0, wall_ms=0.0, rest=None)
        for _ in range(n)
    ]
    t0 = time.perf_counter()
    if n:
        p = _Pool(make, n, mat, config, mattress, bed, min(pool, n))
        _drive(p, list(range(n)), out, every, thickness, dt)
    wall = (time.perf_counter() - t0) * 1e3 / max(n, 1)
    for o in out:
        o["wall_ms"] = wall
    return out


def _drive(p: _Pool, queue: list[int], out: list[dict], every: int, thickness: float, dt: float) -> None:
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
            o["reason"] = reason
            o["steps"] = int(p.step[s])
            o["touch_step"] = int(p.touched[s])
            o["max_speed"], o["max_accel"], o["sink"] = float(p.speed[s]), float(p.accel[s]), float(p.sink[s])
            o["rest"] = ep.resting_params(ep.data.qpos) if keep_state else None
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
                out[k]["reason"] = REASON_OFF_BED
                out[k]["rest"] = ep.resting_params(ep.data.qpos)
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
            ft, e_hold = _hold_roll(ft, R[:, PELVIS], p.roll0[ids], cv, p.mass[ids], p.weight[ids], config)
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


def _hold_roll(ft, R, R0, cv, mass, weight, config: SettleConfig):
    """The trunk roll hold (`SettleConfig.hold_roll_m`): ft (n, C, 6) with the torque about
    the bed's long axis (x) added on the trunk capsules, shared by mass (in place), and the
    hold's spring energy (n,), which the energy check counts as the mattress's. R: (n, 3, 3) the pelvis's
    orientation now, R0 at the drop; cv: (n, C, 6) capsule velocities (angular first)."""

    def E(i, j):  # (R R0^T)[i, j]: the rotation since the drop (world frame)
        return R[:, i, 0] * R0[:, j, 0] + R[:, i, 1] * R0[:, j, 1] + R[:, i, 2] * R0[:, j, 2]

    roll = atan2_each(E(2, 1) - E(1, 2), E(1, 1) + E(2, 2))  # exact for a rotation about x
    m = mass[:, TRUNK]
    share = m / sum_last(m)[:, None]
    omega_x = sum_last(share * cv[:, TRUNK, 0])
    k = config.hold_roll_m * weight
    tau = -k * (roll + config.hold_time_s * omega_x)
    ft[:, TRUNK, 3] += tau[:, None] * share
    return ft, 0.5 * k * roll**2


def as_float64(model: BodyModel) -> BodyModel:
    """The model itself when float64, else a float64 copy (never converts the caller's)."""
    if model.dtype == torch.float64:
        return model
    import copy

    return copy.deepcopy(model).to(torch.float64)


def _quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    q = q / q.norm()
    return axis_angle_to_matrix(quaternion_to_axis_angle(q))


def settle(
    model: BodyModel,
    params: BodyParams,
    mattress: MattressParams | None = None,
    mat: MatSpec | None = None,
    config: SettleConfig | None = None,
    body: CapsuleBody | None = None,
    batch: int = 16,
    bed: BedShape | None = None,
) -> SettleResult:
    """Settle B initial poses (BodyParams, mat frame) onto the mattress: one MuJoCo model per
    body, `batch` of them stepped together. A body's result depends on its own initial pose,
    shape (or capsule body) and bed only - not on `batch`, its slot or the other bodies - bit
    for bit, by construction (module docstring).

    `body` (the capsulised bodies of params.shape) is built body by body when not given
    (`build_capsule_body(..., one_by_one=True)`); a body built in a batch may differ in its
    last bits with the batch. Returns the resting poses and per-sample statistics; unsettled
    samples are flagged, never NaN.
    """
    mattress = mattress or MattressParams()
    mat = mat or MatSpec()
    config = config or SettleConfig()
    params = params.to(torch.float64)
    params.validate(model.shape_dim, torch.float64, params.shape.device)
    B = params.batch_size
    if body is None:
        body = build_capsule_body(as_float64(model), params.shape, volume_points=SIM_VOLUME_POINTS, one_by_one=True)
    if body.capsules.batch_size != B:
        raise UserError(f"capsule body batch ({body.capsules.batch_size}) != params batch ({B})")
    masses = body.mass_kg.sum(-1)
    if not torch.isfinite(masses).all() or bool((masses <= 0).any()):
        raise UserError("every body needs a finite mass > 0 (check the shape parameters)")
    root_rot = params.root_rotation.clone()
    root_t = params.root_translation.clone()
    pose = params.pose.clone()
    stats = {k: np.zeros(B) for k in ("steps", "touch_step", "max_speed", "max_accel", "sink", "wall_ms")}
    reasons = []
    pairs = initial_pairs(body, params) if B else []
    outs = _run_batch(
        lambda i: _Episode(body, i, params, mattress, mat, config, bed, pairs[i]),
        B,
        mat,
        config,
        mattress,
        bed,
        pool=batch,
    )
    for i, o in enumerate(outs):
        reasons.append(o["reason"])
        for k in stats:
            stats[k][i] = o[k]
        if o["rest"] is not None:
            root_rot[i], root_t[i], pose[i] = o["rest"]
    return SettleResult(
        params=params.replace(root_rotation=root_rot, root_translation=root_t, pose=pose),
        ok=np.array([not r for r in reasons]),
        reason=reasons,
        steps=stats["steps"].astype(int),
        touch_step=stats["touch_step"].astype(int),
        max_speed=stats["max_speed"],
        max_accel=stats["max_accel"],
        sink_m=stats["sink"],
        wall_ms=stats["wall_ms"],
    )


__all__ = ["SETTLE_REASONS", "SettleConfig", "SettleResult", "build_mjcf", "settle"]
