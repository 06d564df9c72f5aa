"""`pressurepose generate`: the generator (`generate.run.run_generate`) and its one-line summary."""

from __future__ import annotations

from pressurepose.generate.allocator import tune_allocator
from pressurepose.generate.plan import GenerateConfig
from pressurepose.generate.run import run_generate


def generate(cfg: GenerateConfig) -> None:
    """Generate a dataset (sampling, sim #1, sim #2, sensor) into Parquet shards and
    manifest.json; re-running the same command resumes an interrupted run."""
    tune_allocator()  # this process makes the shards itself with --workers 1
    s = run_generate(cfg)
    print(
        f"{s['total']} samples in {s['shards']} shards -> {cfg.out} ({s['made']} made now, {s['resumed']} "
        f"already there; {s['rejected']} rejected and replaced)"
        + (f", {s['made'] / s['seconds']:.2f} samples/s" if s["made"] else "")
    )


__all__ = ["GenerateConfig", "generate"]
