"""The articulated rest's linearised problem and its Newton solver (`sim.articulated`).

At one posing of the mesh, the cells' heights are affine in the unknowns q (per part: a
(1, x, y) combination), so the energy - gravity on the parts, the joint springs and hinge
limits, the foam and tissue in series per cell, and any `LinearSprings` / `CoulombSprings`
(self-contact, friction) - is convex in q; `minimise` runs Newton on it with a backtracking
line search, Levenberg-Marquardt damping and a trust region (docs/physics.md).
"""

from __future__ import annotations

import torch

from pressurepose.body.joints import NUM_JOINTS
from pressurepose.sim.air_law import AirLaw
from pressurepose.sim.articulation import Dofs
from pressurepose.sim.mattress import GRAVITY_M_S2, MattressParams
from pressurepose.sim.soft_contact import SeriesLaw

# Cells whose lowest point lies higher than this above the mattress top cannot touch within
# one re-posing's trust region (5 cm of shift, 0.25 rad on a limb); they join when they come
# closer. Gravity acts on the parts' masses whatever cells are kept.
_REACH_M = 0.12
# The 3 x 3 stiffness moment sum c (1, x, y)(1, x, y)^T rebuilt from its six distinct entries
# (1, x, y, xx, xy, yy).
_SYMMETRIC = torch.tensor([0, 1, 2, 1, 3, 4, 2, 4, 5])
# A step that moves no unknown more than this (rad or m) has stalled (`minimise`).
_STALLED = 1e-12


