"""Exact nearest-neighbour distances between 3D point sets, for 3DVPE (`eval.metrics`).

3DVPE needs, for every camera-facing vertex of one mesh, the distance to the nearest
camera-facing vertex of another mesh, and back (~6,000 points each; three mesh pairs per
evaluated sample). Brute force (`nearest_brute`, the reference) costs Q x P distances. Here
whole blocks of pairs are skipped by bounding boxes, and the result stays exact:

1. Every point set is cut into leaves of exactly `LEAF` slots (`build_forest`: slabs along
   x, tiles along y), the last point repeated to fill the last leaf (a repeated point
   changes no nearest distance). A leaf is a compact patch of the surface with a tight box.
2. An upper bound per leaf: the exact distances of its points to the `_GUESSES` leaves of
   the other set whose box centres are nearest, the largest of those minima over the leaf.
3. A leaf pair whose box gap (a lower bound of every distance between their points) exceeds
   both leaves' bounds holds no nearest pair either way and is skipped; the others get exact
   distances, (a - b)^2 summed per coordinate like the brute force's final step (identical
   sets give exactly 0), reduced along both axes so one pass serves both directions.

Many pairs of sets are searched in one call (a batch of samples: one loop over pairs for the
small box matrices, then one batched pass over all surviving leaf pairs). The cost grows with
how far apart the two sets lie, not with Q x P: ~14 % of the pairs for a network's estimate
against the truth (6 cm apart on average); docs/benchmarks.md has the timings.
"""

from __future__ import annotations

import dataclasses
import math

import torch

LEAF = 32  # slots per leaf: larger leaves vectorise better, smaller ones prune tighter
_GUESSES = 2  # leaves of the other set whose exact distances give the first bound
_PAIR_BLOCK = 512  # leaf pairs per distance block: block x LEAF^2 values (2 MB in float32)
_SLACK = 1e-5  # relative slack on the squared bound: a pair that round-off would drop stays
_BRUTE_CHUNK = 2048  # query points per block of the brute force


@dataclasses.dataclass(frozen=True)
class Forest:
    """Several point sets, each cut into leaves of S slots (`build_forest`).

    points (N, 3): the sets concatenated; offsets (n + 1,): set k is points[offsets[k]:
    offsets[k + 1]]; first (n + 1,): its leaves are first[k]:first[k + 1]; index (L * S,):
    the point (into `points`) in every leaf slot; leaves (L, 3, S): the slots' coordinates,
    coordinate-major so distance blocks vectorise along the slots; lo, hi (L, 3): leaf boxes."""

    points: torch.Tensor
    offsets: torch.Tensor
    first: torch.Tensor
    index: torch.Tensor
    leaves: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor

    @property
    def size(self) -> int:
        return len(self.offsets) - 1

    @property
    def leaf(self) -> int:
        return self.leaves.shape[2]


def build_forest(sets: list[torch.Tensor], leaf: int = LEAF) -> Forest:
    """A `Forest` of point sets (N_k, 3), N_k >= 1, all of one dtype, cut into leaves of
    `leaf` slots by sort-tile-recursive packing: each set sorted along x and cut into slabs
    of whole leaves, each slab sorted along y and cut into leaves - tiles about square in
    x-y (a body lies along x), so a camera-facing surface falls into compact patches. All
    sets are packed together by two sorts. (A KD tree's level-by-level splits gave ~25 %
    fewer leaf pairs to search but cost ~4x more to build: docs/benchmarks.md.)"""
    if not sets:
        raise ValueError("no point sets given")
    for k, s in enumerate(sets):
        if s.ndim != 2 or s.shape[-1] != 3 or s.shape[0] == 0:
            raise ValueError(f"point set {k} must have shape (N, 3) with N >= 1, got {tuple(s.shape)}")
        if s.dtype != sets[0].dtype:
            raise ValueError(f"point sets differ in dtype: {sets[0].dtype} vs {s.dtype}")
    if leaf < 1:
        raise ValueError(f"leaf size must be >= 1, got {leaf}")
    device = sets[0].device
    points = torch.cat(sets)
    if not torch.isfinite(points).all():
        raise ValueError("point sets hold NaN or infinite coordinates")
    counts = torch.tensor([s.shape[0] for s in sets], device=device)
    n_leaves = (counts + leaf - 1) // leaf
    offsets = torch.cat([counts.new_zeros(1), counts.cumsum(0)])
    first = torch.cat([counts.new_zeros(1), n_leaves.cumsum(0)])
    total = int(first[-1])
    owner = torch.repeat_interleave(torch.arange(len(sets), device=device), n_leaves * leaf)  # set of each slot
    local = torch.arange(total * leaf, device=device) - first[owner] * leaf  # slot position in its set
    # Slot j of a set holds its point j; the last point fills the slots past its count.
    index = offsets[owner] + torch.minimum(local, counts[owner] - 1)
    big = torch.finfo(points.dtype).max
    of_point = torch.repeat_interleave(torch.arange(len(sets), device=device), counts)[:, None].expand(-1, 3)
    lo = points.new_full((len(sets), 3), big).scatter_reduce_(0, of_point, points, "amin")
    ext = (points.new_full((len(sets), 3), -big).scatter_reduce_(0, of_point, points, "amax") - lo).clamp_min(1e-12)
    # Slabs along x, as many as make the tiles about as long as wide.
    n_slabs = torch.minimum((n_leaves * ext[:, 0] / ext[:, 1]).sqrt().round().long().clamp_min(1), n_leaves)
    per_slab = (n_leaves + n_slabs - 1) // n_slabs  # leaves per slab (the last slab may hold fewer)
    slab = torch.cat([n_slabs.new_zeros(1), n_slabs.cumsum(0)])[owner] + local // (leaf * per_slab[owner])

    def sort_within(index: torch.Tensor, group: torch.Tensor, axis: int) -> torch.Tensor:
        """index reordered by (group, coordinate along axis): the group first, then the
        coordinate scaled into [0, 1] (float64 keeps both exact enough)."""
        x = (points[index, axis] - lo[owner, axis]) / ext[owner, axis]
        return index[(group.double() * 2 + x.double()).argsort()]

    index = sort_within(index, owner, 0)  # a set's slots stay in place, sorted along x
    index = sort_within(index, slab, 1)  # each slab sorted along y: consecutive `leaf` slots = a tile
    slots = points[index].view(total, leaf, 3)
    return Forest(points, offsets, first, index, slots.transpose(1, 2).contiguous(), slots.amin(1), slots.amax(1))


