"""Figures of sampled initial poses: the spread of the distal joints over the cells, and a
grid of sampled bodies on the mat."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

from pressurepose.body.joints import J24_NAMES  # noqa: E402
from pressurepose.files import save_figure
from pressurepose.mat import MatSpec  # noqa: E402
from pressurepose.sampling.partitions import ARM_CELLS, LEG_CELLS  # noqa: E402

_J = J24_NAMES.index
_LIMBS = (
    ("left leg", "left_hip", "left_knee", "left_ankle", LEG_CELLS),
    ("right leg", "right_hip", "right_knee", "right_ankle", LEG_CELLS),
    ("left arm", "left_shoulder", "left_elbow", "left_wrist", ARM_CELLS),
    ("right arm", "right_shoulder", "right_elbow", "right_wrist", ARM_CELLS),
)


def distal_offsets(joints: np.ndarray, root_draw: np.ndarray) -> dict[str, np.ndarray]:
    """Per limb: (B, 3) distal minus proximal joint in the bed's axes after the roll (x along
    the body toward the foot, y across, z height), divided by the limb's length."""
    yaw = root_draw[:, 1]
    c, s = np.cos(yaw), np.sin(yaw)
    out = {}
    for name, prox, mid, dist, _ in _LIMBS:
        d = joints[:, _J(dist)] - joints[:, _J(prox)]
        # Undo the yaw (a rotation about z applied after the roll).
        d = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], -1)
        length = np.linalg.norm(joints[:, _J(mid)] - joints[:, _J(prox)], axis=-1) + np.linalg.norm(
            joints[:, _J(dist)] - joints[:, _J(mid)], axis=-1
        )
        out[name] = d / length[:, None]
    return out


def plot_cells(joints: np.ndarray, root_draw: np.ndarray, cells: np.ndarray, path: str | Path, title: str = "") -> Path:
    """Top views of the ankles and wrists relative to their hips and shoulders (in limb
    lengths), coloured by cell, with the cell bounds and the count per cell."""
    offsets = distal_offsets(joints, root_draw)
    fig, axes = plt.subplots(1, 4, figsize=(15, 5.2))
    for k, (ax, (name, *_, n_cells)) in enumerate(zip(axes, _LIMBS)):
        d = offsets[name]
        ax.scatter(d[:, 1], d[:, 0], c=cells[:, k], cmap="tab10", vmin=0, vmax=9, s=4)
        if n_cells == LEG_CELLS:
            bounds = [q / 4 for q in range(0, 4)]
            centres = [(q + 0.5) / 4 for q in range(4)]
        else:
            bounds = [q / 4 for q in range(-3, 4)]
            centres = [(q - 3.5) / 4 for q in range(8)]  # cell 0 highest (toward the head)
        for b in bounds:
            ax.axhline(b, color="0.5", lw=0.6, ls="--")
        counts = np.bincount(cells[:, k], minlength=n_cells)
        for q, y in enumerate(centres):
            ax.text(1.02, y, f"{counts[q]}", transform=ax.get_yaxis_transform(), va="center", fontsize=8)
        ax.set_ylim(1.05, -0.1 if n_cells == LEG_CELLS else -1.05)
        ax.set_xlim(-1.05, 1.05)
        ax.set_aspect("equal")
        ax.set_title(f"{name}: {'ankle - hip' if n_cells == LEG_CELLS else 'wrist - shoulder'}")
        ax.set_xlabel("across the bed / limb length")
        if k == 0:
            ax.set_ylabel("along the body (toward the foot) / limb length")
    fig.suptitle(title or f"distal joints over the cells ({len(cells)} samples; count per cell at the right)")
    fig.tight_layout()
    return _save(fig, path)


def plot_bodies(
    vertices: np.ndarray, mat: MatSpec, path: str | Path, labels: list[str] | None = None, columns: int = 6
) -> Path:
    """Top views of sampled bodies (N, V, 3) in the mat frame on the mattress, coloured by height."""
    n = len(vertices)
    rows = max(1, int(np.ceil(n / columns)))
    fig, axes = plt.subplots(rows, columns, figsize=(2.3 * columns, 4.3 * rows), squeeze=False)
    (x0, x1), (y0, y1) = mat.mattress_bounds_m
    step = max(1, vertices.shape[1] // 3000)
    for i, ax in enumerate(axes.flat):
        ax.set_axis_off()
        if i >= n:
            continue
        ax.add_patch(Rectangle((y0, x0), y1 - y0, x1 - x0, fc="0.93", ec="0.5"))
        ax.add_patch(Rectangle((0, 0), mat.sensing_width_m, mat.sensing_length_m, fc="none", ec="tab:blue", lw=0.8))
        v = vertices[i, ::step]
        order = np.argsort(v[:, 2])
        ax.scatter(v[order, 1], v[order, 0], c=v[order, 2], s=0.5, cmap="viridis", vmin=0, vmax=0.6)
        ax.set_xlim(y0 - 0.3, y1 + 0.3)
        ax.set_ylim(x1 + 0.3, x0 - 0.3)
        ax.set_aspect("equal")
        if labels:
            ax.set_title(labels[i], fontsize=7)
    fig.suptitle("sampled initial poses, top view (head end at the top; colour = height, 0-0.6 m)")
    fig.tight_layout()
    return _save(fig, path)


def posed_vertices(model, params, batch: int = 16) -> np.ndarray:
    """(B, V, 3) meshes of BodyParams in the model's dtype, without gradients."""
    out = []
    with torch.no_grad():
        for i in range(0, params.batch_size, batch):
            chunk = params.index(slice(i, i + batch)).to(model.dtype)
            out.append(model(chunk).vertices.cpu().numpy())
    return np.concatenate(out)


def _save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    return path
