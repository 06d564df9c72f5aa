"""Figures of evaluated cases: the pressure image, and the true and estimated meshes seen from
the side and from above."""

from __future__ import annotations

import numpy as np

from pressurepose.files import save_figure


def plot_cases(path, cases: list[tuple], faces: np.ndarray, points: int = 4000) -> None:
    """cases: [(title, pressure (64, 27), true vertices (V, 3), estimated vertices (V, 3))]."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = max(len(cases), 1)
    fig, axes = plt.subplots(n, 3, figsize=(11, 3.2 * n), squeeze=False, gridspec_kw={"width_ratios": [0.6, 1.6, 1.0]})
    rng = np.random.default_rng(0)
    for row, (title, image, true_v, est_v) in zip(axes, cases):
        keep = rng.permutation(len(true_v))[:points]
        row[0].imshow(image, cmap="viridis", vmin=0, vmax=100)
        row[0].set(title=title, xticks=[], yticks=[])
        for ax, (i, j), name in ((row[1], (0, 2), "side (x along, z up)"), (row[2], (1, 0), "top (y across, x along)")):
            ax.scatter(true_v[keep, i], true_v[keep, j], s=0.5, c="0.6", label="true")
            ax.scatter(est_v[keep, i], est_v[keep, j], s=0.5, c="tab:red", label="estimated")
            ax.set(title=name, aspect="equal")
            if j == 0:
                ax.invert_yaxis()
        row[1].legend(loc="upper right", fontsize=7, markerscale=8)
    fig.tight_layout()
    save_figure(fig, path, format="png", dpi=80)
    plt.close(fig)


__all__ = ["plot_cases"]
