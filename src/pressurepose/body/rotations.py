"""Differentiable rotation helpers (batched torch, any float dtype, any device).

Rotation vectors (axis-angle) are (..., 3), matrices (..., 3, 3); matrices act on column
vectors (`R @ v`). Every function is smooth where the rotation it describes is defined:
gradients are exact at the zero rotation (Taylor branches), which matters because the rest
pose is all zeros.
"""

from __future__ import annotations

import torch

_SMALL = 1e-4  # below this angle (rad) the Taylor branches are exact to float64 round-off


def axis_angle_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula: (..., 3) rotation vectors -> (..., 3, 3) rotation matrices."""
    if rotvec.shape[-1:] != (3,):
        raise ValueError(f"rotvec must have shape (..., 3), got {tuple(rotvec.shape)}")
    theta2 = (rotvec * rotvec).sum(-1, keepdim=True)
    small = theta2 < _SMALL**2
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    safe = safe2.sqrt()
    # sin(t)/t and (1 - cos(t))/t^2, Taylor-expanded near zero so the gradient stays exact.
    a = torch.where(small, 1 - theta2 / 6 + theta2**2 / 120, torch.sin(safe) / safe)
    b = torch.where(small, 0.5 - theta2 / 24 + theta2**2 / 720, (1 - torch.cos(safe)) / safe2)
    K = skew(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device).expand_as(K)
    return eye + a[..., None] * K + b[..., None] * (K @ K)


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 3) rotation vectors with angle in [0, pi].

    Goes through the quaternion, which is stable everywhere except exactly at pi.
    """
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3), got {tuple(R.shape)}")
    return quaternion_to_axis_angle(matrix_to_quaternion(R))


def rotation_angle(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """Geodesic angle (rad, in [0, pi]) between rotation matrices R1, R2 (..., 3, 3): the
    angle of R = R1^T R2, as atan2(2 sin, 2 cos) with 2 cos = trace(R) - 1 and 2 sin = the
    norm of R's antisymmetric part (R32 - R23, R13 - R31, R21 - R12).

    Accurate to a few units of the dtype's round-off at every angle, 0 and pi included, where
    acos((trace - 1) / 2) loses sqrt(eps) (~0.03 deg in float32 at 0) and asin of the chord
    loses it near pi. Each entry of R is summed in the same order from elementwise products,
    so R is exactly symmetric, and the angle exactly 0, when R1 == R2 (no matmul whose
    rounding could differ between R_ij and R_ji)."""
    if R1.shape[-2:] != (3, 3) or R2.shape[-2:] != (3, 3):
        raise ValueError(f"R1 and R2 must have shape (..., 3, 3), got {tuple(R1.shape)} and {tuple(R2.shape)}")
    P = R1[..., :, :, None] * R2[..., :, None, :]  # P[..., k, i, j] = R1[k, i] R2[k, j]
    M = P[..., 0, :, :] + P[..., 1, :, :] + P[..., 2, :, :]  # R1^T R2
    cos2 = M[..., 0, 0] + M[..., 1, 1] + M[..., 2, 2] - 1
    sin2 = torch.stack(
        [M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1
    ).norm(dim=-1)
    return torch.atan2(sin2, cos2)


def matrix_to_quaternion(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> unit quaternions (..., 4) as (w, x, y, z) with w >= 0."""
    m = R
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    # Four candidate (unnormalised) quaternions, each well conditioned in its own region;
    # pick per element the one with the largest denominator (Shepperd's method).
    cands = torch.stack(
        [
            torch.stack(
                [1 + trace, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1
            ),
            torch.stack(
                [
                    m[..., 2, 1] - m[..., 1, 2],
                    1 + 2 * m[..., 0, 0] - trace,
                    m[..., 0, 1] + m[..., 1, 0],
                    m[..., 0, 2] + m[..., 2, 0],
                ],
                -1,
            ),
            torch.stack(
                [
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 0, 1] + m[..., 1, 0],
                    1 + 2 * m[..., 1, 1] - trace,
                    m[..., 1, 2] + m[..., 2, 1],
                ],
                -1,
            ),
            torch.stack(
                [
                    m[..., 1, 0] - m[..., 0, 1],
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 1, 2] + m[..., 2, 1],
                    1 + 2 * m[..., 2, 2] - trace,
                ],
                -1,
            ),
        ],
        -2,
    )  # (..., 4, 4): row k is candidate k
    diag = torch.stack(
        [1 + trace, 1 + 2 * m[..., 0, 0] - trace, 1 + 2 * m[..., 1, 1] - trace, 1 + 2 * m[..., 2, 2] - trace], -1
    )
    best = diag.argmax(-1, keepdim=True)
    q = torch.gather(cands, -2, best[..., None].expand(*best.shape, 4)).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def quaternion_to_axis_angle(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternions (..., 4) as (w, x, y, z) -> rotation vectors (..., 3)."""
    w, v = q[..., :1], q[..., 1:]
    s2 = (v * v).sum(-1, keepdim=True)
    small = s2 < _SMALL**2
    s = torch.where(small, torch.ones_like(s2), s2).sqrt()
    angle = 2 * torch.atan2(s, w)
    # angle / sin(angle / 2) -> 2 / w near zero (first order is exact enough there).
    factor = torch.where(small, 2 / w * (1 + s2 / (6 * w * w)), angle / s)
    return v * factor


def skew(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) cross-product matrices, skew(a) @ b == a x b."""
    zero = torch.zeros_like(v[..., 0])
    x, y, z = v.unbind(-1)
    return torch.stack(
        [torch.stack([zero, -z, y], -1), torch.stack([z, zero, -x], -1), torch.stack([-y, x, zero], -1)],
        -2,
    )


def rotation_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Smallest rotation (..., 3, 3) taking direction a (..., 3) onto direction b (..., 3).

    a and b need not be unit length; undefined only for exactly opposite directions.
    """
    a = a / a.norm(dim=-1, keepdim=True)
    b = b / b.norm(dim=-1, keepdim=True)
    axis = torch.linalg.cross(a, b, dim=-1)
    cos = (a * b).sum(-1, keepdim=True)
    K = skew(axis)
    eye = torch.eye(3, dtype=a.dtype, device=a.device).expand_as(K)
    # R = I + K + K^2 / (1 + cos): exact, no trigonometry, smooth away from cos = -1.
    return eye + K + (K @ K) / (1 + cos)[..., None]


def swing_twist(rotvec: torch.Tensor, axis: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Split rotations R(rotvec) = swing @ twist, twist about the unit `axis` (3,) or (..., 3).

    Returns (swing, twist) as (..., 3, 3) matrices. The twist angle is
    2 atan2(v . axis, w) of the quaternion (w, v) of R, which is smooth except for a swing
    of exactly pi.
    """
    theta2 = (rotvec * rotvec).sum(-1, keepdim=True)
    small = theta2 < _SMALL**2
    theta = torch.where(small, torch.ones_like(theta2), theta2).sqrt()
    half_sinc = torch.where(small, 0.5 - theta2 / 48, torch.sin(theta / 2) / theta)
    w = torch.where(small, 1 - theta2 / 8, torch.cos(theta / 2))
    v = rotvec * half_sinc
    axis = axis.to(rotvec).expand_as(rotvec)
    twist_angle = 2 * torch.atan2((v * axis).sum(-1, keepdim=True), w)
    twist = axis_angle_to_matrix(twist_angle * axis)
    swing = axis_angle_to_matrix(rotvec) @ twist.transpose(-1, -2)
    return swing, twist