class Linearised:
    """Everything the Newton steps need at one posing of the mesh: the cells under the body
    (packed, K per body), their height h, part and (1, x, y), the DoFs' geometry, gravity's
    gradient, the springs and the limits."""

    def __init__(
        self,
        h,
        part,
        xy,
        dof_a,
        mass,
        com,
        e,
        k,
        dofs: Dofs,
        area,
        tissue=None,
        limits=None,
        springs=(),
        section_a=None,
        section_cos=None,
    ):
        # springs: sim.self_contact.LinearSprings (self-contact, friction anchors) added to the energy.
        # section_a (B, N, S, 3): on a bed of S sections (a raised head section, `sim.raised`),
        # each DoF's coefficients of the normal height over the section's (1, s, y); the cells
        # of section j carry part + 24 j, and section_cos (S,) is the cosine of each section's
        # slope (the share of a cell's normal force that holds the weight). None: flat.
        self.springs = tuple(springs)
        self._law_key, self._law_cached = None, None  # `_law`: the series law of the last mattress
        # Hinge limits as a stiff one-sided spring on the hinge angle (angle + q within
        # [lo, hi]); limits = (angle (B, N), lo (N,), hi (N,), stiffness (B, N)) or None.
        self.limits = limits
        valid = h < _REACH_M
        K = max(int(valid.sum(1).max()), 1)
        self.index = torch.argsort((~valid).to(torch.int8), dim=1, stable=True)[:, :K]
        self.h = h.gather(1, self.index)
        self.mask = valid.gather(1, self.index).to(h.dtype)
        self.part = part.gather(1, self.index)
        self.area, self.dofs, self.dof_a = area, dofs, dof_a
        # Tissue modulus per cell (B, K) from its lowest point (`tissue` (B, all cells)), or a
        # number, or None (no tissue).
        self.tissue = tissue.gather(1, self.index) if isinstance(tissue, torch.Tensor) else tissue
        self.dof_parts = dofs.desc[dofs.joint]  # (N, 24): parts each DoF moves
        # Constant within the linearisation: each cell's x, y and index into the per-part
        # coefficients (B, n_parts * 3), and its moments (1, x, y) and the six distinct entries of
        # (1, x, y)(1, x, y)^T (masked), summed per part with the force or the stiffness,
        # coordinate-major (B, 9, K): the scatter along the cells' own axis is ~3x faster.
        cell_xy = xy[self.index]
        self._x, self._y = cell_xy[..., 0].contiguous(), cell_xy[..., 1].contiguous()
        self._coef = self.part * 3
        m, mx, my = self.mask, self._x * self.mask, self._y * self.mask
        self._moments = torch.stack([m, mx, my, m, mx, my, mx * self._x, my * self._x, my * self._y], 1)
        self._scatter_index = self.part[:, None].expand(-1, 9, -1)
        self._symmetric = _SYMMETRIC.to(h.device)
        # Gravity: d(sum m g z)/d(theta_n) over the parts in the subtree, constant.
        gb = torch.cat([torch.ones_like(com[..., :1]), com[..., :2]], -1) * (mass * GRAVITY_M_S2)[..., None]
        sub_g = torch.einsum("js,bst->bjt", dofs.desc, gb)  # (B, 24, 3)
        self.g_grav = (dof_a * sub_g[:, dofs.joint]).sum(-1)
        self.e, self.k = e, k
        # (B, N, n_parts * 3): a_n in the slots of the parts DoF n moves (zero elsewhere); the parts'
        # affine height coefficients are q G, the gradient's force term G (per-part force
        # moments), the Hessian G M G^T with M the parts' 3 x 3 stiffness moments.
        if section_a is None:
            self.n_parts, self.vertical = NUM_JOINTS, None
            self._G = (dof_a[:, :, None, :] * self.dof_parts[None, :, :, None]).reshape(dof_a.shape[0], dofs.n, -1)
        else:  # (B, N, S, 24, 3): a section's coefficients in the slots of (section, part)
            self.n_parts = NUM_JOINTS * section_a.shape[2]
            G = section_a[:, :, :, None, :] * self.dof_parts[None, :, None, :, None]
            self._G = G.reshape(dof_a.shape[0], dofs.n, -1)
            cos = torch.as_tensor(section_cos, dtype=h.dtype, device=h.device)
            self.vertical = cos[torch.div(self.part, NUM_JOINTS, rounding_mode="floor")]  # (B, K)

    # Attributes with one row per body (`take` selects them): per cell (B, K), (B, 9, K) and
    # per DoF.
    _PER_CELL = ("h", "mask", "part", "index", "_x", "_y", "_coef", "_moments", "vertical")
    _PER_DOF = ("g_grav", "e", "k", "dof_a", "_G")

    def take(self, idx: torch.Tensor) -> Linearised:
        """The same problem for the bodies `idx` only (a (B',) index): each body's rows are
        computed the same way whatever else is in its batch, so `minimise` can drop the bodies
        that are done and step the others alone. The cells are trimmed to the most any of
        these bodies has (the others' padding: masked cells, which add exact zeros)."""
        new = object.__new__(Linearised)
        new.__dict__.update(self.__dict__)
        K = max(int(self.mask[idx].sum(1).max()), 1) if len(idx) else 1
        for name in self._PER_CELL:
            value = getattr(self, name)
            if value is not None:
                setattr(new, name, value[..., :K][idx])
        for name in self._PER_DOF:
            setattr(new, name, getattr(self, name)[idx])
        new._scatter_index = new.part[:, None].expand(-1, 9, -1)
        if isinstance(self.tissue, torch.Tensor):
            new.tissue = self.tissue[:, :K][idx]
        if self.limits is not None:
            new.limits = tuple(x[idx] if x.ndim == 2 else x for x in self.limits)
        new.springs = tuple(s.take(idx) for s in self.springs)
        if self._law_cached is not None:
            new._law_cached = self._law_cached.take(idx, K)
        return new

    def _law(self, mp: MattressParams) -> SeriesLaw | AirLaw:
        """The law of these cells' tissue on this mattress: in series with the foam, or with air
        at one pressure (`sim.air_law`; its constants computed once)."""
        if mp.has_air_support:
            key = ("air", mp.air_pressure_pa, mp.air_stiffness_pa_per_m3, mp.thickness_m)
            if self._law_key != key:
                self._law_key, self._law_cached = key, AirLaw(mp, self.tissue, self.area)
        else:
            key = (mp.k1_pa_per_m, mp.k3_pa_per_m3, mp.densify_pa, mp.thickness_m)
            if self._law_key != key:
                self._law_key, self._law_cached = key, SeriesLaw(mp, self.tissue)
        return self._law_cached

    def bed_compression(self, w, f, mp: MattressParams):
        """The bed's share (B, K) m of the cells' compressions w carrying forces f (N): the
        foam's, or how far the air tubes' top went down."""
        return self._law(mp).bed_share(w, f / self.area)

    def compression(self, q):
        # The height change of a cell is affine in its (x, y) with per-part coefficients
        # A_s = sum over the DoFs that move part s of q_n a_n: no (cells x DoFs) matrix.
        A = (q[:, None] @ self._G)[:, 0]  # (B, n_parts * 3)
        dz = A.gather(1, self._coef + 1).mul_(self._x).add_(A.gather(1, self._coef))
        dz.add_(A.gather(1, self._coef + 2).mul_(self._y))
        return dz.add_(self.h).neg_().clamp_(min=0).mul_(self.mask)  # relu(-(h + dz)), masked

    def energy(self, q, mp: MattressParams):
        w = self.compression(q)
        law = self._law(mp)
        phi = law.energy(w)
        out = (
            (self.g_grav * q).sum(1)
            + 0.5 * (self.k * (self.e + q) ** 2).sum(1)
            + phi.sum(1) * self.area
            + self._limit(q)[0]
        )
        if law.coupled:
            out = out + law.air_energy()
        for s in self.springs:
            out = out + s.energy(q)
        return out

    def _limit(self, q):
        """Energy (B,), gradient (B, N) and curvature (B, N) of the hinge-limit springs."""
        if self.limits is None:
            return q.new_zeros(q.shape[0]), torch.zeros_like(q), torch.zeros_like(q)
        angle, lo, hi, k_lim = self.limits
        a = angle + q
        over = a - torch.clamp(a, lo, hi)  # signed excess beyond the range
        active = (over != 0).to(q.dtype)
        return 0.5 * (k_lim * over**2).sum(1), k_lim * over, k_lim * active

    def newton_step(self, q, mp: MattressParams):
        """Gradient (B, N), Hessian (B, N, N), cell forces (B, K) N, compressions (B, K) m and
        the energy (B,) at q."""
        w = self.compression(q)
        law = self._law(mp)
        p, dp, phi = law(w)
        f = p * self.area
        c = dp.mul_(self.area).masked_fill_(w <= 0, 0.0)
        B = q.shape[0]
        # One pass over the cells: per part the force moments sum f (1, x, y) and the stiffness
        # moments sum c (1, x, y)(1, x, y)^T (its six distinct entries).
        weighted = torch.empty_like(self._moments)
        torch.mul(self._moments[:, :3], f[:, None], out=weighted[:, :3])
        torch.mul(self._moments[:, 3:], c[:, None], out=weighted[:, 3:])
        P = self.n_parts
        sums = q.new_zeros(B, 9, P).scatter_add_(2, self._scatter_index, weighted).transpose(1, 2)
        f_part = sums[..., :3]
        e_lim, g_lim, c_lim = self._limit(q)
        energy = (self.g_grav * q).sum(1) + 0.5 * (self.k * (self.e + q) ** 2).sum(1) + phi.sum(1) * self.area + e_lim
        grad = self.g_grav + self.k * (self.e + q) + g_lim - self._force_term(f_part)
        # Hessian from the parts' stiffness moments M_s = sum c (1, x, y)(1, x, y)^T: H_nl = sum
        # over the parts s both DoFs move of a_n^T M_s a_l, i.e. G M G^T (M block-diagonal).
        m_part = sums[..., 3:].index_select(-1, self._symmetric).view(B, P, 3, 3)  # from the six entries
        n = self.dof_a.shape[1]
        gm = self._G.view(B, n, P, 3).transpose(1, 2) @ m_part  # (B, P, N, 3): a_n^T M_s
        H = gm.transpose(1, 2).reshape(B, n, -1) @ self._G.transpose(1, 2)
        H = H + torch.diag_embed(self.k + c_lim)
        if law.coupled:
            # The air: its energy term, and the rank-one coupling of the displaced cells
            # (beta g g^T, g = sum over them of dw/dq, from their parts' moments of (1, x, y)).
            energy = energy + law.air_energy()
            d = law.displaced.to(q.dtype)
            d_part = (
                q.new_zeros(B, 3, P)
                .scatter_add_(2, self._scatter_index[:, :3], self._moments[:, :3] * d[:, None])
                .transpose(1, 2)
            )
            g = self._force_term(d_part)
            H = H + law.beta[:, None, None] * (g[:, :, None] * g[:, None, :])
        for s in self.springs:
            e_s, g_s, h_s = s.gradient_hessian(q)
            energy, grad, H = energy + e_s, grad + g_s, H + h_s
        return grad, H, f, w, energy

    @property
    def sectioned(self) -> bool:
        """The cells lie on more than one section of the bed (a raised head section)."""
        return self.vertical is not None

    def support(self, f):
        """(B,) what the cells' forces f (B, K) hold of the weight: their sum, or on a sectioned
        bed their vertical resultant."""
        return (f * self.vertical).sum(1) if self.sectioned else f.sum(1)

    def _force_term(self, per_part):
        """(B, N): sum over the parts of G's rows times the parts' moments (B, P, 3) of (1, x, y)."""
        if self.sectioned:
            return torch.matmul(self._G, per_part.reshape(per_part.shape[0], -1, 1))[..., 0]
        return (self.dof_a * torch.matmul(self.dof_parts, per_part)).sum(-1)

    def contact_state(self, q, mp: MattressParams):
        """At q: each cell's part (B, K), contact point (B, K, 3), force (B, K) N and vertical
        stiffness (B, K) N/m (zero off contact), for `sim.friction`."""
        w = self.compression(q)
        p, dp, _ = self._law(mp)(w)
        on = (w > 0).to(w.dtype) * self.mask
        xyz = torch.stack([self._x, self._y, -w], -1)
        return self.part, xyz, p * self.area * on, dp * self.area * on

    def unpack(self, values, cells):
        out = values.new_zeros(values.shape[0], cells)
        return out.scatter(1, self.index, values * self.mask)


