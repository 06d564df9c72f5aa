"""Static friction of the articulated rest (`sim.articulated`): a part that touches the sheet
sticks where it touched, until the horizontal force on it exceeds mu times its load.

Without it the quasi-static rest has nothing horizontal to push against: a supine body's bent
knee, held up in sim #1 by the hip's spring and the foot's grip on the sheet, falls outward
because its foot slides freely. Per J24 part in contact: an anchor on the sheet (where its
centre of pressure was when it first touched) and the material point that touched (in the
part's frame); the part's horizontal offset from its anchor e + J q (J: the horizontal part of
sum_k u_k x (r - p_k) over the DoFs moving the part) is held by a spring whose stiffness is the
part's vertical contact stiffness (foam shear ~ its compression) up to mu N, beyond which the
force stays mu N (Coulomb sliding, `CoulombSprings`); between re-posings an anchor left beyond
mu N / k slides after its part (slip); a part that lifts off forgets its anchor. This is sim #1's static-friction spring
(`sim.settle`) per part instead of per capsule and bed section.
"""

from __future__ import annotations

import dataclasses

import torch

from pressurepose.body.joints import NUM_JOINTS


@dataclasses.dataclass
class CoulombSprings:
    """Per part, the horizontal offset s(q) = offset + J q from its anchor (B, 24, 2), J (B, 24,
    2, N), held by a spring k (B, 24) N/m up to the sliding force f (B, 24) = mu N; beyond it the
    force stays f (Coulomb): energy 1/2 k |s|^2 for |s| <= f / k, f |s| - f^2 / (2 k) beyond
    (convex, continuous gradient). Parts with k = 0 carry nothing."""

    offset: torch.Tensor
    jac: torch.Tensor
    stiffness: torch.Tensor
    sliding_force: torch.Tensor

    def take(self, idx: torch.Tensor) -> CoulombSprings:
        """The springs of the bodies `idx` (a (B',) index)."""
        return CoulombSprings(self.offset[idx], self.jac[idx], self.stiffness[idx], self.sliding_force[idx])

    def _s(self, q):
        B, P = self.offset.shape[:2]
        return self.offset + (self.jac.reshape(B, 2 * P, -1) @ q[..., None]).view(B, P, 2)

    def energy(self, q: torch.Tensor) -> torch.Tensor:
        s = self._s(q)
        n = s.norm(dim=-1)
        k, f = self.stiffness, self.sliding_force
        reach = f / k.clamp(min=1e-12)
        e = torch.where(n <= reach, 0.5 * k * n**2, f * n - 0.5 * f * reach)
        return (e * (k > 0)).sum(1)

    def gradient_hessian(self, q: torch.Tensor):
        """Energy (B,), gradient (B, N), Hessian (B, N, N) (beyond the sliding force: f / |s|
        times the projection across s - the force keeps its size, turns with s)."""
        s = self._s(q)
        n = s.norm(dim=-1)
        k, f = self.stiffness, self.sliding_force
        on = (k > 0).to(q.dtype)
        reach = f / k.clamp(min=1e-12)
        stick = (n <= reach).to(q.dtype)
        e = (torch.where(n <= reach, 0.5 * k * n**2, f * n - 0.5 * f * reach) * on).sum(1)
        scale = torch.where(n <= reach, k, f / n.clamp(min=1e-15)) * on  # force = scale * s
        force = scale[..., None] * s  # (B, 24, 2)
        B, P = s.shape[:2]
        jac = self.jac.reshape(B, 2 * P, -1)
        grad = (force.reshape(B, 1, 2 * P) @ jac)[:, 0]
        # Tangent stiffness per part: scale (I - slip u u^T), slip = 1 beyond the sliding force;
        # the Hessian sum_p J_p^T T_p J_p as one (N x 2P)(2P x N) product.
        unit = s / n.clamp(min=1e-15)[..., None]
        slip = (scale * (1 - stick))[..., None, None] * unit[..., :, None] * unit[..., None, :]
        tangent = scale[..., None, None] * torch.eye(2, dtype=q.dtype, device=q.device) - slip  # (B, P, 2, 2)
        tj = tangent[..., 0:1] * self.jac[..., 0:1, :] + tangent[..., 1:2] * self.jac[..., 1:2, :]  # T_p J_p
        hess = jac.transpose(1, 2) @ tj.reshape(B, 2 * P, -1)
        return e, grad, hess


