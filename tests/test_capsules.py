import math

import pytest
import torch

from pressurepose.body.capsule_geometry import dot
from pressurepose.body.capsules import (
    CAPSULE_NAMES,
    CAPSULE_PARENTS,
    CAPSULES,
    DISTAL_CAPSULES,
    JOINT_STIFFNESS,
    NUM_CAPSULES,
    Capsules,
    build_capsule_body,
    capsule_clearance,
    capsule_index,
    capsule_inertia,
    capsule_volumes,
    collision_pairs,
    fit_capsules,
    home_pose,
    point_segment_distance,
    segment_distance,
)
from pressurepose.body.joints import J24_NAMES
from pressurepose.body.kinematics import forward_kinematics, pose_in_mat, rest_joints
from pressurepose.body.limits import JointLimits
from pressurepose.body.params import BodyParams

D = torch.float64


def _random_params(model, B, seed=0):
    g = torch.Generator().manual_seed(seed)
    lim = JointLimits.default(D)
    pose = lim.lower + (lim.upper - lim.lower) * torch.rand(B, 23, 3, generator=g, dtype=D)
    shape = (
        torch.rand(B, model.shape_dim, generator=g, dtype=D)
        if model.name == "anny"
        else torch.randn(B, model.shape_dim, generator=g, dtype=D)
    )
    return BodyParams(
        shape=shape,
        root_rotation=torch.randn(B, 3, generator=g, dtype=D),
        root_translation=torch.randn(B, 3, generator=g, dtype=D),
        pose=pose,
    )


@pytest.mark.parametrize("backend", ["anny64", "smpl64"])
def test_j24_forward_kinematics_reproduces_the_body_model(backend, request):
    model = request.getfixturevalue(backend)
    params = _random_params(model, 8)
    rest = rest_joints(model, params.shape)
    _, joints = pose_in_mat(rest, params)
    # exact on SMPL; on Anny within 0.1 mm (its elbow twist sits on a bone a hair off the
    # forearm's axis)
    torch.testing.assert_close(joints, model.joints(params), atol=1e-4 if model.name == "anny" else 1e-9, rtol=0)


def test_forward_kinematics_rejects_bad_shapes():
    with pytest.raises(ValueError, match="rest joints"):
        forward_kinematics(torch.zeros(2, 23, 3), torch.zeros(2, 23, 3))
    with pytest.raises(ValueError, match="pose"):
        forward_kinematics(torch.zeros(2, 24, 3), torch.zeros(3, 23, 3))


def _brute_segment_distance(p1, q1, p2, q2, n=801):
    s = torch.linspace(0, 1, n, dtype=D)
    a = p1 + s[:, None] * (q1 - p1)
    b = p2 + s[:, None] * (q2 - p2)
    return torch.cdist(a, b).min()


def test_segment_distance_matches_brute_force_including_degenerate_cases():
    g = torch.Generator().manual_seed(1)
    cases = [torch.randn(4, 3, generator=g, dtype=D) for _ in range(40)]
    p = torch.randn(3, dtype=D)
    d = torch.tensor([1.0, 0.5, 0.0], dtype=D)
    cases += [
        torch.stack(
            [p, p + d, p + torch.tensor([0, 0, 1.0], dtype=D), p + d + torch.tensor([0, 0, 1.0], dtype=D)]
        ),  # parallel
        torch.stack([p, p, p + 1, p + 2]),  # point vs segment
        torch.stack([p, p + 1, p - 1, p - 1]),  # segment vs point
        torch.stack([p, p, p + 0.3, p + 0.3]),  # point vs point
        torch.stack([p, p + d, p + 0.5 * d, p + 2 * d]),  # collinear, overlapping
    ]
    got = segment_distance(*[torch.stack([c[k] for c in cases]) for k in range(4)])
    want = torch.stack([_brute_segment_distance(*c) for c in cases])
    torch.testing.assert_close(got, want, atol=2e-3, rtol=0)  # brute force resolves ~1/800 of a length
    assert (got <= want + 1e-12).all()  # exact minimum is never above a sampled one
    # point to segment
    x = torch.randn(50, 3, generator=g, dtype=D)
    a, b = torch.zeros(3, dtype=D), torch.tensor([1.0, 0, 0], dtype=D)
    t = torch.linspace(0, 1, 2001, dtype=D)
    brute = torch.cdist(x, a + t[:, None] * (b - a)).min(-1).values
    torch.testing.assert_close(point_segment_distance(x, a, b), brute, atol=1e-6, rtol=0)


