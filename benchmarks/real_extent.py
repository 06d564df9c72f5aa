"""How long a stretch of the mat bodies load, simulated against PmatData (issue 22: the heatmap
model's +10 cm PmatData heights), and a model's height error on both.

    PYTHONPATH=src .venv/bin/python benchmarks/real_extent.py --data DIR [--model RUN]
        [--pmatdata ../shared/data/pmatdata] [--every 1]

Per pose partition of the dataset (from the shard names) and per PmatData posture group
(B supine, C right, D left): the rows holding 2% and 98% of the summed force (row 0 at the
head), that stretch over the subject's height, and the share of the force in rows 0-7 (the
head end). With --model: the estimated height (`body.measure` of the estimated shape) minus the
true one, median and mean absolute, on the dataset's first 512 images and on PmatData.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import torch

from pressurepose.data.pmatdata import distinct_frames, load_images, load_index
from pressurepose.eval.real import read_bodies
from pressurepose.mat import MatSpec
from pressurepose.samples import resolve_pmatdata
from pressurepose.train.checkpoint import load_network


def force_rows(p: np.ndarray, lo: float = 0.02, hi: float = 0.98) -> tuple[np.ndarray, np.ndarray]:
    """First and last rows (N,) of the stretch holding the force between quantiles lo and hi."""
    prof = p.sum(-1)
    cum = np.cumsum(prof, -1) / np.maximum(prof.sum(-1, keepdims=True), 1e-9)
    return (cum < lo).sum(-1), (cum < hi).sum(-1)


def synthetic(data: Path, every: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{partition: (images (N, 64, 27), heights (N,))} from a generated dataset's shards."""
    parts: dict[str, list] = {}
    for f in sorted((data / "shards").glob("*.parquet")):
        m = re.match(r"(train|test)-([a-z_]+)-(female|male)", f.name)
        if m is None:
            continue
        t = pq.read_table(f, columns=["pressure_mmhg", "height_m"]).to_pydict()
        p = np.array([np.asarray(x, np.float32).reshape(64, 27) for x in t["pressure_mmhg"][::every]])
        parts.setdefault(m.group(2), []).append((p, np.array(t["height_m"][::every])))
    return {k: (np.concatenate([a for a, _ in v]), np.concatenate([b for _, b in v])) for k, v in parts.items()}


def height_error(net, images: np.ndarray, heights: np.ndarray) -> str:
    est = read_bodies(net, torch.from_numpy(images), batch=64).height_m.double().numpy()
    d = est - heights
    r = np.corrcoef(est, heights)[0, 1]
    return f"height error median {100 * np.median(d):+.1f} cm, MAE {100 * np.abs(d).mean():.1f} cm, r {r:.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--model", default=None)
    parser.add_argument("--pmatdata", type=Path, default=Path("pmatdata"))
    parser.add_argument("--every", type=int, default=1, help="use every n-th image of each shard")
    args = parser.parse_args()
    torch.set_num_threads(1)
    pitch = MatSpec().pitch_row_m
    sets = synthetic(args.data, args.every)
    records = distinct_frames([r for r in load_index(resolve_pmatdata(args.pmatdata)) if r.group in "BCD"])
    real = load_images(records, 20.0)
    real_h = np.array([r.height_cm / 100 for r in records])
    for g in "BCD":
        keep = np.array([r.group == g for r in records])
        sets[f"PmatData {g}"] = (real[keep], real_h[keep])
    print("| images | n | height (m) | rows of 2-98% force | stretch / height | force in rows 0-7 |")
    print("| --- | --- | --- | --- | --- | --- |")
    for name, (p, h) in sets.items():
        first, last = force_rows(p)
        head = p[:, :8].sum((-1, -2)) / p.sum((-1, -2))
        print(
            f"| {name} | {len(h)} | {np.median(h):.3f} | {np.median(first):.0f}-{np.median(last):.0f} "
            f"| {np.median((last - first + 1) * pitch / h):.3f} | {100 * np.median(head):.1f}% |"
        )
    if args.model:
        net, _ = load_network(args.model)
        p = np.concatenate([v[0] for k, v in sets.items() if not k.startswith("PmatData")])[:512]
        h = np.concatenate([v[1] for k, v in sets.items() if not k.startswith("PmatData")])[:512]
        print(f"synthetic ({len(h)}): {height_error(net, p, h)}")
        print(f"PmatData ({len(real_h)}): {height_error(net, real, real_h)}")


if __name__ == "__main__":
    main()
