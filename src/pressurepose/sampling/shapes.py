"""Body shapes for the pose sampler: the box of each backend (`BodyModel.shape_bounds`; the
population, its tables and its measured heights and weights are in `body.shape_ranges`) and a
draw in it: each entry on its interval with density ~ t^(p - 1), p its power
(`BodyModel.shape_powers`; 1 = uniform)."""

from __future__ import annotations

import numpy as np

from pressurepose.body import backend_class


def shape_bounds(backend: str, gender: str, shape_names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) arrays (S,) of the uniform shape distribution for a backend (by name) and
    gender: `BodyModel.shape_bounds` of its class, for callers without a loaded model."""
    return backend_class(backend).shape_bounds(gender, shape_names)


def draw_shape(
    rng: np.random.Generator, low: np.ndarray, high: np.ndarray, power: np.ndarray | None = None
) -> np.ndarray:
    """One shape (S,) in the box [low, high]: uniform, or with `power` (S,) p per entry a density
    ~ t^(p - 1) on its interval (t = u^(1/p); the same S uniform numbers drawn either way)."""
    u = rng.random(low.shape[0])
    if power is not None:
        u = u ** (1.0 / power)
    return low + (high - low) * u
