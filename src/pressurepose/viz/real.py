"""Figures of the real-data evaluation (`pressurepose evaluate-real`: real.png): posture
confusion and height / mass scatter per mattress (PmatData), or 3DVPE per participant and
the height / mass errors (point clouds)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pressurepose.eval.real import POSTURES  # noqa: E402
from pressurepose.files import save_figure  # noqa: E402


def plot_real(path, rows: list[dict], summary: dict) -> None:
    mattresses = list(summary)
    fig, axes = plt.subplots(len(mattresses), 3, figsize=(12, 3.6 * len(mattresses)), squeeze=False)
    for row, name in zip(axes, mattresses):
        sel = [r for r in rows if r["mattress"] == name]
        conf = np.array([[summary[name]["confusion"][t][e] for e in POSTURES] for t in ("supine", "left", "right")])
        row[0].imshow(conf, cmap="Blues")
        for (i, j), v in np.ndenumerate(conf):
            row[0].text(j, i, str(v), ha="center", va="center")
        row[0].set(
            xticks=range(len(POSTURES)),
            xticklabels=POSTURES,
            yticks=range(3),
            yticklabels=["supine", "left", "right"],
            xlabel="estimated",
            ylabel="true",
            title=f"{name}: posture {summary[name]['posture_accuracy'] * 100:.0f}%",
        )
        for ax, key, unit in ((row[1], "height_m", "m"), (row[2], "mass_kg", "kg")):
            t = [r[key] for r in sel]
            e = [r[f"estimated_{key}"] for r in sel]
            ax.scatter(t, e, s=12)
            lo, hi = min(t + e), max(t + e)
            ax.plot([lo, hi], [lo, hi], "k--", lw=0.8)
            ax.set(xlabel=f"subject ({unit})", ylabel=f"estimated ({unit})", title=f"{name}: {key.split('_')[0]}")
    fig.tight_layout()
    save_figure(fig, path, format="png", dpi=80)
    plt.close(fig)


def plot_tilt(path, rows: list[dict]) -> None:
    """Tilted frames (`evaluate-real`'s group E rows): the roll read against the documented one,
    a panel per mattress; the frames of one documented roll spread sideways to be seen apart."""
    mattresses = sorted({r["mattress"] for r in rows})
    fig, axes = plt.subplots(1, len(mattresses), figsize=(5 * len(mattresses), 4.2), squeeze=False)
    offsets = np.linspace(-4, 4, 9)
    for ax, name in zip(axes[0], mattresses):
        sel = [r for r in rows if r["mattress"] == name]
        doc = np.array([r["documented_roll_deg"] for r in sel])
        x = doc + offsets[np.arange(len(sel)) % len(offsets)]
        ax.scatter(x, [r["roll_deg"] for r in sel], s=14)
        ax.plot([-50, 50], [-50, 50], "k--", lw=0.8)
        ax.axhline(0, color="0.7", lw=0.6)
        ax.set(
            xlabel="documented roll (deg, + right)",
            ylabel="read roll (deg)",
            ylim=(-185, 185),
            yticks=range(-180, 181, 45),
            title=f"{name}: tilted on wedges or a pillow",
        )
    fig.tight_layout()
    save_figure(fig, path, format="png", dpi=80)
    plt.close(fig)


def plot_real_cloud(path, rows: list[dict], by_subject: dict) -> None:
    names = list(by_subject)
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 3.8))
    a.bar(range(len(names)), [by_subject[s]["vpe_m"] * 100 for s in names])
    a.set(xticks=range(len(names)), ylabel="3DVPE (cm)", title="per participant")
    a.set_xticklabels(names, rotation=60, fontsize=7)
    b.hist([r["vpe_m"] * 100 for r in rows], bins=30)
    b.set(xlabel="3DVPE (cm)", ylabel="frames", title="per frame")
    fig.tight_layout()
    save_figure(fig, path, format="png", dpi=80)
    plt.close(fig)


__all__ = ["plot_real", "plot_real_cloud", "plot_tilt"]
