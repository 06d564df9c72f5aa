"""Contact sheet: a grid of pressure images from a dataset."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from pressurepose.files import save_figure


def plot_contact_sheet(
    path: Path, images: np.ndarray, labels: list[str], max_pressure: float = 100.0, cols: int = 8
) -> Path:
    """Write a PNG of (N, 64, 27) pressure images (mmHg, row 0 = head end at the top), one
    label per image, on one colour scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(images)
    cols = min(cols, n)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(1.6 * cols, 3.4 * rows), squeeze=False)
    im = None
    for k, ax in enumerate(axes.flat):
        ax.set_axis_off()
        if k < n:
            im = ax.imshow(images[k], cmap="viridis", vmin=0, vmax=max_pressure, aspect="equal")
            ax.set_title(labels[k], fontsize=6)
    if im is not None:
        fig.colorbar(im, ax=axes, fraction=0.02, label="mmHg")
    save_figure(fig, path, dpi=90, format="png")
    plt.close(fig)
    return Path(path)


__all__ = ["plot_contact_sheet"]
