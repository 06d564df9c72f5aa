"""The articulated rest on a bed with its head section raised (`sim.raised`): the sections'
linearisation by finite differences and against autograd, continuity with the flat bed, the
vertical balance, mirror symmetry, and the generator's routing."""

import math

import numpy as np
import pytest
import torch
from test_articulated import _bodies

from pressurepose.bed import BedShape
from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.sim.articulated import FAIL_SLIDES, ArticulatedConfig, rest_articulated
from pressurepose.sim.mattress import GRAVITY_M_S2, MattressParams
from pressurepose.sim.raised import RaisedBed


def test_section_coefficients_by_finite_differences():
    """A point's normal height above the raised section changes under a small rotation about
    any axis through any pivot (or a vertical shift) as its coefficients over (1, s, y) say."""
    mat = MatSpec()
    raised = RaisedBed(BedShape(35.0), mat, torch.float64, "cpu")
    g = torch.Generator().manual_seed(0)
    B, N = 3, 5
    axes = torch.randn(B, N, 3, generator=g, dtype=torch.float64)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    axes[:, 0] = 0.0  # the vertical shift
    pivots = torch.rand(B, N, 3, generator=g, dtype=torch.float64) * torch.tensor([0.8, 0.7, 0.3], dtype=torch.float64)
    flat = torch.zeros(B, N, 3, dtype=torch.float64)
    a = raised.section_a(flat, axes, pivots)[:, :, 1]  # the raised section's
    # Points above the raised section (s < the hinge's 0.46 m), near its top.
    r = torch.tensor([[0.2, 0.3, 0.0], [0.4, 0.1, 0.0], [0.05, 0.6, 0.0]], dtype=torch.float64)
    r = raised.to_world(r + torch.tensor([0.0, 0.0, 0.02], dtype=torch.float64))
    theta = 1e-6
    for b in range(B):
        for k in range(N):
            surf = raised.to_surface(r[b][None])[0]
            if k == 0:
                moved = r[b] + torch.tensor([0.0, 0.0, theta], dtype=torch.float64)
            else:
                u, p = axes[b, k], pivots[b, k]
                moved = r[b] + theta * torch.linalg.cross(u, r[b] - p)
            dn = (raised.to_surface(moved[None])[0, 2] - surf[2]) / theta
            pred = a[b, k] @ torch.stack([torch.ones((), dtype=torch.float64), surf[0], surf[1]])
            assert float(dn) == pytest.approx(float(pred), abs=1e-5)


def _sectioned(anny64, angle=10.0):
    """A home-pose body dropped onto a raised bed (10 deg: both sections within reach) and its
    linearisation: (lin, raised, the pose's params, rot, joints, body_com, labels, xy)."""
    from pressurepose.body.kinematics import forward_kinematics, rest_joints
    from pressurepose.body.params import root_matrix
    from pressurepose.body.rotations import axis_angle_to_matrix
    from pressurepose.maps import cell_centres, surface_points
    from pressurepose.sim.articulation import Dofs, dof_axes_pivots, dof_geometry, joint_stiffness, part_mass_and_com
    from pressurepose.sim.linearised import Linearised
    from pressurepose.sim.soft_contact import lowest_points

    mat = MatSpec()
    raised = RaisedBed(BedShape(angle), mat, torch.float64, "cpu")
    p = _bodies(anny64, 1)
    pts = surface_points(anny64(p).vertices, anny64.faces)
    p = p.replace(root_translation=p.root_translation - torch.tensor([[0.0, 0.0, float(raised.drop(pts)[0])]]))
    out = anny64(p)
    faces = anny64.faces
    face_part = anny64.part_labels[faces[:, 0]]
    labels = torch.cat([anny64.part_labels, face_part])
    mass, com = part_mass_and_com(out.vertices, faces, face_part)
    dofs = Dofs("cpu", torch.float64)
    rot, _ = forward_kinematics(rest_joints(anny64, p.shape), p.pose, root_matrix(p.root_rotation))
    h, part, _ = lowest_points(raised.to_surface(surface_points(out.vertices, faces)), labels, mat, 2)
    X, Y = cell_centres(mat, 2, covered=True, dtype=torch.float64)
    xy = torch.stack([X.reshape(-1), Y.reshape(-1)], -1)
    part = raised.section_parts(part, raised.head_cells(xy[:, 0]))
    body_com = (mass[..., None] * com).sum(1) / mass.sum(1, keepdim=True)
    a, e = dof_geometry(dofs, rot, out.joints, body_com, p.pose, axis_angle_to_matrix(p.pose))
    axes, pivots = dof_axes_pivots(dofs, rot, out.joints, body_com)
    k = joint_stiffness(mass.sum(1), dofs)
    area = mat.pitch_row_m * mat.pitch_col_m / 4
    section_a = raised.section_a(a, axes, pivots)
    lin = Linearised(h, part, xy, a, mass, com, e + 0.05, k, dofs, area, 3e5, None, (), section_a, raised.section_cos)
    return lin, raised, p, rot, out.joints, body_com, labels


