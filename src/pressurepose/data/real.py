"""Real pressure images from other mats onto the BT3510 grid the network expects (seed A.8).

A real mat may have another taxel pitch, another size and another orientation than the
BodiTrak BT3510 (64 x 27 taxels, 2.86 x 2.75 cm, row 0 at the head). `resample_to_mat` maps a
pressure image onto our grid by area: each of our taxels gets the area-weighted mean pressure
of the source taxels it overlaps (pressure is intensive, so the summed force over the overlap
is kept); the two sensing areas are centred on each other unless an offset is given, and our
taxels outside the source mat read 0. `orient` turns an image so row 0 is the head end.
"""

from __future__ import annotations

import numpy as np

from pressurepose.errors import UserError
from pressurepose.mat import MatSpec


def _overlap(n_src: int, pitch_src: float, n_dst: int, pitch_dst: float, offset: float) -> np.ndarray:
    """(n_dst, n_src) overlap length of destination cell i with source cell j along one axis
    (source cell j spans offset + [j, j+1) pitch_src in destination coordinates)."""
    d0 = np.arange(n_dst)[:, None] * pitch_dst
    s0 = offset + np.arange(n_src)[None, :] * pitch_src
    return np.clip(np.minimum(d0 + pitch_dst, s0 + pitch_src) - np.maximum(d0, s0), 0.0, None)


def resample_to_mat(
    image: np.ndarray,
    pitch_row_m: float,
    pitch_col_m: float,
    mat: MatSpec | None = None,
    offset_m: tuple[float, float] | None = None,
) -> np.ndarray:
    """(H, W) pressure image (row 0 at the head) at another pitch -> (64, 27) on our grid.

    offset_m: where the source's first taxel corner lies in our mat frame (x along, y across);
    default: the two sensing areas share their centre."""
    mat = mat or MatSpec()
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2 or min(img.shape) < 1:
        raise UserError(f"pressure image must be 2-D (rows, columns), got shape {img.shape}")
    if not np.isfinite(img).all():
        raise UserError("pressure image holds NaN or infinite values")
    if (img < 0).any():
        raise UserError("pressure image has negative values: subtract the empty level and clip first")
    if not (pitch_row_m > 0 and pitch_col_m > 0):
        raise UserError(f"taxel pitches must be > 0 m, got {pitch_row_m}, {pitch_col_m}")
    H, W = img.shape
    if offset_m is None:
        offset_m = ((mat.sensing_length_m - H * pitch_row_m) / 2, (mat.sensing_width_m - W * pitch_col_m) / 2)
    A_r = _overlap(H, pitch_row_m, mat.rows, mat.pitch_row_m, offset_m[0]) / mat.pitch_row_m
    A_c = _overlap(W, pitch_col_m, mat.cols, mat.pitch_col_m, offset_m[1]) / mat.pitch_col_m
    return A_r @ img @ A_c.T


def orient(image: np.ndarray, head_row: str = "first", flip_columns: bool = False) -> np.ndarray:
    """An image with row 0 at the head end: head_row 'first' (already) or 'last' (PmatData
    files, which run foot to head); flip_columns mirrors left-right (a mat turned over)."""
    if head_row not in ("first", "last"):
        raise UserError(f"head_row must be 'first' or 'last', got {head_row!r}")
    img = np.asarray(image)
    if head_row == "last":
        img = img[::-1]
    if flip_columns:
        img = img[:, ::-1]
    return np.ascontiguousarray(img)


__all__ = ["orient", "resample_to_mat"]
