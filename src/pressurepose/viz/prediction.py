"""One figure per predicted image: the pressure image with the estimated skeleton projected
onto it, and top and side views of the estimated mesh."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pressurepose.body.joints import J24_PARENTS  # noqa: E402
from pressurepose.files import save_figure
from pressurepose.mat import MatSpec  # noqa: E402


def _bones(ax, u: np.ndarray, v: np.ndarray, color: str = "crimson") -> None:
    for j, parent in enumerate(J24_PARENTS):
        if parent >= 0:
            ax.plot([u[parent], u[j]], [v[parent], v[j]], "-", color=color, lw=1.5)
    ax.plot(u, v, "o", color=color, ms=2.5)


# Heatmap spreads (m) that split a joint's trust (docs/network.md "How far to trust a joint": on
# simulated images arm joints under 10 cm are ~4 cm off, 10-25 cm ~8-17, over 25 cm ~30).
TRUST_BANDS = ((0.10, "lime", "< 10 cm"), (0.25, "gold", "10-25 cm"), (float("inf"), "red", ">= 25 cm"))


def _trust(ax, u: np.ndarray, v: np.ndarray, spread_m: np.ndarray) -> None:
    """Each joint marked by its heatmap spread's band, with a legend."""
    lower = 0.0
    for upper, color, label in TRUST_BANDS:
        m = (spread_m >= lower) & (spread_m < upper)
        ax.plot(u[m], v[m], "o", color=color, ms=4.5, mec="black", mew=0.5, label=label, ls="none")
        lower = upper
    ax.legend(title="heatmap spread", fontsize=6, title_fontsize=6, loc="lower right", framealpha=0.6)


def plot_prediction(
    path: str | Path,
    pressure_mmhg: np.ndarray,
    vertices: np.ndarray,
    joints: np.ndarray,
    mat: MatSpec,
    title: str = "",
    spread_m: np.ndarray | None = None,
) -> Path:
    """pressure (64, 27) mmHg, vertices (V, 3) and joints (24, 3) in the mat frame (m); with
    spread_m (24,), each joint on the pressure image marked by how sharply its heatmap pins it. PNG."""
    fig, (ax_p, ax_top, ax_side) = plt.subplots(1, 3, figsize=(11, 5), gridspec_kw={"width_ratios": [1, 1, 1.6]})
    im = ax_p.imshow(pressure_mmhg, cmap="magma", origin="upper", extent=(0, mat.cols, mat.rows, 0))
    rc = mat.to_taxel(joints[:, :2])
    _bones(ax_p, rc[:, 1], rc[:, 0], "cyan")
    if spread_m is not None:
        _trust(ax_p, rc[:, 1], rc[:, 0], np.asarray(spread_m))
    ax_p.set_xlim(0, mat.cols)
    ax_p.set_ylim(mat.rows, 0)
    ax_p.set_title("pressure + skeleton")
    ax_p.set_xlabel("column")
    ax_p.set_ylabel("row (head end at the top)")
    fig.colorbar(im, ax=ax_p, shrink=0.6, label="mmHg")
    v = vertices[:: max(1, len(vertices) // 5000)]
    ax_top.scatter(v[:, 1], v[:, 0], c=v[:, 2], s=0.5, cmap="viridis")
    _bones(ax_top, joints[:, 1], joints[:, 0])
    ax_top.set_xlim(-0.05, mat.sensing_width_m + 0.05)
    ax_top.set_ylim(mat.sensing_length_m + 0.05, -0.05)
    ax_top.set_aspect("equal")
    ax_top.set_title("mesh, top")
    ax_top.set_xlabel("y (m)")
    ax_top.set_ylabel("x (m)")
    ax_side.scatter(v[:, 0], v[:, 2], c=v[:, 2], s=0.5, cmap="viridis")
    _bones(ax_side, joints[:, 0], joints[:, 2])
    ax_side.axhline(0.0, color="0.4", lw=1)
    ax_side.set_aspect("equal")
    ax_side.set_title("mesh, side (z = 0: mattress top)")
    ax_side.set_xlabel("x (m), head end on the left")
    ax_side.set_ylabel("z (m)")
    fig.suptitle(title)
    fig.tight_layout()
    save_figure(fig, Path(path), dpi=90, format="png")
    plt.close(fig)
    return Path(path)
