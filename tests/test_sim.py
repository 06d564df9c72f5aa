"""Physics: sim #2 (foundation), sensor, label maps, sim #1 (MuJoCo) - physical invariants."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from pressurepose.body.capsules import home_pose
from pressurepose.body.params import BodyParams
from pressurepose.errors import UserError
from pressurepose.maps import EMPTY_HEIGHT_M, depth_map, mesh_centroid
from pressurepose.mat import MatSpec
from pressurepose.sim.articulated_config import ArticulatedConfig
from pressurepose.sim.foundation import FAIL_NO_SUPPORT, simulate_pressure
from pressurepose.sim.mattress import GRAVITY_M_S2, MMHG_PA, MattressParams
from pressurepose.sim.objects import capsule_mesh, settle_capsule
from pressurepose.sim.sensor import label_maps, sensing_area, taxel_reading

MAT = MatSpec()
D = torch.float64


@pytest.fixture(scope="module")
def supine(anny64):
    """Two supine bodies (male, female) in the home pose, above the middle of the mat."""
    shape = anny64.default_shape(2)
    shape[1, 0] = 1.0
    p = BodyParams.zeros(2, shape).replace(
        pose=home_pose(2, dtype=D), root_translation=torch.tensor([[0.85, 0.37, 0.15]] * 2, dtype=D)
    )
    out = anny64(p)
    return out.vertices, out.faces, anny64.measure(shape).mass_kg


@pytest.fixture(scope="module")
def rest(supine):
    v, f, m = supine
    return simulate_pressure(v, f, m)


def test_force_balance_and_moments(supine, rest):
    v, f, m = supine
    assert rest.failure == ["", ""]
    image = sensing_area(rest.pressure_pa)
    force = image.sum((1, 2)) * MAT.taxel_area_m2
    weight = m * GRAVITY_M_S2
    assert torch.allclose(force, weight, rtol=0.01)
    # Moments: the centre of pressure lies under the centre of mass.
    com = mesh_centroid(rest.vertices, f)
    centres = torch.from_numpy(MAT.taxel_centres_m(covered=True)).to(D)
    p = rest.pressure_pa
    cop = (p[..., None] * centres).sum((1, 2)) / p.sum((1, 2))[:, None]
    assert (cop - com[:, :2]).abs().max() < 2e-3


def test_pressure_nonnegative_and_zero_away_from_contact(rest):
    p = rest.pressure_pa
    assert torch.isfinite(p).all() and (p >= 0).all()
    contact = (rest.foundation_pa > 0).to(D)[:, None]
    # The spread reaches 3 sigma; beyond it (plus a taxel) there is no pressure.
    reach = math.ceil(3 * MattressParams().spread_m / (MAT.pitch_col_m / rest.sub)) + rest.sub
    near = torch.nn.functional.max_pool2d(contact, 2 * reach + 1, stride=1, padding=reach)
    near = torch.nn.functional.max_pool2d(near, rest.sub)[:, 0] > 0  # per taxel
    assert (p[~near] == 0).all()
    assert (p[near] > 0).any()


def test_mirrored_body_gives_mirrored_image(supine):
    v, f, m = supine
    width = MAT.sensing_width_m
    mirrored = v.clone()
    mirrored[..., 1] = width - mirrored[..., 1]
    a = simulate_pressure(v[:1], f, m[:1]).pressure_pa
    b = simulate_pressure(mirrored[:1], f.flip(-1), m[:1]).pressure_pa
    assert torch.allclose(a, b.flip(-1), atol=1e-6 * float(a.max()))


def _capsule(mass, length=0.3, radius=0.06, **kw):
    v, f = capsule_mesh(length, radius, centre=(0.9, 0.37, radius + 0.01))
    return simulate_pressure(v[None], f, torch.tensor([mass], dtype=D), **kw)


def test_heavier_sinks_deeper_and_stiffer_is_smaller():
    light, heavy = _capsule(5.0), _capsule(10.0)
    assert heavy.max_compression_m > light.max_compression_m > 0
    soft = _capsule(8.0)
    stiff = _capsule(8.0, params=MattressParams(k1_pa_per_m=8e4))
    assert (stiff.foundation_pa > 0).sum() < (soft.foundation_pa > 0).sum()
    assert stiff.max_compression_m < soft.max_compression_m


def test_capsule_force_equals_weight_exactly():
    for mass in (1.3, 4.5, 18.0):
        res = _capsule(mass)
        assert res.failure == [""]
        assert math.isclose(float(res.pressure_pa.sum()) * MAT.taxel_area_m2, mass * GRAVITY_M_S2, rel_tol=1e-3)


def test_gradients_flow_to_vertices_mass_and_parameters():
    v, f = capsule_mesh(0.3, 0.06, centre=(0.9, 0.37, 0.07), n_around=16, n_cap=4, n_along=8)
    v = v[None].clone().requires_grad_(True)
    mass = torch.tensor([8.0], dtype=D, requires_grad=True)
    k1 = torch.tensor(2.0e4, dtype=D, requires_grad=True)
    res = simulate_pressure(v, f, mass, params=MattressParams(k1_pa_per_m=k1))
    depth = res.max_compression_m.sum()
    gv, gm, gk = torch.autograd.grad(depth, (v, mass, k1))
    assert torch.isfinite(gv).all() and gv.abs().sum() > 0
    # Finite differences of the rest depth in the mass and the stiffness (both smooth there).
    h = 1e-4
    for value, grad, make in (
        (8.0, gm, lambda x: _capsule_depth(v.detach(), f, x, 2.0e4)),
        (2.0e4, gk, lambda x: _capsule_depth(v.detach(), f, 8.0, x)),
    ):
        fd = (make(value * (1 + h)) - make(value * (1 - h))) / (2 * h * value)
        assert math.isclose(float(grad), fd, rel_tol=0.05), (float(grad), fd)


def _capsule_depth(v, f, mass, k1):
    res = simulate_pressure(v, f, torch.tensor([mass], dtype=D), params=MattressParams(k1_pa_per_m=k1))
    return float(res.max_compression_m)


def test_bad_inputs_are_clear():
    v, f = capsule_mesh(0.3, 0.06, centre=(0.9, 0.37, 0.07))
    with pytest.raises(ValueError, match="NaN"):
        bad = v.clone()
        bad[0, 0] = float("nan")
        simulate_pressure(bad[None], f, torch.tensor([5.0], dtype=D))
    with pytest.raises(ValueError, match="mass"):
        simulate_pressure(v[None], f, torch.tensor([0.0], dtype=D))
    off, _ = capsule_mesh(0.3, 0.06, centre=(5.0, 5.0, 0.07))
    res = simulate_pressure(off[None], f, torch.tensor([5.0], dtype=D))
    assert res.failure == [FAIL_NO_SUPPORT]
    assert torch.isfinite(res.pressure_pa).all() and (res.pressure_pa == 0).all()


def test_sensor_law_saturation_and_noise():
    params = MattressParams(c0_mmhg=-2.0, c1_mmhg_per_mm=1.5, c2_mmhg_per_mm2=0.01)
    p = torch.tensor([[[0.0, 10 * MMHG_PA, 50 * MMHG_PA, 500 * MMHG_PA]]], dtype=D)
    r = taxel_reading(p, params)
    d = p / params.mat_stiffness_pa_per_mm
    expected = (-2.0 + 1.5 * d + 0.01 * d**2).clamp(0, 100)
    expected[..., 0] = 0.0
    assert torch.allclose(r, expected)
    assert float(r[..., 3]) == 100.0
    noisy = params.replace(noise_mmhg=2.0)
    g1, g2 = torch.Generator().manual_seed(1), torch.Generator().manual_seed(1)
    a, b = taxel_reading(p, noisy, generator=g1), taxel_reading(p, noisy, generator=g2)
    assert torch.equal(a, b) and not torch.equal(a, r) and float(a[..., 0]) == 0.0
    with pytest.raises(ValueError, match=">= 0"):
        taxel_reading(-p - 1.0)
    with pytest.raises(ValueError, match="NaN"):
        taxel_reading(p * float("nan"))


def test_sensor_floor_zeroes_readings_below_it_only():
    # Readings (c0 = -1, c1 = 1): 0, 0.5, 2, 3.3, 3.4, 20 mmHg; with a 3.31 mmHg floor the first four read 0.
    d = torch.tensor([[[0.0, 1.5, 3.0, 4.3, 4.4, 21.0]]], dtype=D)
    p = d * MattressParams().mat_stiffness_pa_per_mm
    plain = taxel_reading(p, MattressParams())
    floored = taxel_reading(p, MattressParams(floor_mmhg=3.31))
    assert torch.allclose(plain, torch.tensor([[[0.0, 0.5, 2.0, 3.3, 3.4, 20.0]]], dtype=D))
    assert torch.equal(floored, torch.where(plain >= 3.31, plain, torch.zeros_like(plain)))
    assert float(floored[..., 3]) == 0.0 and float(floored[..., 4]) == float(plain[..., 4])
    # Both PmatData presets read from their mattress's floor; files without the field read as before.
    assert MattressParams.preset("sponge").floor_mmhg == 3.31 and MattressParams.preset("air").floor_mmhg == 3.61
    assert (
        "floor_mmhg" not in MattressParams().to_dict()
        and MattressParams.preset("sponge").to_dict()["floor_mmhg"] == 3.31
    )
    for bad in (-1.0, 60.0, float("nan")):
        with pytest.raises(UserError, match="floor_mmhg"):
            MattressParams(floor_mmhg=bad)


def test_depth_and_contact_maps_of_a_capsule():
    r = 0.05
    v, f = capsule_mesh(0.4, r, centre=(0.9, 0.37, r - 0.02), n_around=64, n_along=40)
    q, c = label_maps(v[None], f)
    assert q.shape == (1, 64, 27)
    # The lowest point is 2 cm below the top; taxels far from the capsule are empty.
    assert math.isclose(float(q.min()), -20.0, abs_tol=0.5)
    assert float(q.max()) == EMPTY_HEIGHT_M * 1000
    assert torch.equal(c, (q < 0).to(q.dtype))
    # Taxels along the axis: contact; across it the contact band is about 2 sqrt(2 r d - d^2).
    row = int(0.9 / MAT.pitch_row_m)
    band = float(c[0, row].sum()) * MAT.pitch_col_m
    assert abs(band - 2 * math.sqrt(2 * r * 0.02 - 0.02**2)) < 2 * MAT.pitch_col_m


def test_depth_map_is_differentiable():
    v, f = capsule_mesh(0.2, 0.05, centre=(0.9, 0.37, 0.03), n_around=12, n_cap=3, n_along=6)
    # Jitter breaks the exact ties of a symmetric mesh (where the minimum has no derivative).
    v = v + 1e-4 * torch.randn(v.shape, generator=torch.Generator().manual_seed(0), dtype=D)
    v = v[None].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: depth_map(x, f, MAT).clamp(max=0), (v,), eps=1e-7, atol=1e-4)


def test_underside_patches_holes_only_between_filled_cells():
    h = torch.full((1, 5, 5), EMPTY_HEIGHT_M, dtype=D)
    h[0, 1:4, 1:4] = -0.01
    h[0, 2, 2] = EMPTY_HEIGHT_M
    from pressurepose.maps import patch_holes

    out = patch_holes(h)
    assert float(out[0, 2, 2]) == pytest.approx(-0.01)
    assert float(out[0, 0, 0]) == EMPTY_HEIGHT_M and float(out[0, 0, 2]) == EMPTY_HEIGHT_M


def test_mattress_params_round_trip_and_bad_files(tmp_path):
    p = MattressParams(k1_pa_per_m=3.0e4, spread_m=0.01)
    path = tmp_path / "bed.json"
    p.save(path)
    assert MattressParams.load(path) == p
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="not readable"):
        MattressParams.load(tmp_path / "bad.json")
    (tmp_path / "unknown.json").write_text(json.dumps({"format": "pressurepose.mattress/1", "params": {"k9": 1}}))
    with pytest.raises(ValueError, match="unknown mattress parameters k9"):
        MattressParams.load(tmp_path / "unknown.json")
    with pytest.raises(ValueError, match="does not exist"):
        MattressParams.load(tmp_path / "missing.json")
    with pytest.raises(ValueError, match="k1_pa_per_m"):
        MattressParams(k1_pa_per_m=-1.0)
    with pytest.raises(ValueError, match="finite"):
        MattressParams(spread_m=float("nan"))


@pytest.mark.parametrize(
    "length,radius,mass", [(0.2, 0.05, 1.3), (0.2, 0.05, 9.1), (0.4, 0.06, 4.5), (0.4, 0.06, 18.0)]
)
def test_sim1_and_sim2_sink_alike(length, radius, mass):
    v, f = capsule_mesh(length, radius, centre=(0.9, 0.37, radius + 0.01))
    sim2 = float(simulate_pressure(v[None], f, torch.tensor([mass], dtype=D)).max_compression_m)
    sim1 = settle_capsule(length, radius, mass)["sink_m"]
    assert abs(sim1 - sim2) / sim2 < 0.10, (sim1, sim2)


# --- sim #1 (MuJoCo) ------------------------------------------------------------------------
from pressurepose.sampling.partitions import PARTITIONS, SamplingConfig  # noqa: E402
from pressurepose.sampling.sampler import PoseSampler  # noqa: E402
from pressurepose.sim.capsule_foundation import hold_roll_torque  # noqa: E402
from pressurepose.sim.mjcf import build_mjcf  # noqa: E402
from pressurepose.sim.run import settle_config_for  # noqa: E402
from pressurepose.sim.settle import settle  # noqa: E402
from pressurepose.sim.settle_config import REASON_OFF_BED, TRUNK, SettleConfig  # noqa: E402


def _initial(model, partition, gender="male", indices=(0, 1)):
    over = partition in ("hands_behind_head", "prone_hands_up")
    cfg = SamplingConfig(partition=partition, gender=gender, over_bed=over, seed=0)
    return PoseSampler(model, cfg).sample(list(indices)).params


@pytest.mark.slow
@pytest.mark.parametrize("partition", sorted(PARTITIONS))
def test_sim1_settles_typical_poses_of_every_partition(anny64, partition):
    over = partition in ("hands_behind_head", "prone_hands_up")
    poses = PoseSampler(anny64, SamplingConfig(partition=partition, gender="male", over_bed=over)).sample([0, 1, 3])
    ok = 0
    for bed in set(poses.beds()):  # the half_sitting partition's samples rest on raised beds
        rows = [i for i, b in enumerate(poses.beds()) if b == bed]
        params = BodyParams(
            **{f: getattr(poses.params, f)[rows] for f in ("shape", "root_rotation", "root_translation", "pose")}
        )
        res = settle(anny64, params, bed=bed, config=settle_config_for(partition))
        for name in ("root_rotation", "root_translation", "pose"):
            assert torch.isfinite(getattr(res.params, name)).all()
        assert np.isfinite(res.sink_m).all() and (res.steps <= SettleConfig().max_steps).all()
        ok += int(res.ok.sum())
        for i in np.flatnonzero(res.ok):
            # At rest on the mattress: slow, touching, not sunk through.
            assert res.max_speed[i] < 0.05 and res.max_accel[i] < 0.5
            assert 0.0 < res.sink_m[i] < MattressParams().thickness_m
            assert res.touch_step[i] >= 0
        # The pelvis stays over the bed and ends near the mattress top.
        z = res.params.root_translation[torch.from_numpy(res.ok), 2]
        assert (z > -0.1).all() and (z < 0.4).all()
    assert ok >= 2


def test_trunk_roll_hold_torque_and_energy():
    """The hold pulls the pelvis's roll about the bed's long axis back, shared by the trunk
    capsules' masses, stores 1/2 k roll^2, and ignores a turn about the vertical."""
    cfg = SettleConfig(hold_roll_m=0.5, hold_time_s=0.1)
    C = 20
    mass = np.arange(1.0, C + 1.0)[None]
    weight = np.array([700.0])
    k = 0.5 * 700.0
    R0 = np.eye(3)[None]
    for theta in (0.3, -1.2, 2.5):
        c, s = math.cos(theta), math.sin(theta)
        Rx = np.array([[[1, 0, 0], [0, c, -s], [0, s, c]]])
        cv = np.zeros((1, C, 6))
        cv[0, :, 0] = 0.4  # rolling at 0.4 rad/s
        ft, e = hold_roll_torque(np.zeros((1, C, 6)), Rx, R0, cv, mass, weight, cfg)
        tau = ft[0, TRUNK, 3]
        assert math.isclose(tau.sum(), -k * (theta + 0.1 * 0.4), rel_tol=1e-12)
        np.testing.assert_allclose(tau / tau.sum(), mass[0, TRUNK] / mass[0, TRUNK].sum())
        assert np.count_nonzero(ft) == len(TRUNK) and math.isclose(e[0], 0.5 * k * theta**2, rel_tol=1e-12)
    yaw = np.array([[[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]])
    ft, e = hold_roll_torque(np.zeros((1, C, 6)), yaw, R0, np.zeros((1, C, 6)), mass, weight, cfg)
    assert np.abs(ft).max() < 1e-12 and e[0] < 1e-20
    with pytest.raises(ValueError, match="hold_roll_m"):
        SettleConfig(hold_roll_m=-1.0)
    assert settle_config_for("lateral_straight").hold_roll_m > 0 and settle_config_for("lateral").hold_roll_m == 0


def test_trunk_roll_hold_keeps_straight_legged_side_lying_bodies_on_their_side(anny64):
    from pressurepose.eval.real import roll_deg

    cfg = SamplingConfig(partition="lateral_straight", gender="female", seed=5)
    params = PoseSampler(anny64, cfg).sample([3, 5]).params  # both passive bodies roll onto their back
    start = roll_deg(params.root_rotation)
    passive = settle(anny64, params)
    held = settle(anny64, params, config=settle_config_for("lateral_straight"))
    assert passive.ok.all() and held.ok.all()
    assert (roll_deg(passive.params.root_rotation).abs() < 30).all()
    assert ((roll_deg(held.params.root_rotation) - start).abs() < 10).all() and (start.abs() > 70).all()
    assert (held.sink_m > 0).all()
    # The whole pipeline, as `generate` calls it (one bed per sample), holds them too: they rest
    # on their side after sim #2.
    from pressurepose.bed import BedShape
    from pressurepose.sim.run import simulate_poses

    sim = simulate_poses(
        anny64, params, bed=[BedShape(), BedShape()], settle_config=settle_config_for("lateral_straight")
    )
    assert sim.reason == ["", ""]
    assert (roll_deg(sim.params.root_rotation).abs() > 45).all()


def test_sim1_is_deterministic_and_batch_independent(anny64):
    # Bitwise on purpose: settle guarantees it by construction (its capsule bodies are built
    # one at a time, and the batched force code has no reduction whose rounding could depend
    # on the batch; test_sim1_batch.py checks the pieces), so any difference is a bug.
    # batch=2 with 3 bodies: the third starts in whichever slot frees first (slot refill).
    params = _initial(anny64, "supine", indices=(1, 2, 4))
    a = settle(anny64, params, batch=2)
    b = settle(anny64, params, batch=1)
    assert a.reason == b.reason and (a.steps == b.steps).all() and len(set(a.steps)) == 3
    assert torch.equal(a.params.pose, b.params.pose) and torch.equal(
        a.params.root_translation, b.params.root_translation
    )
    # Alone, a body settles exactly as it does among others.
    c = settle(
        anny64,
        params.replace(**{k: getattr(params, k)[2:] for k in ("shape", "root_rotation", "root_translation", "pose")}),
    )
    assert c.steps[0] == a.steps[2] and torch.equal(c.params.pose[0], a.params.pose[2])


def test_sim1_rejects_bodies_off_the_bed_and_bad_input(anny64):
    params = _initial(anny64, "supine", indices=(0,))
    off = params.replace(root_translation=params.root_translation + torch.tensor([[5.0, 0.0, 0.0]], dtype=D))
    res = settle(anny64, off)
    assert res.reason == [REASON_OFF_BED] and not res.ok[0]
    bad = params.replace(pose=params.pose * float("nan"))
    with pytest.raises(ValueError, match="NaN"):
        settle(anny64, bad)


def test_mjcf_has_the_capsule_chain(anny64):
    import mujoco

    from pressurepose.body.capsules import build_capsule_body

    params = _initial(anny64, "supine", indices=(0,))
    body = build_capsule_body(anny64, params.shape)
    model = mujoco.MjModel.from_xml_string(build_mjcf(body, 0, SettleConfig(), mat=MAT))
    assert model.nv == 55  # free root 6 + 15 ball x 3 + 4 hinges
    # masses are written with 9 significant digits: each within 5e-9 of itself, so is their sum
    assert math.isclose(float(model.body_subtreemass[0]), float(body.mass_kg.sum()), rel_tol=5e-9)
    hinge = mujoco.mjtJoint.mjJNT_HINGE
    assert int((model.jnt_type == hinge).sum()) == 4
    assert model.jnt_stiffness.max() > 0 and (model.dof_damping >= 0).all()


@pytest.mark.slow
def test_sim2_matches_an_explicit_dynamic_simulation():
    from pressurepose.sim.reference import dynamic_reference, image_correlation

    v, f = capsule_mesh(0.4, 0.06, centre=(0.9, 0.37, 0.07))
    v[:, 2] += 0.05 * (v[:, 0] - 0.9)  # tilted: the solver must find the pitch
    ref = dynamic_reference(v, f, 9.1)
    quasi = simulate_pressure(v[None], f, torch.tensor([9.1], dtype=D))
    assert ref.at_rest
    assert image_correlation(ref.pressure_pa, quasi.pressure_pa[0]) >= 0.95
    force = float(quasi.pressure_pa.sum()) * MAT.taxel_area_m2
    assert abs(ref.force_n - force) / force < 0.02


def test_pipeline_parameters_reproduce_the_mesh_at_rest(anny64):
    from pressurepose.sim.run import simulate_poses

    params = _initial(anny64, "general", indices=(1,))
    sim = simulate_poses(anny64, params)
    assert sim.reason == [""]
    again = anny64(sim.params).vertices
    assert (again - sim.vertices).abs().max() < 1e-6


# --- head of the bed raised -------------------------------------------------------------------
from pressurepose.bed import BedShape  # noqa: E402
from pressurepose.sim.foundation import FAIL_SLIDES  # noqa: E402


def test_bed_shape_round_trip_and_bad_angles():
    bed = BedShape(40.0)
    pts = torch.tensor([[0.2, 0.3, 0.05], [0.45, 0.1, 0.02], [1.2, 0.5, 0.1], [0.3, 0.2, -0.03]], dtype=D)
    world = bed.to_world(pts, MAT)
    assert torch.allclose(bed.to_surface(world, MAT), pts, atol=1e-12)
    assert math.isclose(bed.hinge_x(MAT), 16 * MAT.pitch_row_m)
    head_point = bed.to_world(torch.tensor([[bed.hinge_x(MAT) - 1.0, 0.0, 0.0]], dtype=D), MAT)[0]
    assert math.isclose(float(head_point[2]), math.sin(math.radians(40.0)), rel_tol=1e-12)
    for bad in (-5.0, 95.0, float("nan")):
        with pytest.raises(ValueError, match="head_angle_deg"):
            BedShape(bad)


@pytest.mark.parametrize("angle", [0.0, 10.0, 20.0])
def test_raised_bed_normal_force_and_friction_balance_the_weight(angle):
    bed = BedShape(angle)
    v, f = capsule_mesh(0.3, 0.06, centre=(0.22, 0.37, 0.065))  # on the head section
    res = simulate_pressure(bed.to_world(v, MAT)[None], f, torch.tensor([9.0], dtype=D), bed=bed)
    assert res.failure == [""]
    normal = float(res.foundation_pa.sum()) * MAT.taxel_area_m2 / res.sub**2
    phi = math.radians(angle)
    assert math.isclose(normal, 9.0 * GRAVITY_M_S2 * math.cos(phi), rel_tol=1e-4)
    assert math.isclose(-float(res.friction_ratio), math.tan(phi), rel_tol=1e-4, abs_tol=1e-9)
    steep = BedShape(35.0)  # tan 35 deg > the sheet's friction 0.5: it slides
    res = simulate_pressure(steep.to_world(v, MAT)[None], f, torch.tensor([9.0], dtype=D), bed=steep)
    assert res.failure == [FAIL_SLIDES] and (res.pressure_pa == 0).all()


def test_sim1_and_sim2_rest_a_half_sitting_body_on_a_raised_bed(anny64):
    from pressurepose.sampling.sitting import half_sitting_params
    from pressurepose.sim.run import simulate_poses

    bed = BedShape(30.0)
    params = half_sitting_params(anny64, anny64.default_shape(1), bed, MAT)
    sim = simulate_poses(anny64, params, bed=bed)
    assert sim.reason == [""]
    rows = (sim.pressure_mmhg[0].sum(-1) > 0).nonzero().flatten()
    assert int(rows.min()) < 16 < int(rows.max())  # loads on both sides of the hinge (row 16)
    assert (sim.depth_mm[0] < 0).sum() > 50 and torch.equal(sim.contact, (sim.depth_mm < 0).to(sim.contact.dtype))
    # The articulated settling engine rests it on the raised bed itself (no MuJoCo: its steps
    # are its re-posings; `sim.raised`, tests/test_raised_rest.py), loading both sections too.
    # Settled within the re-posing cap (a body still moving there reports cap + 1), in fewer steps
    # than MuJoCo's; the count itself moves with the machine's round-off (21 on an AVX2 CPU, 22 on
    # an AVX-512 one), so it is not pinned.
    again = simulate_poses(anny64, params, bed=bed, settle="articulated")
    cap = ArticulatedConfig().outer
    assert again.reason == [""] and 0 < int(again.settle_steps[0]) <= cap < int(sim.settle_steps[0])
    rows = (again.pressure_mmhg[0].sum(-1) > 0).nonzero().flatten()
    assert int(rows.min()) < 16 < int(rows.max())


def test_simulation_never_converts_the_callers_model(anny32):
    from pressurepose.sim.settle import as_float64

    copy64 = as_float64(anny32)
    assert anny32.dtype == torch.float32 and copy64.dtype == torch.float64


def _lowest_point_reference(a, b, r, x, y, n=4001):
    """Lowest surface point of the capsule (a, b, r) on the vertical line through (x, y), by
    brute force: the minimum over many axis points of the lowest point of the ball there."""
    t = np.linspace(0.0, 1.0, n)[:, None]
    p = a + t * (b - a)
    d2 = (p[:, 0] - x) ** 2 + (p[:, 1] - y) ** 2
    inside = d2 <= r * r
    return float((p[inside, 2] - np.sqrt(r * r - d2[inside])).min()) if inside.any() else math.inf


def test_sim1_underside_matches_a_brute_force_search():
    from pressurepose.sim.capsule_foundation import CapsuleFoundation

    found = CapsuleFoundation(MAT, MattressParams())
    rng = np.random.default_rng(3)
    centre = np.array([0.9, 0.4, 0.0])
    caps = []
    for _ in range(12):  # random orientations, partly below the top
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        c = centre + np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2), rng.uniform(-0.02, 0.05)])
        half = rng.uniform(0.0, 0.2)
        caps.append((c - half * u, c + half * u, rng.uniform(0.03, 0.07)))
    caps.append((centre + [0, 0, 0.01], centre + [0, 0, 0.3], 0.05))  # upright
    caps.append((centre + [0, 0, 0.3], centre + [0, 0, 0.01], 0.05))  # upright, ends swapped
    caps.append((centre - [0.2, 0, -0.02], centre + [0.2, 0, 0.02], 0.06))  # horizontal
    a = np.array([c[0] for c in caps])
    b = np.array([c[1] for c in caps])
    r = np.array([c[2] for c in caps])
    cap, node, x, y, z = found.underside(a, b, r)
    got = {(int(c), int(k)): float(h) for c, k, h in zip(cap, node, z)}
    assert (z < 0).all() and len(got) == len(z) > 100
    checked = 0
    for c in range(len(caps)):
        # Every node of the grid near the capsule: inside the returned set exactly when the
        # brute-force lowest point is below the top (away from round-off at the boundary).
        xs = found.x0 + (np.arange(found.nr) + 0.5) * found.hx
        ys = found.y0 + (np.arange(found.nc) + 0.5) * found.hy
        near_x = np.flatnonzero(np.abs(xs - (a[c, 0] + b[c, 0]) / 2) < 0.35)
        near_y = np.flatnonzero(np.abs(ys - (a[c, 1] + b[c, 1]) / 2) < 0.35)
        for i in near_x:
            for j in near_y:
                ref = _lowest_point_reference(a[c], b[c], r[c], xs[i], ys[j])
                key = (c, int(i * found.nc + j))
                if ref < -1e-5:
                    assert key in got, (c, i, j, ref)
                    assert abs(got[key] - ref) < 1e-5, (c, got[key], ref)
                    checked += 1
                elif ref > 1e-5:
                    assert key not in got, (c, i, j, ref)
    assert checked == len(got) - sum(1 for (c, _), h in got.items() if h > -1e-5)
