"""The calibration's convergence figure (`pressurepose calibrate`: convergence.png)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pressurepose.calib.cmaes import CMAResult  # noqa: E402
from pressurepose.calib.loss import ParamSpace  # noqa: E402
from pressurepose.files import atomic_write  # noqa: E402


def convergence_plot(result: CMAResult, space: ParamSpace, path: Path) -> Path:
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    F = result.history_f
    if len(F):
        g = np.arange(1, len(F) + 1)
        axes[0].semilogy(g, np.minimum.accumulate(F.min(1)), label="best so far")
        axes[0].semilogy(g, np.median(F, 1), label="generation median", alpha=0.7)
        axes[0].semilogy(g, result.history_std, label="largest std (scaled units)", alpha=0.7)
        for j, name in enumerate(space.free):
            axes[1].plot(g, result.history_mean[:, j], label=name)
    axes[0].set_xlabel("generation")
    axes[0].set_title("loss (eq. 13 + penalties)")
    axes[0].legend()
    axes[1].set_xlabel("generation")
    axes[1].set_title("CMA-ES mean, scaled (parameter / loss.SCALES)")
    axes[1].legend(fontsize=7)
    fig.tight_layout()

    def write(tmp):
        fig.savefig(tmp, dpi=80, format="png")

    atomic_write(path, write)
    plt.close(fig)
    return path


__all__ = ["convergence_plot"]
