"""Body shapes for the pose sampler: the box of each backend (`BodyModel.shape_bounds`; the
population, its tables and its measured heights and weights are in `body.shape_ranges`) and a
uniform draw in it."""

from __future__ import annotations

import numpy as np

from pressurepose.body import backend_class


def shape_bounds(backend: str, gender: str, shape_names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) arrays (S,) of the uniform shape distribution for a backend (by name) and
    gender: `BodyModel.shape_bounds` of its class, for callers without a loaded model."""
    return backend_class(backend).shape_bounds(gender, shape_names)


def draw_shape(rng: np.random.Generator, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """One shape (S,) uniform in the box [low, high]."""
    return low + (high - low) * rng.random(low.shape[0])
