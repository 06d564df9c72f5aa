import dataclasses
import math
import subprocess
import sys

import numpy as np
import pytest
import torch

from pressurepose.body.capsules import capsule_clearance, collision_pairs, fit_capsules
from pressurepose.body.joints import J24_NAMES
from pressurepose.body.kinematics import forward_kinematics
from pressurepose.body.limits import JointLimits
from pressurepose.body.params import root_matrix
from pressurepose.mat import MatSpec
from pressurepose.sampling import PARTITIONS, PoseSampler, SamplingConfig, UnreachableConstraints, get_partition
from pressurepose.sampling.partitions import (
    FACE_DOWN_LEG_CELLS,
    FACE_DOWN_LEG_CELLS_OVER_BED,
    FACE_DOWN_ROLL_RAD,
    HEIGHT_TOLERANCE_M,
)
from pressurepose.sampling.shapes import draw_shape, shape_bounds

J = J24_NAMES.index
# Chi-square critical values at p = 0.01 (df = 3 and df = 7).
CHI2_CRIT = {3: 11.345, 7: 18.475}


@pytest.fixture(scope="module")
def anny(anny32):
    return anny32


_CACHE = {}


def draw(model, n, **kwargs):
    key = (n, tuple(sorted(kwargs.items())))
    if key not in _CACHE:
        cfg = SamplingConfig(**kwargs)
        _CACHE[key] = PoseSampler(model, cfg).sample(range(n))
    return _CACHE[key]


def roll_frame(poses):
    """Joints relative to the pelvis, yaw undone: x along the body toward the foot, z height."""
    yaw = torch.as_tensor(poses.root_draw[:, 1])
    c, s = torch.cos(yaw), torch.sin(yaw)
    d = poses.joints - poses.params.root_translation[:, None]
    return torch.stack(
        [c[:, None] * d[..., 0] + s[:, None] * d[..., 1], -s[:, None] * d[..., 0] + c[:, None] * d[..., 1], d[..., 2]],
        -1,
    )


def body_axes(poses):
    R = root_matrix(poses.params.root_rotation)
    return (poses.joints - poses.params.root_translation[:, None]) @ R


def limb_cells(poses):
    """Cells recomputed from the joints: (B, 4)."""
    p = roll_frame(poses)
    out = []
    for side in ("left", "right"):
        hip, knee, ankle = (p[:, J(f"{side}_{n}")] for n in ("hip", "knee", "ankle"))
        L = (knee - hip).norm(dim=-1) + (ankle - knee).norm(dim=-1)
        drop = ankle[:, 0] - hip[:, 0]
        assert (drop >= 0).all(), "an ankle lies above its hip"
        out.append((drop / (L / 4)).floor().clamp(0, 3))
    for side in ("left", "right"):
        sh, el, wr = (p[:, J(f"{side}_{n}")] for n in ("shoulder", "elbow", "wrist"))
        A = (el - sh).norm(dim=-1) + (wr - el).norm(dim=-1)
        rise = -(wr[:, 0] - sh[:, 0])
        out.append(3 - (rise / (A / 4)).floor().clamp(-4, 3))
    return torch.stack(out, -1).long().numpy()


def assert_collision_free(model, poses, checked):
    caps = fit_capsules(model, poses.params.shape.to(model.dtype))
    caps = type(caps)(*(x.double() for x in (caps.start, caps.end, caps.radius, caps.rest)))
    rot, pos = forward_kinematics(caps.rest, poses.params.pose)
    a, b = caps.place(rot, pos)
    clear = capsule_clearance(a, b, caps.radius, collision_pairs(checked))
    assert (clear >= -1e-6).all(), f"{int((clear < 0).any(-1).sum())} samples in self-collision"


