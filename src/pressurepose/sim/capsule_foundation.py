"""Sim #1's mattress acting on capsules: sim #2's foundation law, damping and friction applied
per grid node to the lowest capsule surface point, vectorised over every running body
(`sim.settle`, docs/physics.md)."""

from __future__ import annotations

import math

import numpy as np

from pressurepose.bed import BedShape
from pressurepose.mat import MatSpec
from pressurepose.sim.fixed_order import atan2_each, matvec3, sq_norm3, sum_last
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.mjcf import cross3
from pressurepose.sim.settle_config import (
    STICK_STIFFNESS,
    TRUNK,
    V_STICK,
    SettleConfig,
)


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
        self.dense = params.densification if float(params.densify_pa) > 0 else None  # (p, dp/dw, energy) of w
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
        p = (self.k1 + self.k3 * w2) * w
        k = self.k1 + 3.0 * self.k3 * w2
        energy = (self.k1 / 2 + self.k3 / 4 * w2) * w2 * self.area
        if self.dense is not None:
            p_d, k_d, e_d = self.dense(w)
            p, k, energy = p + p_d, k + k_d, energy + e_d * self.area
        c = self.nu * k * self.area
        arm2 = sq_norm3(arm)
        c_lin = np.bincount(cap, c, minlength=C)
        c_rot = np.bincount(cap, c * arm2, minlength=C)
        scale = 1.0 / (1.0 + dt * np.maximum(c_lin / mass, c_rot / inertia))
        fn = np.maximum(p * self.area - scale[cap] * c * vz, 0.0)
        out = np.zeros((C, 6))
        out[:, 2] = np.bincount(cap, fn, minlength=C)
        out[:, 3] = np.bincount(cap, arm[:, 1] * fn, minlength=C)
        out[:, 4] = np.bincount(cap, -arm[:, 0] * fn, minlength=C)
        self._friction(out, cap, arm, vx, vy, fn, mass, inertia, dt, stick)
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
        out[:, 3:] += cross3(arm_c, f)


def hold_roll_torque(ft, R, R0, cv, mass, weight, config: SettleConfig):
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
