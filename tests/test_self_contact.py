"""Self-contact of the articulated sim #2: closest points, the gap's Jacobian against moved
poses, the energy's derivatives against autograd, and a forearm resting on the belly."""

import math

import numpy as np
import torch

from pressurepose.body.capsule_geometry import segment_closest_points as closest_points
from pressurepose.body.capsules import fit_capsules, home_pose
from pressurepose.body.joints import joint_index
from pressurepose.body.kinematics import pose_in_mat, rest_joints
from pressurepose.body.params import BodyParams
from pressurepose.mat import MatSpec
from pressurepose.sim.articulated import ArticulatedConfig, rest_articulated
from pressurepose.sim.articulation import Dofs, apply_motion, dof_axes_pivots
from pressurepose.sim.self_contact import LinearSprings, SelfContact


def test_closest_points_match_a_dense_search():
    g = torch.Generator().manual_seed(0)
    p1, q1, p2, q2 = (torch.randn(200, 3, generator=g, dtype=torch.float64) for _ in range(4))
    q2[:20] = p2[:20]  # point-like second segments
    q1[20:30] = p1[20:30]  # point-like first segments
    q2[30:40] = p2[30:40] + 2.0 * (q1[30:40] - p1[30:40])  # parallel segments
    c1, c2 = closest_points(p1, q1, p2, q2)
    s = torch.linspace(0, 1, 401, dtype=torch.float64)
    a = p1[:, None] + s[None, :, None] * (q1 - p1)[:, None]  # (200, 401, 3)
    b = p2[:, None] + s[None, :, None] * (q2 - p2)[:, None]
    brute = torch.cdist(a, b).amin((1, 2))
    got = (c1 - c2).norm(dim=-1)
    assert (got <= brute + 1e-12).all()  # never farther than the grid's best
    np.testing.assert_allclose(got.numpy(), brute.numpy(), atol=2e-2)  # grid step 1/400 of ~2-4
    # The points lie on their segments.
    for c, p, q in ((c1, p1, q1), (c2, p2, q2)):
        d = q - p
        t = ((c - p) * d).sum(-1) / (d * d).sum(-1).clamp(min=1e-30)
        assert ((t > -1e-9) & (t < 1 + 1e-9)).all()


def _forearm_over_belly(model, B=1):
    """Supine, the left upper arm raised over the chest and the elbow bent: the forearm hangs
    above the trunk (every capsule pair of the forearm and hand apart)."""
    mat = MatSpec()
    pose = home_pose(B)
    pose[:, joint_index("left_shoulder") - 1] = torch.tensor([0.5, -1.0, -1.0], dtype=torch.float64)
    pose[:, joint_index("left_elbow") - 1] = torch.tensor([0.0, -1.6, 0.0], dtype=torch.float64)
    return BodyParams.zeros(B, model.default_shape(B)).replace(
        pose=pose, root_translation=torch.tensor([[0.85, mat.sensing_width_m / 2, 0.25]] * B, dtype=torch.float64)
    )


def test_gap_jacobian_matches_moved_poses(anny64):
    """J q predicts the gap change of a small motion q (applied exactly to the pose)."""
    p = _forearm_over_belly(anny64)
    rest = rest_joints(anny64, p.shape)
    rot, joints = pose_in_mat(rest, p)
    dofs = Dofs("cpu", torch.float64)
    contact = SelfContact(fit_capsules(anny64, p.shape), rot, joints, torch.tensor([700.0], dtype=torch.float64))
    com = joints.mean(1)
    axes, pivots = dof_axes_pivots(dofs, rot, joints, com)
    lin = contact.linearise(rot, joints, axes, pivots, dofs.desc[dofs.joint])
    g = torch.Generator().manual_seed(1)
    q = 1e-4 * torch.randn(1, dofs.n, generator=g, dtype=torch.float64)
    moved = apply_motion(p, q, dofs, rot, joints, com)
    gap2, _, _ = contact._gap(*pose_in_mat(rest, moved))
    gap2 = gap2.gather(1, lin.rows)  # the pairs within reach, as the linearisation packs them
    predicted = lin.gap + (lin.jac @ q[..., None])[..., 0]
    keep = lin.mask.bool()
    assert int(keep.sum()) >= 3
    err = (gap2 - predicted)[keep].abs().max()
    change = (gap2 - lin.gap)[keep].abs().max()
    assert float(change) > 1e-5  # the motion does move the capsules
    assert float(err) < 0.02 * float(change)