def test_shape_draw_weights_its_entries_by_their_powers():
    # Density ~ t^(p - 1) on each entry's interval: the CDF of t is t^p (Kolmogorov-Smirnov
    # against it, 4,000 draws: the 1% critical distance is 0.026); powers of 1 are the uniform
    # draw, number for number, from the same stream.
    low, high = np.array([1.0, -2.0, 0.0]), np.array([1.0, 3.0, 0.5])
    power = np.array([1.0, 1.0, 2.0])
    a, b = np.random.default_rng(5), np.random.default_rng(5)
    skewed = np.stack([draw_shape(a, low, high, power) for _ in range(4000)])
    uniform = np.stack([draw_shape(b, low, high) for _ in range(4000)])
    assert np.array_equal(skewed[:, :2], uniform[:, :2])
    assert (skewed >= low).all() and (skewed <= high).all()
    for t, p in ((np.sort((skewed[:, 2] - low[2]) / (high[2] - low[2])), 2.0), (np.sort(uniform[:, 2] / 0.5), 1.0)):
        ecdf = np.arange(1, t.size + 1) / t.size
        assert np.abs(ecdf - t**p).max() < 0.026
    # each draw's t is the uniform draw's u^(1/2) >= u: never lighter, on average heavier
    assert (skewed[:, 2] >= uniform[:, 2]).all() and skewed[:, 2].mean() > uniform[:, 2].mean() + 0.04


def test_the_sampled_population_is_heavier_shape_by_shape(anny):
    # Sampling law 3: Anny's weight phenotype alone is drawn with a rising density; a body drawn
    # from the same numbers with the uniform law differs only in that entry, and is never
    # lighter (Anny's mass rises with the weight phenotype), the others exactly equal.
    names = anny.shape_names
    power = type(anny).shape_powers(names)
    assert power.tolist() == [2.0 if n == "weight" else 1.0 for n in names]
    for gender in ("female", "male"):
        low, high = shape_bounds("anny", gender, names)
        a, b = np.random.default_rng(1), np.random.default_rng(1)
        new = np.stack([draw_shape(a, low, high, power) for _ in range(48)])
        old = np.stack([draw_shape(b, low, high) for _ in range(48)])
        other = [i for i, n in enumerate(names) if n != "weight"]
        assert np.array_equal(new[:, other], old[:, other])
        with torch.no_grad():
            m_new = anny.measure(torch.tensor(new, dtype=anny.dtype)).mass_kg
            m_old = anny.measure(torch.tensor(old, dtype=anny.dtype)).mass_kg
        assert (m_new >= m_old - 1e-3 * m_old).all() and float((m_new - m_old).mean()) > 2.0
    # the pose sampler draws from it
    assert np.array_equal(PoseSampler(anny, SamplingConfig(gender="male")).shape_power, power)


def test_unknown_partition_lists_the_valid_ones():
    with pytest.raises(ValueError, match="valid partitions: general, supine, hands_behind_head"):
        SamplingConfig(partition="sideways")
    with pytest.raises(ValueError, match="unknown gender"):
        SamplingConfig(gender="x")
    with pytest.raises(ValueError, match="over_bed=True"):
        SamplingConfig(partition="hands_behind_head", over_bed=False)
    with pytest.raises(ValueError, match="max_limb_draws"):
        SamplingConfig(max_limb_draws=0)
    assert set(PARTITIONS) == {
        "general",
        "supine",
        "hands_behind_head",
        "prone_hands_up",
        "crossed_legs",
        "straight_limbs",
        "half_sitting",
        "lateral",
        "lateral_straight",
        "tilted",
    }
    assert get_partition("supine").roll == (0.0, 0.0)


