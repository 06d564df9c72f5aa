"""Underside height maps of a mesh over the mat grid, and the label maps built on them.

One definition, used by the generator's ground truth (sim/) and by the network's PMR (net/):
- `underside_height(vertices, faces, mat, sub)`: per grid cell, the height (m) of the lowest
  surface point of the mesh above the cell, from the vertices plus one point per triangle
  (its centroid); cells no point falls in but that lie between filled cells (two opposite
  neighbours filled) are patched with the mean of their filled neighbours; the rest stay
  `EMPTY_HEIGHT_M` (no body above the cell).
- `depth_map(...)` Q: per sensing taxel, that height in mm, capped at +`EMPTY_HEIGHT_M`
  (negative = below the undeformed mattress top, i.e. sunk in).
- `contact_map(Q)` C: 1 where Q < 0, else 0 (the released original's C = (Q < 0)).

The per-cell minimum is a `scatter_reduce("amin")`: differentiable with respect to the
vertices (the gradient of a cell flows to its lowest point; the released original cast
vertices to integers, so none flowed). Grid cells are taxels split `sub` x `sub` times.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from pressurepose.mat import MatSpec

# Height given to cells with no body above them (m); also the cap of Q (+500 mm).
EMPTY_HEIGHT_M = 0.5


def grid_shape(mat: MatSpec, sub: int = 1, covered: bool = True) -> tuple[int, int]:
    rows, cols = mat.covered_shape if covered else mat.shape
    return rows * sub, cols * sub


def grid_origin(mat: MatSpec, covered: bool = True) -> tuple[float, float]:
    """(x, y) of the grid's outer corner in the mat frame (m)."""
    if not covered:
        return 0.0, 0.0
    return -mat.border_head_foot_m, -mat.border_side_m


def cell_centres(
    mat: MatSpec, sub: int = 1, covered: bool = True, dtype=torch.float32, device=None
) -> tuple[torch.Tensor, torch.Tensor]:
    """(rows*sub, cols*sub) x and y (m) of the grid-cell centres."""
    nr, nc = grid_shape(mat, sub, covered)
    x0, y0 = grid_origin(mat, covered)
    hx, hy = mat.pitch_row_m / sub, mat.pitch_col_m / sub
    x = x0 + (torch.arange(nr, dtype=dtype, device=device) + 0.5) * hx
    y = y0 + (torch.arange(nc, dtype=dtype, device=device) + 0.5) * hy
    return torch.meshgrid(x, y, indexing="ij")


def surface_points(
    vertices: torch.Tensor, faces: torch.Tensor | None, corners: torch.Tensor | None = None
) -> torch.Tensor:
    """(B, V [+ F], 3): the vertices and, with faces (F, 3), each triangle's centroid.
    `corners` (B, F, 3, 3): the triangles' corners when the caller has gathered them already."""
    if faces is None:
        return vertices
    if corners is None:
        corners = vertices[:, faces]
    # The three corners summed explicitly: mean() over the middle axis of (B, F, 3, 3) is
    # ~3x slower on the CPU (strided reduction), and this runs in every sim #2 call; unbind
    # (not three slices) keeps the backward cheap (one stack, no full-size zero tensors).
    c0, c1, c2 = corners.unbind(2)
    centroids = (c0 + c1 + c2) * (1.0 / 3.0)
    return torch.cat([vertices, centroids], 1)


def _check_vertices(vertices: torch.Tensor) -> None:
    if vertices.ndim != 3 or vertices.shape[-1] != 3:
        raise ValueError(f"vertices must have shape (B, V, 3), got {tuple(vertices.shape)}")
    if not torch.isfinite(vertices).all():
        raise ValueError("vertices contain NaN or infinite values")


def underside_height(
    vertices: torch.Tensor,
    faces: torch.Tensor | None,
    mat: MatSpec,
    sub: int = 1,
    covered: bool = True,
    patch: bool = True,
) -> torch.Tensor:
    """(B, rows*sub, cols*sub) height (m) of the lowest mesh point over each grid cell.

    vertices: (B, V, 3) in the mat frame (m); faces: (F, 3) or None (vertices only).
    Cells with no body above them hold EMPTY_HEIGHT_M; heights are capped there too.
    """
    _check_vertices(vertices)
    return heights_from_points(surface_points(vertices, faces), mat, sub, covered, patch)


