"""Half-sitting on a raised bed: the sit-up fold, the placement on the bent bed, the
half_sitting partition, and simulating samples that rest on different beds."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from pressurepose.bed import BedShape
from pressurepose.body.capsules import Capsules, capsule_clearance, collision_pairs, fit_capsules, home_pose
from pressurepose.body.joints import J24_NAMES
from pressurepose.body.kinematics import pose_in_mat
from pressurepose.body.limits import JointLimits
from pressurepose.body.params import BodyParams, root_matrix
from pressurepose.body.rotations import axis_angle_to_matrix
from pressurepose.mat import MatSpec
from pressurepose.sampling import PARTITIONS, PoseSampler, SamplingConfig
from pressurepose.sampling.partitions import HEIGHT_TOLERANCE_M
from pressurepose.sampling.sitting import (
    TRUNK_CAPSULES,
    bed_lift,
    capsule_gaps,
    fold_params,
    half_sitting_params,
    pitch_matrix,
    sit_up,
    sit_up_frame,
    trunk_pitch,
)
from pressurepose.sampling.sitting_draws import SEAT_TOLERANCE_M

J = J24_NAMES.index
MAT = MatSpec()
D = torch.float64
LEGS = [J(f"{s}_{n}") for s in ("left", "right") for n in ("hip", "knee", "ankle", "foot")]
HIPS = [J("left_hip"), J("right_hip")]


@pytest.fixture(scope="module")
def caps(anny64):
    c = fit_capsules(anny64, anny64.default_shape(2).to(D))
    return Capsules(*(x.to(D) for x in (c.start, c.end, c.radius, c.rest)))


def lying(caps, yaw=(0.0, 0.2), x=1.0):
    """Two bodies in the home pose lying on their back, pelvis at mat x, yawed."""
    root = torch.tensor([[0.0, 0.0, y] for y in yaw], dtype=D)
    trans = torch.tensor([[x, 0.37, 0.1], [x, 0.40, 0.1]], dtype=D)
    return BodyParams(shape=torch.zeros(2, 1, dtype=D), root_rotation=root, root_translation=trans, pose=home_pose(2))


def pitch_about_y(pitch):
    zero = torch.zeros_like(pitch)
    return axis_angle_to_matrix(torch.stack([zero, pitch, zero], -1))


def test_fold_keeps_the_thighs_and_turns_the_trunk_about_the_hips(caps):
    params = lying(caps)
    pitch = torch.tensor([0.3, 0.7], dtype=D)
    rot0, pos0 = pose_in_mat(caps.rest, params)
    rot1, pos1 = pose_in_mat(caps.rest, fold_params(params, caps.rest, pitch))
    P = pitch_about_y(pitch)
    c = pos0[:, HIPS].mean(1)
    trunk = [J(n) for n in ("pelvis", "spine1", "spine2", "spine3", "neck", "head", "left_wrist", "right_hand")]
    # Trunk, head and arms: turned rigidly about the hip midpoint, head up.
    expected = c[:, None] + ((pos0[:, trunk] - c[:, None]) @ P.transpose(1, 2))
    torch.testing.assert_close(pos1[:, trunk], expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(rot1[:, 0], P @ rot0[:, 0], rtol=0, atol=1e-12)
    assert (pos1[:, J("head"), 2] > pos0[:, J("head"), 2] + 0.2).all()
    # Legs: same orientation everywhere, so the same shape; unmoved where the hips lie on the
    # pitch axis (no yaw).
    torch.testing.assert_close(rot1[:, LEGS], rot0[:, LEGS], rtol=0, atol=1e-12)
    for leg in (LEGS[:4], LEGS[4:]):
        torch.testing.assert_close(pos1[:, leg] - pos1[:, leg[:1]], pos0[:, leg] - pos0[:, leg[:1]], rtol=0, atol=1e-12)
    torch.testing.assert_close(pos1[0, LEGS], pos0[0, LEGS], rtol=0, atol=1e-12)


def test_rigid_fold_turns_the_whole_body(caps):
    params = lying(caps)
    pitch = torch.tensor([0.5, 0.2], dtype=D)
    _, pos0 = pose_in_mat(caps.rest, params)
    folded = fold_params(params, caps.rest, pitch, keep_thighs=False)
    _, pos1 = pose_in_mat(caps.rest, folded)
    c = pos0[:, HIPS].mean(1, keepdim=True)
    torch.testing.assert_close(pos1, c + (pos0 - c) @ pitch_about_y(pitch).transpose(1, 2), rtol=0, atol=1e-12)
    assert torch.equal(folded.pose, params.pose)


def _naive_lowest_gap(a, b, r, bed):
    """Min over 401 points per capsule axis of (min over section planes of the signed
    distance) - radius: the mattress is the union of the half-spaces under the planes."""
    t = torch.linspace(0, 1, 401, dtype=D)[:, None]
    best = math.inf
    for k in range(a.shape[0]):
        pts = a[k] + t * (b[k] - a[k])
        hinge = torch.tensor([bed.hinge_x(MAT), 0.0, 0.0], dtype=D)
        d = torch.stack([(pts - hinge) @ torch.as_tensor(R[:, 2], dtype=D) for R, _, _ in bed.sections(MAT)], -1)
        best = min(best, float(d.amin(-1).amin() - r[k]))
    return best


@pytest.mark.parametrize("angle", [0.0, 30.0, 60.0])
def test_bed_lift_sets_the_lowest_capsule_on_the_bent_mattress(caps, angle):
    bed = BedShape(angle)
    params = fold_params(lying(caps, x=0.75), caps.rest, torch.tensor([0.4, 0.1], dtype=D))
    a, b = caps.posed(params.pose, params.root_rotation, params.root_translation)
    lift = bed_lift(a, b, caps.radius, bed, MAT)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=D)
    for i in range(2):
        gap = _naive_lowest_gap(a[i] + lift[i] * up, b[i] + lift[i] * up, caps.radius[i], bed)
        assert abs(gap) < 1e-9, gap
    if angle == 0.0:
        torch.testing.assert_close(lift, -(torch.minimum(a[..., 2], b[..., 2]) - caps.radius).amin(-1))


def test_trunk_pitch_rests_the_trunk_on_both_sections(caps):
    bed = BedShape(50.0)
    trunk = list(TRUNK_CAPSULES)
    pitches = []
    for hips_past_hinge in (0.15, 0.3, 0.45):
        params = lying(caps, yaw=(0.0, 0.0))
        hip_x = pose_in_mat(caps.rest, params)[1][:, HIPS, 0].mean(1)
        params = params.replace(
            root_translation=params.root_translation
            + torch.stack([bed.hinge_x(MAT) + hips_past_hinge - hip_x, 0 * hip_x, 0 * hip_x], -1)
        )
        pitch = trunk_pitch(caps, params, bed, MAT)
        assert ((pitch > 0) & (pitch < bed.angle_rad)).all()
        sat = fold_params(params, caps.rest, pitch)
        a, b = caps.posed(sat.pose, sat.root_rotation, sat.root_translation)
        a, b, r = a[:, trunk], b[:, trunk], caps.radius[:, trunk]
        up = bed_lift(a, b, r, bed, MAT)[:, None, None] * torch.tensor([0.0, 0.0, 1.0], dtype=D)
        gaps = capsule_gaps(a + up, b + up, r, bed, MAT).amin(1)  # (B, 2): head section, foot section
        assert (gaps.abs() < 1e-4).all(), gaps  # the trunk touches both (bisection tolerance)
        pitches.append(pitch)
    # Hips farther down the bed: a flatter trunk.
    assert (pitches[0] > pitches[1]).all() and (pitches[1] > pitches[2]).all()
    # A flat bed never pitches.
    assert (trunk_pitch(caps, lying(caps), BedShape(0.0), MAT) == 0).all()


def _bisected_pitch(caps, params, bed, iterations=40):
    """Reference: bisection on the trunk's clearance above the two sections, each body's
    trunk turned by `fold_params` and lowered by `bed_lift` (the slow way)."""
    trunk = list(TRUNK_CAPSULES)
    lo = torch.zeros(params.batch_size, dtype=D)
    hi = torch.full_like(lo, bed.angle_rad)
    for _ in range(iterations):
        mid = (lo + hi) / 2
        sat = fold_params(params, caps.rest, mid, keep_thighs=False)
        a, b = caps.posed(sat.pose, sat.root_rotation, sat.root_translation)
        a, b, r = a[:, trunk], b[:, trunk], caps.radius[:, trunk]
        up = bed_lift(a, b, r, bed, MAT)[:, None, None] * torch.tensor([0.0, 0.0, 1.0], dtype=D)
        head, foot = capsule_gaps(a + up, b + up, r, bed, MAT).amin(1).unbind(-1)
        steeper = foot > head  # the buttocks still above the foot section: pitch more
        lo, hi = torch.where(steeper, mid, lo), torch.where(steeper, hi, mid)
    return (lo + hi) / 2


@pytest.mark.parametrize("angle", [20.0, 45.0, 60.0])
def test_trunk_pitch_agrees_with_a_bisection(caps, angle):
    bed = BedShape(angle)
    params = lying(caps, yaw=(0.0, 0.15))
    hip_x = pose_in_mat(caps.rest, params)[1][:, HIPS, 0].mean(1)
    shift = torch.tensor([0.2, 0.45], dtype=D)
    params = params.replace(
        root_translation=params.root_translation
        + torch.stack([bed.hinge_x(MAT) + shift - hip_x, 0 * hip_x, 0 * hip_x], -1)
    )
    pitch = trunk_pitch(caps, params, bed, MAT)
    # the grid's resolution (the angle / 64^3), plus the trunk's curvature at the touch
    torch.testing.assert_close(pitch, _bisected_pitch(caps, params, bed), atol=1e-5, rtol=0)


def test_sit_up_frame_maps_the_sat_up_body_onto_the_head_section(caps):
    bed = BedShape(50.0)
    # the hips past the hinge, as the sampler places them: the trunk pitches less than the bed
    params = lying(caps, yaw=(0.0, 0.2), x=bed.hinge_x(MAT) + 0.3)
    # arms raised to the head and clear of the bed (on its plane beyond the head they would
    # press into the steeper head section and prop the body up), so that they lie on the head
    # section once sat up
    pose = params.pose.clone()
    for side, sign in (("left", -1.0), ("right", 1.0)):
        pose[:, J(f"{side}_shoulder") - 1] = torch.tensor([0.0, sign * 2.6, 0.0], dtype=D)
    params = params.replace(pose=pose)
    hands = [J("left_hand"), J("right_hand")]
    lying_joints = pose_in_mat(caps.rest, params)[1]
    up = sit_up_frame(caps, params, bed, MAT)
    pitch, row, offset = up.pitch, up.head_row, up.head_offset
    assert ((pitch > 0.1) & (pitch < bed.angle_rad - 0.1)).all()  # neither end of the range
    # the map is not the flat bed's x: the arms lie elsewhere along the bed once sat up
    flat_x = (lying_joints - params.root_translation[:, None]) @ root_matrix(params.root_rotation)
    assert ((flat_x * row[:, None]).sum(-1) + offset[:, None] - lying_joints[..., 0]).abs()[:, hands].min() > 0.05
    torch.testing.assert_close(pitch, trunk_pitch(caps, params, bed, MAT), atol=1e-12, rtol=0)
    torch.testing.assert_close(up.turn, pitch_matrix(params.root_rotation, pitch), atol=1e-12, rtol=0)
    folded = fold_params(params, caps.rest, pitch, keep_thighs=False)
    torch.testing.assert_close(up.pelvis, folded.root_translation, atol=1e-12, rtol=0)
    # (the thighs kept on the foot section, as the sampler draws them; the arms ride the trunk)
    sat, seat = sit_up(caps, params, bed, MAT, pitch=pitch)
    assert (seat.abs() < 1e-9).all()  # the trunk carries the body: the lift is the trunk's
    _, joints = pose_in_mat(caps.rest, sat)
    _, lying_joints = pose_in_mat(caps.rest, params)
    v = (lying_joints - params.root_translation[:, None]) @ root_matrix(params.root_rotation)  # body axes
    s = bed.to_surface(joints, MAT)[..., 0]
    on_head = joints[..., 0] < bed.hinge_x(MAT) - 0.05
    arms = [J(f"{side}_{n}") for side in ("left", "right") for n in ("elbow", "wrist", "hand")]
    assert on_head[:, arms].all()
    predicted = (v * row[:, None]).sum(-1) + offset[:, None]
    torch.testing.assert_close(predicted[on_head], s[on_head], atol=1e-9, rtol=0)
    # A limb that props the body up lifts it further: the surface coordinate only moves toward
    # the head end, so a head-end bound tested on the prediction never refuses a pose it holds.
    propped = params.pose.clone()
    propped[:, J("left_hip") - 1, 0] += 0.8  # the left leg pressed down into the foot section
    sat2, seat2 = sit_up(caps, params.replace(pose=propped), bed, MAT, pitch=pitch)
    assert (seat2 > 1e-3).all()
    s2 = bed.to_surface(pose_in_mat(caps.rest, sat2)[1], MAT)[..., 0]
    assert (s2[:, arms] < predicted[:, arms]).all()


def test_sit_up_frame_on_a_flat_bed_is_the_mat(caps):
    params = lying(caps)
    up = sit_up_frame(caps, params, BedShape(0.0), MAT)
    assert (up.pitch == 0).all()
    torch.testing.assert_close(up.turn, torch.eye(3, dtype=D).expand(2, 3, 3))
    torch.testing.assert_close(up.pelvis, params.root_translation)
    _, joints = pose_in_mat(caps.rest, params)
    v = (joints - params.root_translation[:, None]) @ root_matrix(params.root_rotation)
    torch.testing.assert_close((v * up.head_row[:, None]).sum(-1) + up.head_offset[:, None], joints[..., 0])


def test_half_sitting_params_keep_the_legs_straight_and_flat(anny64):
    bed = BedShape(40.0)
    params = half_sitting_params(anny64, anny64.default_shape(1), bed, MAT)
    c = fit_capsules(anny64, anny64.default_shape(1).to(D))
    _, pos = pose_in_mat(c.rest.to(D), params)
    # The legs lie on the flat foot section as in the home pose lying flat; the hips flex by
    # the trunk's pitch.
    flat = BodyParams.zeros(1, anny64.default_shape(1).to(D)).replace(pose=home_pose(1))
    _, pos_flat = pose_in_mat(c.rest.to(D), flat)
    torch.testing.assert_close(
        pos[0, LEGS] - pos[0, LEGS[:1]], pos_flat[0, LEGS] - pos_flat[0, LEGS[:1]], rtol=0, atol=1e-9
    )
    assert float(params.pose[0, J("left_hip") - 1, 0]) < -0.2
    assert float(pos[0, J("head"), 2]) > 0.25


@pytest.fixture(scope="module")
def sitting(anny32):
    cfg = SamplingConfig(partition="half_sitting", gender="male", seed=3)
    return PoseSampler(anny32, cfg).sample(range(24)), cfg


def test_half_sitting_partition_sits_on_its_raised_bed(anny32, anny64, sitting):
    poses, _ = sitting
    part = PARTITIONS["half_sitting"]
    assert set(poses.head_angle_deg.tolist()) <= set(part.head_angles_deg) and len(set(poses.head_angle_deg)) >= 3
    assert [b.head_angle_deg for b in poses.beds()] == poses.head_angle_deg.tolist()
    assert JointLimits.default(D).contains(poses.params.pose).all()
    c = fit_capsules(anny64, poses.params.shape)
    caps = Capsules(*(x.to(D) for x in (c.start, c.end, c.radius, c.rest)))
    a, b = caps.posed(poses.params.pose, poses.params.root_rotation, poses.params.root_translation)
    pairs = collision_pairs(part.checked_capsules)
    assert (capsule_clearance(a, b, caps.radius, pairs) > -1e-6).all()
    trunk = list(TRUNK_CAPSULES)
    for i, bed in enumerate(poses.beds()):
        gaps = capsule_gaps(a[i : i + 1], b[i : i + 1], caps.radius[i : i + 1], bed, MAT)
        assert abs(float(gaps.amin())) < 1e-6  # resting on the bed, nothing inside it
        assert float(gaps[:, trunk].amin()) <= SEAT_TOLERANCE_M + 1e-9  # on its trunk
        # Sitting: the head well above the flat bed; the legs on the foot section within the
        # seed's 10 cm of their hip's height.
        j = poses.joints[i]
        assert float(j[J("head"), 2]) > 0.15
        for side in ("left", "right"):
            dz = j[J(f"{side}_ankle"), 2] - j[J(f"{side}_hip"), 2]
            assert abs(float(dz)) <= HEIGHT_TOLERANCE_M + 1e-6
            assert float(j[J(f"{side}_ankle"), 0]) > float(j[J(f"{side}_hip"), 0])  # toward the foot
        assert float(j[HIPS, 0].mean()) > bed.hinge_x(MAT)  # hips past the hinge


def test_half_sitting_is_deterministic_and_keeps_flat_partitions_as_they_were(anny32, sitting):
    poses, cfg = sitting
    alone = PoseSampler(anny32, cfg).sample([5])
    for f in ("shape", "root_rotation", "root_translation", "pose"):
        assert torch.equal(getattr(alone.params, f)[0], getattr(poses.params, f)[5])
    assert alone.head_angle_deg[0] == poses.head_angle_deg[5]
    flat = PoseSampler(anny32, SamplingConfig(partition="supine")).sample(range(3))
    assert (flat.head_angle_deg == 0).all() and all(b.flat for b in flat.beds())
    assert (flat.rejections["sit_up_rejections"] == 0).all()


def test_half_sitting_over_the_bed_keeps_limbs_over_the_mattress(anny32):
    poses = PoseSampler(anny32, SamplingConfig(partition="half_sitting", gender="female", over_bed=True)).sample(
        range(6)
    )
    (x0, x1), (y0, y1) = MAT.mattress_bounds_m
    ends = [J(f"{s}_{n}") for s in ("left", "right") for n in ("knee", "ankle", "foot", "elbow", "wrist", "hand")]
    for i, bed in enumerate(poses.beds()):
        s = bed.to_surface(poses.joints[i, ends], MAT)
        assert ((s[:, 0] > x0) & (s[:, 0] < x1) & (s[:, 1] > y0) & (s[:, 1] < y1)).all()


def test_over_the_bed_arms_are_drawn_where_they_will_lie(anny32):
    # Drawn over the flat bed's outline and then sat up, raised hands passed the head end of
    # the raised section and the whole pose was drawn again: 3.57 such attempts per sample
    # (sampling law 4). Measured on the head section (law 5) few remain; the same 24 samples.
    poses = PoseSampler(anny32, SamplingConfig(partition="half_sitting", gender="male", over_bed=True)).sample(
        range(24)
    )
    assert float(np.mean(poses.rejections["sit_up_rejections"])) < 1.0


def test_a_partition_mixing_flat_and_raised_beds_samples_both(anny32):
    part = dataclasses.replace(PARTITIONS["half_sitting"], head_angles_deg=(0.0, 30.0))
    for over_bed in (False, True):
        poses = PoseSampler(anny32, SamplingConfig(partition="half_sitting", over_bed=over_bed), partition=part).sample(
            range(6)
        )
        assert set(poses.head_angle_deg.tolist()) == {0.0, 30.0}


@pytest.mark.slow
def test_simulating_samples_on_different_beds_equals_simulating_each_bed(anny64):
    from pressurepose.sim.run import simulate_poses

    bed_a, bed_b = BedShape(0.0), BedShape(30.0)
    flat = PoseSampler(anny64, SamplingConfig(partition="supine", gender="male")).sample([1]).params
    sat = half_sitting_params(anny64, anny64.default_shape(1), bed_b, MAT)
    both = BodyParams(
        **{
            f: torch.cat([getattr(sat, f), getattr(flat, f)])
            for f in ("shape", "root_rotation", "root_translation", "pose")
        }
    )
    mixed = simulate_poses(anny64, both, bed=[bed_b, bed_a])
    alone = simulate_poses(anny64, flat, bed=bed_a)
    assert mixed.reason == ["", ""]
    np.testing.assert_array_equal(mixed.head_angle_deg, [30.0, 0.0])
    torch.testing.assert_close(mixed.pressure_mmhg[1], alone.pressure_mmhg[0], rtol=0, atol=0)
    torch.testing.assert_close(mixed.params.pose[1], alone.params.pose[0], rtol=0, atol=0)
    rows = (mixed.pressure_mmhg[0].sum(-1) > 0).nonzero().flatten()
    assert int(rows.min()) < 16 < int(rows.max())  # the sitting body loads both sides of the hinge (row 16)
    with pytest.raises(ValueError, match="one per sample"):
        simulate_poses(anny64, both, bed=[bed_a])
