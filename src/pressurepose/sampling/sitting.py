"""Half-sitting on a bed whose head section is raised (seed A.2's sitting poses).

Sitting up pitches the trunk - with the head and both arms - up about the line through the
hip joints, across the bed (`fold_params`). The sampler draws the whole pose in the trunk's
frame and turns it rigidly (hip angles unchanged), measuring the legs' cells, heights and bed
outline in the bed's frame turned back by the pitch, so the legs land on the flat foot
section as drawn; a pose given lying flat (`half_sitting_params`) keeps its thighs instead
(each hip rotation conjugated by the pitch). The pitch is not the bed's angle: the
hips lie 10-40 cm foot-ward of the hinge (PmatData group F: the buttocks load rows 29-42
counted from the foot, the mat lifts off around rows 44-48, the upper back loads rows 49-56),
so the stiff trunk rests as a straight board on the buttocks and the upper back, less steep
than the head section. `trunk_pitch` finds that pitch by a grid search: the pitch at which the
trunk touches the foot section and the head section at once. `bed_lift` then lowers the body
onto the bent bed exactly (the mattress is the union of the half-spaces under the two
section planes, so a capsule clears it when both end points clear both planes).

The sampler checks the result again (hip limits, self-collisions, the over-bed rule in
surface coordinates, and that the trunk - not a hand or a heel - carries the body); sim #1
then settles it like any other pose.
"""

from __future__ import annotations

import dataclasses
import functools

import torch

from pressurepose.bed import BedShape
from pressurepose.body.capsules import CAPSULES, Capsules
from pressurepose.body.joints import J24_NAMES
from pressurepose.body.kinematics import forward_kinematics
from pressurepose.body.params import BodyParams, root_matrix
from pressurepose.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from pressurepose.mat import MatSpec

HIP_JOINTS = (J24_NAMES.index("left_hip"), J24_NAMES.index("right_hip"))
# Capsules that rest on the bed when sitting (none moves with a limb, so the pitch depends on
# the shape, root and bed only).
TRUNK_CAPSULES = tuple(
    i for i, c in enumerate(CAPSULES) if c.name in ("pelvis", "spine1", "spine2", "spine3", "neck", "head")
)
# The pitch's search: PITCH_ROUNDS grids of PITCH_GRID intervals, each within the last one's
# bracketing interval - the pitch to within 60 deg / 64^3 ~ 0.0002 deg in 3 batched evaluations
# of 65 pitches (the bisection before it: 18 steps and the 2 ends, one pitch at a time, ~6x the
# time; sampling law 5).
PITCH_GRID = 64
PITCH_ROUNDS = 3


def _about_y(pitch: torch.Tensor) -> torch.Tensor:
    zero = torch.zeros_like(pitch)
    return axis_angle_to_matrix(torch.stack([zero, pitch, zero], -1))


def fold_params(params: BodyParams, rest: torch.Tensor, pitch: torch.Tensor, keep_thighs: bool = True) -> BodyParams:
    """Sit B bodies up: trunk, head and arms pitched up by `pitch` (B,) rad about the mat's y
    axis through the midpoint of the hip joints. keep_thighs: the thighs keep their
    orientation (hip rotations conjugated by the pitch); otherwise the whole body turns
    rigidly. rest: (B, 24, 3) T-pose joints, pelvis at the origin. float64."""
    P = _about_y(pitch)  # (B, 3, 3) head up for pitch > 0
    R0 = root_matrix(params.root_rotation)
    t = params.root_translation
    c = (R0 @ rest[:, list(HIP_JOINTS)].mean(1)[..., None])[..., 0] + t  # hip midpoint, mat frame
    root = matrix_to_axis_angle(P @ axis_angle_to_matrix(params.root_rotation))
    trans = c + (P @ (t - c)[..., None])[..., 0]
    if not keep_thighs:
        return params.replace(root_rotation=root, root_translation=trans)
    Q = R0.transpose(1, 2) @ P @ R0  # the pitch in body axes
    pose = params.pose.clone()
    for j in HIP_JOINTS:
        pose[:, j - 1] = matrix_to_axis_angle(Q.transpose(1, 2) @ axis_angle_to_matrix(params.pose[:, j - 1]))
    return params.replace(root_rotation=root, root_translation=trans, pose=pose)