@pytest.mark.slow
def test_distal_joint_cells_are_uniform_and_reached(anny):
    poses = draw(anny, 2000, partition="general", gender="male")
    cells = limb_cells(poses)
    np.testing.assert_array_equal(cells, poses.cells)  # every distal joint lies in its drawn cell
    # Face-down bodies draw their legs from the far cells (FACE_DOWN_LEG_CELLS); every other
    # cell choice is uniform.
    down = np.abs(poses.root_draw[:, 0]) > FACE_DOWN_ROLL_RAD
    assert 0.12 < down.mean() < 0.22  # the roll's share beyond 150 deg: 1/6
    assert np.isin(cells[down, :2], FACE_DOWN_LEG_CELLS).all()
    for k, n_cells in enumerate((4, 4, 8, 8)):
        sel = cells[~down, k] if k < 2 else cells[:, k]
        counts = np.bincount(sel, minlength=n_cells)
        expected = len(sel) / n_cells
        chi2 = ((counts - expected) ** 2 / expected).sum()
        assert chi2 < CHI2_CRIT[n_cells - 1], (k, counts)
    for k in (0, 1):
        counts = np.bincount(cells[down, k], minlength=4)[list(FACE_DOWN_LEG_CELLS)]
        assert abs(counts[0] - counts[1]) < 3 * math.sqrt(counts.sum()), counts  # about even
    # The roll is the sample's own, whatever its shapes failed: uniform on the circle (12 bins).
    counts = np.histogram(poses.root_draw[:, 0], bins=12, range=(-math.pi, math.pi))[0]
    assert ((counts - len(cells) / 12) ** 2 / (len(cells) / 12)).sum() < 24.725  # chi-square, df 11, p 0.01
    # distal joints start within 10 cm of their proximal joint's height, knees and elbows no
    # lower than 10 cm below it
    p = roll_frame(poses)
    for prox, mid, dist in (("hip", "knee", "ankle"), ("shoulder", "elbow", "wrist")):
        for side in ("left", "right"):
            dz = p[:, J(f"{side}_{dist}"), 2] - p[:, J(f"{side}_{prox}"), 2]
            assert dz.abs().max() <= HEIGHT_TOLERANCE_M + 1e-9
            dz = p[:, J(f"{side}_{mid}"), 2] - p[:, J(f"{side}_{prox}"), 2]
            assert dz.min() >= -HEIGHT_TOLERANCE_M - 1e-9
    # angles inside the limits, unsampled joints at zero
    assert JointLimits.default(torch.float64).contains(poses.params.pose).all()
    sampled = {J(f"{s}_{n}") - 1 for s in ("left", "right") for n in ("hip", "knee", "collar", "shoulder", "elbow")}
    others = [j for j in range(23) if j not in sampled]
    assert (poses.params.pose[:, others] == 0).all()
    assert_collision_free(anny, poses, PARTITIONS["general"].checked_capsules)
    # roll spread over the full circle, yaw within +-30 degrees
    assert poses.root_draw[:, 0].min() < -3.0 and poses.root_draw[:, 0].max() > 3.0
    assert np.abs(poses.root_draw[:, 1]).max() <= math.pi / 6


def test_lateral_lies_on_either_side_with_the_legs_drawn_up(anny):
    poses = draw(anny, 40, partition="lateral", gender="female")
    roll, yaw = poses.root_draw[:, 0], poses.root_draw[:, 1]
    assert (np.abs(np.abs(roll) - math.pi / 2) <= math.pi / 9 + 1e-12).all()
    assert 8 <= int((roll < 0).sum()) <= 32  # both sides, about half each
    assert np.abs(yaw).max() <= math.pi / 18 + 1e-12
    cells = limb_cells(poses)
    np.testing.assert_array_equal(cells, poses.cells)
    assert set(cells[:, :2].ravel()) <= {1, 2, 3} and set(cells[:, 2:].ravel()) <= {2, 3, 4, 5}
    # the body's left axis points down on the left side (roll < 0) and up on the right
    from pressurepose.eval.real import roll_deg

    measured = roll_deg(poses.params.root_rotation)
    np.testing.assert_allclose(measured.numpy(), np.degrees(roll), atol=1e-6)
    assert_collision_free(anny, poses, PARTITIONS["lateral"].checked_capsules)


