"""The articulated rest's bookkeeping (`sim.articulated.rest_articulated`): the state of the
bodies still moving, and the rests of those that finished, filled in as they leave."""

from __future__ import annotations

import dataclasses

import torch

from pressurepose.body.joints import NUM_JOINTS
from pressurepose.body.params import BodyParams, root_matrix
from pressurepose.body.rotations import rotation_angle
from pressurepose.sim.articulation import Dofs, apply_motion
from pressurepose.sim.foundation import FAIL_BOTTOM, FAIL_NO_SUPPORT, FAIL_NOT_CONVERGED, FAIL_SLIDES
from pressurepose.sim.linearised import Linearised
from pressurepose.sim.mattress import MattressParams

# The pose parameters the articulated rest changes.
MOVED = ("pose", "root_rotation", "root_translation")

# (no support, through the foam, not converged, sliding: the rigid rest's reasons, `sim.foundation`)
FAIL_TILT = "unstable: the body rolls over (its centre of mass leaves its support)"
MAX_ROLL_RAD = 1.0  # ~57 deg: a body on its side has rolled onto its front or back


@dataclasses.dataclass
class MovingBodies:
    """The per-body state of the bodies still moving (`rest_articulated`)."""

    cur: BodyParams  # the pose of this re-posing
    rest: torch.Tensor  # (B, 24, 3) rest joints
    local_com: torch.Tensor  # (B, 24, 3) parts' centres of mass in their joint frames
    mass: torch.Tensor  # (B, 24)
    local_pts: torch.Tensor  # (B, P, 3) surface points in their parts' joint frames
    point_tissue: torch.Tensor | None  # (B, P) tissue modulus under each point
    point_sag: torch.Tensor | None  # (B, P) how far each point's tissue hangs down (m)
    dof_lo: torch.Tensor  # (B, N) hinge limits
    dof_hi: torch.Tensor
    ref_local: torch.Tensor  # (B, 23, 3, 3) the springs' rest rotations
    root_start: torch.Tensor  # (B, 3, 3)
    k: torch.Tensor  # (B, N) joint stiffness
    weight: torch.Tensor  # (B,)
    pillow_m: torch.Tensor | None = None  # (B,) pillow thickness (0: none)
    pillow_under: torch.Tensor | None = None  # (B, C) cells under the pillow
    wedge_m: torch.Tensor | None = None  # (B, C) the wedge's thickness per cell (`sim.wedge`)
    # Swing damping (`damp_swings`): the last re-posing's motion, each unknown's share of its
    # motion taken, and how many re-posings in a row its motion kept its direction without shrinking.
    last_q: torch.Tensor | None = None  # (B, N)
    share: torch.Tensor | None = None  # (B, N)
    streak: torch.Tensor | None = None  # (B, N)
    # The coarse grid's points (`coarse_points`), their tissue, sag and pillow cells.
    c_pts: torch.Tensor | None = None
    c_tissue: torch.Tensor | None = None
    c_sag: torch.Tensor | None = None
    c_under: torch.Tensor | None = None
    c_wedge_m: torch.Tensor | None = None

    def coarse_points(
        self, keep: torch.Tensor | None, under: torch.Tensor | None, wedge_m: torch.Tensor | None = None
    ) -> None:
        """Keep the surface points `keep` (P,) bool for the coarse grid (coordinate-major, as
        `articulation.to_part_frames` lays them out); `under` (B, C'): its pillow cells; `wedge_m`
        (B, C'): its wedge thickness. None: drop them (the coarse re-posings are over)."""
        if keep is None:
            self.c_pts = self.c_tissue = self.c_sag = self.c_under = self.c_wedge_m = None
            return
        self.c_wedge_m = wedge_m
        self.c_pts = self.local_pts[:, keep].transpose(1, 2).contiguous().transpose(1, 2)
        self.c_tissue = None if self.point_tissue is None else self.point_tissue[:, keep].contiguous()
        self.c_sag = None if self.point_sag is None else self.point_sag[:, keep].contiguous()
        self.c_under = under

    def take(self, idx: torch.Tensor) -> MovingBodies:
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return MovingBodies(
            **{n: v if v is None else v.index(idx) if n == "cur" else v[idx] for n, v in fields.items()}
        )


# Re-posings in a row that an unknown's motion keeps its direction without shrinking before its
# share is doubled back toward 1 (`damp_swings`): a slide after a swing regains its reach.
_REGAIN = 3