def test_capsule_clearance_is_the_segment_distance_minus_the_radii_bit_for_bit():
    # capsule_clearance is segment_closest_points written out per coordinate (the pose
    # sampler's collision test): the same operations in the same order, so the same bits.
    g = torch.Generator().manual_seed(3)
    B, C = 300, 20
    start = 0.3 * torch.randn(B, C, 3, generator=g, dtype=D)
    end = start + 0.2 * torch.randn(B, C, 3, generator=g, dtype=D)
    end[:, 0] = start[:, 0]  # point-like capsules
    end[:, 1] = start[:, 1] + torch.tensor([0.1, 0.0, 0.0], dtype=D)  # parallel to capsule 2's
    end[:, 2] = start[:, 2] + torch.tensor([0.3, 0.0, 0.0], dtype=D)
    start[:5, 3] = start[:5, 4]  # touching ends
    radius = 0.1 * torch.rand(B, C, generator=g, dtype=D)
    pairs = torch.cat(
        [torch.tensor([[0, 5], [1, 2], [3, 4], [0, 0], [6, 0]]), torch.randint(0, C, (40, 2), generator=g)]
    )
    i, j = pairs[:, 0], pairs[:, 1]
    want = segment_distance(start[:, i], end[:, i], start[:, j], end[:, j]) - radius[:, i] - radius[:, j]
    got = capsule_clearance(start, end, radius, pairs)
    assert torch.equal(got.view(torch.int64), want.view(torch.int64))
    x, y = torch.randn(2, 7, 11, 3, generator=g, dtype=D)
    assert torch.equal(dot(x, y), (x * y).sum(-1))


def test_capsule_inertia_matches_monte_carlo():
    r, L, m = 0.05, 0.3, 2.0
    g = torch.Generator().manual_seed(2)
    pts = (torch.rand(400_000, 3, generator=g, dtype=D) - 0.5) * torch.tensor([2 * r, 2 * r, L + 2 * r], dtype=D)
    inside = (
        point_segment_distance(pts, torch.tensor([0, 0, -L / 2], dtype=D), torch.tensor([0, 0, L / 2], dtype=D)) <= r
    )
    q = pts[inside]
    axial = m * (q[:, 0] ** 2 + q[:, 1] ** 2).mean()
    perp = m * (q[:, 1] ** 2 + q[:, 2] ** 2).mean()
    got = capsule_inertia(torch.tensor(m, dtype=D), torch.tensor(r, dtype=D), torch.tensor(L, dtype=D))
    torch.testing.assert_close(got, torch.stack([axial, perp, perp]), rtol=1e-2, atol=0)
    # volume fraction check of the Monte Carlo box against the analytic capsule volume
    box = 2 * r * 2 * r * (L + 2 * r)
    assert inside.double().mean() * box == pytest.approx(math.pi * r**2 * (L + 4 * r / 3), rel=1e-2)


def test_layout_is_the_smplify_twenty_on_j24():
    assert NUM_CAPSULES == 20
    assert len(set(CAPSULE_NAMES)) == 20
    # 19 joints between 20 capsules: a tree rooted at the pelvis
    assert sum(p == -1 for p in CAPSULE_PARENTS) == 1
    assert CAPSULE_PARENTS[capsule_index("left_forearm")] == capsule_index("left_upper_arm")
    assert CAPSULE_PARENTS[capsule_index("left_calf")] == capsule_index("left_thigh")
    with pytest.raises(ValueError, match="unknown capsule"):
        capsule_index("tail")


def test_collision_pairs_skip_neighbours_and_cover_the_distal_capsules():
    pairs = collision_pairs()
    names = {(CAPSULE_NAMES[i], CAPSULE_NAMES[j]) for i, j in pairs.tolist()}
    assert ("left_upper_arm", "left_forearm") not in names and ("left_forearm", "left_upper_arm") not in names
    assert ("left_hand", "left_forearm") not in names and ("left_forearm", "left_hand") not in names
    assert ("spine1", "left_hand") in names or ("left_hand", "spine1") in names
    assert ("left_calf", "right_calf") in names or ("right_calf", "left_calf") in names
    # thighs are not checked against each other (seed A.8: they overlap in valid poses)
    assert ("left_thigh", "right_thigh") not in names and ("right_thigh", "left_thigh") not in names
    for i, j in pairs.tolist():
        assert CAPSULE_NAMES[i] in DISTAL_CAPSULES or CAPSULE_NAMES[j] in DISTAL_CAPSULES


@pytest.fixture(scope="module")
def two_bodies(anny64):
    shape = anny64.default_shape(2)
    shape[1] = torch.tensor([1.0, 0.8, 0.3, 0.9, 0.2, 0.5], dtype=D)
    return shape, fit_capsules(anny64, shape)