def test_sectioned_hessian_matches_autograd(anny64):
    """The Newton step's gradient and Hessian with the cells split between two sections (parts
    + 24 on the raised one) against autograd on the same linearised energy; the force holding
    the weight is the normals' vertical resultant."""
    lin, raised, *_ = _sectioned(anny64)
    mp = MattressParams()
    on = lin.mask.bool()
    assert bool((lin.part[on] >= 24).any()) and bool((lin.part[on] < 24).any())
    q = torch.zeros(1, lin.dofs.n, dtype=torch.float64)
    q[0, 0] = -float(lin.h[on].min()) - 0.03
    q[0, 1:] = 0.01 * torch.sin(torch.arange(1, lin.dofs.n, dtype=torch.float64))
    grad, H, f, _, energy = lin.newton_step(q, mp)
    qa = q.clone().requires_grad_(True)
    g_auto = torch.autograd.grad(lin.energy(qa, mp).sum(), qa)[0]
    np.testing.assert_allclose(grad.numpy(), g_auto.numpy(), rtol=1e-6, atol=1e-6)
    H_auto = torch.autograd.functional.hessian(lambda x: lin.energy(x[None], mp).sum(), q[0])
    np.testing.assert_allclose(H[0].numpy(), H_auto.numpy(), rtol=1e-6, atol=1e-4)
    head = lin.part >= 24
    expected = (f * torch.where(head, torch.full_like(f, raised.cos), torch.ones_like(f))).sum(1)
    np.testing.assert_allclose(lin.support(f).numpy(), expected.numpy(), rtol=1e-12)


def test_sectioned_heights_follow_the_motion(anny64):
    """The linearised normal heights of the cells on both sections against the mesh moved by a
    small motion (`apply_motion`) and rasterised again in surface coordinates: the same to second
    order (a wrong section or part slot in the coefficients would be first-order off)."""
    from pressurepose.maps import surface_points
    from pressurepose.sim.articulation import apply_motion
    from pressurepose.sim.soft_contact import lowest_points

    lin, raised, p, rot, joints, body_com, labels = _sectioned(anny64)
    q = 2e-3 * torch.cos(torch.arange(lin.dofs.n, dtype=torch.float64))[None]
    deep = lin.take(torch.tensor([0]))
    deep.h = lin.h - 10.0  # every cell compressed: compression = -(h - 10 + dz)
    dz = -deep.compression(q) - deep.h
    moved = anny64(apply_motion(p, q, lin.dofs, rot, joints, body_com))
    h_new, part_new, _ = lowest_points(
        raised.to_surface(surface_points(moved.vertices, anny64.faces)), labels, MatSpec(), 2
    )
    h_new = h_new.gather(1, lin.index)
    same = lin.mask.bool() & (part_new.gather(1, lin.index) == lin.part % 24)
    for section in (lin.part < 24, lin.part >= 24):
        sel = same & section
        assert int(sel.sum()) > 50
        actual, predicted = (h_new - lin.h)[sel], dz[sel]
        assert float((actual - predicted).abs().median()) < 0.05 * float(predicted.abs().median())


@pytest.fixture(scope="module")
def raised_rest(anny64):
    p = _bodies(anny64, 1)
    return p, rest_articulated(anny64, p, bed=BedShape(30.0))


def test_raised_rest_balances_the_weight_vertically(anny64, raised_rest):
    """At 30 deg: nothing fails, the image's normal pressures hold the weight with their
    vertical components (cos 30 deg on the raised section's cells), the raised section carries
    part of it, and the friction the rest needs is what the raised section's normals push
    toward the foot, below the sheet's."""
    from pressurepose.maps import cell_centres

    p, r = raised_rest
    mat = MatSpec()
    weight = float(anny64.measure(p.shape).mass_kg[0]) * GRAVITY_M_S2
    assert r.failure == [""] and torch.isfinite(r.foundation_pa).all()
    X, _ = cell_centres(mat, r.sub, covered=True, dtype=torch.float64)
    head = X < BedShape(30.0).hinge_x(mat)
    cell_force = r.foundation_pa[0] * mat.pitch_row_m * mat.pitch_col_m / r.sub**2
    vertical = (cell_force * torch.where(head, math.cos(math.radians(30)), 1.0)).sum()
    assert float(vertical) == pytest.approx(weight, rel=2e-3)
    share = float(cell_force[head].sum() / cell_force.sum())
    assert 0.1 < share < 0.9
    assert float(r.friction_ratio[0]) == pytest.approx(share * math.sin(math.radians(30)), rel=1e-6)
    assert float(r.friction_ratio[0]) < MattressParams().friction
    np.testing.assert_allclose(float(r.part_force_n.sum()), float(cell_force.sum()), rtol=1e-9)


