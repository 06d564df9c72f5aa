"""How far to trust a joint: a heatmap network's joint error against its heatmap's spread.

    PYTHONPATH=src .venv/bin/python benchmarks/joint_spread.py --model default --data DATASET \
        [--n N] [--pmatdata pmatdata]

For every J24 joint of a generated dataset's test split: the heatmap's spread (the RMS distance of
its probability from its mean over the mat grid, the square root of `Localisation.spread_m2`;
`predict` writes it per joint as `joint_spread_m`) and the error of the estimated body's joint
(after the IK), the image read alone (no gender, height or mass, as `predict` reads it). Prints, per
region, the rank correlation of the two and the error in bands of spread; with --pmatdata, the
share of real frames' joints (PmatData experiment II, groups B-D, distinct frames) in each band
beside the simulated share (real frames have no joint labels: what their spreads say is how often
the network is as unsure of them as of the simulated joints it misplaces). docs/network.md "How
far to trust a joint" quotes it; "default" is the packaged model.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from pressurepose.body.joints import J24_NAMES
from pressurepose.data.pmatdata import distinct_frames, load_images, load_index
from pressurepose.eval.evaluation import REGIONS, _batches, open_split
from pressurepose.eval.real import read_bodies
from pressurepose.net.model import NetInputs
from pressurepose.samples import resolve_pmatdata
from pressurepose.train.checkpoint import load_network

BANDS_CM = (0.0, 10.0, 15.0, 25.0, float("inf"))


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Rank correlation (no ties among continuous values)."""
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    return float(np.corrcoef(ra, rb)[0, 1])


def _bands(s: np.ndarray) -> list[np.ndarray]:
    """One mask over s (cm) per band of BANDS_CM."""
    return [(s >= lo) & (s < hi) for lo, hi in zip(BANDS_CM[:-1], BANDS_CM[1:])]


def _header(first: list[str]) -> str:
    names = [
        f"spread < {hi:.0f}" if lo == 0 else f">= {lo:.0f}" if hi == float("inf") else f"{lo:.0f}-{hi:.0f}"
        for lo, hi in zip(BANDS_CM[:-1], BANDS_CM[1:])
    ]
    cols = first + names
    return "| " + " | ".join(cols) + " |\n|" + " --- |" * len(cols)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default="default")
    ap.add_argument("--data", type=Path, required=True, help="a generated dataset folder (its test split)")
    ap.add_argument("--n", type=int, default=None, help="the first N test samples (default: all)")
    ap.add_argument("--pmatdata", type=Path, default=None, help='PmatData folder ("pmatdata": the packaged copy)')
    args = ap.parse_args()
    torch.set_num_threads(1)
    net, _ = load_network(Path(args.model))
    if net.config.arch != "heatmap":
        raise SystemExit(f"{args.model} is arch {net.config.arch}: only heatmap networks localise joints")
    errors, spreads = [], []
    with torch.inference_mode():
        for _, b in _batches(open_split(args.data, "test"), 64, args.n):
            est = net(NetInputs(b["pressure_mmhg"]), mesh=False)[-1]
            errors.append((est.joints - b["joints"].to(est.joints)).norm(dim=-1) * 100)
            spreads.append(est.localisation.spread_m * 100)
        E, S = torch.cat(errors).numpy(), torch.cat(spreads).numpy()
        real = None
        if args.pmatdata is not None:
            records = distinct_frames([r for r in load_index(resolve_pmatdata(args.pmatdata)) if r.group in "BCD"])
            real = (read_bodies(net, torch.from_numpy(load_images(records))).spread_m * 100).numpy()
    regions = {region: [J24_NAMES.index(n) for n in names] for region, names in REGIONS.items()}
    print(f"{len(E)} test samples of {args.data}, model {args.model}; cm\n")
    print(_header(["region", "rank correlation", "spread p10 / p50 / p90"]))
    for region, idx in regions.items():
        e, s = E[:, idx].ravel(), S[:, idx].ravel()
        cells = [
            f"{m.mean() * 100:.0f}%: {e[m].mean():.1f} / {np.median(e[m]):.1f} / {np.percentile(e[m], 90):.1f}"
            if m.any()
            else "-"
            for m in _bands(s)
        ]
        p = np.percentile(s, [10, 50, 90])
        print(f"| {region} | {spearman(e, s):.2f} | {p[0]:.1f} / {p[1]:.1f} / {p[2]:.1f} | " + " | ".join(cells) + " |")
    print("\n(each band: the share of the region's joints in it: mean / median / p90 error)")
    if real is not None:
        print(f"\nShare of joints per band, simulated test split against PmatData ({len(real)} distinct frames):\n")
        print(_header(["region"]))
        for region, idx in regions.items():
            pairs = zip(_bands(S[:, idx].ravel()), _bands(real[:, idx].ravel()))
            print(
                f"| {region} | " + " | ".join(f"{a.mean() * 100:.0f}% / {b.mean() * 100:.0f}%" for a, b in pairs) + " |"
            )


if __name__ == "__main__":
    main()
