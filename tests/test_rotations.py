import math

import numpy as np
import pytest
import roma
import torch
from torch.autograd import gradcheck

from pressurepose.body import rotations as rotations_module
from pressurepose.body.rotations import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    matrix_to_quaternion,
    quaternion_to_axis_angle,
    rotation_angle,
    rotation_between,
    skew,
    swing_twist,
)
from pressurepose.sampling.poses import root_axis_angle, root_axis_angles


def naive_rodrigues(r):
    theta = r.norm()
    if theta == 0:
        return torch.eye(3, dtype=r.dtype)
    k = r / theta
    K = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=r.dtype)
    return torch.eye(3, dtype=r.dtype) + math.sin(theta) * K + (1 - math.cos(theta)) * K @ K


def test_rodrigues_matches_naive_and_is_orthonormal():
    torch.manual_seed(0)
    r = torch.randn(20, 3, dtype=torch.float64) * 1.5
    r[0] = 0
    r[1] = 1e-7
    R = axis_angle_to_matrix(r)
    for i in range(20):
        assert torch.allclose(R[i], naive_rodrigues(r[i]), atol=1e-12)
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(20, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(20, dtype=torch.float64))


def test_gradients_exact_at_zero_and_elsewhere():
    r = torch.zeros(2, 3, dtype=torch.float64, requires_grad=True)
    assert gradcheck(axis_angle_to_matrix, (r,))
    r = (torch.randn(4, 3, dtype=torch.float64)).requires_grad_()
    assert gradcheck(axis_angle_to_matrix, (r,))
    assert gradcheck(lambda x: swing_twist(x, torch.tensor([1.0, 0, 0], dtype=torch.float64)), (r,))


def test_axis_angle_round_trip():
    torch.manual_seed(1)
    r = torch.randn(100, 3, dtype=torch.float64)
    r = r / r.norm(dim=-1, keepdim=True) * torch.rand(100, 1, dtype=torch.float64) * 3.0
    assert torch.allclose(matrix_to_axis_angle(axis_angle_to_matrix(r)), r, atol=1e-9)


def test_rotation_between_and_swing_twist():
    torch.manual_seed(2)
    a, b = torch.randn(10, 3, dtype=torch.float64), torch.randn(10, 3, dtype=torch.float64)
    R = rotation_between(a, b)
    Ra = (R @ a[..., None])[..., 0]
    assert torch.allclose(Ra / Ra.norm(dim=-1, keepdim=True), b / b.norm(dim=-1, keepdim=True), atol=1e-12)
    axis = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    r = torch.randn(10, 3, dtype=torch.float64)
    swing, twist = swing_twist(r, axis)
    assert torch.allclose(swing @ twist, axis_angle_to_matrix(r), atol=1e-12)
    # The twist keeps the axis fixed; the swing has no component about it.
    assert torch.allclose(twist @ axis, axis.expand(10, 3), atol=1e-12)
    assert torch.allclose(matrix_to_axis_angle(swing)[:, 0], torch.zeros(10, dtype=torch.float64), atol=1e-9)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("theta", [0.0, 1e-6, math.pi / 2, math.pi - 1e-6, math.pi])
