"""The IK fit without autograd (predict, evaluate): `ik.fit_to_joints`'s steps, fused.

The same damped Gauss-Newton steps as `ik.ik_step` (the reference, differentiable; the tests
check the two agree to float64 round-off), written for a CPU at batch 1, where a step is
per-operation overhead on small tensors: 125 torch calls a step here against 300 in `ik_step` and
~330 in the no-grad branch this replaced (every call a TorchFunctionMode sees, attribute reads and
indexing included; `fit_to_joints` with 3 steps, the shape pass kept: 6.2-7.4 -> 3.1-3.6 ms on the
2-core AMD EPYC, ~0.8 ms a step; docs/benchmarks.md "Session 58"). How:

- what the steps share is made once a fit: the limits' centres and half-widths, the square roots
  of the joints' weights, the lever-arm mask, the Jacobian's translation columns, the bone
  offsets;
- the 24 rotation matrices and left Jacobians of SO(3) (`rotations_and_left_jacobians`) from one
  set of trigonometric terms and one batched product: R = I + A K + B K^2 and
  J_l = I + B K + C K^2, K = skew(phi), A = sin a / a, B = (1 - cos a) / a^2,
  C = (a - sin a) / a^3 (their Taylor series below a = 0.05);
- the joints' rotations relative to the pelvis by pointer jumping: three rounds of
  W_k <- W_anc(k) W_k, anc(k) <- anc(anc(k)) compose every chain of J24 (at most 8 bones below
  the pelvis) where `kinematics.forward_kinematics` takes 23 products in turn;
- the positions as sums of the rotated bone offsets along each chain (one product with a 0/1
  matrix), and the unknowns (t, r, u) kept as one (B, 75) vector;
- no Python numbers in tensor operations (each costs a conversion, ~2x the operation here); the
  Cholesky factor without its check (`cholesky_ex`: the damping keeps H positive definite) and
  two triangular solves.
"""

from __future__ import annotations

import torch

from pressurepose.body.joints import J24_PARENTS, NUM_JOINTS, NUM_POSE_JOINTS
from pressurepose.body.kinematics import DESCENDANTS
from pressurepose.body.limits import ALPHA, JointLimits
from pressurepose.body.params import BodyParams, supine_rotation
from pressurepose.body.rotations import skew
from pressurepose.constants import kept

_SERIES_BELOW = 2.5e-3  # a^2: Taylor series of A, B, C to a^6 below a = 0.05 (next terms < 1e-15)
_CONSTANTS: dict[tuple[torch.dtype, torch.device], dict[str, torch.Tensor]] = {}


def _pointer_jumps() -> list[list[int]]:
    """anc_r(k) for the rounds r = 0, 1, 2: the parent, grandparent, 4th ancestor (the pelvis
    its own); after the third round W_k is the product over k's whole chain."""
    anc, rounds = [0, *J24_PARENTS[1:]], []
    while any(a != 0 for a in anc):
        rounds.append(anc)
        anc = [anc[a] for a in anc]
    return rounds


def _make_constants(dtype: torch.dtype, device: torch.device) -> dict[str, torch.Tensor]:
    # [k, a] = 1 when bone a (ending at joint a, a != pelvis) lies on k's chain: a is k or above it
    chains = (DESCENDANTS.T | torch.eye(NUM_JOINTS, dtype=torch.bool)).float()
    chains[:, 0] = 0
    series = [  # the Taylor series in a^2 of (A, B, B, C), by power
        (1.0, 0.5, 0.5, 1 / 6),
        (-1 / 6, -1 / 24, -1 / 24, -1 / 120),
        (1 / 120, 1 / 720, 1 / 720, 1 / 5040),
        (-1 / 5040, -1 / 40320, -1 / 40320, -1 / 362880),
    ]
    made = {
        "eye9": torch.eye(3).reshape(9),
        "eye": torch.eye(3),
        "series": torch.tensor(series, dtype=torch.float64),  # cast from float64: exact 1/6 etc.
        "series_below": torch.tensor(_SERIES_BELOW),
        "one": torch.tensor(1.0),
        "chains": chains,
        "mask": DESCENDANTS.float(),
        "supine": supine_rotation(torch.float64),
    }
    made = {k: v.to(dtype=dtype, device=device) for k, v in made.items()}
    parents = torch.tensor([0, *J24_PARENTS[1:]], device=device)
    made["parents"] = parents  # into [I, W_0, ..., W_23] below: the root's parent rotation is I
    made["parents_or_eye"] = torch.tensor([0, *[p + 1 for p in J24_PARENTS[1:]]], device=device)
    made["jumps"] = torch.tensor(_pointer_jumps(), device=device)
    return made


def _constants(like: torch.Tensor) -> dict[str, torch.Tensor]:
    key = (like.dtype, like.device)
    return kept(_CONSTANTS, key, lambda: _make_constants(*key))