def test_lateral_straight_lies_on_either_side_with_the_legs_nearly_straight(anny):
    poses = draw(anny, 30, partition="lateral_straight", gender="male")
    roll = poses.root_draw[:, 0]
    assert (np.abs(np.abs(roll) - math.pi / 2) <= math.pi / 9 + 1e-12).all()
    assert 5 <= int((roll < 0).sum()) <= 25
    cells = limb_cells(poses)
    np.testing.assert_array_equal(cells, poses.cells)
    assert set(cells[:, :2].ravel()) == {3} and set(cells[:, 2:].ravel()) <= {2, 3, 4, 5}
    assert PARTITIONS["lateral_straight"].hold_roll_m > 0 and PARTITIONS["lateral"].hold_roll_m == 0
    assert_collision_free(anny, poses, PARTITIONS["lateral_straight"].checked_capsules)


def test_determinism_same_index_same_sample(anny):
    cfg = SamplingConfig(partition="supine", gender="female", seed=7)
    batch = PoseSampler(anny, cfg).sample(range(6))
    alone = PoseSampler(anny, cfg).sample([3])
    for field in ("shape", "root_rotation", "root_translation", "pose"):
        torch.testing.assert_close(getattr(alone.params, field)[0], getattr(batch.params, field)[3], rtol=0, atol=0)
    np.testing.assert_array_equal(alone.cells[0], batch.cells[3])
    assert {k: int(v[0]) for k, v in alone.rejections.items()} == {k: int(v[3]) for k, v in batch.rejections.items()}
    # another index, another seed or another partition -> another sample
    assert not torch.equal(batch.params.pose[3], batch.params.pose[4])
    other_seed = PoseSampler(anny, dataclasses.replace(cfg, seed=8)).sample([3])
    assert not torch.equal(other_seed.params.shape[0], alone.params.shape[0])
    other_part = PoseSampler(anny, dataclasses.replace(cfg, partition="general")).sample([3])
    assert not torch.equal(other_part.params.shape[0], alone.params.shape[0])


def test_records_partition_rejections_and_rests_on_the_mat(anny):
    poses = draw(anny, 40, partition="supine", gender="female", over_bed=True)
    assert poses.config.partition == "supine" and poses.config.over_bed
    assert set(poses.rejections) == {
        "limb_draws_rejected",
        "limb_failures",
        "collisions",
        "shape_resamples",
        "cell_redraws",
        "sit_up_rejections",
    }
    assert (poses.rejections["sit_up_rejections"] == 0).all()  # a flat partition never sits up
    assert sum(int(v.sum()) for v in poses.rejections.values()) > 0
    anny.check_params(poses.params.to(anny.dtype))  # valid BodyParams for the model
    # shapes from the female box
    low, high = shape_bounds("anny", "female", anny.shape_names)
    s = poses.params.shape.numpy()
    assert (s >= low - 1e-12).all() and (s <= high + 1e-12).all() and (s[:, 0] == 1.0).all()
    # the lowest capsule point touches z = 0 (pelvis set accordingly)
    caps = fit_capsules(anny, poses.params.shape.to(anny.dtype))
    caps = type(caps)(*(x.double() for x in (caps.start, caps.end, caps.radius, caps.rest)))
    a, b = caps.posed(poses.params.pose, poses.params.root_rotation, poses.params.root_translation)
    lowest = (torch.minimum(a[..., 2], b[..., 2]) - caps.radius).amin(-1)
    torch.testing.assert_close(lowest, torch.zeros_like(lowest), atol=1e-6, rtol=0)
    # over the bed: knees, ankles, feet, elbows, wrists, hands inside the mattress
    (x0, x1), (y0, y1) = MatSpec().mattress_bounds_m
    limbs = [J(f"{s}_{n}") for s in ("left", "right") for n in ("knee", "ankle", "foot", "elbow", "wrist", "hand")]
    xy = poses.joints[:, limbs, :2]
    assert ((xy[..., 0] > x0) & (xy[..., 0] < x1) & (xy[..., 1] > y0) & (xy[..., 1] < y1)).all()
    assert_collision_free(anny, poses, PARTITIONS["supine"].checked_capsules)
    # supine: the body's front faces up
    front = root_matrix(poses.params.root_rotation)[:, :, 2]
    assert (front[:, 2] > 0.99).all()


