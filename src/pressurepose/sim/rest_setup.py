"""The articulated rest's set-up (`sim.articulated`): the posed mesh's surface points sorted by
J24 part, coordinate-major, and its triangles' corners in the same order, gathered once.

The rest keeps each part's surface points (the mesh's vertices, then its triangles' centroids,
as `maps.surface_points`) as one contiguous slice, and the parts' masses and centres come from
the same triangles' corners (`articulation.corner_mass_and_com`). Gathering each corner once, in
part order, for both, replaces a gather of the (B, F, 3, 3) corners, a concatenation and a
reorder of all the points, and the mass's own three gathers; the numbers are the same bit for
bit (the same element-wise operations in the same order). The rest then lays the points out as
(B, P, 3) (one copy) before its part transforms and tissue depths, whose matrix products and
norms round differently on other layouts (the rests amplify any round-off: docs/benchmarks.md
"Session 50")."""

from __future__ import annotations

import dataclasses

import torch


@dataclasses.dataclass(frozen=True, eq=False)
class SurfaceLayout:
    """Where a mesh's V + F surface points go when sorted by part (stable: within a part its
    vertices in index order, then its triangles in index order)."""

    labels: torch.Tensor  # (P,) the sorted points' J24 parts
    vertex: torch.Tensor  # (P,) bool: the sorted point is a vertex (not a centroid)
    source: torch.Tensor  # (P,) each sorted point's index among the V vertices, then the F centroids in part order
    triangles: torch.Tensor  # (F, 3) the faces in part order (stable)
    triangle_part: torch.Tensor  # (F,) the part of each face in part order

    @staticmethod
    def build(faces: torch.Tensor, vertex_part: torch.Tensor) -> SurfaceLayout:
        """faces (F, 3), vertex_part (V,) J24 part of each vertex (a face is its first corner's)."""
        V = vertex_part.shape[0]
        face_part = vertex_part[faces[:, 0]]
        order = torch.argsort(torch.cat([vertex_part, face_part]), stable=True)
        is_vertex = order < V
        # The faces come in the stable part order of the faces alone, so the k-th centroid
        # among the sorted points is the k-th face in part order.
        source = order.clone()
        source[~is_vertex] = V + torch.arange(faces.shape[0], device=order.device)
        face_order = order[~is_vertex] - V
        return SurfaceLayout(
            labels=torch.cat([vertex_part, face_part])[order],
            vertex=is_vertex,
            source=source,
            triangles=faces[face_order],
            triangle_part=face_part[face_order],
        )

    def points(self, vertices: torch.Tensor) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
        """(B, V, 3) vertices -> the sorted surface points (B, 3, P) and the triangles'
        corners (three (B, 3, F), faces in part order). Gathers along the rows of a (3 B, V)
        array: `gather` on these is several times faster than `index_select` on the CPU."""
        B, V = vertices.shape[:2]
        rows = vertices.transpose(1, 2).reshape(3 * B, V)
        corners = [rows.gather(1, self.triangles[:, i].expand(3 * B, -1)) for i in range(3)]
        # The centroid as `maps.surface_points` computes it: (c0 + c1 + c2) x (1 / 3).
        centroid = (corners[0] + corners[1]).add_(corners[2]).mul_(1.0 / 3.0)
        out = torch.cat([rows, centroid], 1).gather(1, self.source.expand(3 * B, -1))
        return out.view(B, 3, -1), tuple(c.view(B, 3, -1) for c in corners)


__all__ = ["SurfaceLayout"]
