"""The body's height from the localised joints' bone lengths (heatmap arch, inference only;
docs/network.md "Height from the localised skeleton").

The regression head reads the body's shape, hence its height, from the image as a whole, and on
real frames whose load runs longer than a simulated body's of the same height (a pillow, the
head end of the mat; docs/realism.md) it reads the bodies 7-9 cm tall. The localised joints carry
a second, pose-independent reading of the height: the length of the bone chain head - neck -
spine3 - spine2 - spine1 - pelvis plus the mean of the two legs' pelvis - hip - knee - ankle
(`chain_length`). `stature_from_joints` moves the body's 'height' shape parameter a share `weight`
of the way from the head's answer to the value whose rest skeleton has the localised chain's
length - the linear combination of the two readings; the share is the combination that
minimises the height's squared error on simulated data (`optimal_weight`, measured per network:
benchmarks/stature.py), so it is chosen without real frames.
"""

from __future__ import annotations

import torch

from pressurepose.body.joints import J24_NAMES

_TRUNK = ("head", "neck", "spine3", "spine2", "spine1", "pelvis")  # the first link: head - neck
_LEG = ("pelvis", "{side}_hip", "{side}_knee", "{side}_ankle")
HEIGHT_PARAMETER = "height"  # the body model's shape parameter that sets the height (Anny)


def _links(names: tuple[str, ...]) -> list[tuple[int, int]]:
    """The J24 indices of a chain's consecutive joints, (from, to) per link."""
    idx = [J24_NAMES.index(n) for n in names]
    return list(zip(idx[:-1], idx[1:]))


def _chain_links(head: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The links of `chain_length` as index tensors (from, to) and each link's weight: the trunk's
    5 (`head` False: 4, from the neck down) at 1, each leg's 3 at 1/2 (the mean of the two legs)."""
    trunk = _links(_TRUNK)[0 if head else 1 :]
    legs = [link for side in ("left", "right") for link in _links(tuple(n.format(side=side) for n in _LEG))]
    links = trunk + legs
    weights = [1.0] * len(trunk) + [0.5] * len(legs)
    return torch.tensor([a for a, _ in links]), torch.tensor([b for _, b in links]), torch.tensor(weights)


_CHAINS = {head: _chain_links(head) for head in (True, False)}


def chain_length(joints: torch.Tensor, head: bool = True) -> torch.Tensor:
    """(B,) the head-to-pelvis chain (`head` False: neck-to-pelvis) plus the mean of the two legs'
    pelvis-to-ankle chains of (B, 24, 3) joints: a length the pose does not change. All links in
    one gather (inference calls it twice an image: 0.29 -> ~0.05 ms at batch 1)."""
    start, end, weights = _CHAINS[head]
    links = joints.index_select(1, end.to(joints.device)) - joints.index_select(1, start.to(joints.device))
    return links.norm(dim=-1) @ weights.to(joints)


def stature_from_joints(
    body,
    shape: torch.Tensor,
    joints: torch.Tensor,
    weight: float,
    iterations: int = 1,
    step: float = 1e-3,
    head: bool = True,
) -> torch.Tensor:
    """(B, S) `shape` with its height parameter moved `weight` of the way to the value whose rest
    skeleton's `chain_length` equals the localised `joints`' (secant steps on a one-sided finite
    difference, kept within the parameter's [0, 1]; the chain is linear in the parameter between
    Anny's anchors, so one step lands there); the other parameters unchanged. weight 0: `shape`
    itself. The rest skeleton is the body's `rest_pose_joints` (Anny: the bone lengths without
    the T-pose's rotations; ~1 ms against 2.7 at batch 1). `head` False: the chain from the neck
    down (`chain_length`), so the head's localisation - where a real mat's edge or a pillow makes it
    least sure - does not enter."""
    if weight == 0:
        return shape
    if HEIGHT_PARAMETER not in body.shape_names:
        raise ValueError(f"the body model has no {HEIGHT_PARAMETER!r} shape parameter")
    k = body.shape_names.index(HEIGHT_PARAMETER)
    target = chain_length(joints, head).to(shape)
    value = shape[:, k].clone()
    for _ in range(iterations):
        h = torch.where(value > 0.5, -step, step)
        probe = shape.clone()
        probe[:, k] = value
        pair = torch.cat([probe, probe])
        pair[len(shape) :, k] += h
        lengths = chain_length(body.rest_pose_joints(pair), head)
        length, moved = lengths[: len(shape)], lengths[len(shape) :]
        slope = ((moved - length) / h).clamp(min=1e-3)  # m per unit: taller for a larger value
        value = (value + (target - length) / slope).clamp(0.0, 1.0)
    out = shape.clone()
    out[:, k] = shape[:, k] + weight * (value - shape[:, k])
    return out


def optimal_weight(head_error: torch.Tensor, joints_error: torch.Tensor) -> float:
    """The share w in [0, 1] minimising the mean squared error of (1 - w) a + w b for two
    readings with errors a (the head's) and b (the joints'), (N,) each: (var a - cov) / (var a +
    var b - 2 cov) on their centred errors."""
    a = head_error.double() - head_error.double().mean()
    b = joints_error.double() - joints_error.double().mean()
    va, vb, c = (a * a).mean(), (b * b).mean(), (a * b).mean()
    den = va + vb - 2 * c
    return float(((va - c) / den).clamp(0.0, 1.0)) if den > 0 else 0.0


__all__ = ["HEIGHT_PARAMETER", "chain_length", "optimal_weight", "stature_from_joints"]