def test_fitted_capsules_wrap_their_vertices(anny64, two_bodies):
    shape, caps = two_bodies
    assert (caps.radius > 0.02).all() and (caps.radius < 0.2).all()
    vertices = anny64.rest_vertices(shape)
    labels = anny64.part_labels
    for c, spec in enumerate(CAPSULES):
        mask = torch.zeros_like(labels, dtype=torch.bool)
        for part in spec.parts:
            mask |= labels == part
        d = point_segment_distance(vertices[:, mask], caps.start[:, c : c + 1], caps.end[:, c : c + 1])
        # most of a part's surface lies within 1.5 radii of the axis (the chest is flatter)
        assert ((d <= 1.5 * caps.radius[:, c : c + 1]).double().mean(-1) > 0.75).all(), spec.name
    # the capsule union has about the mesh's volume
    volume = capsule_volumes(caps).sum(-1)
    mesh = anny64.measure(shape).volume_m3
    assert ((volume / mesh - 1).abs() < 0.15).all()


def _reference_fit(model, shape):
    """The capsule fit written plainly on the whole skinned T-pose mesh (fit_capsules builds
    each capsule's vertices part by part from the linear mesh instead)."""
    vertices = model.rest_vertices(shape)  # pelvis at the origin
    rest = rest_joints(model, shape)
    labels = model.part_labels
    out = []
    for spec in CAPSULES:
        mask = torch.zeros_like(labels, dtype=torch.bool)
        for part in spec.parts:
            mask |= labels == part
        v = vertices[:, mask]
        if spec.crosswise:
            a0 = v.mean(1)
            u = torch.tensor([1.0, 0.0, 0.0], dtype=v.dtype).expand_as(a0)
            t = v[..., 0] - a0[:, None, 0]
            t_lo, t_hi = t.amin(1), t.amax(1)
            band_lo, band_hi = t_lo + 0.25 * (t_hi - t_lo), t_hi - 0.25 * (t_hi - t_lo)
        else:
            a0 = rest[:, spec.joint]
            direction = (
                rest[:, spec.joint] - rest[:, J24_NAMES.index("neck")]
                if spec.name == "head"
                else rest[:, spec.child] - rest[:, spec.joint]
            )
            u = direction / direction.norm(dim=-1, keepdim=True)
            t = ((v - a0[:, None]) * u[:, None]).sum(-1)
            t_lo = t.amin(1) if spec.extend_start else torch.zeros_like(t[:, 0])
            t_hi = t.amax(1) if (spec.extend_end or spec.child is None) else direction.norm(dim=-1)
            band_lo, band_hi = t_lo + 0.2 * (t_hi - t_lo), t_hi - 0.2 * (t_hi - t_lo)
        dist = (v - (a0[:, None] + t[..., None] * u[:, None])).norm(dim=-1)
        band = (t >= band_lo[:, None]) & (t <= band_hi[:, None])
        band |= ~band.any(1, keepdim=True)
        r = torch.where(band, dist, torch.nan).nanmedian(1).values
        if spec.crosswise:
            half = ((t_hi - t_lo) / 2 - r).clamp_min(0)
            mid = a0 + ((t_hi + t_lo) / 2)[:, None] * u
            s, e = mid - half[:, None] * u, mid + half[:, None] * u
        else:
            lo = torch.minimum(t_lo + r, torch.zeros_like(r)) if spec.extend_start else t_lo
            hi = torch.maximum((t_hi - r) if (spec.extend_end or spec.child is None) else t_hi, lo)
            s, e = a0 + lo[:, None] * u, a0 + hi[:, None] * u
        out.append((s, e, r))
    return torch.stack([o[0] for o in out], 1), torch.stack([o[1] for o in out], 1), torch.stack([o[2] for o in out], 1)


def test_part_by_part_fit_equals_the_whole_mesh_fit(anny64):
    g = torch.Generator().manual_seed(3)
    shape = torch.rand(5, anny64.shape_dim, generator=g, dtype=D)
    caps = fit_capsules(anny64, shape)
    start, end, radius = _reference_fit(anny64, shape)
    for got, want in ((caps.start, start), (caps.end, end), (caps.radius, radius)):
        torch.testing.assert_close(got, want, atol=1e-12, rtol=0)
    torch.testing.assert_close(caps.rest, rest_joints(anny64, shape), atol=1e-12, rtol=0)
    # the same bodies fitted alone: batch-independent up to float round-off
    one = fit_capsules(anny64, shape[3:4])
    torch.testing.assert_close(one.radius, caps.radius[3:4], atol=1e-13, rtol=0)
    # and differentiable in the shape, with the same gradient
    grads = []
    for fit in (
        lambda s: (lambda c: (c.start, c.end, c.radius))(fit_capsules(anny64, s)),
        lambda s: _reference_fit(anny64, s),
    ):
        s = shape[:2].clone().requires_grad_()
        a, b, r = fit(s)
        (a.sum() + 2 * b.sum() + 3 * r.sum()).backward()
        grads.append(s.grad)
    torch.testing.assert_close(grads[0], grads[1], atol=1e-9, rtol=1e-9)


