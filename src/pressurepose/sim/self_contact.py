"""Self-contact of the articulated sim #2: body capsules that must not pass through each other.

The articulated rest (`sim.articulated`) lets every part settle on the bed; without this a
forearm lying across the belly or one calf over the other would sink through the body
beneath it to the foam. The body's capsules (`body.capsules`, the ones sim #1 collides) stand
for its volume: the seed's distal capsules (hands, forearms, feet, calves) against every
non-adjacent capsule, like sim #1 and the sampler, each pair only if it is apart in the
starting pose (a pair that starts overlapped is left alone, as MuJoCo does).

Per linearisation, for each pair the closest points c1, c2 of the two axes give the gap
g = |c1 - c2| - r1 - r2 and the normal n = (c1 - c2) / |c1 - c2|; a small motion q changes the
gap by n . (dc1 - dc2) = J q, with dc = sum_k q_k u_k x (c - p_k) over the DoFs k whose subtree
holds the point's part (the vertical shift and the root move both points alike and drop out).
The energy is a stiff one-sided spring 1/2 k relu(-(g + J q))^2, k = the body's weight /
`sink_m`: the whole weight on one contact would press it that far in.
"""

from __future__ import annotations

import dataclasses

import torch

from pressurepose.body.capsule_geometry import segment_closest_points
from pressurepose.body.capsules import CAPSULE_JOINTS, Capsules, collision_pairs

# The whole body's weight on one capsule contact presses it this far in (a leg's ~17% of
# it: ~3 mm). Stiffer than the tissue on the foam; soft enough for Newton. `SelfContact`'s own
# default; the articulated rest's is `ArticulatedConfig.self_contact_sink_m` (5 cm since session 42).
SELF_CONTACT_SINK_M = 0.02
# Pairs farther apart than this cannot meet within one re-posing's trust region.
_REACH_M = 0.15


