"""The articulated rest's set-up (`sim.rest_setup`) and the motion's composition
(`body.kinematics.compose_down`) against the straightforward computations they replace: the
same numbers bit for bit (the rests amplify any round-off, so the engine's revision holds only
if these are exact)."""

from __future__ import annotations

import torch
from test_articulated import _bodies

from pressurepose.body.joints import J24_PARENTS, NUM_JOINTS
from pressurepose.body.kinematics import compose_down, pose_in_mat, rest_joints
from pressurepose.body.rotations import axis_angle_to_matrix
from pressurepose.maps import surface_points
from pressurepose.sim.articulation import Dofs, apply_motion, corner_mass_and_com, part_mass_and_com
from pressurepose.sim.rest_setup import SurfaceLayout


def _posed(model, B=3):
    p = _bodies(model, B)
    g = torch.Generator().manual_seed(3)
    return p.replace(pose=p.pose + 0.2 * torch.randn(p.pose.shape, generator=g, dtype=p.pose.dtype))


def test_layout_points_are_the_surface_points_sorted_by_part(anny64):
    vertices = anny64(_posed(anny64)).vertices
    faces, labels_v = anny64.faces, anny64.part_labels
    labels_all = torch.cat([labels_v, labels_v[faces[:, 0]]])
    order = torch.argsort(labels_all, stable=True)
    layout = SurfaceLayout.build(faces, labels_v)
    pts, corners = layout.points(vertices)
    assert pts.shape == (3, 3, labels_all.shape[0])
    assert torch.equal(pts.transpose(1, 2), surface_points(vertices, faces)[:, order])
    assert torch.equal(layout.labels, labels_all[order])
    assert torch.equal(layout.vertex, order < labels_v.shape[0])
    assert bool((layout.labels[1:] >= layout.labels[:-1]).all())
    # The corners: the faces in part order, each corner's coordinates as (B, 3, F) rows.
    assert torch.equal(layout.triangle_part, labels_v[layout.triangles[:, 0]])
    assert bool((layout.triangle_part[1:] >= layout.triangle_part[:-1]).all())
    for i, c in enumerate(corners):
        assert torch.equal(c, vertices[:, layout.triangles[:, i]].transpose(1, 2))


def test_corner_mass_is_part_mass_bit_for_bit(anny64):
    vertices = anny64(_posed(anny64)).vertices
    layout = SurfaceLayout.build(anny64.faces, anny64.part_labels)
    _, corners = layout.points(vertices)
    shift = torch.tensor([0.0, 0.0, 0.2], dtype=vertices.dtype)
    mass, com = part_mass_and_com(vertices - shift, anny64.faces, anny64.part_labels[anny64.faces[:, 0]])
    mass2, com2 = corner_mass_and_com(*(c - shift[:, None] for c in corners), layout.triangle_part)
    assert torch.equal(mass, mass2) and torch.equal(com, com2)
    assert bool((mass > 0).all())


def test_compose_down_is_the_product_along_each_chain():
    g = torch.Generator().manual_seed(0)
    D = axis_angle_to_matrix(0.5 * torch.randn(4, NUM_JOINTS, 3, generator=g, dtype=torch.float64))
    U = compose_down(D)
    for j in range(NUM_JOINTS):
        expected, k = torch.eye(3, dtype=D.dtype).expand(4, 3, 3), j
        while k >= 0:  # D_j D_parent(j) ... D_root
            expected = expected @ D[:, k]
            k = J24_PARENTS[k] if k > 0 else -1
        torch.testing.assert_close(U[:, j], expected, rtol=0, atol=1e-12)


def test_apply_motion_moves_each_subtree_rigidly(anny64):
    p = _posed(anny64, 2)
    rest = rest_joints(anny64, p.shape)
    rot, joints = pose_in_mat(rest, p)
    dofs = Dofs("cpu", torch.float64)
    q = 0.05 * torch.randn(2, dofs.n, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    com = joints.mean(1)
    moved = apply_motion(p, q, dofs, rot, joints, com)
    rot2, joints2 = pose_in_mat(rest, moved)
    # Each joint's world rotation is its subtree's composed turn times the old one.
    delta = torch.zeros(2, NUM_JOINTS, 3, dtype=q.dtype).index_add_(1, dofs.joint, q[..., None] * dofs.axes(rot))
    U = compose_down(axis_angle_to_matrix(delta))
    torch.testing.assert_close(rot2, U @ rot, rtol=0, atol=1e-12)
    # The pelvis turns about the centre of mass and rises by the vertical shift.
    pelvis = com + (U[:, 0] @ (joints[:, 0] - com)[..., None])[..., 0]
    pelvis[:, 2] += q[:, 0]
    torch.testing.assert_close(joints2[:, 0], pelvis, rtol=0, atol=1e-12)


def _apply_motion_joint_by_joint(params, q, dofs, rot, body_com):
    """`apply_motion` as it was before `compose_down` (session 49): the subtree turns composed
    joint by joint, the joints' and the root's rotation vectors converted apart."""
    from pressurepose.body.params import supine_rotation
    from pressurepose.body.rotations import matrix_to_axis_angle

    delta = q.new_zeros(q.shape[0], NUM_JOINTS, 3).index_add_(1, dofs.joint, q[..., None] * dofs.axes(rot))
    D = axis_angle_to_matrix(delta)
    U = [D[:, 0]] + [None] * (NUM_JOINTS - 1)
    new_rot = rot.clone()
    new_rot[:, 0] = U[0] @ rot[:, 0]
    for j in range(1, NUM_JOINTS):
        U[j] = D[:, j] @ U[J24_PARENTS[j]]
        new_rot[:, j] = U[j] @ rot[:, j]
    par = [max(p, 0) for p in J24_PARENTS[1:]]
    pose = matrix_to_axis_angle(new_rot[:, par].transpose(-1, -2) @ new_rot[:, 1:])
    root = matrix_to_axis_angle(new_rot[:, 0] @ supine_rotation(q.dtype, q.device).T)
    moved = body_com + (U[0] @ (params.root_translation - body_com)[..., None])[..., 0]
    moved = moved + torch.stack([torch.zeros_like(q[:, 0]), torch.zeros_like(q[:, 0]), q[:, 0]], -1)
    return pose, root, moved


def test_apply_motion_is_the_joint_by_joint_composition_bit_for_bit(anny64):
    # The engine's revision rests on this: any round-off here would move the rests.
    for B in (1, 5, 32):
        p = _posed(anny64, B)
        rot, joints = pose_in_mat(rest_joints(anny64, p.shape), p)
        dofs = Dofs("cpu", torch.float64)
        q = 0.05 * torch.randn(B, dofs.n, generator=torch.Generator().manual_seed(B), dtype=torch.float64)
        moved = apply_motion(p, q, dofs, rot, joints, joints.mean(1))
        pose, root, translation = _apply_motion_joint_by_joint(p, q, dofs, rot, joints.mean(1))
        assert torch.equal(moved.pose, pose)
        assert torch.equal(moved.root_rotation, root)
        assert torch.equal(moved.root_translation, translation)