def damp_swings(q, last_q, share, streak, cap, tol):
    """The part of each unknown's re-posing motion q (B, N) the bodies take (B, N), with the
    updated `share` and `streak` (module `MovingBodies`). A re-posing moves a body to its
    linearisation's rest; where that overshoots - an elbow or a hip whose linearisation on
    either side of a contact's onset points to the other - the unknown swings between two
    poses to the cap (docs/realism.md "Bodies still moving when the re-posings run out"). Per
    unknown, a secant step on its motion: its motion reversed (q and last_q of opposite signs,
    both beyond `tol` (N,) and within `cap` (N,)) - the rest lies between the last two poses,
    at the share |last| / (|last| + |q|) of the last step (the root of the line through the
    two motions); kept its direction but shrank by rho < 1 - a slow approach, the share grows
    to share / (1 - rho) (at most 1); neither, `_REGAIN` times in a row - doubled (at most 1);
    at its cap (a large motion, not a rest nearby) - 1 again. A swing about a smooth rest ends
    in one step; about a kink (a contact's onset) it halves each swing (bisection)."""
    free = (q.abs() < 0.999 * cap) & (last_q.abs() < 0.999 * cap)
    both = (q.abs() > tol) & (last_q.abs() > tol) & free
    reverse = both & (q * last_q < 0)
    onward = both & ~reverse
    rho = q.abs() / last_q.abs().clamp(min=1e-15)
    new = torch.where(reverse, share * last_q.abs() / (last_q.abs() + q.abs()).clamp(min=1e-15), share)
    new = torch.where(onward & (rho < 1), (share / (1 - rho).clamp(min=1e-3)).clamp(max=1.0), new)
    streak = torch.where(onward & (rho >= 1), streak + 1, torch.zeros_like(streak))
    regain = streak >= _REGAIN
    new = torch.where(regain, (2 * new).clamp(max=1.0), new)
    streak = torch.where(regain, torch.zeros_like(streak), streak)
    new = torch.where(q.abs() >= 0.999 * cap, torch.ones_like(new), new)
    return q * new, new, streak


class RestsDone:
    """The rests of B bodies, filled in as they finish (`rest_articulated`)."""

    def __init__(self, params: BodyParams, cells: int, area: float, dofs: Dofs, raised=None):
        B = params.batch_size
        self.params, self.area, self.dofs, self.cells = params, area, dofs, cells
        self.raised = raised  # a `sim.raised.RaisedBed`, or None (flat)
        self.friction_ratio = params.pose.new_zeros(B)
        new = params.pose.new_zeros
        self.foundation, self.part_force = new(B, cells), new(B, NUM_JOINTS)
        self.force, self.max_compression = new(B), new(B)
        self.support = torch.zeros(B, dtype=torch.bool, device=params.pose.device)
        # A body whose last allowed re-posing still moved it has not settled (`ArticulatedRest.settled`).
        self.moving = torch.zeros(B, dtype=torch.bool, device=params.pose.device)
        self.reposings = torch.zeros(B, dtype=torch.long, device=params.pose.device)

    def finish(self, idx, lin: Linearised, q, cur: BodyParams, rot, joints, body_com, mp: MattressParams) -> None:
        """Bodies `idx` rest at q of their linearisation `lin` (at the posing cur, rot, joints):
        its field balances the weight; the mesh is moved by its motion exactly (small for a body
        that settled; for one settled by swing damping at a kink up to a few tens of mrad,
        docs/realism.md "Swing damping")."""
        _, _, f, w, _ = lin.newton_step(q, mp)
        w = lin.bed_compression(w, f, mp)  # the bed's share of the compression
        final = apply_motion(cur, q, self.dofs, rot, joints, body_com)
        self.params = self.params.replace(
            **{n: getattr(self.params, n).index_copy(0, idx, getattr(final, n)) for n in MOVED}
        )
        self.foundation[idx] = lin.unpack(f, self.cells) / self.area
        part = lin.part % NUM_JOINTS  # the raised section's cells carry part + 24
        self.part_force[idx] = f.new_zeros(len(idx), NUM_JOINTS).scatter_add_(1, part, f * lin.mask)
        if self.raised is None:
            self.force[idx] = f.sum(1)
        else:  # the normal forces' vertical resultant (it balances the weight), and the push
            fm = f * lin.mask
            self.force[idx] = lin.support(fm)
            self.friction_ratio[idx] = self.raised.foot_push(lin.part, fm) / fm.sum(1).clamp(min=1e-12)
        self.max_compression[idx] = w.amax(1)
        self.support[idx] = lin.mask.any(1)

    def failures(self, start_root: torch.Tensor, weight: torch.Tensor, mp: MattressParams) -> list[str]:
        """Per body, why its rest is rejected ("" if it is not): no contact, rolled over (its root
        turned beyond MAX_ROLL_RAD from `start_root` (B, 3)), through the foam, force not
        balancing the weight (B,) N, or (raised) more friction than the sheet holds."""
        turned = rotation_angle(root_matrix(start_root), root_matrix(self.params.root_rotation))
        out = []
        for i in range(len(weight)):
            force, w = float(self.force[i]), float(weight[i])
            if not bool(self.support[i]) or force <= 0:
                out.append(FAIL_NO_SUPPORT)
            elif float(turned[i]) > MAX_ROLL_RAD:
                out.append(FAIL_TILT)
            elif float(self.max_compression[i]) > float(mp.thickness_m):  # (on air the travel ends on a base)
                out.append(FAIL_BOTTOM)
            elif abs(force - w) > 1e-3 * w:
                out.append(FAIL_NOT_CONVERGED)
            elif self.raised is not None and float(self.friction_ratio[i]) > float(mp.friction):
                out.append(FAIL_SLIDES)
            else:
                out.append("")
        return out


__all__ = ["FAIL_TILT", "MAX_ROLL_RAD", "MOVED", "MovingBodies", "RestsDone", "damp_swings"]
