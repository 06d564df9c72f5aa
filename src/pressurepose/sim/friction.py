"""Static friction of the articulated rest (`sim.articulated`): a part that touches the sheet
sticks where it touched, until the horizontal force on it exceeds mu times its load.

Without it the quasi-static rest has nothing horizontal to push against: a supine body's bent
knee, held up in sim #1 by the hip's spring and the foot's grip on the sheet, falls outward
because its foot slides freely. Per J24 part in contact: an anchor on the sheet (where its
centre of pressure was when it first touched) and the material point that touched (in the
part's frame); the part's horizontal offset from its anchor e + J q (J: the horizontal part of
sum_k u_k x (r - p_k) over the DoFs moving the part) is held by a spring whose stiffness is the
part's vertical contact stiffness (foam shear ~ its compression). Between re-posings a spring
pulled beyond mu N lets the anchor slide after the part (slip, the anchor kept at mu N / k);
a part that lifts off forgets its anchor. This is sim #1's static-friction spring
(`sim.settle`) per part instead of per capsule and bed section.
"""

from __future__ import annotations

import torch

from pressurepose.body.joints import NUM_JOINTS
from pressurepose.sim.self_contact import LinearSprings


class Friction:
    """Anchors of B bodies' J24 parts on the sheet (module doc)."""

    def __init__(self, batch: int, mu: float, dtype, device):
        self.mu = float(mu)
        self.anchored = torch.zeros(batch, NUM_JOINTS, dtype=torch.bool, device=device)
        self.anchor = torch.zeros(batch, NUM_JOINTS, 2, dtype=dtype, device=device)  # on the sheet, m
        self.local = torch.zeros(batch, NUM_JOINTS, 3, dtype=dtype, device=device)  # in the part's frame
        self.stiffness = torch.zeros(batch, NUM_JOINTS, dtype=dtype, device=device)

    def _points(self, rot, joints):
        """(B, 24, 3) the anchored material points in the mat frame."""
        return (rot @ self.local[..., None])[..., 0] + joints

    def update(self, rot, joints, part, xyz, force, stiffness):
        """After a solve, at the posing it reached (rot (B, 24, 3, 3), joints (B, 24, 3)): cells'
        part (B, K), contact points xyz (B, K, 3) and force (B, K) N; stiffness (B, K) N/m."""
        B = force.shape[0]
        load = force.new_zeros(B, NUM_JOINTS).scatter_add_(1, part, force)
        k = force.new_zeros(B, NUM_JOINTS).scatter_add_(1, part, stiffness)
        moment = force.new_zeros(B, NUM_JOINTS, 3).scatter_add_(1, part[..., None].expand(-1, -1, 3),
                                                                 force[..., None] * xyz)
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

    def linearise(self, rot, joints, axes, pivots, dof_parts) -> LinearSprings:
        """Springs on the anchored parts' horizontal offsets (two rows per part: x, y) at the
        posing (rot, joints); axes, pivots (B, N, 3) of the DoFs, dof_parts (N, 24)."""
        r = self._points(rot, joints)  # (B, 24, 3)
        offset = r[..., :2] - self.anchor  # (B, 24, 2)
        # d r / d q_n = u_n x (r - p_n) where DoF n moves the part; the vertical shift moves nothing
        # horizontally (its axis is zero).
        d = r[:, :, None] - pivots[:, None]  # (B, 24, N, 3)
        move = torch.linalg.cross(axes[:, None].expand_as(d), d)[..., :2] * dof_parts.T[None, :, :, None]
        jac = move.permute(0, 1, 3, 2).reshape(r.shape[0], NUM_JOINTS * 2, -1)  # rows: part x, part y
        mask = self.anchored.repeat_interleave(2, 1).to(r.dtype)
        return LinearSprings(gap=offset.reshape(r.shape[0], -1), jac=jac * mask[..., None],
                             stiffness=self.stiffness.repeat_interleave(2, 1), mask=mask, one_sided=False)


__all__ = ["Friction"]
