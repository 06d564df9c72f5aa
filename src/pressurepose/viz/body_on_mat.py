"""Top and side views of a posed body over the mat grid."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

from pressurepose.body.joints import J24_NAMES, J24_PARENTS  # noqa: E402
from pressurepose.files import save_figure
from pressurepose.mat import MatSpec  # noqa: E402


def plot_body_on_mat(vertices: np.ndarray, joints: np.ndarray, mat: MatSpec, path: str | Path, title: str = "") -> Path:
    """Write a PNG: top view (image orientation: row 0 = head end at the top, column 0 on
    the left) and side view of one body. vertices (V, 3), joints (24, 3), mat frame, metres."""
    vertices = np.asarray(vertices)
    joints = np.asarray(joints)
    fig, (top, side) = plt.subplots(1, 2, figsize=(9, 7), gridspec_kw={"width_ratios": [1, 1.3]})
    (x0, x1), (y0, y1) = mat.mattress_bounds_m
    # Top view: y (columns) to the right, x (rows) downwards, like the pressure image.
    top.add_patch(Rectangle((y0, x0), y1 - y0, x1 - x0, fc="0.93", ec="0.5", label="mattress"))
    top.add_patch(
        Rectangle(
            (0, 0),
            mat.sensing_width_m,
            mat.sensing_length_m,
            fc="none",
            ec="tab:blue",
            lw=1.2,
            label=f"sensing area {mat.rows} x {mat.cols}",
        )
    )
    for r in range(0, mat.rows + 1, 8):
        top.axhline(r * mat.pitch_row_m, color="tab:blue", lw=0.3, alpha=0.5)
    step = max(1, len(vertices) // 6000)
    v = vertices[::step]
    sc = top.scatter(v[:, 1], v[:, 0], c=v[:, 2], s=1, cmap="viridis")
    _skeleton(top, joints[:, 1], joints[:, 0])
    top.text(joints[22, 1], joints[22, 0], " L hand", color="crimson", fontsize=8)
    top.set_xlim(y0 - 0.05, y1 + 0.05)
    top.set_ylim(x1 + 0.05, x0 - 0.05)
    top.set_aspect("equal")
    top.set_xlabel("y (m) - columns")
    top.set_ylabel("x (m) - rows, head end at the top")
    top.legend(loc="lower left", fontsize=7)
    fig.colorbar(sc, ax=top, shrink=0.6, label="height z (m)")
    side.scatter(v[:, 0], v[:, 2], c=v[:, 2], s=1, cmap="viridis")
    _skeleton(side, joints[:, 0], joints[:, 2])
    side.axhline(0.0, color="0.4", lw=1)
    side.set_xlim(x0 - 0.05, x1 + 0.05)
    side.set_aspect("equal")
    side.set_xlabel("x (m), head end on the left")
    side.set_ylabel("z (m), 0 = mattress top")
    fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


def _skeleton(ax, a: np.ndarray, b: np.ndarray) -> None:
    for j, p in enumerate(J24_PARENTS):
        if p >= 0:
            ax.plot([a[p], a[j]], [b[p], b[j]], color="crimson", lw=1.2)
    ax.scatter(a, b, color="crimson", s=8, zorder=3)
    ax.text(a[J24_NAMES.index("head")], b[J24_NAMES.index("head")], " head", color="crimson", fontsize=8)