def _box_gap2(lo_a, hi_a, lo_b, hi_b) -> torch.Tensor:
    """(A, B) squared distances between boxes (A, 3) and (B, 3): 0 where they overlap."""
    gap = torch.maximum(lo_b[None] - hi_a[:, None], lo_a[:, None] - hi_b[None]).clamp_min_(0)
    return (gap * gap).sum(-1)


def _pair_d2(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(K, Sa, Sb) squared distances between the slots of leaves a (K, 3, Sa) and b (K, 3, Sb),
    pair by pair: (a - b)^2 summed per coordinate, no |a|^2 - 2 a.b expansion."""
    d2 = torch.sub(a[:, 0, :, None], b[:, 0, None, :]).square_()
    tmp = torch.empty_like(d2)
    for c in (1, 2):
        diff = torch.sub(a[:, c, :, None], b[:, c, None, :], out=tmp)
        d2.addcmul_(diff, diff)
    return d2


def nearest_pairs(fa: Forest, fb: Forest, pairs: list[tuple[int, int]]) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """For every (i, j) in pairs: ((N_i,), (N_j,)) the distance from each point of set i of fa
    to its nearest point of set j of fb, and from each point of set j to its nearest of set i.

    Memory: a (leaves of i) x (leaves of j) box matrix per pair - meant for sets of up to
    ~10^5 points (a body's camera-facing vertices: ~6,000)."""
    if fa.leaves.dtype != fb.leaves.dtype:
        raise ValueError(f"the point sets differ in dtype: {fa.leaves.dtype} vs {fb.leaves.dtype}")
    if fa.leaf != fb.leaf:
        raise ValueError(f"the forests have leaves of different sizes: {fa.leaf} vs {fb.leaf}")
    for i, j in pairs:
        if not (0 <= i < fa.size and 0 <= j < fb.size):
            raise ValueError(f"pair ({i}, {j}) is out of range: the forests hold {fa.size} and {fb.size} sets")
    if not pairs:
        return []
    dev = fa.leaves.device
    # Every pair gets its own rows of running minima (a set may be in several pairs): rows
    # ra[p]:ra[p + 1] of best_a are pair p's leaves of set i, likewise rb / best_b for set j.
    spans, ra, rb = [], [0], [0]
    for i, j in pairs:
        a0, a1, b0, b1 = int(fa.first[i]), int(fa.first[i + 1]), int(fb.first[j]), int(fb.first[j + 1])
        spans.append((a0, a1, b0, b1))
        ra.append(ra[-1] + a1 - a0)
        rb.append(rb[-1] + b1 - b0)
    leaf_a = torch.cat([torch.arange(a0, a1, device=dev) for a0, a1, _, _ in spans])  # row -> leaf
    leaf_b = torch.cat([torch.arange(b0, b1, device=dev) for _, _, b0, b1 in spans])
    best_a = fa.leaves.new_full((ra[-1], fa.leaf), math.inf)  # squared distances so far
    best_b = fa.leaves.new_full((rb[-1], fb.leaf), math.inf)
    guesses, local, gaps = [], [], []
    for p, (a0, a1, b0, b1) in enumerate(spans):
        centre = torch.cdist((fa.lo[a0:a1] + fa.hi[a0:a1]) / 2, (fb.lo[b0:b1] + fb.hi[b0:b1]) / 2)
        ka, kb = min(_GUESSES, b1 - b0), min(_GUESSES, a1 - a0)
        near_b = centre.topk(ka, dim=1, largest=False).indices  # (na, ka): leaves of j per leaf of i
        near_a = centre.topk(kb, dim=0, largest=False).indices  # (kb, nb): leaves of i per leaf of j
        rows_a, rows_b = torch.arange(a1 - a0, device=dev), torch.arange(b1 - b0, device=dev)
        local.append(
            torch.stack(
                [
                    torch.cat([rows_a.repeat_interleave(ka), near_a.T.reshape(-1)]),
                    torch.cat([near_b.reshape(-1), rows_b.repeat_interleave(kb)]),
                ]
            )
        )
        guesses.append(local[-1] + torch.tensor([[ra[p]], [rb[p]]], device=dev))
        gaps.append(_box_gap2(fa.lo[a0:a1], fa.hi[a0:a1], fb.lo[b0:b1], fb.hi[b0:b1]))
    guesses = torch.cat(guesses, 1)
    _reduce_pairs(fa.leaves, fb.leaves, leaf_a, leaf_b, guesses[0], guesses[1], best_a, best_b)
    # No nearest neighbour of a leaf's points lies farther than its bound.
    bound_a, bound_b = best_a.amax(1) * (1 + _SLACK), best_b.amax(1) * (1 + _SLACK)
    todo = []
    for p, gap2 in enumerate(gaps):
        need = (gap2 <= bound_a[ra[p] : ra[p + 1], None]) | (gap2 <= bound_b[None, rb[p] : rb[p + 1]])
        need[local[p][0], local[p][1]] = False  # the guessed pairs are in the minima already
        rows_a, rows_b = need.nonzero(as_tuple=True)
        todo.append(torch.stack([rows_a + ra[p], rows_b + rb[p]]))
    todo = torch.cat(todo, 1)
    _reduce_pairs(fa.leaves, fb.leaves, leaf_a, leaf_b, todo[0], todo[1], best_a, best_b)
    return [
        (_unleaf(fa, i, best_a[ra[p] : ra[p + 1]]), _unleaf(fb, j, best_b[rb[p] : rb[p + 1]]))
        for p, (i, j) in enumerate(pairs)
    ]


def _reduce_pairs(leaves_a, leaves_b, leaf_a, leaf_b, rows_a, rows_b, best_a, best_b) -> None:
    """Lower best_a[rows_a[k]] and best_b[rows_b[k]] to the squared distances between leaf
    leaf_a[rows_a[k]] and leaf leaf_b[rows_b[k]], for every k, block by block."""
    la, lb = leaf_a[rows_a], leaf_b[rows_b]
    for lo in range(0, rows_a.shape[0], _PAIR_BLOCK):
        qa, qb = rows_a[lo : lo + _PAIR_BLOCK], rows_b[lo : lo + _PAIR_BLOCK]
        d2 = _pair_d2(
            leaves_a.index_select(0, la[lo : lo + _PAIR_BLOCK]), leaves_b.index_select(0, lb[lo : lo + _PAIR_BLOCK])
        )  # (K, Sa, Sb)
        best_a.scatter_reduce_(0, qa[:, None].expand(-1, d2.shape[1]), d2.amin(2), reduce="amin")
        best_b.scatter_reduce_(0, qb[:, None].expand(-1, d2.shape[2]), d2.amin(1), reduce="amin")


def _unleaf(f: Forest, k: int, best2: torch.Tensor) -> torch.Tensor:
    """(N_k,) distances of set k from its leaves' squared distances (n_leaves, S)."""
    a0, a1 = int(f.first[k]), int(f.first[k + 1])
    out = best2.new_empty(int(f.offsets[k + 1] - f.offsets[k]))
    out[f.index[a0 * f.leaf : a1 * f.leaf] - f.offsets[k]] = best2.reshape(-1).sqrt()  # repeats agree
    return out


def nearest_distance(query: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """(Q,) distance from every query point (Q, 3) to its nearest point (P, 3), exact."""
    return nearest_pairs(build_forest([query]), build_forest([points]), [(0, 0)])[0][0]


def nearest_brute(query: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """(Q,) the same by brute force (the reference; what 3DVPE used before the forest): the
    nearest point of each query (Q, 3) from |p|^2 - 2 q.p (one matrix product per block),
    then that pair's exact distance."""
    out = []
    pp = (points * points).sum(-1)
    for lo in range(0, query.shape[0], _BRUTE_CHUNK):
        q = query[lo : lo + _BRUTE_CHUNK]
        nearest = torch.addmm(pp[None], q, points.T, alpha=-2).argmin(-1)
        out.append((q - points[nearest]).norm(dim=-1))
    return torch.cat(out) if out else query.new_zeros(0)


__all__ = ["Forest", "LEAF", "build_forest", "nearest_brute", "nearest_distance", "nearest_pairs"]