def test_energy_derivatives_match_autograd():
    g = torch.Generator().manual_seed(2)
    B, P, N = 2, 7, 5
    lin = LinearSprings(
        gap=0.01 * torch.randn(B, P, generator=g, dtype=torch.float64),
        jac=torch.randn(B, P, N, generator=g, dtype=torch.float64),
        stiffness=torch.tensor([1e4, 3e4], dtype=torch.float64),
        mask=(torch.rand(B, P, generator=g) > 0.2).to(torch.float64),
    )
    q = 0.01 * torch.randn(B, N, generator=g, dtype=torch.float64)
    e, grad, hess = lin.gradient_hessian(q)
    qa = q.clone().requires_grad_(True)
    np.testing.assert_allclose(e.numpy(), lin.energy(q).numpy(), rtol=1e-12)
    g_auto = torch.autograd.grad(lin.energy(qa).sum(), qa)[0]
    np.testing.assert_allclose(grad.numpy(), g_auto.numpy(), rtol=1e-9, atol=1e-9)
    for b in range(B):
        h_auto = torch.autograd.functional.hessian(
            lambda x: lin.energy(x[None])[0] if b == 0 else lin.energy(torch.stack([q[0], x]))[1], q[b]
        )
        np.testing.assert_allclose(hess[b].numpy(), h_auto.numpy(), rtol=1e-9, atol=1e-6)


def test_forearm_rests_on_the_belly_instead_of_sinking_through(anny64):
    p = _forearm_over_belly(anny64)
    free = rest_articulated(anny64, p, config=ArticulatedConfig(self_contact=False))
    held = rest_articulated(anny64, p)
    assert held.failure == [""] and free.failure == [""]
    rest = rest_joints(anny64, p.shape)
    contact = SelfContact(fit_capsules(anny64, p.shape), *pose_in_mat(rest, p), torch.ones(1, dtype=torch.float64))
    sunk = float(contact.penetration(*pose_in_mat(rest, free.params))[0])
    assert sunk > 0.03, sunk  # without self-contact the forearm passes into the trunk
    assert float(held.self_penetration_m[0]) < 0.003
    # ... and its wrist ends on the foam, while the held one rests on the chest.
    wrist = joint_index("left_wrist")
    assert float(free.joints[0, wrist, 2]) < 0.06 < 0.1 < float(held.joints[0, wrist, 2])
    # The forearm's weight goes through the belly: it carries (almost) none on the foam.
    elbow = joint_index("left_elbow")
    assert float(held.part_force_n[0, elbow]) < 0.5 * float(free.part_force_n[0, elbow]) + 1e-9
    assert math.isfinite(float(held.force_n[0]))


def test_friction_anchors_where_a_part_touches_and_slips_beyond_mu_n():
    from pressurepose.sim.friction import Friction

    B = 1
    rot = torch.eye(3, dtype=torch.float64).expand(B, 24, 3, 3).clone()
    joints = torch.zeros(B, 24, 3, dtype=torch.float64)
    part = torch.tensor([[5, 5, 7]])
    xyz = torch.tensor([[[1.0, 0.2, -0.01], [1.2, 0.2, -0.01], [0.5, 0.5, -0.02]]], dtype=torch.float64)
    force = torch.tensor([[10.0, 30.0, 0.0]], dtype=torch.float64)  # part 7 does not touch
    stiff = torch.tensor([[1e3, 1e3, 0.0]], dtype=torch.float64)
    fr = Friction(B, mu=0.5, dtype=torch.float64, device="cpu")
    fr.update(rot, joints, part, xyz, force, stiff)
    assert fr.anchored[0].nonzero().ravel().tolist() == [5]
    np.testing.assert_allclose(fr.anchor[0, 5].numpy(), [1.15, 0.2])  # the centre of pressure
    assert float(fr.stiffness[0, 5]) == 2e3
    # The part moves 1 mm: it sticks (mu N / k = 0.5 * 40 / 2000 = 10 mm).
    joints[0, 5, 0] = 0.001
    fr.update(rot, joints, part, xyz, force, stiff)
    np.testing.assert_allclose(fr.anchor[0, 5].numpy(), [1.15, 0.2])
    springs = fr.linearise(
        rot,
        joints,
        torch.zeros(B, 4, 3, dtype=torch.float64),
        torch.zeros(B, 4, 3, dtype=torch.float64),
        torch.ones(4, 24, dtype=torch.float64),
    )
    np.testing.assert_allclose(float(springs.energy(torch.zeros(B, 4, dtype=torch.float64))[0]), 0.5 * 2e3 * 1e-6)
    assert float(springs.sliding_force[0, 5]) == 0.5 * 40
    # It moves 5 cm: the anchor slides after it, the spring at mu N.
    joints[0, 5, 0] = 0.05
    fr.update(rot, joints, part, xyz, force, stiff)
    np.testing.assert_allclose(fr.anchor[0, 5].numpy(), [1.15 + 0.04, 0.2])
    # It lifts off: the anchor is forgotten.
    fr.update(rot, joints, part, xyz, torch.zeros_like(force), stiff)
    assert not fr.anchored.any() and float(fr.stiffness.abs().sum()) == 0


