"""Anny's phenotype blendshape coefficients laid out for inference (body/anny_phenotype.py)
against Anny's own code."""

import pytest
import torch

from pressurepose.body.anny_phenotype import PhenotypeCoefficients


def _annys(model, shape):
    zeros = shape.new_zeros(len(shape), 0)
    with torch.no_grad():
        return model._get_phenotype_blendshape_coefficients(shape, zeros, zeros)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_coefficients_match_annys_own(anny32, anny64, dtype):
    """Random phenotypes, every anchor of every phenotype (the hat functions' corners), the
    range's ends and values beyond them (Anny clamps them to its anchors' range): Anny's numbers
    to a few units of round-off; the body's path without autograd is this one."""
    body = anny32 if dtype == torch.float32 else anny64
    m = body.anny
    g = torch.Generator().manual_seed(8)
    corners = torch.tensor(sorted({float(a) for f in m.phenotype_labels for a in m.anchors[f]} | {-0.5, 0.0, 1.0, 1.5}))
    assert (corners < 0).any() and (corners > 1).any()  # the clamp is exercised
    grid = corners[torch.randint(len(corners), (128, 6), generator=g)]
    shape = torch.cat([torch.rand(64, 6, generator=g), grid]).to(dtype)
    expected = _annys(m, shape)
    got = PhenotypeCoefficients(m)(shape)
    eps = torch.finfo(dtype).eps
    torch.testing.assert_close(got, expected, atol=8 * eps, rtol=8 * eps)
    inside = shape[:64]
    assert torch.equal(body._coefficients(inside), PhenotypeCoefficients(m)(inside))


def test_with_autograd_annys_own_code_runs(anny64):
    m = anny64.anny
    shape = torch.rand(4, 6, generator=torch.Generator().manual_seed(9), dtype=torch.float64).requires_grad_(True)
    coeffs = anny64._coefficients(shape)
    assert coeffs.requires_grad
    assert torch.equal(coeffs.detach(), _annys(m, shape.detach()))
    (grad,) = torch.autograd.grad(coeffs.square().sum(), shape)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0


def test_refuses_phenotypes_it_does_not_lay_out(anny32):
    class Racial:  # an Anny exposing a race phenotype (weights normalised across races, not interpolated)
        phenotype_labels = [*anny32.anny.phenotype_labels, "african"]
        anchors = anny32.anny.anchors

    with pytest.raises(ValueError, match="interpolated phenotypes only"):
        PhenotypeCoefficients(Racial())
