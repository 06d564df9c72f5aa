"""The articulated rest's bookkeeping (`sim.articulated.rest_articulated`): the state of the
bodies still moving, and the rests of those that finished, filled in as they leave."""

from __future__ import annotations

import dataclasses

import torch

from pressurepose.body.joints import NUM_JOINTS
from pressurepose.body.params import BodyParams
from pressurepose.sim.articulation import Dofs, apply_motion
from pressurepose.sim.linearised import Linearised
from pressurepose.sim.mattress import MattressParams

# The pose parameters the articulated rest changes.
MOVED = ("pose", "root_rotation", "root_translation")


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

    def take(self, idx: torch.Tensor) -> MovingBodies:
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return MovingBodies(
            **{n: v if v is None else v.index(idx) if n == "cur" else v[idx] for n, v in fields.items()}
        )


class RestsDone:
    """The rests of B bodies, filled in as they finish (`rest_articulated`)."""

    def __init__(self, params: BodyParams, cells: int, area: float, dofs: Dofs):
        B = params.batch_size
        self.params, self.area, self.dofs, self.cells = params, area, dofs, cells
        new = params.pose.new_zeros
        self.foundation, self.part_force = new(B, cells), new(B, NUM_JOINTS)
        self.force, self.max_compression = new(B), new(B)
        self.support = torch.zeros(B, dtype=torch.bool, device=params.pose.device)
        # A body whose last allowed re-posing still moved it has not settled (`ArticulatedRest.settled`).
        self.moving = torch.zeros(B, dtype=torch.bool, device=params.pose.device)
        self.reposings = torch.zeros(B, dtype=torch.long, device=params.pose.device)

    def finish(self, idx, lin: Linearised, q, cur: BodyParams, rot, joints, body_com, mp: MattressParams) -> None:
        """Bodies `idx` rest at q of their linearisation `lin` (at the posing cur, rot, joints):
        its field balances the weight; the mesh is moved by its (small) motion exactly."""
        _, _, f, w, _ = lin.newton_step(q, mp)
        w = lin.bed_compression(w, f, mp)  # the bed's share of the compression
        final = apply_motion(cur, q, self.dofs, rot, joints, body_com)
        self.params = self.params.replace(
            **{n: getattr(self.params, n).index_copy(0, idx, getattr(final, n)) for n in MOVED}
        )
        self.foundation[idx] = lin.unpack(f, self.cells) / self.area
        self.part_force[idx] = f.new_zeros(len(idx), NUM_JOINTS).scatter_add_(1, lin.part, f * lin.mask)
        self.force[idx], self.max_compression[idx] = f.sum(1), w.amax(1)
        self.support[idx] = lin.mask.any(1)


__all__ = ["MOVED", "MovingBodies", "RestsDone"]