@dataclasses.dataclass
class LinearSprings:
    """Springs on quantities linear in the DoFs q: g(q) = gap + jac q, energy 1/2 k g^2 per
    row - one-sided (only where g < 0: contacts) or two-sided (friction anchors). gap (B, M),
    jac (B, M, N), stiffness (B,) or (B, M), mask (B, M) of the rows that count."""

    gap: torch.Tensor
    jac: torch.Tensor
    stiffness: torch.Tensor
    mask: torch.Tensor
    one_sided: bool = True
    rows: torch.Tensor | None = None
    """(B, M) which of the source's rows these are (self-contact: the pairs within reach, packed
    first), or None (all, in order)."""

    def take(self, idx: torch.Tensor) -> LinearSprings:
        """The springs of the bodies `idx` (a (B',) index)."""
        return dataclasses.replace(
            self,
            gap=self.gap[idx],
            jac=self.jac[idx],
            stiffness=self.stiffness[idx],
            mask=self.mask[idx],
            rows=None if self.rows is None else self.rows[idx],
        )

    def _stretch(self, q):
        g = self.gap + (self.jac @ q[..., None])[..., 0]
        return (torch.relu(-g) if self.one_sided else -g) * self.mask

    def _k(self):
        return self.stiffness[:, None] if self.stiffness.ndim == 1 else self.stiffness

    def energy(self, q: torch.Tensor) -> torch.Tensor:
        return 0.5 * (self._k() * self._stretch(q) ** 2).sum(1)

    def gradient_hessian(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Energy (B,), gradient (B, N) and Hessian (B, N, N) at q (one-sided: the Hessian of
        the active rows; piecewise quadratic)."""
        pen = self._stretch(q)
        k = self._k()
        grad = -((k * pen)[..., None] * self.jac).sum(1)
        active = ((pen > 0).to(q.dtype) if self.one_sided else self.mask) * k
        hess = (self.jac * active[..., None]).transpose(1, 2) @ self.jac
        return 0.5 * (k * pen**2).sum(1), grad, hess


class SelfContact:
    """The capsule pairs of B bodies that self-contact keeps apart (module doc)."""

    def __init__(
        self,
        caps: Capsules,
        rot: torch.Tensor,
        joints: torch.Tensor,
        weight_n: torch.Tensor,
        sink_m: float = SELF_CONTACT_SINK_M,
    ):
        """caps: the bodies' capsules; rot, joints: the starting pose's world rotations (B, 24, 3,
        3) and joint positions (B, 24, 3); weight_n (B,)."""
        self.caps = caps
        self.pairs = collision_pairs().to(joints.device)
        cj = torch.tensor(CAPSULE_JOINTS, device=joints.device)
        self.part = cj[self.pairs]  # (P, 2) J24 part each capsule rides
        self.stiffness = weight_n / sink_m
        gap, _, _ = self._gap(rot, joints)
        self.apart = gap > 0  # (B, P)

    def take(self, idx: torch.Tensor) -> SelfContact:
        """The pairs of the bodies `idx` (a (B',) index)."""
        out = object.__new__(SelfContact)
        out.__dict__.update(self.__dict__)
        caps = self.caps
        out.caps = dataclasses.replace(caps, **{f.name: getattr(caps, f.name)[idx] for f in dataclasses.fields(caps)})
        out.stiffness, out.apart = self.stiffness[idx], self.apart[idx]
        return out

    def _gap(self, rot, joints):
        a, b = self.caps.place(rot, joints)
        i, j = self.pairs[:, 0], self.pairs[:, 1]
        c1, c2 = segment_closest_points(a[:, i], b[:, i], a[:, j], b[:, j])
        gap = (c1 - c2).norm(dim=-1) - self.caps.radius[:, i] - self.caps.radius[:, j]
        return gap, c1, c2

    def linearise(self, rot, joints, axes, pivots, dof_parts) -> LinearSprings:
        """At the posing (rot, joints): axes (B, N, 3) and pivots (B, N, 3) of the DoFs,
        dof_parts (N, 24) the parts each DoF moves."""
        gap, c1, c2 = self._gap(rot, joints)
        near = self.apart & (gap < _REACH_M)
        # Only the pairs within reach count: packed first per body (M of them at most).
        m = max(int(near.sum(1).max()), 1)
        rows = torch.argsort((~near).to(torch.int8), dim=1, stable=True)[:, :m]
        pick = rows[..., None].expand(-1, -1, 3)
        c1, c2 = c1.gather(1, pick), c2.gather(1, pick)
        diff = c1 - c2
        dist = diff.norm(dim=-1, keepdim=True)
        up = torch.zeros_like(diff)
        up[..., 2] = 1.0
        normal = torch.where(dist > 1e-9, diff / dist.clamp(min=1e-9), up)  # (B, M, 3)
        # n . (u x (c - p)) = u . (c x n) - n . (u x p), per DoF (two (M x 3)(3 x N) products per
        # capsule); the DoF counts where it moves the capsule's part.
        part = self.part[rows]  # (B, M, 2)
        m1 = dof_parts.T[part[..., 0]]  # (B, M, N)
        m2 = dof_parts.T[part[..., 1]]
        ut = axes.transpose(1, 2)  # (B, 3, N)
        about = normal @ torch.linalg.cross(axes, pivots).transpose(1, 2)  # n . (u x p), (B, M, N)
        j1 = torch.linalg.cross(c1, normal) @ ut - about
        j2 = torch.linalg.cross(c2, normal) @ ut - about
        return LinearSprings(
            gap=gap.gather(1, rows),
            jac=j1 * m1 - j2 * m2,
            stiffness=self.stiffness,
            mask=near.gather(1, rows).to(gap.dtype),
            rows=rows,
        )

    def penetration(self, rot, joints) -> torch.Tensor:
        """(B,) deepest overlap (m, >= 0) of the pairs that started apart."""
        gap, _, _ = self._gap(rot, joints)
        return torch.relu(-gap * self.apart).amax(1)


__all__ = ["SELF_CONTACT_SINK_M", "LinearSprings", "SelfContact"]
