"""Row-wise numpy arithmetic whose result for a row depends on that row only.

Sim #1 steps many bodies together, and a body must settle exactly (bit for bit) as it does
alone. Elementwise +, -, *, /, sqrt, min and max are correctly rounded, so they give the same
bits for a value whatever array it sits in. Reductions and products over a batched array
(`sum`, `einsum`, `@`) do not promise that: numpy and BLAS choose SIMD kernels, pairwise
blocks, fused multiply-adds and remainder loops by the array's length, strides and alignment,
so an element's rounding can change with the number of bodies next to it, or with the CPU
(seen on an AVX-512 Xeon). Transcendental ufuncs (`np.arctan2`, ...) may switch between a
SIMD and a scalar implementation by the same criteria. The helpers here spell every sum out
as elementwise operations in a fixed order; `atan2_each` goes through the C library per value.
"""

from __future__ import annotations

import math

import numpy as np


def sq_norm3(v: np.ndarray) -> np.ndarray:
    """|v|^2 over the last axis (length 3): (v0^2 + v1^2) + v2^2."""
    return v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1] + v[..., 2] * v[..., 2]


def matvec3(R: np.ndarray, x: np.ndarray) -> np.ndarray:
    """R @ x for (..., 3, 3) matrices and (..., 3) vectors (broadcast), as
    (R[:, 0] x0 + R[:, 1] x1) + R[:, 2] x2."""
    return R[..., :, 0] * x[..., 0:1] + R[..., :, 1] * x[..., 1:2] + R[..., :, 2] * x[..., 2:3]


def sum_last(x: np.ndarray) -> np.ndarray:
    """Sum over the last axis, in index order ((x0 + x1) + x2) + ..."""
    if x.shape[-1] == 0:
        return np.zeros(x.shape[:-1])
    s = x[..., 0].copy()
    for k in range(1, x.shape[-1]):
        s += x[..., k]
    return s


def atan2_each(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """np.arctan2 of 1-d arrays, one value at a time through `math.atan2` (the C library)."""
    return np.array([math.atan2(a, b) for a, b in zip(y.tolist(), x.tolist())], dtype=np.float64)


__all__ = ["atan2_each", "matvec3", "sq_norm3", "sum_last"]