def test_crossed_legs_are_always_crossed(anny):
    poses = draw(anny, 30, partition="crossed_legs", gender="male")
    body = body_axes(poses)
    assert (body[:, J("left_ankle"), 0] < body[:, J("right_ankle"), 0]).all()
    assert_collision_free(anny, poses, PARTITIONS["crossed_legs"].checked_capsules)
    np.testing.assert_array_equal(limb_cells(poses), poses.cells)


def test_straight_limbs_have_straight_knees_and_elbows(anny):
    poses = draw(anny, 30, partition="straight_limbs", gender="female")
    for n in ("knee", "elbow"):
        for s in ("left", "right"):
            assert (poses.params.pose[:, J(f"{s}_{n}") - 1] == 0).all()
    np.testing.assert_array_equal(limb_cells(poses), poses.cells)


@pytest.mark.slow
def test_straight_limbs_over_the_bed_always_yield_a_sample(anny):
    # seed 0, male, index 73 used to give up: a straight arm held out sideways (cells 3-5)
    # leaves the mattress or crosses the torso for nearly every body and root.
    (x0, x1), (y0, y1) = MatSpec().mattress_bounds_m
    for gender in ("female", "male"):
        cfg = SamplingConfig(partition="straight_limbs", gender=gender, over_bed=True)
        poses = PoseSampler(anny, cfg).sample(range(200))
        assert poses.batch_size == 200
        assert not np.isin(poses.cells[:, 2:], (3, 4, 5)).any()
        assert (poses.cells[:, :2] == 3).all()
        np.testing.assert_array_equal(limb_cells(poses), poses.cells)
        for n in ("knee", "elbow"):
            for side in ("left", "right"):
                assert (poses.params.pose[:, J(f"{side}_{n}") - 1] == 0).all()
        limbs = [J(f"{s}_{n}") for s in ("left", "right") for n in ("knee", "ankle", "foot", "elbow", "wrist", "hand")]
        xy = poses.joints[:, limbs, :2]
        assert ((xy[..., 0] > x0) & (xy[..., 0] < x1) & (xy[..., 1] > y0) & (xy[..., 1] < y1)).all()
        assert_collision_free(anny, poses, PARTITIONS["straight_limbs"].checked_capsules)


def test_over_the_bed_attempts_per_shape_are_capped(anny):
    """Over the bed, hands behind the head, crossed legs and straight limbs give a shape and
    root at most `over_bed_max_failures` failed attempts (issue 21); flat rows and the other
    partitions keep the config's max_failures, a smaller config value wins, and a sample still
    follows from its index alone."""
    from pressurepose.sampling.partitions import OVER_BED_MAX_FAILURES, max_failures

    cap = OVER_BED_MAX_FAILURES
    assert cap < SamplingConfig().max_failures
    capped = {n for n, p in PARTITIONS.items() if p.over_bed_max_failures is not None}
    assert capped == {"hands_behind_head", "crossed_legs", "straight_limbs"}
    cfg = SamplingConfig(partition="straight_limbs", gender="male", over_bed=True)
    assert max_failures(cfg.spec, cfg) == cap
    assert max_failures(cfg.spec, dataclasses.replace(cfg, over_bed=False)) == cfg.max_failures
    assert max_failures(cfg.spec, dataclasses.replace(cfg, max_failures=2)) == 2
    general = SamplingConfig(partition="general", over_bed=True)
    assert max_failures(general.spec, general) == general.max_failures
    # Failures per sample: at most cap + 1 per given-up shape, at most cap on the accepted one.
    bound = lambda r, c: r["shape_resamples"] * (c + 1) + c  # noqa: E731
    failed = lambda r: r["limb_failures"] + r["sit_up_rejections"]  # noqa: E731
    poses = PoseSampler(anny, cfg).sample(range(48))
    assert (failed(poses.rejections) <= bound(poses.rejections, cap)).all()
    # The law before (the seed's 20 attempts): some shapes took more than the cap allows.
    old = PoseSampler(anny, cfg, partition=dataclasses.replace(cfg.spec, over_bed_max_failures=None))
    before = old.sample(range(48)).rejections
    assert (failed(before) > bound(before, cap)).any()
    for i in (5, 31):
        alone = PoseSampler(anny, cfg).sample([i])
        for field in ("shape", "root_rotation", "root_translation", "pose"):
            torch.testing.assert_close(getattr(alone.params, field)[0], getattr(poses.params, field)[i], rtol=0, atol=0)


