"""Body-model speed: forward and forward+backward, joints-only and full mesh, both backends.

    .venv/bin/python benchmarks/body.py            # prints a Markdown table (ms, median)

SMPL runs on a generated SMPL-format file (same sizes as the real model). Float32, CPU,
torch's default thread count.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import torch

from pressurepose.body import BodyParams, load_body_model
from pressurepose.body.smpl_backend import write_synthetic_smpl_file


def timed(fn, repeats: int) -> float:
    fn()  # warm-up
    samples = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t)
    return statistics.median(samples) * 1e3


def bench(model, B: int, joints_only: bool, repeats: int) -> tuple[float, float]:
    g = torch.Generator().manual_seed(0)
    shape = model.default_shape(B)
    pose = (torch.randn(B, 23, 3, generator=g) * 0.3).requires_grad_()
    p = BodyParams.zeros(B, shape).replace(pose=pose)

    def forward():
        with torch.no_grad():
            return model.joints(p) if joints_only else model(p).vertices

    def forward_backward():
        out = model.joints(p) if joints_only else model(p).vertices
        out.sum().backward()

    return timed(forward, repeats), timed(forward_backward, repeats)


def main() -> None:
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    print("| backend | path | B | forward (ms) | forward+backward (ms) |")
    print("| --- | --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        write_synthetic_smpl_file(Path(tmp) / "SMPL_NEUTRAL.npz")
        models = {"anny": load_body_model("anny"), "smpl": load_body_model("smpl", model_dir=tmp)}
        for name, model in models.items():
            for joints_only in (True, False):
                for B in (1, 64, 128, 256):
                    repeats = 20 if B == 1 else 5
                    f, fb = bench(model, B, joints_only, repeats)
                    path = "joints" if joints_only else "mesh"
                    print(f"| {name} | {path} | {B} | {f:.1f} | {fb:.1f} |", flush=True)


if __name__ == "__main__":
    main()
