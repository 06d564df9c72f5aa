"""Differentiable rotation helpers (batched torch, any float dtype, any device).

Rotation vectors (axis-angle) are (..., 3), matrices (..., 3, 3); matrices act on column
vectors (`R @ v`); quaternions here are (w, x, y, z) (MuJoCo's order; roma's is x, y, z, w).

The conversions are roma's (`roma.rotvec_to_unitquat`, `unitquat_to_rotmat`,
`rotmat_to_unitquat`, `unitquat_to_rotvec`); these names stay as thin wrappers because half the
package calls them. Rotation vector -> matrix goes through the unit quaternion rather than
`roma.rotvec_to_rotmat`: that one switches to the first-order I + K below 1e-6 rad (off by
theta^2 / 2, 5e-13 at the switch) and divides by the angle above it, which makes float32
gradients of small rotations wrong by up to 3e-5; through the quaternion (roma's sinc has a
Taylor branch chosen for its derivative) the matrix is within 1e-15 of Rodrigues' formula in
float64 and float32 gradients within 3e-7 at every angle, 0 included (the rest pose is all
zeros). What roma does not have stays here: `rotation_angle` (see its docstring),
`rotation_between`, `swing_twist` and `skew`.
"""

from __future__ import annotations

import roma
import torch


def axis_angle_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """(..., 3) rotation vectors -> (..., 3, 3) rotation matrices (through roma's unit
    quaternion; exact gradients at the zero rotation)."""
    if rotvec.shape[-1:] != (3,):
        raise ValueError(f"rotvec must have shape (..., 3), got {tuple(rotvec.shape)}")
    return roma.unitquat_to_rotmat(roma.rotvec_to_unitquat(rotvec))


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 3) rotation vectors with angle in [0, pi]
    (`roma.rotmat_to_rotvec`: Markley's quaternion, stable everywhere except exactly at pi)."""
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3), got {tuple(R.shape)}")
    return roma.rotmat_to_rotvec(R)


def rotation_angle(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """Geodesic angle (rad, in [0, pi]) between rotation matrices R1, R2 (..., 3, 3): the
    angle of R = R1^T R2, as atan2(2 sin, 2 cos) with 2 cos = trace(R) - 1 and 2 sin = the
    norm of R's antisymmetric part (R32 - R23, R13 - R31, R21 - R12).

    Kept instead of roma for exactness: accurate to a few units of the dtype's round-off at
    every angle, 0 and pi included, where `roma.rotmat_geodesic_distance` (an asin of the
    chord |R2 - R1|) loses sqrt(eps) near pi and `rotmat_geodesic_distance_naive` (an acos of
    (trace - 1) / 2) loses it near 0 (~0.03 deg in float32); the metrics and the tests of
    rests and fits measure angles near both ends. Each entry of R is summed in the same order
    from elementwise products, so R is exactly symmetric, and the angle exactly 0, when
    R1 == R2 (no matmul whose rounding could differ between R_ij and R_ji)."""
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
    """(..., 3, 3) -> unit quaternions (..., 4) as (w, x, y, z) with w >= 0
    (`roma.rotmat_to_unitquat`, Markley's variant of Shepperd's method)."""
    q = roma.quat_xyzw_to_wxyz(roma.rotmat_to_unitquat(R))
    return torch.where(q[..., :1] < 0, -q, q)


def quaternion_to_axis_angle(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternions (..., 4) as (w, x, y, z) -> rotation vectors (..., 3) of angle
    2 atan2(|(x, y, z)|, w): in (pi, 2 pi) when w < 0, as the quaternion says (roma's
    `unitquat_to_rotvec` without `shortest_arc`)."""
    return roma.unitquat_to_rotvec(roma.quat_wxyz_to_xyzw(q), shortest_arc=False)


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
    2 atan2(v . axis, w) of the quaternion (v, w) of R (`roma.rotvec_to_unitquat`), which is
    smooth except for a swing of exactly pi.
    """
    q = roma.rotvec_to_unitquat(rotvec)  # (..., 4) as (x, y, z, w)
    axis = axis.to(rotvec).expand_as(rotvec)
    twist_angle = 2 * torch.atan2((q[..., :3] * axis).sum(-1, keepdim=True), q[..., 3:])
    twist = axis_angle_to_matrix(twist_angle * axis)
    swing = roma.unitquat_to_rotmat(q) @ twist.transpose(-1, -2)
    return swing, twist