def test_determinism_over_the_bed(anny):
    # Over the bed most draws are rejected: several rounds are tested at once and the
    # generator is wound back to the winner's round - invisible in the samples.
    cfg = SamplingConfig(partition="general", gender="male", over_bed=True, seed=3)
    batch = PoseSampler(anny, cfg).sample(range(10))
    for i in (2, 7):
        alone = PoseSampler(anny, cfg).sample([i])
        for field in ("shape", "root_rotation", "root_translation", "pose"):
            torch.testing.assert_close(getattr(alone.params, field)[0], getattr(batch.params, field)[i], rtol=0, atol=0)
        assert {k: int(v[0]) for k, v in alone.rejections.items()} == {
            k: int(v[i]) for k, v in batch.rejections.items()
        }


def test_the_float32_screen_drops_no_valid_draw(anny, monkeypatch):
    # With the screen let through every draw, only the exact tests decide: same samples.
    configs = [
        SamplingConfig(partition=p, gender=g, over_bed=o, seed=5)
        for p, g, o in (
            ("general", "male", True),
            ("crossed_legs", "female", True),
            ("hands_behind_head", "male", True),
        )
    ]
    screened = [PoseSampler(anny, cfg).sample(range(4)) for cfg in configs]

    def everything(self, ctx, pending, limb, u):
        P, M = u.shape[:2]
        return torch.arange(P).repeat_interleave(M), torch.arange(M).repeat(P)

    monkeypatch.setattr(PoseSampler, "_screen", everything)
    for cfg, want in zip(configs, screened):
        got = PoseSampler(anny, cfg).sample(range(4))
        torch.testing.assert_close(got.params.pose, want.params.pose, rtol=0, atol=0)
        assert all((got.rejections[k] == want.rejections[k]).all() for k in want.rejections)


