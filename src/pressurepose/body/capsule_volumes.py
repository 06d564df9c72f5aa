"""Capsule volumes with overlaps shared fractionally (seed A.2): Sobol points (default) or the
seed's voxels."""

from __future__ import annotations

import math

import torch

from pressurepose.body.capsule_fit import Capsules
from pressurepose.body.capsule_geometry import capsule_clearance, point_segment_distance
from pressurepose.body.capsule_layout import (
    NUM_CAPSULES,
)

# --- volumes --------------------------------------------------------------------------------
_QMC_CACHE: dict[tuple[int, torch.dtype], torch.Tensor] = {}


def _sobol(n: int, dtype: torch.dtype) -> torch.Tensor:
    key = (n, dtype)
    if key not in _QMC_CACHE:
        engine = torch.quasirandom.SobolEngine(3, scramble=True, seed=20200601)
        _QMC_CACHE[key] = engine.draw(n, dtype=torch.float64).to(dtype)
    return _QMC_CACHE[key]


def overlap_pairs(caps: Capsules) -> torch.Tensor:
    """(P, 2) ordered pairs (c, d), c != d, of capsules that intersect in any of the bodies."""
    i, j = torch.triu_indices(NUM_CAPSULES, NUM_CAPSULES, 1)
    pairs = torch.stack([i, j], -1)
    hit = (capsule_clearance(caps.start, caps.end, caps.radius, pairs) < 0).any(0)
    pairs = pairs[hit.cpu()]
    return torch.cat([pairs, pairs.flip(-1)], 0)


def _containing(points: torch.Tensor, owner: torch.Tensor, caps: Capsules, pairs: torch.Tensor) -> torch.Tensor:
    """Number of capsules containing points (B, C, N, 3) that lie in capsules `owner` (C,):
    1 (the owner) plus the overlapping capsules of `pairs` that contain them. (B, C, N)."""
    count = torch.ones(points.shape[:3], dtype=points.dtype, device=points.device)
    for slot, c in enumerate(owner.tolist()):
        others = pairs[pairs[:, 0] == c, 1]
        if others.numel() == 0:
            continue
        d = point_segment_distance(points[:, slot, :, None], caps.start[:, None, others], caps.end[:, None, others])
        count[:, slot] += (d <= caps.radius[:, None, others]).sum(-1).to(points.dtype)
    return count


def capsule_volumes(caps: Capsules, method: str = "qmc", resolution: float = 0.002, points: int = 8192) -> torch.Tensor:
    """(B, 20) capsule volumes (m^3) with overlaps shared fractionally (seed A.2).

    method "voxel": voxel centres on a `resolution` grid (the seed's 2 mm), each voxel split
    equally between the capsules that contain it. method "qmc" (default): exact capsule volume
    times the mean of 1/n(x) over `points` fixed Sobol points inside the capsule (cylinder and
    caps integrated separately).
    """
    if method == "voxel":
        return _voxel_volumes(caps, resolution)
    if method != "qmc":
        raise ValueError(f"unknown volume method {method!r}; expected 'qmc' or 'voxel'")
    u = _sobol(points, caps.radius.dtype).to(caps.radius.device)
    a, b, r = caps.start, caps.end, caps.radius
    axis = b - a
    L = axis.norm(dim=-1)
    w = axis / L.clamp_min(1e-12)[..., None]
    # An orthonormal frame (w, e1, e2) per capsule.
    helper = torch.where(
        (w[..., :1].abs() < 0.9),
        torch.tensor([1.0, 0, 0], dtype=w.dtype, device=w.device),
        torch.tensor([0, 1.0, 0], dtype=w.dtype, device=w.device),
    )
    e1 = torch.linalg.cross(w, helper, dim=-1)
    e1 = e1 / e1.norm(dim=-1, keepdim=True)
    e2 = torch.linalg.cross(w, e1, dim=-1)
    # Cylinder: rho = r sqrt(u0), phi = 2 pi u1, z = L u2.  Ball: radius r u0^(1/3), direction
    # from (u1, u2); its lower half sits on the start cap, its upper half on the end cap.
    rho, phi = u[:, 0].sqrt(), 2 * math.pi * u[:, 1]
    cyl = torch.stack([rho * phi.cos(), rho * phi.sin(), u[:, 2]], -1)  # unit radius/length
    rb = u[:, 0].pow(1 / 3)
    cz = 1 - 2 * u[:, 1]
    sz = (1 - cz**2).clamp_min(0).sqrt()
    ph2 = 2 * math.pi * u[:, 2]
    ball = torch.stack([rb * sz * ph2.cos(), rb * sz * ph2.sin(), rb * cz], -1)

    def to_world(z, x1, x2):  # (B, 20, N) each -> (B, 20, N, 3)
        return (
            a[:, :, None]
            + z[..., None] * w[:, :, None]
            + x1[..., None] * e1[:, :, None]
            + x2[..., None] * e2[:, :, None]
        )

    rr = r[..., None]
    cyl_pts = to_world(cyl[:, 2] * L[..., None], cyl[:, 0] * rr, cyl[:, 1] * rr)
    upper = (ball[:, 2] > 0).to(r.dtype)
    ball_pts = to_world(ball[:, 2] * rr + upper * L[..., None], ball[:, 0] * rr, ball[:, 1] * rr)
    pairs = overlap_pairs(caps)
    owner = torch.arange(NUM_CAPSULES)
    inv = [(1.0 / _containing(pts, owner, caps, pairs)).mean(-1) for pts in (cyl_pts, ball_pts)]
    v_cyl = math.pi * r**2 * L
    v_ball = 4.0 / 3.0 * math.pi * r**3
    return v_cyl * inv[0] + v_ball * inv[1]


def _voxel_volumes(caps: Capsules, h: float) -> torch.Tensor:
    if not h > 0:
        raise ValueError(f"voxel resolution must be > 0, got {h}")
    out = torch.zeros_like(caps.radius)
    lo_all = torch.minimum(caps.start, caps.end) - caps.radius[..., None]
    hi_all = torch.maximum(caps.start, caps.end) + caps.radius[..., None]
    for bi in range(caps.batch_size):
        c1 = Capsules(caps.start[bi : bi + 1], caps.end[bi : bi + 1], caps.radius[bi : bi + 1], caps.rest[bi : bi + 1])
        pairs = overlap_pairs(c1)
        origin = lo_all[bi].amin(0)
        for c in range(NUM_CAPSULES):
            # Voxel centres of one global grid inside this capsule's bounding box.
            i0 = torch.floor((lo_all[bi, c] - origin) / h).long()
            i1 = torch.ceil((hi_all[bi, c] - origin) / h).long()
            axes = [origin[k] + (torch.arange(i0[k], i1[k] + 1, dtype=caps.radius.dtype) + 0.5) * h for k in range(3)]
            for xs in axes[0].split(max(1, 2_000_000 // (len(axes[1]) * len(axes[2])))):
                grid = torch.stack(torch.meshgrid(xs, axes[1], axes[2], indexing="ij"), -1).reshape(-1, 3)
                pts = grid[point_segment_distance(grid, c1.start[0, c], c1.end[0, c]) <= c1.radius[0, c]]
                if pts.shape[0]:
                    n = _containing(pts[None, None], torch.tensor([c]), c1, pairs)
                    out[bi, c] += (1.0 / n).sum() * h**3
    return out