def test_rotation_angle_is_accurate_at_every_angle(dtype, theta):
    # R2 = R1 Rot(axis, theta), built in float64: the angle between them is theta (to float64
    # round-off), whatever R1 and the axis. Rounded to `dtype`, the matrices move by eps/2 per
    # entry, so the angle may move by a few eps (in rad) - at 0 and pi too, where
    # acos((trace - 1) / 2) is off by sqrt(eps) (3e-4 rad in float32).
    g = torch.Generator().manual_seed(5)
    R1 = axis_angle_to_matrix(torch.randn(64, 3, generator=g, dtype=torch.float64) * 2)
    axis = torch.randn(64, 3, generator=g, dtype=torch.float64)
    Rt = axis_angle_to_matrix(axis / axis.norm(dim=-1, keepdim=True) * theta)
    R2 = R1 @ Rt
    got = rotation_angle(R1.to(dtype), R2.to(dtype))
    assert got.dtype == dtype and got.shape == (64,)
    err = (got.double() - theta).abs().max()
    assert err <= 8 * torch.finfo(dtype).eps, (theta, float(err))
    # Against itself, every rotation is exactly 0 away; the function is symmetric (bitwise:
    # each entry of R2^T R1 is the same sum of the same products as that of R1^T R2).
    assert (rotation_angle(R2.to(dtype), R2.to(dtype)) == 0).all()
    assert torch.equal(rotation_angle(R2.to(dtype), R1.to(dtype)), got)
    # The float64 result is the reference for the float32 one within float32's resolution.
    if dtype == torch.float32:
        ref = rotation_angle(R1.float().double(), R2.float().double())
        assert (got.double() - ref).abs().max() <= 4 * torch.finfo(dtype).eps


def test_rotation_angle_rejects_bad_shapes():
    with pytest.raises(ValueError, match="3, 3"):
        rotation_angle(torch.eye(3), torch.eye(4))


