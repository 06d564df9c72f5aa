"""Exact nearest-neighbour distances between 3D point sets, for 3DVPE (`eval.metrics`).

3DVPE needs, for every camera-facing vertex of one mesh, the distance to the nearest
camera-facing vertex of another mesh, and back (~6,000-7,000 points each; three mesh pairs
per evaluated sample). `PointSets` packs each set with a k-d tree (scipy's `cKDTree`, exact:
identical sets give exactly 0) built once, so a mesh compared with several others is indexed
once. `nearest_brute` (one matrix product per block of queries) stays as the reference the
tests compare with; `benchmarks/evaluate.py` times both.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

_BRUTE_CHUNK = 2048  # query points per block of the brute force


class PointSets:
    """Point sets (N_k, 3) with a k-d tree each; the distances come back in each set's dtype."""

    def __init__(self, sets: list[torch.Tensor]):
        for k, s in enumerate(sets):
            if s.ndim != 2 or s.shape[-1] != 3 or s.shape[0] == 0:
                raise ValueError(f"point set {k} must have shape (N, 3) with N >= 1, got {tuple(s.shape)}")
            if not bool(torch.isfinite(s).all()):
                raise ValueError(f"point set {k} holds NaN or infinite coordinates")
        self.points = [s.detach() for s in sets]
        self._arrays = [s.cpu().double().numpy() for s in self.points]
        # Unbalanced trees with larger leaves build ~2x and query ~2x faster on body surfaces
        # (benchmarks/evaluate.py; docs/benchmarks.md).
        self.trees = [cKDTree(a, leafsize=32, balanced_tree=False, compact_nodes=False) for a in self._arrays]

    @property
    def size(self) -> int:
        return len(self.points)

    def nearest(self, query: int, other: PointSets, target: int) -> torch.Tensor:
        """(N_query,) distance from every point of set `query` to the nearest point of set
        `target` of `other`."""
        dist, _ = other.trees[target].query(self._arrays[query], k=1)
        ref = self.points[query]
        return torch.from_numpy(np.asarray(dist)).to(dtype=ref.dtype, device=ref.device)


def nearest_pairs(a: PointSets, b: PointSets, pairs: list[tuple[int, int]]) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """For each (i, j): distances from set i of a to set j of b, and back."""
    return [(a.nearest(i, b, j), b.nearest(j, a, i)) for i, j in pairs]


def nearest_distance(query: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """(Q,) distance from every query point (Q, 3) to its nearest point (P, 3), exact."""
    return PointSets([query]).nearest(0, PointSets([points]), 0)


def nearest_brute(query: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """(Q,) the same by brute force (the reference): the nearest point of each query (Q, 3)
    from |p|^2 - 2 q.p (one matrix product per block), then that pair's exact distance."""
    out = []
    pp = (points * points).sum(-1)
    for lo in range(0, query.shape[0], _BRUTE_CHUNK):
        q = query[lo : lo + _BRUTE_CHUNK]
        nearest = torch.addmm(pp[None], q, points.T, alpha=-2).argmin(-1)
        out.append((q - points[nearest]).norm(dim=-1))
    return torch.cat(out) if out else query.new_zeros(0)


__all__ = ["PointSets", "nearest_brute", "nearest_distance", "nearest_pairs"]
