"""The picture `pressurepose click` shows (`viz.clicker`): a photo (.png/.jpg) or a depth image
(.npy, metres or millimetres) shown through a colour map, with its readings."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from pressurepose.errors import UserError
from pressurepose.validate import read_npy

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclasses.dataclass(frozen=True)
class ClickImage:
    """The image shown: rgb (H, W, 3) uint8; depth_m (H, W) float32 metres (0 = no reading) or None."""

    rgb: np.ndarray
    depth_m: np.ndarray | None

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.rgb.shape[1], self.rgb.shape[0]

    def depth_at(self, u: float, v: float) -> float | None:
        """The reading at the pixel nearest (u, v) (pixel centres at integers), None if invalid."""
        if self.depth_m is None:
            return None
        c, r = int(math.floor(u + 0.5)), int(math.floor(v + 0.5))
        h, w = self.depth_m.shape
        if not (0 <= r < h and 0 <= c < w):
            return None
        d = float(self.depth_m[r, c])
        return round(d, 4) if math.isfinite(d) and d > 0 else None


def load_image(path: Path, depth_unit: str = "auto") -> ClickImage:
    """Read IMAGE; UserError naming the problem (missing, unreadable, wrong shape or type)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"no image at {path}")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        return _load_depth(path, depth_unit)
    if suffix not in IMAGE_SUFFIXES:
        raise UserError(f"{path}: IMAGE must be a .png or .jpg picture or a depth image .npy (H, W)")
    import matplotlib.image

    try:
        img = np.asarray(matplotlib.image.imread(path))
    except (OSError, ValueError, SyntaxError, EOFError) as exc:  # PIL's errors for corrupt files
        raise UserError(f"{path} is not a readable image ({exc})") from None
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] not in (3, 4) or min(img.shape[:2]) < 2:
        raise UserError(f"{path}: expected a grey, RGB or RGBA picture, got an array of shape {img.shape}")
    img = img[..., :3]
    if img.dtype.kind == "f":  # PNGs come as floats in [0, 1]
        img = np.clip(img * 255 + 0.5, 0, 255)
    return ClickImage(np.ascontiguousarray(img.astype(np.uint8)), None)


def _load_depth(path: Path, unit: str) -> ClickImage:
    if unit not in ("auto", "m", "mm"):
        raise UserError(f"--depth-unit must be auto, m or mm, got {unit!r}")
    arr = read_npy(path, what="depth image (H, W)")
    if arr.ndim != 2 or min(arr.shape) < 2:
        raise UserError(f"depth image {path} must be 2-D (H, W), got shape {arr.shape}")
    depth = arr.astype(np.float64)
    valid = np.isfinite(depth) & (depth > 0)
    if not valid.any():
        raise UserError(f"depth image {path} has no valid reading (all 0, negative or non-finite)")
    if unit == "mm" or (unit == "auto" and (arr.dtype.kind in "iu" or np.median(depth[valid]) > 20)):
        depth = depth / 1000.0  # a camera 20 m away from a bed is not a setup we expect
    depth = np.where(valid, depth, 0.0).astype(np.float32)
    # Colour map over the 1st-99th percentile of the valid readings; no reading = black.
    lo, hi = np.percentile(depth[valid], [1, 99])
    t = np.clip((depth - lo) / max(hi - lo, 1e-6), 0, 1)
    import matplotlib

    rgb = (matplotlib.colormaps["viridis"](t)[..., :3] * 255 + 0.5).astype(np.uint8)
    rgb[~valid] = 0
    return ClickImage(rgb, depth)


__all__ = ["IMAGE_SUFFIXES", "ClickImage", "load_image"]
