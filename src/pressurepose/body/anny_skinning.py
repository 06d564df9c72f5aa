"""Anny's linear blend skinning: the differentiable form and a blocked one for inference.

`sparse_linear_blend_skinning` (training, anything that needs gradients) blends the 12 entries
of every bone's transform per vertex with one sparse product - a (V, 12 B) temporary, 82 MB
at batch 128 - and the caller then moves the mesh into SMPL's axes and onto the mat, each step
another mesh-sized tensor. On a CPU that is memory-bound: fresh buffers are page-faulted in
(~0.35 ms per MB measured on the project machine) and nothing stays in cache.

`BlockedSkinning.pose` (no autograd) does the same arithmetic per block of vertices: the
block's rest vertices from the blendshapes (a small matrix product), its blended transforms
(CSR rows of the weights) and the posed positions, written straight into the output. The
caller folds the change of axes, the root rotation and the translation into the bone
transforms first (a vertex's weights sum to 1, so a common affine map passes through the
blend). Same numbers to float rounding (tests/test_body.py); at batch 128 on one core
~5x faster (docs/benchmarks.md).
"""

from __future__ import annotations

import warnings

import torch

BLOCK_FLOATS = 1 << 20  # blended transforms per block: ~4 MB in float32 (cache-sized, reused)
TRANSPOSED_FROM = 8  # batches from this size take the rest vertices from a transposed basis


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


class BlockedSkinning:
    """Rest mesh + skinning of a linear-blendshape body, per block of vertices, no autograd.

    template (V, 3), blendshapes (A, V, 3) (rest = template + sum_a c_a blendshape_a),
    weights sparse (V, K) with rows summing to 1."""

    def __init__(self, template: torch.Tensor, blendshapes: torch.Tensor, weights: torch.Tensor) -> None:
        V = template.shape[0]
        if blendshapes.shape[1:] != (V, 3) or weights.shape[0] != V:
            raise ValueError(
                f"template (V, 3), blendshapes (A, V, 3) and weights (V, K) must agree, got "
                f"{tuple(template.shape)}, {tuple(blendshapes.shape)}, {tuple(weights.shape)}"
            )
        self.num_vertices, self.num_bones = V, weights.shape[1]
        self.template = template.detach().reshape(1, V * 3)
        self.basis = blendshapes.detach().reshape(-1, V * 3)  # (A, 3V): a view, no copy
        self.weights = weights.detach().coalesce()
        self._blocks: dict[int, list[tuple[int, int, torch.Tensor]]] = {}
        self._basis_t: tuple[torch.Tensor, torch.Tensor] | None = None

    @classmethod
    def of_anny(cls, model, weights: torch.Tensor) -> BlockedSkinning:
        """For an Anny model (template_vertices, blendshapes) and its sparse weights."""
        return cls(model.template_vertices, model.blendshapes, weights)

    def _rows(self, batch: int) -> list[tuple[int, int, torch.Tensor]]:
        """[(start, end, CSR weight rows)] in blocks of ~BLOCK_FLOATS blended entries."""
        size = min(self.num_vertices, max(256, BLOCK_FLOATS // (12 * batch)))
        if size not in self._blocks:
            index, values = self.weights.indices(), self.weights.values()
            blocks = []
            for start in range(0, self.num_vertices, size):
                end = min(start + size, self.num_vertices)
                keep = (index[0] >= start) & (index[0] < end)
                rows = index[:, keep] - torch.tensor([[start], [0]], device=index.device)
                shape = (end - start, self.num_bones)
                coo = torch.sparse_coo_tensor(rows, values[keep], shape, check_invariants=True).coalesce()
                with warnings.catch_warnings():  # "sparse CSR support is in beta"
                    warnings.simplefilter("ignore", UserWarning)
                    blocks.append((start, end, coo.to_sparse_csr()))
            self._blocks[size] = blocks
        return self._blocks[size]

    @torch.no_grad()
    def pose(self, coeffs: torch.Tensor, T: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """Blendshape coefficients (B, A) and per-bone transforms T (B, K, 3, 3), t (B, K, 3)
        -> posed vertices (B, V, 3): sum_k w_vk (T_k rest_v + t_k)."""
        B, K = T.shape[:2]
        if K != self.num_bones or t.shape != (B, K, 3) or coeffs.shape != (B, self.basis.shape[0]):
            raise ValueError(
                f"expected T (B, {self.num_bones}, 3, 3), t (B, {self.num_bones}, 3) and coeffs "
                f"(B, {self.basis.shape[0]}), got {tuple(T.shape)}, {tuple(t.shape)}, {tuple(coeffs.shape)}"
            )
        affine = torch.cat([T, t[..., None]], -1).permute(1, 2, 3, 0).reshape(K, 12 * B)  # (K, [i, j, b])
        out = T.new_empty(B, self.num_vertices, 3)
        transposed = self._transposed() if B >= TRANSPOSED_FROM else None
        for start, end, rows in self._rows(B):
            n = end - start
            blended = (rows @ affine).view(n, 3, 4, B)
            block = slice(3 * start, 3 * end)
            if transposed is None:
                rest = torch.addmm(self.template[:, block], coeffs, self.basis[:, block]).T.reshape(n, 3, B)
            else:  # the rest vertices straight in the (n, 3, B) layout: no transposing copy
                rest = torch.addmm(transposed[0][block], transposed[1][block], coeffs.T).view(n, 3, B)
            posed = torch.addcmul(blended[:, :, 3], blended[:, :, 0], rest[:, :1])  # (n, 3, B)
            for j in (1, 2):
                posed.addcmul_(blended[:, :, j], rest[:, j : j + 1])
            out[:, start:end].copy_(posed.permute(2, 0, 1))
        return out

    def _transposed(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The template (3V, 1) and the blendshapes (3V, A) transposed, contiguous (a copy of
        the basis, made on first use): with B >= TRANSPOSED_FROM bodies the product basis^T
        coeffs^T writes the rest vertices as (3V, B) at full speed, where the product with
        the transposed view is slow (its rows lie 3V floats apart) and transposing
        coeffs basis (B, 3V) is a pass over the block (batch 128: 78 -> 48 ms for the mesh)."""
        if self._basis_t is None:
            self._basis_t = (self.template.T.contiguous(), self.basis.T.contiguous())
        return self._basis_t


def wants_grad(*tensors: torch.Tensor) -> bool:
    """Whether autograd would record an operation on these tensors."""
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)


__all__ = [
    "BLOCK_FLOATS",
    "TRANSPOSED_FROM",
    "BlockedSkinning",
    "skin_matrix",
    "sparse_linear_blend_skinning",
    "wants_grad",
]
