"""Differentiable rotation helpers (batched torch, any float dtype, any device).

Rotation vectors (axis-angle) are (..., 3), matrices (..., 3, 3); matrices act on column
vectors (`R @ v`); quaternions here are (w, x, y, z) (MuJoCo's order; roma's is x, y, z, w).

The conversions are roma's (`roma.rotvec_to_unitquat`, `unitquat_to_rotmat`,
`rotmat_to_unitquat`, `unitquat_to_rotvec`) except the one every pose passes through: rotation
vector -> matrix is written here, through the unit quaternion (w, v) = (cos h, sin(h) / (2 h) phi),
h = |phi| / 2, as roma does it (not `roma.rotvec_to_rotmat`, which switches to the first-order
I + K below 1e-6 rad and so makes float32 gradients of small rotations wrong by up to 3e-5), but
in a third of the time (one body's 23 joints: 0.42 -> 0.13 ms, all of it per-operation overhead;
predict at batch 1 converts ~12 times; docs/benchmarks.md, session 57). The half-angle sinc takes its Taylor series below roma's threshold (2 eps^(1/6)), chosen for
the first derivative, so the matrix is within 1e-15 of Rodrigues' formula in float64 and float32
gradients within 3e-7 at every angle, 0 included (the rest pose is all zeros). What roma does
not have stays here too: `rotation_angle` (see its docstring), `rotation_between`, `swing_twist`
and `skew`.
"""

from __future__ import annotations

import roma
import torch

from pressurepose.constants import kept

_EPSILON_TENSOR = torch.zeros(3, 3, 3)  # [k, i, j]: skew(v)[i, j] = sum_k v[k] E[k, i, j]
for _k, _i, _j in ((0, 2, 1), (1, 0, 2), (2, 1, 0)):
    _EPSILON_TENSOR[_k, _i, _j], _EPSILON_TENSOR[_k, _j, _i] = 1.0, -1.0
_CONSTANTS: dict[tuple[torch.dtype, torch.device], tuple[torch.Tensor, ...]] = {}


def _constants(like: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The conversion's constants in `like`'s dtype and device, made once: the (3, 9) cross-product
    map, the identity and 0-d tensors (an operation with a Python number costs ~2x one with a
    0-d tensor at these sizes): 1/2, 1/12, 1/240, roma's sinc threshold on h, 1."""
    dtype, device = like.dtype, like.device
    numbers = (0.5, 1 / 12, 1 / 240, 2.0 * torch.finfo(dtype).eps ** (1 / 6), 1.0)
    return kept(
        _CONSTANTS,
        (dtype, device),
        lambda: (
            _EPSILON_TENSOR.reshape(3, 9).to(dtype).to(device),
            torch.eye(3, dtype=dtype, device=device),
            *(torch.tensor(x, dtype=dtype, device=device) for x in numbers),
        ),
    )


def _quaternion(rotvec: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Angle |phi| (..., 1), and the unit quaternion's w = cos(h) (..., 1) and v (..., 3)."""
    _, _, half, twelfth, c240, threshold, one = _constants(rotvec)
    angle = torch.linalg.vector_norm(rotvec, dim=-1, keepdim=True)  # its gradient at 0 is 0
    h = angle * half
    small = h < threshold
    h2 = h * h
    # s = sin(h) / (2 h), its Taylor series 1/2 - h^2 / 12 + h^4 / 240 below the threshold
    taylor = half - h2 * (twelfth - h2 * c240)
    s = torch.where(small, taylor, torch.sin(h) / torch.where(small, one, h) * half)
    return angle, torch.cos(h), rotvec * s


def axis_angle_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """(..., 3) rotation vectors -> (..., 3, 3) rotation matrices, through the unit quaternion
    (module doc; exact gradients at the zero rotation)."""
    if rotvec.shape[-1:] != (3,):
        raise ValueError(f"rotvec must have shape (..., 3), got {tuple(rotvec.shape)}")
    return _matrix(*_quaternion(rotvec))


def _matrix(angle: torch.Tensor, w: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """The rotation matrix of `_quaternion`'s (angle, w, v)."""
    cross, eye = _constants(v)[:2]
    # R = 2 (v v^T + w skew(v)) + (w^2 - |v|^2) I, and w^2 - |v|^2 = cos(2 h)
    vv = torch.addcmul(v.unsqueeze(-1) * v.unsqueeze(-2), w.unsqueeze(-1), (v @ cross).unflatten(-1, (3, 3)))
    return torch.add(torch.cos(angle).unsqueeze(-1) * eye, vv, alpha=2)


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
    return (v @ _constants(v)[0]).unflatten(-1, (3, 3))


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
    2 atan2(v . axis, w) of the quaternion (w, v) of R, which is
    smooth except for a swing of exactly pi.
    """
    angle, w, v = _quaternion(rotvec)
    axis = axis.to(rotvec).expand_as(rotvec)
    twist_angle = 2 * torch.atan2((v * axis).sum(-1, keepdim=True), w)
    twist = axis_angle_to_matrix(twist_angle * axis)
    swing = _matrix(angle, w, v) @ twist.transpose(-1, -2)
    return swing, twist
