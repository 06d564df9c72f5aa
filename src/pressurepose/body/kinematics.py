"""Forward kinematics on the J24 tree, shared by every backend.

Both backends pose J24 as SMPL does: joint j's world rotation is its parent's times its local
rotation, and its position is the parent's plus the parent's world rotation applied to the
rest-pose (T-pose) offset. Given a shape's rest joints, this reproduces the body model's posed
joints (exactly on SMPL, within 0.03 mm on Anny, whose elbow twist rides a bone a hair off the
forearm axis; tests/test_capsules.py) at a fraction of the cost,
and it also yields the per-joint world rotations that rigid parts (capsules) ride on.
"""

from __future__ import annotations

import torch

from pressurepose.body.joints import J24_PARENTS, NUM_JOINTS, NUM_POSE_JOINTS
from pressurepose.body.model import BodyModel
from pressurepose.body.params import BodyParams, root_matrix
from pressurepose.body.rotations import axis_angle_to_matrix

# Joints grouped by depth in the tree, so `compose_down` runs one batched step per level (8 levels).
_DEPTH = [0] * NUM_JOINTS
for _j in range(1, NUM_JOINTS):
    _DEPTH[_j] = _DEPTH[J24_PARENTS[_j]] + 1
LEVELS: tuple[tuple[int, ...], ...] = tuple(
    tuple(j for j in range(NUM_JOINTS) if _DEPTH[j] == d) for d in range(1, max(_DEPTH) + 1)
)
# Per level: the joints and their parents, as index tensors made once.
_LEVEL_INDEX = tuple((torch.tensor(level), torch.tensor([J24_PARENTS[j] for j in level])) for level in LEVELS)
_PARENTS = torch.tensor([0, *J24_PARENTS[1:]])


def _strict_descendants() -> torch.Tensor:
    desc = torch.zeros(NUM_JOINTS, NUM_JOINTS, dtype=torch.bool)
    for k in range(NUM_JOINTS):
        j = J24_PARENTS[k]
        while j >= 0:
            desc[j, k] = True
            j = J24_PARENTS[j]
    return desc


DESCENDANTS = _strict_descendants()  # (24, 24) bool, [j, k] = k lies below j in J24


def rest_joints(model: BodyModel, shape: torch.Tensor) -> torch.Tensor:
    """(B, 24, 3) T-pose joints of (B, S) shapes in body axes (x left, y head, z front),
    pelvis at the origin (`BodyModel.rest_joints`)."""
    return model.rest_joints(shape)


def forward_kinematics(
    rest: torch.Tensor, pose: torch.Tensor, root_rotation: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """World rotations (B, 24, 3, 3) and positions (B, 24, 3) of J24.

    rest: (B, 24, 3) T-pose joints, pelvis at the origin (see `rest_joints`).
    pose: (B, 23, 3) axis-angle of joints 1..23 (BodyParams.pose).
    root_rotation: (B, 3, 3) or (3, 3) rotation of the whole body (default identity: body axes).
    The pelvis stays at the origin; add the root translation yourself.
    """
    if rest.ndim != 3 or rest.shape[1:] != (NUM_JOINTS, 3):
        raise ValueError(f"rest joints must have shape (B, {NUM_JOINTS}, 3), got {tuple(rest.shape)}")
    if pose.ndim != 3 or pose.shape[1:] != (NUM_POSE_JOINTS, 3) or pose.shape[0] != rest.shape[0]:
        raise ValueError(f"pose must have shape ({rest.shape[0]}, {NUM_POSE_JOINTS}, 3), got {tuple(pose.shape)}")
    local = axis_angle_to_matrix(pose).unbind(1)
    offsets = (rest - rest[:, _PARENTS.to(rest.device)]).unsqueeze(-1).unbind(1)  # (B, 3, 1) each, the root's 0
    root = torch.eye(3, dtype=rest.dtype, device=rest.device) if root_rotation is None else root_rotation.to(rest)
    rot = [root.expand(rest.shape[0], 3, 3)]  # (3, 3) or (B, 3, 3)
    pos = [torch.zeros_like(offsets[0])]
    # joint by joint (23 small products each way): at batch 1 to 128 ~1.7x faster than one
    # batched step per level of the tree, whose gathers and scatters cost more than they save
    # (docs/benchmarks.md, session 57)
    for j in range(1, NUM_JOINTS):
        parent = rot[J24_PARENTS[j]]
        rot.append(torch.bmm(parent, local[j - 1]))  # bmm: a third of matmul's dispatch cost here
        pos.append(torch.baddbmm(pos[J24_PARENTS[j]], parent, offsets[j]))
    return torch.stack(rot, 1), torch.stack(pos, 1).squeeze(-1)


def compose_down(D: torch.Tensor) -> torch.Tensor:
    """(B, 24, 3, 3) -> U with U_0 = D_0 and U_j = D_j U_parent(j): rotations each joint
    applies to its subtree (world frame), composed from the root down, one batched product per
    level of the tree."""
    U = D.clone()
    for idx, par in _LEVEL_INDEX:
        if idx.device != D.device:
            idx, par = idx.to(D.device), par.to(D.device)
        U[:, idx] = D[:, idx] @ U[:, par]
    return U


def pose_in_mat(rest: torch.Tensor, params: BodyParams) -> tuple[torch.Tensor, torch.Tensor]:
    """World rotations (B, 24, 3, 3, body axes -> mat frame) and joint positions (B, 24, 3)
    in the mat frame for BodyParams whose shapes have these rest joints."""
    rot, pos = forward_kinematics(rest, params.pose, root_matrix(params.root_rotation))
    return rot, pos + params.root_translation[:, None, :]
