"""Batched inverse kinematics: fit a body's J24 joints to localised joint positions.

The unknowns are the root translation t (3), the root rotation r (3, axis-angle, mat frame)
and the 23 joint rotations theta (69, axis-angle, BodyParams.pose); the shape, hence the
bone lengths (the rest joints `body.kinematics.rest_joints`), stays fixed. One step is a
damped Gauss-Newton step on

    E = sum_j w_j |p_j(t, r, theta) - q_j|^2 / sigma^2  +  |theta - theta_0|^2 / sigma_theta^2

(q the targets, w per-joint confidences, theta_0 the prior pose - the regression head's
answer). Under joint limits the pose is solved for in the squashed coordinates of the output
head, theta = JointLimits.squash(u) (the limits inflated by ALPHA, as the head's output), so
every step lands inside them and a joint's range shrinks its Jacobian columns (a hinge's two
locked axes barely move); the prior then reads |u - u_0|. A projection (solve freely, clamp)
was tried first: it stalled ~1 cm from reachable targets. The Jacobian is analytic,
so a step needs no autograd yet is itself differentiable (gradcheck in float64,
tests/test_heatmap.py). Without autograd `fit_to_joints` runs the same steps fused
(`ik_inference.fit`, ~2x faster at batch 1):

- translation: dp_k / dt = I for every joint;
- a rotation at joint j turns its strict descendants k about p_j: a perturbation d of its
  axis-angle theta_j turns the world by omega = R_parent(j) J_l(theta_j) d (J_l the left
  Jacobian of SO(3): exp(theta + d) = exp(J_l(theta) d) exp(theta) to first order), so
  dp_k / d d_i = a_i x (p_k - p_j), a_i the i-th column of R_parent(j) J_l(theta_j);
- the root rotation likewise with R_parent = I (root_matrix(r) = exp(r) R_supine).
"""

from __future__ import annotations

import dataclasses

import torch

from pressurepose.body.anny_skinning import wants_grad
from pressurepose.body.joints import J24_PARENTS, NUM_JOINTS, NUM_POSE_JOINTS
from pressurepose.body.kinematics import DESCENDANTS, pose_in_mat, rest_joints
from pressurepose.body.limits import ALPHA, JointLimits
from pressurepose.body.model import BodyModel
from pressurepose.body.params import BodyParams
from pressurepose.body.rotations import skew
from pressurepose.net import ik_inference

_SMALL = 1e-4
NUM_UNKNOWNS = 6 + 3 * NUM_POSE_JOINTS  # t, r, theta


@dataclasses.dataclass(frozen=True)
class IKConfig:
    """How the localised joints are fitted (defaults measured on validation data, docs/network.md)."""

    steps: int = 3
    joint_sigma_m: float = 0.03  # sigma: how far a localised joint is trusted
    prior_sigma_rad: float = 2.0  # sigma_theta: how far the pose may leave the head's answer
    damping: float = 1.0  # Levenberg-Marquardt mu added to the normal matrix (unitless)
    spread_weights: bool = True  # weight joint j by sigma^2 / (sigma^2 + its heatmap's variance)

    def __post_init__(self) -> None:
        if self.steps < 0:
            raise ValueError(f"IKConfig.steps must be >= 0, got {self.steps}")
        for name in ("joint_sigma_m", "prior_sigma_rad", "damping"):  # damping > 0: Cholesky needs it
            if not getattr(self, name) > 0:
                raise ValueError(f"IKConfig.{name} must be > 0, got {getattr(self, name)}")

    def weights(self, spread_m2: torch.Tensor) -> torch.Tensor:
        """(B, 24) per-joint weights from the heatmaps' variances (m^2): a diffuse heatmap (a
        limb the image does not show) is trusted less, and the prior takes over."""
        if not self.spread_weights:
            return torch.ones_like(spread_m2)
        return self.joint_sigma_m**2 / (self.joint_sigma_m**2 + spread_m2)


_DESCENDANTS_F = DESCENDANTS.float()  # the mask as a factor (float32 models: no conversion per step)
_PARENTS_OF_POSED = torch.tensor(J24_PARENTS[1:])


