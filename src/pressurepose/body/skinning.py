"""Linear blend skinning with sparse weights (`body.anny_backend`'s mesh)."""

from __future__ import annotations

import torch


def skin_matrix(weights: torch.Tensor, indices: torch.Tensor, num_bones: int) -> torch.Tensor:
    """Sparse (V, num_bones) skinning weights from per-vertex slots: weights (V, k) of the
    bones indices (V, k) (Anny: most vertices have 1-3 bones of its 9 slots)."""
    w, i = weights, indices.long()
    V = w.shape[0]
    rows = torch.arange(V).repeat_interleave(w.shape[1])
    keep = w.flatten() > 0
    index = torch.stack([rows[keep], i.flatten()[keep]])
    return torch.sparse_coo_tensor(index, w.flatten()[keep], (V, num_bones), check_invariants=True).coalesce()


def sparse_linear_blend_skinning(
    rest_vertices: torch.Tensor, weights: torch.Tensor, T: torch.Tensor, t: torch.Tensor
) -> torch.Tensor:
    """Linear blend skinning: rest vertices (B, V, 3), sparse weights (V, K), per-bone rigid
    transforms T (B, K, 3, 3), t (B, K, 3) -> posed vertices (B, V, 3).

    Blends the 12 transform entries with one sparse matrix product (cost ~ non-zero weights,
    not V x K), then applies each vertex's blended transform.
    """
    B, K = T.shape[:2]
    affine = torch.cat([T, t[..., None]], -1).permute(1, 0, 2, 3).reshape(K, B * 12)
    blended = torch.sparse.mm(weights, affine).view(-1, B, 3, 4)  # (V, B, 3, 4)
    v = rest_vertices.transpose(0, 1)  # (V, B, 3)
    # Written out per column: much faster on CPU than a batched 3x3 matmul of this shape.
    posed = (
        blended[..., 3] + blended[..., 0] * v[..., :1] + blended[..., 1] * v[..., 1:2] + blended[..., 2] * v[..., 2:]
    )
    return posed.transpose(0, 1)


__all__ = ["skin_matrix", "sparse_linear_blend_skinning"]
