"""Body shapes of adults of both genders over a wide range of heights and weights: the box
each backend's `BodyModel.shape_bounds` gives the pose sampler (docs/sampling.md).

Anny (default): gender is exact (1 female, 0 male); age uniform over adults (Anny age 0.77 to
0.852, i.e. 18 to ~70 years on Anny's anchors); muscle and proportions uniform on [0, 1];
height uniform and weight drawn with a density rising linearly (`ANNY_POWERS`) on per-gender
intervals chosen so the population spans
- male:   ~1.48-2.02 m, ~37-140 kg, BMI ~16-40,
- female: ~1.43-1.95 m, ~35-113 kg, BMI ~16-32.5
(measured over 1,000 draws each: `python benchmarks/sampling.py --shapes`; docs/sampling.md).
The full [0, 1] height range of Anny would reach 2.45 m and weights under BMI 12, outside
any adult population; these intervals keep the seed's "wide, even" spirit (its SMPL betas
were uniform on [-3, 3]) inside plausible adults.

SMPL (optional backend): 10 betas uniform on [-3, 3] as the original; the gender is that of
the SMPL model file.
"""

from __future__ import annotations

import numpy as np

ANNY_RANGES = {  # phenotype -> (low, high) per gender
    "female": {
        "gender": (1.0, 1.0),
        "age": (0.77, 0.852),
        "muscle": (0.0, 1.0),
        "weight": (0.25, 1.0),
        "height": (0.20, 0.63),
        "proportions": (0.0, 1.0),
    },
    "male": {
        "gender": (0.0, 0.0),
        "age": (0.77, 0.852),
        "muscle": (0.0, 1.0),
        "weight": (0.10, 1.0),
        "height": (0.12, 0.60),
        "proportions": (0.0, 1.0),
    },
}
SMPL_BETA_RANGE = (-3.0, 3.0)
# Sampling law 3 (docs/sampling.md "An adult population's body mass"): Anny's weight phenotype
# is drawn with a density rising linearly over its interval (t = u^(1/2) of a uniform u; the
# power p gives a density ~ t^(p - 1)), the others uniform. Uniform weights gave women a median
# mass of 58 kg (BMI 20.4, 17% under 18.5) and men 72 kg; this gives 62 / 78 kg, the seed's
# average adult masses (62.5 / 78.4 kg, Tozeren; REFERENCE.md), the same box kept.
ANNY_POWERS = {"weight": 2.0}


def anny_bounds(gender: str, shape_names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) arrays (S,) of Anny's phenotypes `shape_names` for "female" or "male"."""
    ranges = ANNY_RANGES[gender]
    return np.array([ranges[n][0] for n in shape_names]), np.array([ranges[n][1] for n in shape_names])


def anny_powers(shape_names: tuple[str, ...]) -> np.ndarray:
    """(S,) power p of each phenotype's draw on its interval (density ~ t^(p - 1); 1 = uniform)."""
    return np.array([ANNY_POWERS.get(n, 1.0) for n in shape_names])


def beta_bounds(num_betas: int) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) arrays (S,) of SMPL's betas (either gender: the model file sets it)."""
    return np.full(num_betas, SMPL_BETA_RANGE[0]), np.full(num_betas, SMPL_BETA_RANGE[1])


__all__ = ["ANNY_POWERS", "ANNY_RANGES", "SMPL_BETA_RANGE", "anny_bounds", "anny_powers", "beta_bounds"]