@pytest.mark.parametrize("theta", [0.0, 1e-7, 1e-6, 2e-6, 1e-5, 1e-4, 1e-3, 0.1, 3.0])
def test_float32_gradients_match_float64_at_every_angle(theta):
    # The network trains in float32 through axis_angle_to_matrix, from a rest pose of zeros: its
    # gradients must be float32-accurate at small angles too (roma.rotvec_to_rotmat's branch
    # switch at 1e-6 rad is off by 2e-6 there and by 3e-5 at 1e-3; the quaternion path is not).
    axis = torch.tensor([[0.3, -0.5, 0.8]], dtype=torch.float64)
    r64 = (axis / axis.norm() * theta).requires_grad_()
    r32 = r64.detach().float().requires_grad_()
    weights = torch.randn(1, 3, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    (axis_angle_to_matrix(r64) * weights).sum().backward()
    (axis_angle_to_matrix(r32) * weights.float()).sum().backward()
    assert (r32.grad.double() - r64.grad).abs().max() <= 1e-6


def test_quaternions_are_w_first_and_keep_their_angle():
    torch.manual_seed(4)
    r = torch.randn(50, 3, dtype=torch.float64)
    r = r / r.norm(dim=-1, keepdim=True) * torch.rand(50, 1, dtype=torch.float64) * 3.0
    q = matrix_to_quaternion(axis_angle_to_matrix(r))
    half = r.norm(dim=-1) / 2
    assert (q[:, 0] >= 0).all()
    assert torch.allclose(q[:, 0], torch.cos(half), atol=1e-12)
    assert torch.allclose(q[:, 1:], r / r.norm(dim=-1, keepdim=True) * torch.sin(half)[:, None], atol=1e-12)
    assert torch.allclose(quaternion_to_axis_angle(q), r, atol=1e-12)
    # -q is the same rotation; its angle is 2 pi - theta about the opposite axis, as MuJoCo's
    # joint quaternions say (no shortest-arc flip: a rest's pose stays continuous).
    flipped = quaternion_to_axis_angle(-q)
    assert torch.allclose(flipped.norm(dim=-1), 2 * math.pi - r.norm(dim=-1), atol=1e-12)
    assert torch.allclose(axis_angle_to_matrix(flipped), axis_angle_to_matrix(r), atol=1e-12)


@pytest.mark.parametrize("roll, yaw", [(0.0, 0.0), (1e-9, 0.0), (0.4, -1.2), (math.pi / 2, 2.0), (-2.9, 3.1)])
def test_root_axis_angle_is_yaw_after_roll(roll, yaw):
    aa = torch.from_numpy(root_axis_angle(roll, yaw))
    Rz = axis_angle_to_matrix(torch.tensor([0.0, 0.0, yaw], dtype=torch.float64))
    Rx = axis_angle_to_matrix(torch.tensor([roll, 0.0, 0.0], dtype=torch.float64))
    assert aa.dtype == torch.float64 and aa.shape == (3,) and aa.norm() <= math.pi
    assert torch.allclose(axis_angle_to_matrix(aa), Rz @ Rx, atol=1e-14)


def test_root_axis_angles_of_a_batch_are_those_of_one_sample_bit_for_bit():
    # The sampler converts every new root of an attempt at once: each row must have the bits
    # it has alone, whatever the batch (a sample follows from its seed and index only).
    rng = np.random.default_rng(4)
    roll = np.concatenate([rng.uniform(-math.pi, math.pi, 300), [0.0, math.pi, -math.pi, 1e-9, 0.0]])
    yaw = np.concatenate([rng.uniform(-math.pi / 6, math.pi / 6, 300), [0.0, 0.3, -0.2, 0.0, 1e-3]])
    alone = np.stack([root_axis_angle(r, y) for r, y in zip(roll, yaw)])
    for size in (1, 3, 8, 64, 305):
        batched = np.concatenate([root_axis_angles(roll[i : i + size], yaw[i : i + size]) for i in range(0, 305, size)])
        assert batched.tobytes() == alone.tobytes()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_matrix_matches_roma_quaternion_path_in_value_and_gradient(dtype):
    # The conversion is written out (fewer operations) but must be roma's quaternion path:
    # same matrices and gradients at angles on both sides of the Taylor threshold, and batched.
    g = torch.Generator().manual_seed(6)
    axis = torch.randn(7, 5, 3, generator=g, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angles = torch.tensor([0.0, 1e-8, 1e-4, 3e-3, 0.1, 0.3, 1.0, 3.1], dtype=torch.float64)
    r = (axis[:, :, None] * angles[:, None]).flatten(1, 2).to(dtype).requires_grad_()  # (7, 40, 3)
    r_ref = r.detach().clone().requires_grad_()
    weights = torch.randn(7, 40, 3, 3, generator=g, dtype=torch.float64).to(dtype)
    R = axis_angle_to_matrix(r)
    R_ref = roma.unitquat_to_rotmat(roma.rotvec_to_unitquat(r_ref))
    (R * weights).sum().backward()
    (R_ref * weights).sum().backward()
    tol = 4 * torch.finfo(dtype).eps
    assert R.shape == (7, 40, 3, 3)
    assert (R - R_ref).abs().max() <= tol
    assert (r.grad - r_ref.grad).abs().max() <= 8 * tol * weights.abs().max()


def test_skew_is_the_cross_product():
    g = torch.Generator().manual_seed(7)
    a, b = torch.randn(2, 4, 6, 3, generator=g, dtype=torch.float64)
    assert torch.allclose(skew(a) @ b[..., None], torch.linalg.cross(a, b)[..., None], atol=1e-15)
    assert torch.equal(skew(a), -skew(a).transpose(-1, -2))


def test_cached_constants_first_made_in_inference_mode_serve_autograd():
    # The conversions keep constants per dtype and device, made on first use: when that first
    # use is under inference mode (predict, the sampler), a later backward must still work.
    from pressurepose.body import limits, params

    caches = (rotations_module._CONSTANTS, params._SUPINE, limits._DEFAULTS)
    saved = [dict(c) for c in caches]
    for c in caches:
        c.clear()
    try:
        with torch.inference_mode():
            axis_angle_to_matrix(torch.zeros(1, 3))
            params.root_matrix(torch.zeros(1, 3))
            limits.JointLimits.default()
        r = torch.randn(2, 3, requires_grad=True)
        pose = torch.randn(2, 23, 3, requires_grad=True)
        loss = axis_angle_to_matrix(r).sum() + params.root_matrix(r).sum() + skew(r).sum()
        loss = (
            loss + limits.JointLimits.default().squash(pose).sum() + swing_twist(r, torch.tensor([1.0, 0, 0]))[0].sum()
        )
        loss.backward()
        assert torch.isfinite(r.grad).all() and torch.isfinite(pose.grad).all()
    finally:
        for c, s in zip(caches, saved):
            c.clear()
            c.update(s)