def left_jacobian(phi: torch.Tensor) -> torch.Tensor:
    """(..., 3) rotation vectors -> (..., 3, 3) left Jacobians of SO(3):
    I + (1 - cos a)/a^2 K + (a - sin a)/a^3 K^2, K = skew(phi), a = |phi| (Taylor near 0)."""
    a2 = (phi * phi).sum(-1, keepdim=True)
    small = a2 < _SMALL**2
    safe2 = torch.where(small, torch.ones_like(a2), a2)
    a = safe2.sqrt()
    b = torch.where(small, 0.5 - a2 / 24 + a2**2 / 720, (1 - torch.cos(a)) / safe2)
    c = torch.where(small, 1 / 6 - a2 / 120 + a2**2 / 5040, (a - torch.sin(a)) / (safe2 * a))
    K = skew(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand_as(K)
    return eye + b[..., None] * K + c[..., None] * (K @ K)


def joint_jacobian(rot: torch.Tensor, pos: torch.Tensor, params: BodyParams) -> torch.Tensor:
    """(B, 72, 75) d(joint positions, flattened (k, xyz)) / d(t, r, theta) at the posed body
    with world rotations rot (B, 24, 3, 3) and positions pos (B, 24, 3) (`pose_in_mat`)."""
    B = pos.shape[0]
    angles = torch.cat([params.root_rotation[:, None], params.pose], 1)  # (B, 24, 3)
    parent_rot = torch.cat(
        [torch.eye(3, dtype=rot.dtype, device=rot.device).expand(B, 1, 3, 3), rot[:, _PARENTS_OF_POSED.to(rot.device)]],
        1,
    )  # (B, 24, 3, 3)
    a = (parent_rot @ left_jacobian(angles)).transpose(-1, -2)[:, :, :, None, :]  # (B, j, i, 1, xyz)
    arm = pos[:, None, :, :] - pos[:, :, None, :]  # (B, j, k, xyz)
    d = (arm * _DESCENDANTS_F.to(arm)[None, :, :, None])[:, :, None]  # (B, j, 1, k, xyz), 0 off the subtree
    # a x d written out on broadcast views (linalg.cross materialises both (B, j, i, k, 3) operands)
    cols = torch.stack(
        [
            a[..., 1] * d[..., 2] - a[..., 2] * d[..., 1],
            a[..., 2] * d[..., 0] - a[..., 0] * d[..., 2],
            a[..., 0] * d[..., 1] - a[..., 1] * d[..., 0],
        ],
        -1,
    )  # (B, j, i, k, xyz)
    J_rot = cols.permute(0, 3, 4, 1, 2).reshape(B, 3 * NUM_JOINTS, 3 * NUM_JOINTS)
    J_t = torch.eye(3, dtype=pos.dtype, device=pos.device).repeat(NUM_JOINTS, 1).expand(B, -1, -1)
    return torch.cat([J_t, J_rot], -1)


@dataclasses.dataclass(frozen=True)
class IKState:
    """The unknowns of the fit: root translation (B, 3) m and rotation (B, 3) rad (mat frame),
    and the free pose u (B, 23, 3): the pose is JointLimits.squash(u) under limits, u without."""

    root_translation: torch.Tensor
    root_rotation: torch.Tensor
    free_pose: torch.Tensor

    def params(self, shape: torch.Tensor, limits: JointLimits | None) -> BodyParams:
        pose = self.free_pose if limits is None else limits.squash(self.free_pose, ALPHA)
        return BodyParams(
            shape=shape, root_rotation=self.root_rotation, root_translation=self.root_translation, pose=pose
        )


def free_pose(pose: torch.Tensor, limits: JointLimits | None) -> torch.Tensor:
    """(B, 23, 3) u with squash(u) = pose; angles at or beyond the inflated limits are taken
    from just inside them (float32 tanh reaches its bounds)."""
    if limits is None:
        return pose
    mid = (limits.lower + limits.upper).to(pose) / 2
    half = ALPHA * (limits.upper - limits.lower).to(pose) / 2
    x = ((pose - mid) / half).clamp(-1 + 1e-6, 1 - 1e-6)
    return torch.atanh(x) * half + mid


def ik_step(
    rest: torch.Tensor,
    shape: torch.Tensor,
    state: IKState,
    target: torch.Tensor,
    weights: torch.Tensor,
    prior_free_pose: torch.Tensor,
    config: IKConfig = IKConfig(),
    limits: JointLimits | None = None,
) -> IKState:
    """One damped Gauss-Newton step of the fit (module doc).

    rest (B, 24, 3): T-pose joints of `shape` (B, S) (pelvis at the origin, body axes);
    target (B, 24, 3) m, mat frame; weights (B, 24) >= 0; prior_free_pose (B, 23, 3): the
    prior's centre u_0 in free coordinates (`free_pose`). limits None: unconstrained angles.
    Differentiable in every tensor input."""
    B = rest.shape[0]
    for name, value, tail in (
        ("rest", rest, (NUM_JOINTS, 3)),
        ("target", target, (NUM_JOINTS, 3)),
        ("weights", weights, (NUM_JOINTS,)),
        ("prior_free_pose", prior_free_pose, (NUM_POSE_JOINTS, 3)),
        ("state.free_pose", state.free_pose, (NUM_POSE_JOINTS, 3)),
    ):
        if tuple(value.shape) != (B, *tail):
            raise ValueError(f"{name} must have shape {(B, *tail)}, got {tuple(value.shape)}")
    params = state.params(shape, limits)
    rot, pos = pose_in_mat(rest, params)
    slope = None
    if limits is not None:  # d theta / d u of theta = squash(u) = mid + half tanh((u - mid) / half)
        mid = (limits.lower + limits.upper).to(pos) / 2
        half = ALPHA * (limits.upper - limits.lower).to(pos) / 2
        slope = 1 - torch.tanh((state.free_pose - mid) / half).square()
    w = weights / config.joint_sigma_m**2  # (B, 24)
    residual = (pos - target).reshape(B, -1)
    prior = torch.zeros(NUM_UNKNOWNS, dtype=pos.dtype, device=pos.device)
    prior[6:] = 1.0 / config.prior_sigma_rad**2
    J = joint_jacobian(rot, pos, params)  # (B, 72, 75)
    if slope is not None:
        J = torch.cat([J[..., :6], J[..., 6:] * slope.reshape(B, 1, -1)], -1)
    Jw = J.transpose(1, 2) * w.repeat_interleave(3, 1)[:, None, :]  # (B, 75, 72)
    H = Jw @ J + torch.diag(prior + config.damping)
    g = (Jw @ residual[..., None])[..., 0]
    g = torch.cat([g[:, :6], g[:, 6:] + prior[6:] * (state.free_pose - prior_free_pose).reshape(B, -1)], 1)
    # H is symmetric positive definite (damping > 0): Cholesky, ~2x cheaper than LU (the upper
    # factor: ~15% faster than the lower one in torch 2.13 on a CPU)
    delta = -torch.cholesky_solve(g[..., None], torch.linalg.cholesky(H, upper=True), upper=True)[..., 0]  # (B, 75)
    return IKState(
        root_translation=state.root_translation + delta[:, :3],
        root_rotation=state.root_rotation + delta[:, 3:6],
        free_pose=state.free_pose + delta[:, 6:].reshape(B, NUM_POSE_JOINTS, 3),
    )


def fit_to_joints(
    body: BodyModel,
    params: BodyParams,
    target: torch.Tensor,
    weights: torch.Tensor | None = None,
    config: IKConfig = IKConfig(),
) -> BodyParams:
    """`config.steps` IK steps from `params` towards the targets (B, 24, 3), the pose prior
    centred on params.pose, within the default joint limits (inflated by ALPHA, as the
    output head's). weights (B, 24), default 1."""
    B = params.batch_size
    if target.shape != (B, NUM_JOINTS, 3):
        raise ValueError(f"target must have shape ({B}, {NUM_JOINTS}, 3), got {tuple(target.shape)}")
    if weights is not None and weights.shape != (B, NUM_JOINTS):
        raise ValueError(f"weights must have shape ({B}, {NUM_JOINTS}), got {tuple(weights.shape)}")
    if params.pose.shape != (B, NUM_POSE_JOINTS, 3):
        raise ValueError(f"params.pose must have shape ({B}, {NUM_POSE_JOINTS}, 3), got {tuple(params.pose.shape)}")
    if config.steps == 0:
        return params
    rest = rest_joints(body, params.shape)
    weights = torch.ones_like(target[..., 0]) if weights is None else weights
    target, weights = target.to(rest), weights.to(rest)
    limits = JointLimits.default(params.pose.dtype, params.pose.device)
    state = IKState(params.root_translation, params.root_rotation, free_pose(params.pose, limits))
    tensors = (rest, target, weights, params.shape, params.pose, params.root_rotation, params.root_translation)
    if not wants_grad(*tensors):  # the same steps, fused (ik_inference.py)
        steps = (config.steps, config.joint_sigma_m, config.prior_sigma_rad, config.damping)
        return ik_inference.fit(rest, params, state.free_pose, target, weights, *steps, limits)
    prior = state.free_pose
    for _ in range(config.steps):
        state = ik_step(rest, params.shape, state, target, weights, prior, config, limits)
    return state.params(params.shape, limits)


__all__ = [
    "IKConfig",
    "IKState",
    "fit_to_joints",
    "free_pose",
    "ik_step",
    "joint_jacobian",
    "left_jacobian",
]
