"""The network's smoothing of a reading within its loaded taxels (`net.preprocess.smooth_loaded`,
`NetConfig.texture_sigma_taxels`): against a per-taxel reference, its invariants, and that it
takes out a mat's row-to-row gain texture."""

import math

import numpy as np
import pytest
import torch

from pressurepose.errors import UserError
from pressurepose.net.model import NetConfig
from pressurepose.net.preprocess import smooth_loaded
from pressurepose.train.config import TrainConfig


def _image(seed=0, B=3):
    g = torch.Generator().manual_seed(seed)
    p = torch.rand(B, 64, 27, generator=g, dtype=torch.float64) * 40
    return p * (torch.rand(B, 64, 27, generator=g, dtype=torch.float64) > 0.5)


def _reference(p, sigma):
    """Per taxel: the Gaussian-weighted sum of the image over the mat (zero beyond it), kept on
    the loaded taxels, scaled to the image's total."""
    R, C = p.shape
    r = max(1, math.ceil(3 * sigma))
    w = [math.exp(-0.5 * (d / sigma) ** 2) for d in range(-r, r + 1)]
    norm = sum(w)
    out = torch.zeros_like(p)
    for i in range(R):
        for j in range(C):
            if p[i, j] <= 0:
                continue
            acc = 0.0
            for di in range(-r, r + 1):
                for dj in range(-r, r + 1):
                    a, b = i + di, j + dj
                    if 0 <= a < R and 0 <= b < C:
                        acc += w[di + r] * w[dj + r] / norm**2 * float(p[a, b])
            out[i, j] = acc
    return out * (p.sum() / out.sum())


def test_smoothing_against_a_per_taxel_reference():
    p = _image(B=1)
    got = smooth_loaded(p, 1.0)
    np.testing.assert_allclose(got[0].numpy(), _reference(p[0], 1.0).numpy(), rtol=1e-10, atol=1e-10)


def test_smoothing_keeps_force_outline_and_mirror():
    p = _image()
    for sigma in (0.5, 1.0, 2.0):
        got = smooth_loaded(p, sigma)
        np.testing.assert_allclose(got.sum((1, 2)).numpy(), p.sum((1, 2)).numpy(), rtol=1e-12)
        assert torch.equal(got > 0, p > 0)  # the contact's outline, taxel for taxel
        torch.testing.assert_close(smooth_loaded(p.flip(-1), sigma), got.flip(-1), rtol=1e-12, atol=1e-12)
    assert smooth_loaded(p, 0.0) is p
    empty = torch.zeros(1, 64, 27)
    assert torch.equal(smooth_loaded(empty, 1.0), empty)


def test_smoothing_takes_out_row_gain_texture():
    """A smooth body-sized load read through rows alternately 30% more and less sensitive (the
    banding of real frames): smoothed, it lies within a tenth of the textured reading's distance
    of the load without the texture."""
    x = torch.arange(64, dtype=torch.float64)[:, None]
    y = torch.arange(27, dtype=torch.float64)[None, :]
    smooth = 30 * torch.exp(-(((x - 32) / 14) ** 2) - ((y - 13) / 5) ** 2)
    smooth = torch.where(smooth > 1.0, smooth, torch.zeros_like(smooth))[None]
    gain = 1 + 0.3 * (-1.0) ** torch.arange(64, dtype=torch.float64)[None, :, None]
    textured = smooth * gain
    textured = textured * smooth.sum() / textured.sum()
    before = (textured - smooth).abs().sum() / smooth.sum()
    after = (smooth_loaded(textured, 1.0) - smooth_loaded(smooth, 1.0)).abs().sum() / smooth.sum()
    assert float(after) < 0.1 * float(before), (float(before), float(after))


def test_network_reads_the_smoothed_image(anny32):
    from pressurepose.net.model import GENDER_UNKNOWN, NetInputs, PressureNet
    from pressurepose.net.preprocess import pressure_channels

    p = _image(B=2).float()
    inputs = NetInputs(pressure_mmhg=p, gender=torch.full((2,), GENDER_UNKNOWN))
    net = PressureNet(NetConfig(arch="heatmap", gender_input=False, texture_sigma_taxels=1.0), body=anny32)
    torch.testing.assert_close(net.channels(inputs), pressure_channels(smooth_loaded(p, 1.0)))
    plain = PressureNet(NetConfig(arch="heatmap", gender_input=False), body=anny32)
    torch.testing.assert_close(plain.channels(inputs), pressure_channels(p))


def test_bad_texture_sigma_is_refused():
    with pytest.raises(UserError, match="texture_sigma_taxels must lie in"):
        NetConfig(texture_sigma_taxels=-1.0)
    with pytest.raises(UserError, match="texture_sigma must lie in"):
        TrainConfig(texture_sigma=9.0).resolved()
