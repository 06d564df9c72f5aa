"""The co-registration figure (`pressurepose coregister`: coregister.png): clicked and
reprojected markers in the image, the camera and the cloud over the mat from above."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pressurepose.data.coregister import CameraPose, Markers, project  # noqa: E402
from pressurepose.files import save_figure  # noqa: E402
from pressurepose.mat import MatSpec  # noqa: E402


def plot_coregistration(path, mk: Markers, pose: CameraPose, cloud: np.ndarray | None) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    ax = axes[0]
    uv = project(mk.intrinsics.K, pose.R, pose.t, mk.mat_xyz_m)
    ax.scatter(*mk.pixel.T, marker="o", facecolors="none", edgecolors="k", s=80, label="clicked")
    ax.scatter(*uv.T, marker="x", c="r", label=f"reprojected (RMS {pose.rms_px:.2f} px)")
    for name, p in zip(mk.names, mk.pixel):
        ax.annotate(name, p, fontsize=7, xytext=(4, 4), textcoords="offset points")
    ax.invert_yaxis()
    ax.set(title="markers in the image (px)", aspect="equal")
    ax.legend(fontsize=8)
    ax = axes[1]
    mat = MatSpec()
    if cloud is not None:
        p = pose.to_mat(cloud)
        keep = np.random.default_rng(0).permutation(len(p))[:20000]
        ax.scatter(p[keep, 1], p[keep, 0], c=p[keep, 2], s=1, cmap="viridis", vmin=-0.05, vmax=0.4)
    L, W = mat.sensing_length_m, mat.sensing_width_m
    ax.plot([0, W, W, 0, 0], [0, 0, L, L, 0], "k-", lw=1)
    cam = pose.position_m
    ax.plot(cam[1], cam[0], "r^", label=f"camera, {cam[2]:.2f} m up")
    ax.set(title="mat frame, top view (m; head at the top)", xlabel="y", ylabel="x", aspect="equal")
    ax.invert_yaxis()
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, format="png", dpi=90)
    plt.close(fig)


__all__ = ["plot_coregistration"]
