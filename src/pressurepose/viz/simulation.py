"""Figures of one simulated sample: pressure image, depth map, contact, the body at rest."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pressurepose.files import save_figure


def plot_sample(
    path: Path,
    pressure_mmhg: np.ndarray,
    depth_mm: np.ndarray,
    vertices: np.ndarray,
    title: str = "",
    max_pressure: float = 100.0,
    bed_profile: np.ndarray | None = None,
) -> Path:
    """Write a PNG with the (64, 27) pressure image (mmHg), the depth map Q (mm) with the
    contact outline, and side and top views of the mesh at rest (mat frame, m); `bed_profile`
    (n, 2): the mattress top's (x, z) along the bed when it is not flat."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(13, 5.2), gridspec_kw={"width_ratios": [1, 1, 1.6, 1]})
    im = axes[0].imshow(pressure_mmhg, cmap="viridis", vmin=0, vmax=max_pressure, aspect="auto")
    axes[0].set_title("pressure (mmHg)")
    fig.colorbar(im, ax=axes[0], fraction=0.08)
    d = np.minimum(depth_mm, 0.0)
    im = axes[1].imshow(d, cmap="magma", vmin=min(-1.0, float(d.min())), vmax=0, aspect="auto")
    axes[1].contour(depth_mm < 0, levels=[0.5], colors="c", linewidths=0.8)
    axes[1].set_title("depth Q (mm), contact C")
    fig.colorbar(im, ax=axes[1], fraction=0.08)
    for ax in axes[:2]:
        ax.set_xlabel("column")
        ax.set_ylabel("row (head at 0)")
    step = max(1, len(vertices) // 6000)
    v = vertices[::step]
    axes[2].scatter(v[:, 0], v[:, 2] * 100, s=0.3, c=v[:, 1], cmap="coolwarm")
    if bed_profile is None:
        axes[2].axhline(0.0, color="k", lw=0.8)
    else:  # (n, 2) x, z of the mattress top along the bed (raised head section)
        axes[2].plot(bed_profile[:, 0], bed_profile[:, 1] * 100, color="k", lw=0.8)
    axes[2].set_xlabel("x along the bed (m)")
    axes[2].set_ylabel("height (cm)")
    axes[2].set_title("at rest, side view (black: mattress top)")
    axes[3].scatter(v[:, 1], v[:, 0], s=0.3, c=v[:, 2], cmap="viridis")
    axes[3].invert_yaxis()
    axes[3].set_aspect("equal")
    axes[3].set_xlabel("y across (m)")
    axes[3].set_title("top view")
    fig.suptitle(title)
    fig.tight_layout()
    path = save_figure(fig, Path(path), dpi=90, format="png")
    plt.close(fig)
    return path
