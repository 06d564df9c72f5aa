"""The pressure mat and the mattress it lies on: sizes, pitches and coordinate conversions.

Mat frame (docs/conventions.md): right-handed, metres; origin at the outer corner of the
sensing area at the head end on the column-0 side; x along the bed towards the foot
(image rows), y across the bed (image columns), z up, z = 0 the undeformed mattress top.
Taxel (row, col) covers x in [row, row + 1) * pitch_row_m, y in [col, col + 1) * pitch_col_m.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from pressurepose.errors import UserError

ArrayLike = np.ndarray | torch.Tensor


@dataclasses.dataclass(frozen=True)
class MatSpec:
    """BodiTrak BT3510 on a hospital mattress, as in the original (REFERENCE.md, seed A.3).

    The simulated mat covers the whole mattress with a (covered_rows, covered_cols) grid at
    the taxel pitch; the sensing (rows, cols) taxels sit centred inside it, so the
    non-sensing border is `border_rows` taxels at head and foot and `border_cols` at each
    side. The seed reports a measured border of about 6 cm at the sides and 9 cm at head and
    foot, but its own 68 x 33 grid at this pitch gives 5.7 cm at head and foot and 8.25 cm at
    the sides (the two are consistent only with the labels swapped); we keep the grid, which
    is what the original simulated (docs/conventions.md).
    """

    rows: int = 64
    cols: int = 27
    pitch_row_m: float = 0.0286
    # The original scales the across-bed pitch by 1/1.04 (REFERENCE.md).
    pitch_col_m: float = 0.0286 / 1.04
    covered_rows: int = 68
    covered_cols: int = 33
    max_pressure_mmhg: float = 100.0

    def __post_init__(self) -> None:
        for name in ("rows", "cols", "covered_rows", "covered_cols"):
            value = getattr(self, name)
            if not isinstance(value, int) or value <= 0:
                raise UserError(f"MatSpec.{name} must be a positive int, got {value!r}")
        for name in ("pitch_row_m", "pitch_col_m", "max_pressure_mmhg"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise UserError(f"MatSpec.{name} must be a positive number, got {value!r}")
        for covered, inner, what in (
            (self.covered_rows, self.rows, "rows"),
            (self.covered_cols, self.cols, "cols"),
        ):
            if covered < inner or (covered - inner) % 2:
                raise UserError(
                    f"MatSpec.covered_{what} must be >= {what} and differ from it by an even "
                    f"number (sensing area centred), got covered_{what}={covered}, {what}={inner}"
                )

    @property
    def shape(self) -> tuple[int, int]:
        """Sensing image shape (rows, cols)."""
        return (self.rows, self.cols)

    @property
    def covered_shape(self) -> tuple[int, int]:
        return (self.covered_rows, self.covered_cols)

    @property
    def border_rows(self) -> int:
        return (self.covered_rows - self.rows) // 2

    @property
    def border_cols(self) -> int:
        return (self.covered_cols - self.cols) // 2

    @property
    def border_head_foot_m(self) -> float:
        return self.border_rows * self.pitch_row_m

    @property
    def border_side_m(self) -> float:
        return self.border_cols * self.pitch_col_m

    @property
    def sensing_length_m(self) -> float:
        return self.rows * self.pitch_row_m

    @property
    def sensing_width_m(self) -> float:
        return self.cols * self.pitch_col_m

    @property
    def mattress_length_m(self) -> float:
        return self.covered_rows * self.pitch_row_m

    @property
    def mattress_width_m(self) -> float:
        return self.covered_cols * self.pitch_col_m

    @property
    def taxel_area_m2(self) -> float:
        return self.pitch_row_m * self.pitch_col_m

    @property
    def centre_m(self) -> tuple[float, float]:
        """(x, y) of the centre of the sensing area (= centre of the mattress)."""
        return (self.sensing_length_m / 2, self.sensing_width_m / 2)

    @property
    def mattress_bounds_m(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """((x_min, x_max), (y_min, y_max)) of the mattress top in the mat frame."""
        bx, by = self.border_head_foot_m, self.border_side_m
        return ((-bx, self.sensing_length_m + bx), (-by, self.sensing_width_m + by))

    def to_taxel(self, xy_m: ArrayLike) -> ArrayLike:
        """Continuous taxel coordinates (row, col) of points (..., 2) given as (x, y) in metres.

        Taxel (r, c) spans [r, r + 1) x [c, c + 1); its centre is (r + 0.5, c + 0.5).
        Works on numpy arrays and (differentiably) on torch tensors.
        """
        _check_last_dim(xy_m, 2, "xy_m")
        scale = _like(xy_m, [1.0 / self.pitch_row_m, 1.0 / self.pitch_col_m])
        return xy_m * scale

    def to_metres(self, rc: ArrayLike) -> ArrayLike:
        """(x, y) in metres of continuous taxel coordinates (..., 2) given as (row, col)."""
        _check_last_dim(rc, 2, "rc")
        scale = _like(rc, [self.pitch_row_m, self.pitch_col_m])
        return rc * scale

    def taxel_centres_m(self, covered: bool = False) -> np.ndarray:
        """(rows, cols, 2) array of taxel-centre (x, y) in metres; `covered` for the full grid,
        whose row/col 0 lies `border_rows`/`border_cols` taxels outside the sensing area."""
        if covered:
            r = np.arange(self.covered_rows) - self.border_rows + 0.5
            c = np.arange(self.covered_cols) - self.border_cols + 0.5
        else:
            r = np.arange(self.rows) + 0.5
            c = np.arange(self.cols) + 0.5
        rr, cc = np.meshgrid(r, c, indexing="ij")
        return self.to_metres(np.stack([rr, cc], axis=-1))

    def sensing_slice(self) -> tuple[slice, slice]:
        """Index of the sensing taxels inside a covered (covered_rows, covered_cols) grid."""
        return (
            slice(self.border_rows, self.border_rows + self.rows),
            slice(self.border_cols, self.border_cols + self.cols),
        )


def _check_last_dim(a: ArrayLike, n: int, name: str) -> None:
    if a.ndim < 1 or a.shape[-1] != n:
        raise ValueError(f"{name} must have shape (..., {n}), got {tuple(a.shape)}")


def _like(a: ArrayLike, values: list[float]) -> ArrayLike:
    if isinstance(a, torch.Tensor):
        return torch.tensor(values, dtype=a.dtype, device=a.device)
    return np.asarray(values, dtype=np.result_type(a, np.float64))
