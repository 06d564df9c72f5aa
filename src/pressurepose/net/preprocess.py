"""Pressure images -> network input channels, and the seed's calibration-noise augmentation.

As released (REFERENCE.md): clip to [0, 100] mmHg, Gaussian blur (sigma 0.5 taxels), then
three channels - contact (100 where the clipped reading is > 0), the blurred pressure scaled
so each image sums to SUM_TOTAL, and its Sobel gradient magnitude scaled the same way. The
per-image sum normalisation makes the input independent of the overall pressure level (real
mats read ~3x lower under a blanket, seed A.8; PmatData frames are in raw units). Mod2 adds
two channels from Mod1's reconstruction: -min(Q-hat, 0) in mm and C-hat x 100. Optional
extras: two constant planes (height in m, mass in units of 100 kg) and one gender plane.
The paper arch upsamples x2 (bilinear) to 128 x 54; the fast arch works at 64 x 27. A network
whose `NetConfig.texture_sigma_taxels` > 0 first smooths the reading within its loaded taxels
(`smooth_loaded`: detail at the taxel scale out, the outline and the force kept).

Augmentation ("calibration noise", per image, training only): an offset N(0, 14) mmHg and
integer noise on the loaded taxels, re-masked to the originally loaded taxels, a blur of
sigma ~ N(0.5, 0.2) instead of 0.5, and the pressure and Sobel channels multiplied by
independent N(1, 0.2) factors after the sum normalisation (which would cancel them before).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from pressurepose.blur import gaussian_blur

ROWS, COLS = 64, 27
MAX_MMHG = 100.0
SUM_TOTAL = 20000.0
BLUR_SIGMA = 0.5
CONTACT_VALUE = 100.0


def check_pressure(pressure_mmhg: torch.Tensor) -> None:
    """ValueError unless (B, 64, 27), finite and >= 0."""
    if pressure_mmhg.ndim != 3 or tuple(pressure_mmhg.shape[1:]) != (ROWS, COLS):
        raise ValueError(f"pressure_mmhg must have shape (B, {ROWS}, {COLS}), got {tuple(pressure_mmhg.shape)}")
    if not torch.isfinite(pressure_mmhg).all():
        raise ValueError("pressure_mmhg contains NaN or infinite values")
    if bool((pressure_mmhg < 0).any()):
        raise ValueError(f"pressure_mmhg must be >= 0 (min {float(pressure_mmhg.min()):.3g})")


_SOBEL_X = ((-1.0, 0.0, 1.0), (-2.0, 0.0, 2.0), (-1.0, 0.0, 1.0))


def sobel_magnitude(images: torch.Tensor) -> torch.Tensor:
    """(B, H, W) -> (B, H, W) gradient magnitude (Sobel, zero padded). The kernels
    _SOBEL_X and its transpose, separated into a [1, 2, 1] smoothing and a [-1, 0, 1]
    difference and written as shifted sums (a 2-channel conv2d of one input channel takes a
    slow path on CPU: 3x the time at 128 images)."""
    p = F.pad(images, (1, 1, 1, 1))  # (B, H + 2, W + 2)
    diff = p[..., 2:] - p[..., :-2]  # along W, every padded row
    smooth = p[..., :-2] + 2 * p[..., 1:-1] + p[..., 2:]
    gx = diff[..., :-2, :] + 2 * diff[..., 1:-1, :] + diff[..., 2:, :]
    gy = smooth[..., 2:, :] - smooth[..., :-2, :]
    return (gx.square() + gy.square() + 1e-12).sqrt() - 1e-6


def smooth_loaded(pressure_mmhg: torch.Tensor, sigma_taxels: float) -> torch.Tensor:
    """(B, 64, 27) -> the same images smoothed within their loaded taxels: a Gaussian of
    `sigma_taxels` (separable, zero beyond the mat), kept on the taxels that read > 0 and scaled
    so each image keeps its total: detail at the taxel scale (a real mat's rows and taxels of
    uneven gain, a simulation's bony points) out, the contact's outline kept (docs/network.md
    "The sensor's texture"). sigma 0: unchanged."""
    if sigma_taxels <= 0:
        return pressure_mmhg
    y = gaussian_blur(pressure_mmhg, sigma_taxels)
    loaded = pressure_mmhg > 0
    y = torch.where(loaded, y, torch.zeros_like(y))
    scale = pressure_mmhg.sum((-2, -1), keepdim=True) / y.sum((-2, -1), keepdim=True).clamp(min=1e-12)
    return y * scale


def _to_sum(images: torch.Tensor) -> torch.Tensor:
    """Scale each (H, W) image to sum SUM_TOTAL (an all-zero image stays zero)."""
    total = images.sum((-2, -1), keepdim=True)
    return images * (SUM_TOTAL / total.clamp(min=1e-6))


def pressure_channels(
    pressure_mmhg: torch.Tensor, augment: bool = False, generator: torch.Generator | None = None
) -> torch.Tensor:
    """(B, 64, 27) mmHg -> (B, 3, 64, 27): contact, pressure, Sobel (see module doc)."""
    p = pressure_mmhg.clamp(0.0, MAX_MMHG)
    loaded = p > 0
    B = p.shape[0]
    sigma: torch.Tensor | float = BLUR_SIGMA
    if augment:
        p, sigma = _calibration_noise(p, loaded, generator)
    blurred = gaussian_blur(p, sigma)
    channels = [loaded.to(p.dtype) * CONTACT_VALUE, _to_sum(blurred), _to_sum(sobel_magnitude(blurred).clamp(min=0))]
    if augment:
        factors = 1 + 0.2 * torch.randn(2, B, 1, 1, generator=generator).to(p)
        channels[1] = channels[1] * factors[0].clamp(min=0.2)
        channels[2] = channels[2] * factors[1].clamp(min=0.2)
    return torch.stack(channels, 1)


def _calibration_noise(p, loaded, generator):
    B = p.shape[0]
    rand = lambda *shape: torch.randn(*shape, generator=generator).to(p)  # noqa: E731 - CPU generator
    offset = 14.0 * rand(B, 1, 1)
    jitter = torch.round(rand(*p.shape))
    p = torch.where(loaded, (p + offset + jitter).clamp(0.0, MAX_MMHG), torch.zeros_like(p))
    sigma = (BLUR_SIGMA + 0.2 * rand(B)).clamp(min=0.0)
    return p, sigma


def reconstruction_channels(depth_mm: torch.Tensor, contact: torch.Tensor) -> torch.Tensor:
    """Mod1's maps (B, 64, 27) -> Mod2's extra channels (B, 2, 64, 27): sink depth (mm) and
    contact x 100, as released."""
    return torch.stack([-depth_mm.clamp(max=0.0), contact * CONTACT_VALUE], 1)


def constant_planes(values: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """(B, K) scalars -> (B, K, H, W) constant planes shaped like `like` (B, C, H, W)."""
    B, _, H, W = like.shape
    return values.to(like)[:, :, None, None].expand(B, values.shape[1], H, W)


def upsample2(x: torch.Tensor) -> torch.Tensor:
    """(B, C, 64, 27) -> (B, C, 128, 54) bilinear, as the released network's input."""
    return F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)


__all__ = [
    "check_pressure",
    "constant_planes",
    "gaussian_blur",
    "pressure_channels",
    "reconstruction_channels",
    "sobel_magnitude",
    "upsample2",
]