class Friction:
    """Anchors of B bodies' J24 parts on the sheet (module doc)."""

    def __init__(self, batch: int, mu: float, dtype, device):
        self.mu = float(mu)
        self.anchored = torch.zeros(batch, NUM_JOINTS, dtype=torch.bool, device=device)
        self.anchor = torch.zeros(batch, NUM_JOINTS, 2, dtype=dtype, device=device)  # on the sheet, m
        self.local = torch.zeros(batch, NUM_JOINTS, 3, dtype=dtype, device=device)  # in the part's frame
        self.stiffness = torch.zeros(batch, NUM_JOINTS, dtype=dtype, device=device)
        self.load = torch.zeros(batch, NUM_JOINTS, dtype=dtype, device=device)

    def take(self, idx: torch.Tensor) -> Friction:
        """The anchors of the bodies `idx` (a (B',) index)."""
        out = Friction(len(idx), self.mu, self.anchor.dtype, self.anchor.device)
        for name in ("anchored", "anchor", "local", "stiffness", "load"):
            setattr(out, name, getattr(self, name)[idx])
        return out

    def _points(self, rot, joints):
        """(B, 24, 3) the anchored material points in the mat frame."""
        return (rot @ self.local[..., None])[..., 0] + joints

    def update(self, rot, joints, part, xyz, force, stiffness, active=None):
        """After a solve, at the posing it reached (rot (B, 24, 3, 3), joints (B, 24, 3)): cells'
        part (B, K), contact points xyz (B, K, 3) and force (B, K) N; stiffness (B, K) N/m.
        `active` (B,) bool: only these bodies' anchors change (default all)."""
        if active is not None and not bool(active.all()):
            before = (self.anchored, self.anchor, self.local, self.stiffness, self.load)
            self.update(rot, joints, part, xyz, force, stiffness)
            keep = ~active
            self.anchored = torch.where(keep[:, None], before[0], self.anchored)
            self.anchor = torch.where(keep[:, None, None], before[1], self.anchor)
            self.local = torch.where(keep[:, None, None], before[2], self.local)
            self.stiffness = torch.where(keep[:, None], before[3], self.stiffness)
            self.load = torch.where(keep[:, None], before[4], self.load)
            return
        B = force.shape[0]
        load = force.new_zeros(B, NUM_JOINTS).scatter_add_(1, part, force)
        k = force.new_zeros(B, NUM_JOINTS).scatter_add_(1, part, stiffness)
        moment = force.new_zeros(B, NUM_JOINTS, 3).scatter_add_(
            1, part[..., None].expand(-1, -1, 3), force[..., None] * xyz
        )
        touching = load > 0
        cop = moment / load.clamp(min=1e-12)[..., None]
        new = touching & ~self.anchored
        local = ((cop - joints)[..., None, :] @ rot)[..., 0, :]  # R^T (c - p)
        self.local = torch.where(new[..., None], local, self.local)
        self.anchor = torch.where(new[..., None], cop[..., :2], self.anchor)
        self.anchored = touching
        # Slip: a spring beyond mu N drags its anchor after the part.
        offset = self._points(rot, joints)[..., :2] - self.anchor
        length = offset.norm(dim=-1)
        cap = self.mu * load / k.clamp(min=1e-12)
        slide = self.anchored & (length > cap)
        kept = offset * (cap / length.clamp(min=1e-15))[..., None]
        self.anchor = torch.where(slide[..., None], self.anchor + offset - kept, self.anchor)
        self.stiffness = k * self.anchored
        self.load = load

    def linearise(self, rot, joints, axes, pivots, dof_parts) -> CoulombSprings:
        """The anchored parts' friction at the posing (rot, joints); axes, pivots (B, N, 3) of the
        DoFs, dof_parts (N, 24)."""
        r = self._points(rot, joints)  # (B, 24, 3)
        offset = r[..., :2] - self.anchor  # (B, 24, 2)
        # d r / d q_n = u_n x (r - p_n) where DoF n moves the part; the vertical shift moves nothing
        # horizontally (its axis is zero).
        d = r[:, :, None] - pivots[:, None]  # (B, 24, N, 3)
        move = torch.linalg.cross(axes[:, None].expand_as(d), d)[..., :2] * dof_parts.T[None, :, :, None]
        jac = move.permute(0, 1, 3, 2)  # (B, 24, 2, N)
        return CoulombSprings(offset=offset, jac=jac, stiffness=self.stiffness, sliding_force=self.mu * self.load)


__all__ = ["CoulombSprings", "Friction"]