def test_friction_jacobian_matches_moved_poses(anny64):
    from pressurepose.sim.friction import Friction

    p = _forearm_over_belly(anny64)
    rest = rest_joints(anny64, p.shape)
    rot, joints = pose_in_mat(rest, p)
    dofs = Dofs("cpu", torch.float64)
    fr = Friction(1, 0.5, torch.float64, "cpu")
    # Every part touches at its joint (a contact point per part, unit force and stiffness).
    part = torch.arange(24)[None]
    fr.update(
        rot,
        joints,
        part,
        joints.clone(),
        torch.ones(1, 24, dtype=torch.float64),
        torch.ones(1, 24, dtype=torch.float64),
    )
    com = joints.mean(1)
    axes, pivots = dof_axes_pivots(dofs, rot, joints, com)
    springs = fr.linearise(rot, joints, axes, pivots, dofs.desc[dofs.joint])
    g = torch.Generator().manual_seed(3)
    q = 1e-4 * torch.randn(1, dofs.n, generator=g, dtype=torch.float64)
    moved = pose_in_mat(rest, apply_motion(p, q, dofs, rot, joints, com))
    offset = fr._points(*moved)[..., :2] - fr.anchor
    predicted = springs._s(q)
    assert float(offset.abs().max()) > 1e-5
    assert float((offset - predicted).abs().max()) < 0.02 * float(offset.abs().max())


def test_coulomb_springs_derivatives_and_sliding_force():
    """Energy, gradient and Hessian against autograd, sticking and sliding parts alike; a
    sliding part's force is mu N whatever its offset."""
    from pressurepose.sim.friction import CoulombSprings

    g = torch.Generator().manual_seed(4)
    B, N = 2, 6
    springs = CoulombSprings(
        offset=0.01 * torch.randn(B, 24, 2, generator=g, dtype=torch.float64),
        jac=torch.randn(B, 24, 2, N, generator=g, dtype=torch.float64),
        stiffness=torch.rand(B, 24, generator=g, dtype=torch.float64) * 1e3,
        sliding_force=torch.rand(B, 24, generator=g, dtype=torch.float64) * 5.0,
    )
    springs.stiffness[:, :4] = 0.0  # parts without an anchor
    q = 0.01 * torch.randn(B, N, generator=g, dtype=torch.float64)
    s = springs._s(q).norm(dim=-1)
    sliding = (s > springs.sliding_force / springs.stiffness.clamp(min=1e-12)) & (springs.stiffness > 0)
    assert 0 < int(sliding.sum()) < int((springs.stiffness > 0).sum())  # both regimes present
    e, grad, hess = springs.gradient_hessian(q)
    np.testing.assert_allclose(e.numpy(), springs.energy(q).numpy(), rtol=1e-12)
    qa = q.clone().requires_grad_(True)
    np.testing.assert_allclose(grad.numpy(), torch.autograd.grad(springs.energy(qa).sum(), qa)[0].numpy(), rtol=1e-9)
    for b in range(B):

        def one(x):
            qq = q.clone()
            qq[b] = x
            return springs.energy(qq)[b]

        np.testing.assert_allclose(
            hess[b].numpy(), torch.autograd.functional.hessian(one, q[b]).numpy(), rtol=1e-7, atol=1e-7
        )
    # One sliding part alone: its force (the gradient w.r.t. its offset) has size mu N.
    one_part = CoulombSprings(
        offset=torch.tensor([[[0.3, 0.4]]], dtype=torch.float64),
        jac=torch.eye(2, dtype=torch.float64)[None, None],
        stiffness=torch.tensor([[100.0]], dtype=torch.float64),
        sliding_force=torch.tensor([[2.0]], dtype=torch.float64),
    )
    _, grad, _ = one_part.gradient_hessian(torch.zeros(1, 2, dtype=torch.float64))
    np.testing.assert_allclose(grad[0].numpy(), [1.2, 1.6])