def minimise(lin: Linearised, q, mp, weight, cfg, max_steps: int, step_tol: float = 0.0):
    """Newton with backtracking on the (convex) linearised energy from q; weight (B,) N; cfg an
    `ArticulatedConfig` (trust region max_rotation_rad / max_shift_m, tolerance tol); a body
    is also done once a full step moves no unknown more than `step_tol` (re-posings' solves),
    or its step stalls at the trust region. Returns q and the step counts (B,). Each body steps
    on its own: a body that is done leaves the batch (`Linearised.take`), and only the bodies
    whose step needs it backtrack or re-solve, so a body's result and its cost do not depend on
    the others."""
    B, n = q.shape
    iters = torch.zeros(B, dtype=torch.long, device=q.device)
    cap = torch.full((n,), cfg.max_rotation_rad, dtype=q.dtype, device=q.device)
    cap[0] = cfg.max_shift_m
    eye = torch.eye(n, dtype=q.dtype, device=q.device)
    q = q.clone()
    act = torch.arange(B, device=q.device)  # the bodies still stepping; below, their rows only
    grad, H, f, _, e0 = lin.newton_step(q, mp)
    force = lin.support(f)  # (B,): the force holding the weight (the cells are trimmed as bodies leave)
    qa, wa = q.clone(), weight
    for i in range(max_steps):
        scale = H.diagonal(dim1=-2, dim2=-1).abs().amax(-1).clamp(min=1.0)
        # A small Levenberg term (1e-5 x weight x (0.1 m)^2 per unit) keeps DoFs without contact
        # or spring (the root's roll and pitch in the air) from taking arbitrary steps.
        reg = 1e-9 * scale + 1e-7 * wa
        H = H + reg[:, None, None] * eye
        # Levenberg-Marquardt damping on the unknowns whose step would leave the trust region
        # (a limb falling freely): they take a shorter step, the others their Newton step (up
        # to four solves; only the bodies with an unknown over re-solve).
        damp = torch.zeros_like(qa)
        step = -torch.linalg.solve(H, grad[..., None])[..., 0]
        for attempt in range(4):
            room = torch.where(step > 0, cap - qa, cap + qa).clamp(min=0)
            over = step.abs() > room * 1.0001
            if attempt == 3 or not bool(over.any()):
                break
            damp = torch.where(over, 4 * damp + H.diagonal(dim1=-2, dim2=-1), damp)
            redo = over.any(-1).nonzero()[:, 0]
            step[redo] = -torch.linalg.solve(H[redo] + torch.diag_embed(damp[redo]), grad[redo, :, None])[..., 0]
        # Nothing touches yet (no contact stiffness on dz): fall by the cap, no tilt.
        free = H[:, 0, 0] <= 1e-6 * wa
        if bool(free.any()):
            step[:, 0] = torch.where(free, torch.full_like(step[:, 0], -cfg.max_shift_m), step[:, 0])
            step[:, 1:3] = torch.where(free[:, None], torch.zeros_like(step[:, 1:3]), step[:, 1:3])
        # Trust region: the largest t <= 1 that keeps q + t step within the caps, the step's
        # direction kept (clipping components one by one can turn it uphill).
        room = torch.where(step > 0, cap - qa, cap + qa).clamp(min=0)
        t = (room / step.abs().clamp(min=1e-15)).amin(-1).clamp(max=1.0)
        # A body whose step stalls at the trust region (an unknown at its cap that its step pushes
        # further: t = 0) would only repeat it at the same point (the same step, t = 0 again) to
        # the last step: it is done, its point not evaluated again.
        stalled = (t[:, None] * step).abs().amax(-1) < _STALLED
        if bool(stalled.any()):
            q[act] = qa
            keep = (~stalled).nonzero()[:, 0]
            if not len(keep):
                break
            act, lin = act[keep], lin.take(keep)
            qa, wa, grad, H, force, e0 = qa[keep], wa[keep], grad[keep], H[keep], force[keep], e0[keep]
            step, t, free = step[keep], t[keep], free[keep]
        # Backtracking: the full step's evaluation (energy, and the next step's gradient and
        # Hessian) is usually accepted at once; only the bodies whose energy rose halve their
        # step (energies alone) and evaluate again where they end.
        imbalance = (force - wa).abs() / wa
        # The last step needs the energy alone (nothing steps from where it ends).
        final = i == max_steps - 1
        if final:
            energy = lin.energy(qa + t[:, None] * step, mp)
        else:
            grad, H, f, _, energy = lin.newton_step(qa + t[:, None] * step, mp)
            force = lin.support(f)
        better = (energy <= e0) | free
        if not bool(better.all()):
            bad = (~better).nonzero()[:, 0]
            back = lin.take(bad)
            qb, sb, tb, eb, ok = qa[bad], step[bad], t[bad], e0[bad], better[bad]
            for _ in range(9):
                tb = torch.where(ok, tb, tb / 2)
                ok = back.energy(qb + tb[:, None] * sb, mp) <= eb
                if bool(ok.all()):
                    break
            tb = torch.where(ok, tb, torch.zeros_like(tb))  # no descent found: stay (counted as done)
            t[bad] = tb
            better[bad] = ok
            if not final:
                redo = back.newton_step(qb + tb[:, None] * sb, mp)
                grad[bad], H[bad], force[bad], energy[bad] = redo[0], redo[1], back.support(redo[2]), redo[4]
        qa = qa + t[:, None] * step
        e0 = energy
        iters[act] += better.long()
        if final:
            break
        moved = (t[:, None] * step).abs().amax(-1)
        done = ~better | ((imbalance < cfg.tol) & (moved < 1e-6)) | ((t == 1) & (moved < step_tol))
        if bool(done.any()):
            q[act] = qa
            keep = (~done).nonzero()[:, 0]
            if not len(keep):
                break
            act, lin = act[keep], lin.take(keep)
            qa, wa, grad, H, force, e0 = qa[keep], wa[keep], grad[keep], H[keep], force[keep], e0[keep]
    q[act] = qa
    return q, iters


__all__ = ["Linearised", "minimise"]