def rotations_and_left_jacobians(phi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, n, 3) rotation vectors -> their rotation matrices and left Jacobians of SO(3),
    (B, n, 3, 3) each, from shared terms (module doc). For `fit` (no autograd); differentiable
    in form, but only `body.rotations` and `ik.left_jacobian` are tested for gradients."""
    c = _constants(phi)
    a2 = (phi * phi).sum(-1, keepdim=True)  # (B, n, 1)
    small = a2 < c["series_below"]
    safe = torch.where(small, c["one"], a2)
    a = safe.sqrt()
    sin, cos = torch.sin(a), torch.cos(a)
    b = (c["one"] - cos) / safe
    closed = torch.cat([sin / a, b, b, (a - sin) / (safe * a)], -1)  # (A, B, B, C)
    s0, s1, s2, s3 = c["series"]
    series = torch.addcmul(s0, a2, torch.addcmul(s1, a2, torch.addcmul(s2, a2, s3)))
    coef = torch.where(small, series, closed).view(-1, 2, 2)  # [[A, B], [B, C]]
    K = skew(phi.reshape(-1, 3))
    powers = torch.stack([K, torch.bmm(K, K)], 1).view(-1, 2, 9)  # (K, K^2)
    both = torch.baddbmm(c["eye9"], coef, powers).view(*phi.shape[:-1], 2, 3, 3)
    return both[..., 0, :, :], both[..., 1, :, :]


@torch.no_grad()
def fit(
    rest: torch.Tensor,
    params: BodyParams,
    free: torch.Tensor,
    target: torch.Tensor,
    weights: torch.Tensor,
    steps: int,
    joint_sigma_m: float,
    prior_sigma_rad: float,
    damping: float,
    limits: JointLimits,
) -> BodyParams:
    """`steps` steps of `ik.ik_step` from params, whose pose is squash(free) (B, 23, 3) and the
    prior's centre, towards target (B, 24, 3) under limits (inflated by ALPHA); rest (B, 24, 3)
    the T-pose joints of params.shape; the `ik.IKConfig` fields given one by one."""
    B = rest.shape[0]
    c = _constants(rest)
    mid = (limits.lower + limits.upper).to(rest) / 2
    half = (limits.upper - limits.lower).to(rest) * (ALPHA / 2)
    root_w = (weights / joint_sigma_m**2).sqrt()  # (B, 24)
    root_w3 = root_w.repeat_interleave(3, 1)  # (B, 72)
    lever = (c["mask"] * root_w[:, None, :])[..., None]  # (B, j, k, 1): 0 off j's subtree
    diag = torch.full((6 + 3 * NUM_POSE_JOINTS,), damping + prior_sigma_rad**-2, dtype=rest.dtype, device=rest.device)
    diag[:6] = damping
    offsets = (rest - rest[:, c["parents"]])[..., None]  # (B, 24, 3, 1), the pelvis's 0
    J = rest.new_empty(B, 3 * NUM_JOINTS, diag.shape[0])
    J[:, :, :3] = (root_w[:, :, None, None] * c["eye"]).reshape(B, 3 * NUM_JOINTS, 3)  # d p_k / d t
    blocks = J[:, :, 3:].unflatten(2, (NUM_JOINTS, 3)).unflatten(1, (NUM_JOINTS, 3))  # (B, k, xyz, j, i)
    Jt = J.transpose(1, 2)
    eye = c["eye"].expand(B, 1, 3, 3)
    supine = c["supine"].expand(B, 3, 3)
    x = torch.cat([params.root_translation, params.root_rotation, free.flatten(1)], 1)  # (B, 75): t, r, u
    prior, goal = x[:, 6:], target.reshape(B, -1)
    for _ in range(steps):
        tanh = torch.tanh((x[:, 6:].view(B, NUM_POSE_JOINTS, 3) - mid) / half)
        angles = torch.cat([x[:, None, 3:6], torch.addcmul(mid, tanh, half)], 1)  # root, then the pose
        R, J_l = rotations_and_left_jacobians(angles)
        W = torch.cat([eye, R[:, 1:]], 1).view(-1, 3, 3)  # local rotations, the pelvis's I
        for anc in c["jumps"]:
            W = torch.bmm(W.view(B, NUM_JOINTS, 3, 3).index_select(1, anc).view(-1, 3, 3), W)
        world = torch.bmm(R[:, 0], supine)[:, None] @ W.view(B, NUM_JOINTS, 3, 3)  # (B, 24, 3, 3), mat frame
        parent = torch.cat([eye, world], 1).index_select(1, c["parents_or_eye"])  # the root's: I
        pos = torch.baddbmm(x[:, None, :3], c["chains"].expand(B, -1, -1), (parent @ offsets)[..., 0])
        axes = (parent @ J_l).transpose(-1, -2)  # (B, j, i, xyz): d omega / d theta_j's columns
        axes[:, 1:] *= (c["one"] - tanh * tanh)[..., None]  # d theta / d u
        arm = ((pos[:, None, :, :] - pos[:, :, None, :]) * lever).transpose(1, 2)  # (B, k, j, xyz)
        for xyz, (y, z) in enumerate(((1, 2), (2, 0), (0, 1))):  # (a x d)_x = a_y d_z - a_z d_y
            block = blocks[:, :, xyz]
            torch.mul(axes[:, None, :, :, y], arm[:, :, :, None, z], out=block)
            block.addcmul_(axes[:, None, :, :, z], arm[:, :, :, None, y], value=-1)
        H = torch.bmm(Jt, J)
        H.diagonal(dim1=1, dim2=2).add_(diag)
        g = (J * (root_w3 * (pos.view(B, -1) - goal))[..., None]).sum(1)  # faster than a batched gemv
        g[:, 6:].add_(x[:, 6:] - prior, alpha=prior_sigma_rad**-2)
        U = torch.linalg.cholesky_ex(H, upper=True)[0]  # H = U^T U
        y = torch.linalg.solve_triangular(U.transpose(1, 2), g[..., None], upper=False)
        x = x - torch.linalg.solve_triangular(U, y, upper=True)[..., 0]
    pose = torch.addcmul(mid, torch.tanh((x[:, 6:].view(B, NUM_POSE_JOINTS, 3) - mid) / half), half)
    return BodyParams(
        shape=params.shape, root_rotation=x[:, 3:6].contiguous(), root_translation=x[:, :3].contiguous(), pose=pose
    )


__all__ = ["fit", "rotations_and_left_jacobians"]
