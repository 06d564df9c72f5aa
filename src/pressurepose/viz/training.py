"""Per-epoch training curves of a run (metrics.png)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from pressurepose.files import save_figure


def plot_metrics(history: list[dict], path: str | Path) -> Path:
    """Loss (left) and MPJPE in mm (right) per epoch, train and validation (and the weight
    average's validation once `--average-from` begins). Writes a PNG."""
    epochs = [r["epoch"] for r in history]
    fig, (ax_loss, ax_err) = plt.subplots(1, 2, figsize=(9, 3.5))
    ax_loss.plot(epochs, [r["loss"] for r in history], "o-", label="train")
    if any("val_loss" in r for r in history):
        ax_loss.plot(epochs, [r.get("val_loss", float("nan")) for r in history], "o-", label="validation")
    ax_loss.set_yscale("log")
    ax_loss.set_xlabel("epoch")
    ax_loss.set_ylabel("loss")
    ax_loss.legend()
    ax_err.plot(epochs, [r["train_mpjpe_mm"] for r in history], "o-", label="train")
    if any("val_mpjpe_mm" in r for r in history):
        ax_err.plot(epochs, [r.get("val_mpjpe_mm", float("nan")) for r in history], "o-", label="validation")
    if any("average_val_mpjpe_mm" in r for r in history):
        average = [r.get("average_val_mpjpe_mm", float("nan")) for r in history]
        ax_err.plot(epochs, average, "s-", label="validation, weight average")
    ax_err.set_xlabel("epoch")
    ax_err.set_ylabel("MPJPE (mm)")
    ax_err.legend()
    fig.tight_layout()
    save_figure(fig, Path(path), dpi=100, format="png")
    plt.close(fig)
    return Path(path)
