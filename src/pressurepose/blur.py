"""The one Gaussian blur: images (B, H, W), separable, zero padded, sigma per axis in pixels
(a number, a 0-d tensor, or one per image). The mat/cover's spread of sim #2
(`sim.reading.taxel_pressure`) and the network's input channels and augmentations
(`net.preprocess`) both use it."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from pressurepose.constants import kept

_NO_BLUR = 1e-6  # a sigma at or below this (pixels) leaves the image as it is


_FIXED: dict[tuple, tuple[torch.Tensor, int] | None] = {}  # kernels of a Python-number sigma, made once


def _kernels(sigma, B: int, dtype, device) -> tuple[torch.Tensor, int] | None:
    """(B, K) normalised kernels and the radius, or None when no image is blurred."""
    key = (float(sigma), dtype, torch.device(device)) if isinstance(sigma, (int, float)) else None
    # a constant (the network's channels): no gradient, made once (a few: a calibration's many are not kept)
    if key is not None and (key in _FIXED or len(_FIXED) < 64):
        fixed = kept(_FIXED, key, lambda: _kernels(torch.tensor(key[0], dtype=dtype, device=device), 1, dtype, device))
        return None if fixed is None else (fixed[0].expand(B, -1), fixed[1])
    sigma = torch.as_tensor(sigma, dtype=dtype, device=device).expand(B)
    top = float(sigma.detach().max()) if B else 0.0
    if not top > _NO_BLUR:
        return None
    radius = max(1, math.ceil(3.0 * top))
    x = torch.arange(-radius, radius + 1, dtype=dtype, device=device)
    s = sigma.clamp(min=1e-3)[:, None]
    k = torch.exp(-0.5 * (x / s) ** 2)
    k = torch.where((sigma > _NO_BLUR)[:, None], k, (x == 0).to(k).expand_as(k))
    return k / k.sum(1, keepdim=True), radius


def gaussian_blur(images: torch.Tensor, sigma_rows, sigma_cols=None) -> torch.Tensor:
    """(B, H, W) blurred along the rows' axis (H) with `sigma_rows` and along W with
    `sigma_cols` (default: the same), each a number, a 0-d tensor or (B,) per image, in
    pixels; <= 1e-6 leaves that axis (of that image) alone. Force that leaves the grid within
    3 sigma of its edge is lost (zero padding). Differentiable in the images and in sigma."""
    B = images.shape[0]
    out = images
    for axis, sigma in ((-2, sigma_rows), (-1, sigma_cols if sigma_cols is not None else sigma_rows)):
        kr = _kernels(sigma, B, images.dtype, images.device)
        if kr is None:
            continue
        k, radius = kr
        pad = (radius, radius) if axis == -1 else (0, 0, radius, radius)
        # Sliding windows times each image's kernel: a grouped conv2d with one group per image
        # takes a slow generic path on CPU.
        windows = F.pad(out, pad).unfold(axis, 2 * radius + 1, 1)  # (B, H, W, K)
        out = torch.einsum("bhwk,bk->bhw", windows, k)
    return out


__all__ = ["gaussian_blur"]
