"""Anny's phenotype blendshape coefficients without autograd, in a dozen tensor operations.

Anny (`anny.models.phenotype.phenotype_blendshape_weights`) turns each phenotype into weights
over its variations' anchors (linear interpolation, one call and a dictionary per phenotype),
multiplies per blendshape the weights of the variations it is made of, and projects onto the
compact basis. At batch 1 that is ~2 ms of per-call overhead, paid by every shape pass (predict
pays it twice per image: the height blend's rest skeleton, then the fitted body's). Here the same
arithmetic is laid out once, per variation column: the interpolation weight of anchor a_i is
clamp(min((v - a_(i-1)) / (a_i - a_(i-1)), (a_(i+1) - v) / (a_(i+1) - a_i)), 0, 1) (the hat
function of the anchors, the value clamped to their range as Anny does without extrapolation),
the phenotypes the body does not expose keep Anny's default weights (computed by Anny itself,
once), and the products and projection are two batched operations. Same numbers as Anny's to
float rounding (tests/test_body.py); ~0.2 ms at batch 1 (docs/benchmarks.md, session 57).
Used only without autograd; with it (and for an Anny built to extrapolate) Anny's own code runs.
"""

from __future__ import annotations

import torch
from anny.models.phenotype import PHENOTYPE_VARIATIONS
from anny.utils.interpolation import linear_interpolation_coefficients

from pressurepose.body.anny_skinning import wants_grad
from pressurepose.constants import kept


class PhenotypeCoefficients:
    """Anny's compact phenotype blendshape coefficients (B, A) of (B, P) phenotypes, for a model
    without local changes or facial actions."""

    def __init__(self, model) -> None:
        labels = list(model.phenotype_labels)
        exposed = [f for f in PHENOTYPE_VARIATIONS if f in labels]
        if len(exposed) != len(labels) or "race" in labels:  # e.g. race phenotypes: not laid out here
            raise ValueError(f"PhenotypeCoefficients lays out interpolated phenotypes only, got {labels}")
        columns, rising, falling, fixed = [], [], [], []
        for feature, variations in PHENOTYPE_VARIATIONS.items():
            if feature not in exposed:
                columns += [0] * len(variations)
                rising += [(0.0, 1.0)] * len(variations)
                falling += [(0.0, 1.0)] * len(variations)
                fixed += [True] * len(variations)
                continue
            a = model.anchors[feature].double().tolist()
            if len(a) != len(variations):
                raise ValueError(f"Anny's {feature} has {len(a)} anchors for {len(variations)} variations")
            for i in range(len(a)):
                columns.append(labels.index(feature))
                # (slope, intercept) of the rising and falling edges; a flat 1 at either end
                rising.append((1 / (a[i] - a[i - 1]), -a[i - 1] / (a[i] - a[i - 1])) if i > 0 else (0.0, 1.0))
                falling.append((-1 / (a[i + 1] - a[i]), a[i + 1] / (a[i + 1] - a[i])) if i + 1 < len(a) else (0.0, 1.0))
                fixed.append(False)
        self.columns = torch.tensor(columns)
        self.rising = torch.tensor(rising, dtype=torch.float64)  # (26, 2)
        self.falling = torch.tensor(falling, dtype=torch.float64)
        self.fixed = torch.tensor(fixed)
        self.low = torch.tensor([float(model.anchors[f][0]) if f in exposed else 0.0 for f in labels])
        self.high = torch.tensor([float(model.anchors[f][-1]) if f in exposed else 1.0 for f in labels])
        with torch.no_grad():  # the fixed columns' weights: Anny's at its default phenotype value 0.5
            probe = torch.full((1, len(labels)), 0.5, dtype=torch.float64)
            self.defaults = _anny_variation_weights(model, probe)[0]
        self.mask = model.stacked_phenotype_blend_shapes_mask.detach()  # (K, 26), 0 or 1
        projection = model.phenotype_blendshape_projection  # None: Anny's full (not compact) basis
        self.projection = None if projection is None else projection.detach()
        self._typed: dict[tuple[torch.dtype, torch.device], tuple[torch.Tensor, ...]] = {}

    def _constants(self, like: torch.Tensor) -> tuple[torch.Tensor, ...]:
        to = dict(dtype=like.dtype, device=like.device)
        return kept(
            self._typed,
            (like.dtype, like.device),
            lambda: (
                self.columns.to(like.device),
                self.rising[:, 0].to(**to),
                self.rising[:, 1].to(**to),
                self.falling[:, 0].to(**to),
                self.falling[:, 1].to(**to),
                self.fixed.to(like.device),
                self.defaults.to(**to),
                self.low.to(**to),
                self.high.to(**to),
                self.mask.to(**to),
                (1 - self.mask).to(**to),
                None if self.projection is None else self.projection.to(**to),
            ),
        )

    @torch.no_grad()
    def __call__(self, shape: torch.Tensor) -> torch.Tensor:
        columns, r_slope, r_int, f_slope, f_int, fixed, defaults, low, high, mask, unmask, proj = self._constants(shape)
        v = torch.maximum(torch.minimum(shape, high), low)[:, columns]  # (B, 26)
        hat = torch.minimum(torch.addcmul(r_int, v, r_slope), torch.addcmul(f_int, v, f_slope)).clamp_(0, 1)
        weights = torch.where(fixed, defaults, hat)
        products = torch.addcmul(unmask, weights[:, None, :], mask).prod(-1)  # (B, K)
        return products if proj is None else products @ proj


def phenotype_coefficients(model, shape: torch.Tensor, cache: dict) -> torch.Tensor:
    """(B, A) Anny's blendshape coefficients of (B, P) phenotypes: `PhenotypeCoefficients` (made on
    first use, kept in `cache` under "_phenotype") without autograd; Anny's own code with it, or
    for an Anny that extrapolates or has local changes or facial actions."""
    if not wants_grad(shape) and not (
        model.extrapolate_phenotypes or model.local_change_labels or model.facial_action_labels
    ):
        if "_phenotype" not in cache:
            cache["_phenotype"] = PhenotypeCoefficients(model)
        return cache["_phenotype"](shape)
    zeros = shape.new_zeros(shape.shape[0], 0)
    return model._get_phenotype_blendshape_coefficients(shape, zeros, zeros)


def _anny_variation_weights(model, phenotypes: torch.Tensor) -> torch.Tensor:
    """(B, 26) Anny's per-variation weights (the factors of its blendshape products) by its own
    interpolation, the races normalised to sum to 1 (as `phenotype_blendshape_weights`)."""
    labels = list(model.phenotype_labels)
    out = []
    for feature, variations in PHENOTYPE_VARIATIONS.items():
        if feature == "race":
            values = torch.stack([_value(phenotypes, labels, k) for k in variations], 1)
            out.append(torch.nan_to_num(values / values.sum(1, keepdim=True), 1 / 3, 1 / 3, 1 / 3))
            continue
        anchors = model.anchors[feature].to(phenotypes)
        out.append(linear_interpolation_coefficients(_value(phenotypes, labels, feature), anchors, extrapolate=False))
    return torch.cat(out, 1)


def _value(phenotypes: torch.Tensor, labels: list[str], name: str) -> torch.Tensor:
    if name in labels:
        return phenotypes[:, labels.index(name)]
    return phenotypes.new_full((phenotypes.shape[0],), 0.5)


__all__ = ["PhenotypeCoefficients", "phenotype_coefficients"]
