"""The one Gaussian blur (`pressurepose.blur`): a Python-number sigma's kernels are made once and
reused; they must give what a tensor sigma gives, and serve autograd whichever mode made them."""

import pytest
import torch

from pressurepose import blur
from pressurepose.blur import gaussian_blur


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_number_sigma_equals_a_tensor_sigma(dtype):
    g = torch.Generator().manual_seed(11)
    images = torch.rand(5, 64, 27, generator=g, dtype=dtype)
    for rows, cols in ((0.5, 0.5), (1.3, 0.0), (0.0, 2.2), (1e-9, 0.7)):
        expected = gaussian_blur(images, torch.tensor(rows, dtype=dtype), torch.tensor(cols, dtype=dtype))
        for batch in (images, images[:1], images[:0]):  # the kept kernel serves every batch size
            got = gaussian_blur(batch, rows, cols)
            assert got.shape == batch.shape
            torch.testing.assert_close(got, expected[: len(batch)], atol=4 * torch.finfo(dtype).eps, rtol=0)
    # a blur keeps the total of a load far from the edges, and 0 leaves the image as it is
    centre = torch.zeros(1, 64, 27, dtype=dtype)
    centre[0, 32, 13] = 1.0
    assert float(gaussian_blur(centre, 1.0).sum()) == pytest.approx(1.0, abs=1e-6)
    assert torch.equal(gaussian_blur(images, 0.0), images)


def test_kernels_first_made_in_inference_mode_serve_autograd():
    saved = dict(blur._FIXED)
    blur._FIXED.clear()
    try:
        with torch.inference_mode():
            gaussian_blur(torch.rand(1, 8, 8), 0.8)
        images = torch.rand(2, 8, 8, requires_grad=True)
        gaussian_blur(images, 0.8).square().sum().backward()
        assert torch.isfinite(images.grad).all() and images.grad.abs().sum() > 0
    finally:
        blur._FIXED.clear()
        blur._FIXED.update(saved)