def test_sampling_first_leaves_the_body_model_differentiable():
    # A fresh process: libraries that cache tensors on first use (roma) must not end up with
    # inference tensors from the sampler's inference mode.
    code = (
        "import torch\n"
        "from pressurepose.body import load_body_model\n"
        "from pressurepose.body.capsules import fit_capsules\n"
        "from pressurepose.sampling import PoseSampler, SamplingConfig\n"
        "m = load_body_model('anny', dtype=torch.float64)\n"
        "PoseSampler(m, SamplingConfig(partition='supine')).sample([0])\n"
        "s = m.default_shape(1).requires_grad_()\n"
        "fit_capsules(m, s).radius.sum().backward()\n"
        "assert torch.isfinite(s.grad).all()\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300)


def test_hands_behind_head_and_prone_hands_up(anny):
    poses = draw(anny, 20, partition="hands_behind_head", gender="female", over_bed=True)
    body = body_axes(poses)
    p = roll_frame(poses)
    for s in ("left", "right"):
        wr, sh = J(f"{s}_wrist"), J(f"{s}_shoulder")
        assert (body[:, wr, 0].abs() < body[:, sh, 0].abs()).all()  # between midline and shoulder
        assert (p[:, wr, 0] <= p[:, sh, 0]).all()  # toward the head
        assert (p[:, wr, 2] <= p[:, sh, 2] + 1e-9).all()  # not above the shoulder
    assert_collision_free(anny, poses, PARTITIONS["hands_behind_head"].checked_capsules)
    prone = draw(anny, 20, partition="prone_hands_up", gender="male", over_bed=True)
    front = root_matrix(prone.params.root_rotation)[:, :, 2]
    assert (front[:, 2] < -0.99).all()  # face down
    p = roll_frame(prone)
    for s in ("left", "right"):
        assert (p[:, J(f"{s}_wrist"), 0] <= p[:, J(f"{s}_shoulder"), 0]).all()  # hands above the shoulders
        # not kneeling: the knee no lower than 10 cm below the hip (the bed would hold the body
        # up on it), and over the bed face down the legs reach only the far cell
        assert (p[:, J(f"{s}_knee"), 2] - p[:, J(f"{s}_hip"), 2] >= -HEIGHT_TOLERANCE_M - 1e-9).all()
    assert (prone.cells[:, :2] == FACE_DOWN_LEG_CELLS_OVER_BED[0]).all()
    np.testing.assert_array_equal(limb_cells(prone)[:, :2], prone.cells[:, :2])


def test_unreachable_constraints_fail_fast_with_a_clear_error(anny):
    impossible = dataclasses.replace(PARTITIONS["straight_limbs"], leg_cells=(0,))  # straight leg, foot at hip
    cfg = SamplingConfig(partition="straight_limbs", max_limb_draws=256, max_shapes=3)
    with pytest.raises(UnreachableConstraints, match="unreachable"):
        PoseSampler(anny, cfg, partition=impossible).sample([0])


def test_bad_indices_and_config(anny):
    sampler = PoseSampler(anny, SamplingConfig())
    with pytest.raises(ValueError, match="no sample indices"):
        sampler.sample([])
    with pytest.raises(ValueError, match=">= 0"):
        sampler.sample([-1])
    with pytest.raises(ValueError, match="SamplingConfig"):
        PoseSampler(anny, {"partition": "general"})


def test_smpl_backend_samples(smpl64):
    poses = PoseSampler(smpl64, SamplingConfig(partition="supine", gender="male")).sample(range(3))
    assert poses.backend == "smpl"
    s = poses.params.shape
    assert (s >= -3).all() and (s <= 3).all()
    np.testing.assert_array_equal(limb_cells(poses), poses.cells)


def test_tilted_partition_draws_turned_bodies_with_straight_legs(anny64):
    """`tilted`: turned 15-45 deg toward either side, legs nearly straight (ankles more than 3/4 of
    the leg below the hips: cell 3), wrists below the shoulders (arm cells 4-7), small yaw."""
    import math

    from pressurepose.body.params import root_roll
    from pressurepose.sampling.partitions import ARM_CELLS, LEG_CELLS, get_partition
    from pressurepose.sampling.sampler import PoseSampler

    spec = get_partition("tilted")
    assert spec.wedge and spec.either_side and spec.leg_cells == (LEG_CELLS - 1,)
    assert spec.arm_cells == tuple(range(4, ARM_CELLS))
    poses = PoseSampler(anny64, SamplingConfig(partition="tilted", gender="male", seed=3)).sample(list(range(12)))
    roll = torch.rad2deg(root_roll(poses.params.root_rotation.double()))
    assert bool(((roll.abs() >= 15 - 1e-6) & (roll.abs() <= 45 + 1e-6)).all()), roll
    assert bool((roll > 0).any()) and bool((roll < 0).any())  # both sides
    assert math.isclose(spec.roll[0], math.pi / 12) and math.isclose(spec.roll[1], math.pi / 4)