def test_the_radius_is_the_median_of_the_mid_segment_distances_with_and_without_autograd():
    # Without autograd the distances outside the band are masked in place; with it, in a copy;
    # either way the radius is the lower median of the in-band distances, bit for bit.
    from pressurepose.body.capsule_fit import _fit_one

    g = torch.Generator().manual_seed(4)
    v = torch.randn(6, 3, 301, generator=g, dtype=D)
    v[5, 0] = 5.0  # no vertex mid-segment: all of them count
    length = torch.full((6,), 1.0, dtype=D)
    for spec in (CAPSULES[capsule_index("left_thigh")], CAPSULES[capsule_index("pelvis")]):
        with torch.no_grad():
            r = _fit_one(spec, v, None if spec.crosswise else length)[2]
        vg = v.clone().requires_grad_()
        rg = _fit_one(spec, vg, None if spec.crosswise else length)[2]
        rg.sum().backward()
        assert torch.equal(r, rg.detach())
        if spec.crosswise:
            t = v[:, 0] - v[:, 0].mean(-1, keepdim=True)
            dist = torch.hypot(v[:, 1] - v[:, 1].mean(-1, keepdim=True), v[:, 2] - v[:, 2].mean(-1, keepdim=True))
            lo, hi = t.amin(1), t.amax(1)
            lo, hi = lo + 0.25 * (hi - lo), hi - 0.25 * (hi - lo)
        else:
            t, dist = v[:, 0], torch.hypot(v[:, 1], v[:, 2])
            lo, hi = torch.full((6,), 0.2, dtype=D), torch.full((6,), 0.8, dtype=D)
        band = (t >= lo[:, None]) & (t <= hi[:, None])
        band |= ~band.any(1, keepdim=True)
        want = torch.stack([d[b].sort().values[(int(b.sum()) - 1) // 2] for d, b in zip(dist, band)])
        assert torch.equal(r, want)


def test_fitted_capsules_are_mirror_symmetric_for_a_symmetric_body(anny64, two_bodies):
    _, caps = two_bodies
    flip = torch.tensor([-1.0, 1.0, 1.0], dtype=D)
    for name in CAPSULE_NAMES:
        if name.startswith("left_"):
            i, j = capsule_index(name), capsule_index("right_" + name[5:])
            assert caps.radius[0, i] == pytest.approx(caps.radius[0, j].item(), abs=2e-3)
            torch.testing.assert_close(caps.end[0, i] * flip, caps.end[0, j], atol=5e-3, rtol=0)


@pytest.mark.slow
def test_fast_volume_agrees_with_2mm_voxelisation(two_bodies):
    _, caps = two_bodies
    one = Capsules(caps.start[1:], caps.end[1:], caps.radius[1:], caps.rest[1:])
    fast = capsule_volumes(one)
    voxel = capsule_volumes(one, method="voxel", resolution=0.002)
    assert ((fast - voxel).abs() / voxel).max() < 0.01
    # overlap sharing: the shared volumes sum to less than the capsules' own volumes
    assert fast.sum() < one.analytic_volume().sum()


def test_volume_method_is_validated(two_bodies):
    with pytest.raises(ValueError, match="unknown volume method"):
        capsule_volumes(two_bodies[1], method="guess")
    with pytest.raises(ValueError, match="resolution"):
        capsule_volumes(two_bodies[1], method="voxel", resolution=0)


def test_masses_sum_to_the_body_mass_and_follow_the_segments(anny64):
    light = anny64.shape_from_dict({"gender": 0.0, "weight": 0.2})
    heavy = anny64.shape_from_dict({"gender": 0.0, "weight": 0.9})
    body = build_capsule_body(anny64, torch.cat([light, heavy]))
    mass = anny64.measure(torch.cat([light, heavy])).mass_kg
    torch.testing.assert_close(body.mass_kg.sum(-1), mass, rtol=1e-9, atol=0)
    torch.testing.assert_close(body.body_mass_kg, mass, rtol=1e-9, atol=0)
    assert (body.mass_kg > 0).all()
    # heavier shape -> heavier capsules: the trunk and every limb segment that gains volume
    # (hands, feet and head barely grow; the common scale to the mesh mass may leave them even)
    assert mass[1] > mass[0] + 5
    trunk = [capsule_index(n) for n in ("pelvis", "spine1", "spine2", "spine3", "left_collar", "right_collar")]
    assert body.mass_kg[1, trunk].sum() > body.mass_kg[0, trunk].sum() + 2
    for name in ("spine1", "left_thigh", "right_thigh", "left_upper_arm", "right_upper_arm", "left_calf"):
        assert body.mass_kg[1, capsule_index(name)] > body.mass_kg[0, capsule_index(name)], name
    # a male body's segment shares are close to Tozeren's (REFERENCE.md) for the average shape
    avg = build_capsule_body(anny64, anny64.shape_from_dict({"gender": 0.0}))
    share = avg.mass_kg[0] / avg.mass_kg[0].sum()
    thigh = share[capsule_index("left_thigh")]
    trunk = sum(
        share[capsule_index(n)] for n in ("pelvis", "spine1", "spine2", "spine3", "left_collar", "right_collar")
    )
    assert trunk == pytest.approx(0.483, rel=0.05)
    assert thigh == pytest.approx(0.105, rel=0.05)


def test_stiffness_damping_and_home_pose(anny64):
    shape = anny64.shape_from_dict({"gender": 1.0})
    body = build_capsule_body(anny64, shape)
    ratio = body.body_mass_kg[0] / 70.45
    j = J24_NAMES.index
    assert body.stiffness[0, j("left_knee") - 1] == pytest.approx(3.0 * ratio.item())
    assert body.stiffness[0, j("spine2") - 1] == pytest.approx(200.0 * ratio.item())
    # collar and shoulder in series give the seed's 4 N m/rad shoulder
    kc, ks = JOINT_STIFFNESS["collar"], JOINT_STIFFNESS["shoulder"]
    assert 1 / (1 / kc + 1 / ks) == pytest.approx(4.0)
    assert body.stiffness[0, j("left_foot") - 1] == 0  # toes are not simulated
    torch.testing.assert_close(body.damping, 15 * body.stiffness)
    # home pose: arms hang along the body (wrists below the shoulders), legs straight
    rest = body.capsules.rest
    _, pos = forward_kinematics(rest, home_pose(1))
    for side in ("left", "right"):
        arm = pos[0, j(f"{side}_wrist")] - pos[0, j(f"{side}_shoulder")]
        assert arm[1] < -0.9 * arm.norm()  # points down (toward the feet)
    torch.testing.assert_close(pos[0, j("left_ankle")], rest[0, j("left_ankle")])


def test_t_pose_is_free_of_self_collision(two_bodies):
    _, caps = two_bodies
    a, b = caps.posed(torch.zeros(2, 23, 3, dtype=D))
    assert (capsule_clearance(a, b, caps.radius, collision_pairs()) > 0).all()


def test_posed_capsules_move_with_their_joint(two_bodies):
    _, caps = two_bodies
    pose = torch.zeros(2, 23, 3, dtype=D)
    pose[:, J24_NAMES.index("left_elbow") - 1, 1] = -math.pi / 2
    a, b = caps.posed(pose)
    fore, upper = capsule_index("left_forearm"), capsule_index("left_upper_arm")
    # the upper arm stays, the forearm turns 90 degrees with its length kept
    torch.testing.assert_close(a[:, upper], caps.start[:, upper])
    torch.testing.assert_close((b - a)[:, fore].norm(dim=-1), caps.length[:, fore])
    cos = ((b - a)[:, fore] * (caps.end - caps.start)[:, fore]).sum(-1) / caps.length[:, fore] ** 2
    torch.testing.assert_close(cos, torch.zeros(2, dtype=D), atol=1e-9, rtol=0)


def test_capsules_of_the_smpl_backend(smpl64):
    body = build_capsule_body(smpl64, torch.zeros(1, 10, dtype=D))
    assert torch.isfinite(body.mass_kg).all() and (body.mass_kg > 0).all()
    torch.testing.assert_close(body.mass_kg.sum(-1), smpl64.measure(torch.zeros(1, 10, dtype=D)).mass_kg)


def test_bad_shape_is_refused(anny64):
    with pytest.raises(ValueError, match="phenotypes"):
        build_capsule_body(anny64, torch.full((1, 6), 2.0, dtype=D))
