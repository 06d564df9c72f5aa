"""A run's per-epoch metrics: metrics.jsonl (what a resumed run reads back) and metrics.csv."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

from pressurepose.files import atomic_write
from pressurepose.validate import field, read_jsonl

METRICS = "metrics.jsonl"


def read_metrics(run: Path) -> list[dict]:
    """The rows of a run's metrics.jsonl, each with its epoch (UserError naming the file)."""
    path = run / METRICS
    rows = read_jsonl(path, "training metrics", "; delete it to resume without the earlier epochs' metrics")
    for number, row in enumerate(rows, 1):
        field(row, "epoch", "count", path, f"line {number}: ")
    return rows


def write_metrics(run: Path, history: list[dict]) -> None:
    """RUN/metrics.jsonl and metrics.csv (one row per epoch), each written atomically."""
    text = "".join(json.dumps(r) + "\n" for r in history)
    atomic_write(run / METRICS, lambda tmp: Path(tmp).write_text(text))
    keys = list(dict.fromkeys(k for r in history for k in r))
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=keys)
    writer.writeheader()
    writer.writerows(history)
    atomic_write(run / "metrics.csv", lambda tmp: Path(tmp).write_text(buf.getvalue()))


__all__ = ["METRICS", "read_metrics", "write_metrics"]