def heights_from_points(
    pts: torch.Tensor, mat: MatSpec, sub: int = 1, covered: bool = True, patch: bool = True
) -> torch.Tensor:
    """`underside_height` of a point cloud (B, N, 3) (e.g. from `surface_points`)."""
    if sub < 1:
        raise ValueError(f"sub must be a positive int, got {sub}")
    B = pts.shape[0]
    nr, nc = grid_shape(mat, sub, covered)
    x0, y0 = grid_origin(mat, covered)
    r = torch.floor((pts[..., 0].detach() - x0) * (sub / mat.pitch_row_m)).long()
    c = torch.floor((pts[..., 1].detach() - y0) * (sub / mat.pitch_col_m)).long()
    inside = (r >= 0) & (r < nr) & (c >= 0) & (c < nc)
    flat = torch.where(inside, r * nc + c, nr * nc)  # outside points go to a dump cell
    flat = flat + torch.arange(B, device=pts.device)[:, None] * (nr * nc + 1)
    z = pts[..., 2].clamp(max=EMPTY_HEIGHT_M)
    out = torch.full((B * (nr * nc + 1),), EMPTY_HEIGHT_M, dtype=pts.dtype, device=pts.device)
    out = out.scatter_reduce(0, flat.reshape(-1), z.reshape(-1), "amin", include_self=True)
    h = out.view(B, nr * nc + 1)[:, : nr * nc].view(B, nr, nc)
    return patch_holes(h) if patch else h


def patch_holes(h: torch.Tensor) -> torch.Tensor:
    """Fill empty cells (== EMPTY_HEIGHT_M) lying between filled ones - two opposite
    neighbours filled (left-right, up-down or a diagonal pair) - with the mean of their filled
    8-neighbours. (B, R, C) -> (B, R, C)."""
    filled = (h < EMPTY_HEIGHT_M).to(h.dtype)[:, None]
    value = torch.where(filled.bool(), h[:, None], torch.zeros_like(h[:, None]))
    pad_f = F.pad(filled, (1, 1, 1, 1))
    pad_v = F.pad(value, (1, 1, 1, 1))
    R, C = h.shape[-2:]

    def shifted(t, dr, dc):
        return t[..., 1 + dr : 1 + dr + R, 1 + dc : 1 + dc + C]

    offsets = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]
    count = sum(shifted(pad_f, dr, dc) for dr, dc in offsets)
    total = sum(shifted(pad_v, dr, dc) for dr, dc in offsets)
    between = torch.zeros_like(filled, dtype=torch.bool)
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        between |= (shifted(pad_f, dr, dc) * shifted(pad_f, -dr, -dc)).bool()
    hole = (~filled.bool()) & between
    fill = total / count.clamp(min=1)
    return torch.where(hole, fill, h[:, None])[:, 0]


def depth_map(vertices: torch.Tensor, faces: torch.Tensor | None, mat: MatSpec) -> torch.Tensor:
    """Q: (B, rows, cols) per sensing taxel, the height (mm) of the body's lowest surface point
    relative to the undeformed mattress top (negative = sunk in), capped at EMPTY_HEIGHT_M
    (no body above the taxel)."""
    return underside_height(vertices, faces, mat, sub=1, covered=False) * 1000.0


def contact_map(depth_mm: torch.Tensor) -> torch.Tensor:
    """C: (B, rows, cols) 1.0 where the body reaches below the mattress top (Q < 0), else 0."""
    return (depth_mm < 0).to(depth_mm.dtype)


def mesh_centroid(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(B, 3) centre of the enclosed volume (uniform density) of closed meshes, by signed
    tetrahedra; orientation-independent (a mirrored mesh gives the mirrored centroid)."""
    return centroid_and_points(vertices, faces)[0]


def centroid_and_points(vertices: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The volume centroid (B, 3) and the surface points of maps.surface_points (vertices and
    triangle centroids), from one gather of the triangle corners."""
    tri = vertices.index_select(1, faces.reshape(-1)).view(vertices.shape[0], -1, 3, 3)
    v0, v1, v2 = tri.unbind(2)
    tri_sum = v0 + v1 + v2
    # 6 x signed volume (B, F): v0 . (v1 x v2), written out (faster than linalg.cross here)
    vol = (
        v0[..., 0] * (v1[..., 1] * v2[..., 2] - v1[..., 2] * v2[..., 1])
        + v0[..., 1] * (v1[..., 2] * v2[..., 0] - v1[..., 0] * v2[..., 2])
        + v0[..., 2] * (v1[..., 0] * v2[..., 1] - v1[..., 1] * v2[..., 0])
    )
    centroid = (vol[..., None] * tri_sum).sum(1) / (4.0 * vol.sum(1)[:, None])
    return centroid, surface_points(vertices, faces, corners=tri)


__all__ = [
    "EMPTY_HEIGHT_M",
    "cell_centres",
    "centroid_and_points",
    "contact_map",
    "depth_map",
    "grid_origin",
    "grid_shape",
    "heights_from_points",
    "mesh_centroid",
    "patch_holes",
    "surface_points",
    "underside_height",
]