def _planes(bed: BedShape, mat: MatSpec, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit normals (K, 3) of the bed's section planes and a point (3,) on all of them."""
    return _planes_cached(bed, mat, like.dtype, like.device)


@functools.lru_cache(maxsize=64)
def _planes_cached(bed: BedShape, mat: MatSpec, dtype: torch.dtype, device: torch.device):
    # Built once per bed: the sampler asks for them several times per sample (the same
    # numbers). The tensors are shared, so callers only read them; made outside inference mode
    # (a first call inside it would cache tensors autograd cannot save).
    normals = [R[:, 2] for R, _, _ in bed.sections(mat)]
    with torch.inference_mode(False):
        hinge = torch.tensor([bed.hinge_x(mat), 0.0, 0.0], dtype=dtype, device=device)
        return torch.tensor([list(n) for n in normals], dtype=dtype, device=device), hinge


def capsule_gaps(
    start: torch.Tensor, end: torch.Tensor, radius: torch.Tensor, bed: BedShape, mat: MatSpec
) -> torch.Tensor:
    """(B, C, K) clearance (m) of each capsule (end points (B, C, 3), radius (B, C)) above each
    section plane of the undeformed mattress top (negative: inside)."""
    normals, hinge = _planes(bed, mat, start)
    da = (start - hinge) @ normals.T
    db = (end - hinge) @ normals.T
    return torch.minimum(da, db) - radius[..., None]


def bed_lift(start: torch.Tensor, end: torch.Tensor, radius: torch.Tensor, bed: BedShape, mat: MatSpec) -> torch.Tensor:
    """(B,) vertical shift (m) that makes the lowest capsule surface touch the bed: the mattress
    fills the half-spaces under the section planes, so every capsule must clear every plane."""
    normals, _ = _planes(bed, mat, start)
    gaps = capsule_gaps(start, end, radius, bed, mat)  # (B, C, K)
    return (-gaps / normals[:, 2]).flatten(1).amax(-1)


def _trunk(caps: Capsules, params: BodyParams):
    """The trunk capsules' lying end points (B, 2T, 3; starts then ends, mat frame), their radii
    (B, T), the hip midpoint c (B, 3) the body sits up about, and the root's matrix."""
    trunk = list(TRUNK_CAPSULES)
    R0 = root_matrix(params.root_rotation)
    rot, pos = forward_kinematics(caps.rest, params.pose, R0)
    a, b = caps.place(rot, pos, params.root_translation)
    c = (R0 @ caps.rest[:, list(HIP_JOINTS)].mean(1)[..., None])[..., 0] + params.root_translation
    return torch.cat([a[:, trunk], b[:, trunk]], 1), caps.radius[:, trunk], c, R0


def _pitch_search(ends, radius, c, bed: BedShape, mat: MatSpec) -> torch.Tensor:
    """`trunk_pitch` on the trunk's lying end points (`_trunk`), for a raised bed."""
    B, T = radius.shape
    normals, _ = _planes(bed, mat, ends)
    rel = ends - c[:, None]

    def excess(pitch: torch.Tensor) -> torch.Tensor:
        # (B, N) pitches -> (B, N); > 0: the head section lies lower than the foot section
        # under the trunk (pitch enough).
        cs, sn = torch.cos(pitch)[..., None], torch.sin(pitch)[..., None]
        x = c[:, None, None, 0] + cs * rel[:, None, :, 0] + sn * rel[:, None, :, 2]  # rotation about y, head up
        z = c[:, None, None, 2] - sn * rel[:, None, :, 0] + cs * rel[:, None, :, 2]
        pts = torch.stack([x, ends[:, None, :, 1].expand_as(x), z], -1)
        gaps = capsule_gaps(pts[:, :, :T], pts[:, :, T:], radius[:, None], bed, mat).amin(2)  # (B, N, K)
        return gaps[..., 0] / normals[0, 2] - gaps[..., 1]

    # Each round evaluates a grid over [lo, hi] (excess < 0 at lo: the head section still in the
    # way; >= 0 at hi) and keeps the interval where it first turns >= 0.
    lo = torch.zeros(B, dtype=rel.dtype)
    hi = torch.full((B,), bed.angle_rad, dtype=rel.dtype)
    steps = torch.arange(PITCH_GRID + 1, dtype=rel.dtype) / PITCH_GRID
    rows = torch.arange(B)
    for r in range(PITCH_ROUNDS):
        grid = lo[:, None] + (hi - lo)[:, None] * steps
        f = excess(grid)
        if r == 0:
            f_lo, f_hi = f[:, 0], f[:, -1]
        # the first grid point where it is >= 0; the last one when none is (only when the
        # whole range is still "up" - then the bed's angle below - or by round-off at hi)
        ok = f[:, 1:] >= 0
        first = torch.where(ok.any(1), ok.to(torch.int8).argmax(1) + 1, PITCH_GRID)
        lo, hi = grid[rows, first - 1], grid[rows, first]
    pitch = (lo + hi) / 2
    pitch = torch.where(f_hi < 0, torch.full_like(pitch, bed.angle_rad), pitch)
    return torch.where(f_lo >= 0, torch.zeros_like(pitch), pitch)


def trunk_pitch(caps: Capsules, params: BodyParams, bed: BedShape, mat: MatSpec) -> torch.Tensor:
    """(B,) pitch (rad, 0 .. the bed's angle) at which the sat-up trunk rests on both bed
    sections at once (grids, `PITCH_GRID`); the bed's angle when the trunk cannot reach the foot
    section that steep, 0 when it does not reach the head section lying flat.

    Sitting up moves the trunk capsules rigidly about the hip midpoint (what `fold_params`
    does to them), so the search turns their lying end points and never re-poses the body."""
    if bed.flat:
        return torch.zeros(params.batch_size, dtype=params.root_translation.dtype)
    ends, radius, c, _ = _trunk(caps, params)
    return _pitch_search(ends, radius, c, bed, mat)


def pitch_matrix(root_rotation: torch.Tensor, pitch: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) the sitting pitch in body axes, Q = R0^T P R0: a body-axes vector v of the
    turned body points where Q v pointed before."""
    R0 = root_matrix(root_rotation)
    return R0.transpose(1, 2) @ _about_y(pitch) @ R0


@dataclasses.dataclass(frozen=True)
class SitUpFrame:
    """How B bodies lying in the trunk's frame will lie once sat up (`sit_up_frame`)."""

    pitch: torch.Tensor  # (B,) rad (`trunk_pitch`)
    turn: torch.Tensor  # (B, 3, 3) the pitch in body axes (`pitch_matrix`)
    pelvis: torch.Tensor  # (B, 3) the pelvis turned up, not yet lowered (`fold_params`' translation)
    # A point v of the body (body axes, from the pelvis) lies at the head section's surface
    # coordinate s = head_row . v + head_offset (`BedShape.to_surface`) once the body is lowered
    # until its trunk touches the bed.
    head_row: torch.Tensor  # (B, 3)
    head_offset: torch.Tensor  # (B,)


def sit_up_frame(caps: Capsules, params: BodyParams, bed: BedShape, mat: MatSpec) -> SitUpFrame:
    """Where B bodies given lying (pose in the trunk's frame, pelvis over the bed) go when
    `sit_up` turns them rigidly (keep_thighs False) by their `trunk_pitch`, from one forward
    kinematics pass. On a flat bed: no pitch, and the map is the mat's x.

    The head-section map is exact when the trunk carries the body. A limb lower than the trunk
    lifts it further (by seat / cos(angle) for a seat clearance `seat`), which only moves s
    toward the head end: a bound at the head end tested with the map passes every pose the
    exact test passes once sat up. Over the foot section the map is not that section's s; a
    bound at the foot end tested with it holds for arms only because they stay far (> 1 m) from
    the foot end. Across the bed the map is exact (the turn is about the mat's y axis and the
    lift vertical). The sat-up pose is still checked exactly (sampler)."""
    if bed.flat:
        B, dtype = params.batch_size, params.root_translation.dtype
        return SitUpFrame(
            pitch=torch.zeros(B, dtype=dtype),
            turn=torch.eye(3, dtype=dtype).expand(B, 3, 3).clone(),
            pelvis=params.root_translation.clone(),
            head_row=root_matrix(params.root_rotation)[:, 0].clone(),  # the mat's x axis in body axes
            head_offset=params.root_translation[:, 0].clone(),
        )
    ends, radius, c, R0 = _trunk(caps, params)
    pitch = _pitch_search(ends, radius, c, bed, mat)
    P = _about_y(pitch)
    turned = (P[:, None] @ (ends - c[:, None])[..., None])[..., 0] + c[:, None]
    T = radius.shape[1]
    lift = bed_lift(turned[:, :T], turned[:, T:], radius, bed, mat)
    pelvis = c + (P @ (params.root_translation - c)[..., None])[..., 0]
    (R_head, _, _), _ = bed.sections(mat)
    t = torch.as_tensor(R_head[:, 0], dtype=ends.dtype)  # the head section's tangent along s
    hinge = bed.hinge_x(mat)
    return SitUpFrame(
        pitch=pitch,
        turn=R0.transpose(1, 2) @ P @ R0,
        pelvis=pelvis,
        head_row=(P @ R0).transpose(1, 2) @ t,
        head_offset=hinge + (pelvis[:, 0] - hinge) * t[0] + (pelvis[:, 2] + lift) * t[2],
    )


def sit_up(
    caps: Capsules,
    params: BodyParams,
    bed: BedShape,
    mat: MatSpec,
    pitch: torch.Tensor | None = None,
    keep_thighs: bool = True,
) -> tuple[BodyParams, torch.Tensor]:
    """Sit bodies up on a raised bed and lower them onto it.

    caps: their capsules (T-pose); params: the pose in the trunk's frame with the pelvis placed
    over the bed (its height is ignored); pitch: (B,) rad (default `trunk_pitch`); keep_thighs:
    see `fold_params`. Returns the sat-up parameters, whose lowest capsule surface touches the
    bent mattress top, and the trunk's lowest clearance (B,) m above the bed (0 when the trunk
    carries the body; larger when a limb props it up)."""
    if pitch is None:
        pitch = trunk_pitch(caps, params, bed, mat)
    p = fold_params(params, caps.rest, pitch, keep_thighs)
    a, b = caps.posed(p.pose, p.root_rotation, p.root_translation)
    lift = bed_lift(a, b, caps.radius, bed, mat)
    trans = p.root_translation.clone()
    trans[:, 2] = trans[:, 2] + lift
    a, b = (
        a + lift[:, None, None] * a.new_tensor([0.0, 0.0, 1.0]),
        b + lift[:, None, None] * b.new_tensor([0.0, 0.0, 1.0]),
    )
    trunk = list(TRUNK_CAPSULES)
    seat = capsule_gaps(a[:, trunk], b[:, trunk], caps.radius[:, trunk], bed, mat).flatten(1).amin(-1)
    return p.replace(root_translation=trans), seat


def half_sitting_params(
    model, shape: torch.Tensor, bed: BedShape, mat: MatSpec | None = None, hip_offset_m: float = 0.15
) -> BodyParams:
    """BodyParams (float64) of B bodies in the home pose (legs straight, arms at the sides)
    half-sitting on a raised bed: hips `hip_offset_m` (a number or one per body, (B,)) foot-ward
    of the hinge, centred across the bed, sat up and lowered onto it as the half_sitting
    partition does."""
    from pressurepose.body.capsules import fit_capsules, home_pose

    mat = mat or MatSpec()
    shape = shape.to(torch.float64)
    B = shape.shape[0]
    with torch.no_grad():
        caps = fit_capsules(model, shape)
    caps = Capsules(*(x.to(torch.float64).cpu() for x in (caps.start, caps.end, caps.radius, caps.rest)))
    root = torch.zeros(B, 3, dtype=torch.float64)
    hips = (root_matrix(root) @ caps.rest[:, list(HIP_JOINTS)].mean(1)[..., None])[..., 0]
    trans = torch.stack(
        [
            bed.hinge_x(mat) + hip_offset_m - hips[:, 0],
            torch.full((B,), mat.sensing_width_m / 2, dtype=torch.float64) - hips[:, 1],
            torch.zeros(B, dtype=torch.float64),
        ],
        -1,
    )
    params = BodyParams(shape=shape.cpu(), root_rotation=root, root_translation=trans, pose=home_pose(B))
    return sit_up(caps, params, bed, mat)[0]


__all__ = [
    "PITCH_GRID",
    "PITCH_ROUNDS",
    "TRUNK_CAPSULES",
    "bed_lift",
    "capsule_gaps",
    "fold_params",
    "half_sitting_params",
    "SitUpFrame",
    "sit_up_frame",
    "pitch_matrix",
    "sit_up",
    "trunk_pitch",
]