def test_a_barely_raised_bed_rests_like_the_flat_one(anny64, raised_rest):
    """At 0.001 deg the sections' frames are the flat bed's to 2e-5: the rest is the flat one's
    to the round-off level of its path (the same body moved by 1e-12 m moves joints by ~5 mm)."""
    p, _ = raised_rest
    flat = rest_articulated(anny64, p)
    nearly = rest_articulated(anny64, p, bed=BedShape(0.001))
    assert nearly.failure == flat.failure == [""]
    assert float((nearly.joints - flat.joints).norm(dim=-1).max()) < 0.01
    l1 = (nearly.foundation_pa - flat.foundation_pa).abs().sum() / flat.foundation_pa.sum()
    assert float(l1) < 0.1
    assert flat.friction_ratio is None and float(nearly.friction_ratio[0]) < 1e-4


@pytest.mark.parametrize(
    "config", [None, {"friction": False, "coarse_sub": 0}], ids=["defaults", "one_grid_frictionless"]
)
def test_mirrored_bodies_give_mirrored_images_on_a_raised_bed(anny64, config):
    """The home-pose body 3 cm to either side of the mat's centre line (the pose and the bed
    symmetric about it): mirrored images - with the engine's defaults (friction on, as the
    generator rests), and on the image's grid alone without friction - judged by the load's
    centre across and along the bed, which the rest's moment balance ties to the body's centre of
    mass. Not by the whole profiles: how a pair's limbs settle on a raised bed is round-off
    amplified along the rest's path and depends on the CPU (column profiles 0.013-0.089 apart on
    session 49's Intel Xeon, docs/benchmarks.md "Session 49: two grids"; 0.05-0.15 on session
    52's AMD EPYC, where a 0.05 bound failed). Measured on that AMD: the centres 0.1-0.7 cm apart
    across and up to 1.5 cm along for mirrored pairs at 3 and 5 cm; the unmirrored pair's 6-9.5 cm."""
    mat = MatSpec()
    p = _bodies(anny64, 2)
    shift = torch.tensor([[0.0, 0.03, 0.0], [0.0, -0.03, 0.0]], dtype=torch.float64)
    p = p.replace(root_translation=p.root_translation + shift)
    cfg = ArticulatedConfig() if config is None else ArticulatedConfig(**config)
    r = rest_articulated(anny64, p, bed=BedShape(30.0), config=cfg)
    assert r.failure == ["", ""]
    a, b = r.foundation_pa[0], r.foundation_pa[1]
    assert mat.covered_cols % 2 == 1  # the grid is symmetric about the centre line

    def centre(image: torch.Tensor, dim: int, pitch_m: float) -> float:  # the load's centre, m
        profile = image.sum(dim) / image.sum()
        return float((profile * torch.arange(len(profile), dtype=profile.dtype)).sum()) * pitch_m / r.sub

    across, along = mat.pitch_col_m, mat.pitch_row_m
    assert abs(centre(a, 0, across) - centre(b.flip(-1), 0, across)) < 0.02
    assert abs(centre(a, 1, along) - centre(b, 1, along)) < 0.03
    assert abs(centre(a, 0, across) - centre(b, 0, across)) > 0.04  # the bound tells a broken mirror


def test_a_body_the_sheet_cannot_hold_slides(anny64, raised_rest):
    """With a slippery sheet (friction 0.05) the raised section's push toward the foot needs more
    friction than it has: the rest fails with FAIL_SLIDES and an empty image."""
    p, r = raised_rest
    slippery = rest_articulated(anny64, p, mattress=MattressParams(friction=0.05), bed=BedShape(30.0))
    assert float(slippery.friction_ratio[0]) > 0.05
    assert slippery.failure == [FAIL_SLIDES] and float(slippery.foundation_pa.abs().sum()) == 0.0


def test_pillows_are_refused_on_a_raised_bed(anny64):
    p = _bodies(anny64, 1)
    with pytest.raises(UserError, match="flat beds only"):
        rest_articulated(anny64, p, pillow_m=torch.tensor([0.08]), bed=BedShape(30.0))


def test_the_generator_rests_raised_beds_articulated(anny64):
    """`simulate_poses(settle="articulated")` on a raised bed: the articulated rest, no MuJoCo
    (its steps are the re-posings, no settle time), the image loaded on both sections; a
    pillow asked for is not laid on the raised bed."""
    from pressurepose.sampling.sitting import half_sitting_params
    from pressurepose.sim.run import simulate_poses

    mat, bed = MatSpec(), BedShape(40.0)
    params = half_sitting_params(anny64, anny64.default_shape(1), bed, mat)
    sim = simulate_poses(
        anny64,
        params,
        MattressParams.preset("sponge"),
        mat,
        bed=bed,
        settle="articulated",
        pillow_m=torch.tensor([0.08]),
    )
    assert sim.reason == [""]
    assert float(sim.settle_ms[0]) == 0.0 and 0 < int(sim.settle_steps[0]) <= ArticulatedConfig().outer + 1
    hinge_row = mat.rows - bed.hinge_row_from_foot
    img = sim.pressure_mmhg[0]
    assert float(img[:hinge_row].sum()) > 0 and float(img[hinge_row:].sum()) > 0
