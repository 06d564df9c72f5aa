"""`pressurepose train`: the training loop (`train.loop`) plus the run's figure, metrics.png,
redrawn at every save."""

from __future__ import annotations

from pathlib import Path

import torch

from pressurepose.files import atomic_write
from pressurepose.train import loop
from pressurepose.train.config import TrainConfig
from pressurepose.viz.training import plot_metrics


def write_metrics_plot(run: Path, history: list[dict]) -> None:
    """RUN/metrics.png: the training curves so far."""
    atomic_write(run / "metrics.png", lambda tmp: plot_metrics(history, tmp))


def run_train(cfg: TrainConfig, dataset: torch.utils.data.Dataset | None = None) -> Path:
    """Train as configured (`train.loop.train`) and keep RUN/metrics.png current; returns the
    run folder."""
    return loop.train(cfg, dataset, on_save=write_metrics_plot)


def train(cfg: TrainConfig) -> None:
    """Train PressureNet's Mod1 (--module 1) or Mod2 on a trained Mod1 (--module 2 --mod1 RUN);
    writes checkpoints, metrics and a plot to --out and resumes a run found there."""
    run = run_train(cfg)
    rows = loop.read_metrics(run)
    last = rows[-1] if rows else {}
    val = f", val MPJPE {last['val_mpjpe_mm']:.1f} mm" if "val_mpjpe_mm" in last else ""
    if "average_val_mpjpe_mm" in last:
        val += f" (weight average {last['average_val_mpjpe_mm']:.1f} mm, in model.safetensors)"
    print(
        f"{len(rows)} epochs -> {run}: loss {last.get('loss', float('nan')):.4f}, train MPJPE "
        f"{last.get('train_mpjpe_mm', float('nan')):.1f} mm{val}"
    )


__all__ = ["run_train", "train", "write_metrics_plot"]
