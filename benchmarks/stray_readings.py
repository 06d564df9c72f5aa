"""Stray readings: how real and simulated frames differ off the body, and how a network reads
simulated images with stray readings added (`train --speckle`, docs/network.md "Stray readings").

    PYTHONPATH=src .venv/bin/python benchmarks/stray_readings.py --data DATASET [--model RUN] [--n N]

1. Detached loads: per frame, the 8-connected loaded components holding < 2% of the force (all
   but the body), for PmatData's flat groups B-D (each mattress) and the dataset's images: how
   many per frame, their size, mean reading and row (0 = head end).
2. With --model: the network on the dataset's first N test images, as generated and with
   `train.augment.speckle_batch` at share 1 (fixed seed): median signed and mean absolute height
   error, MPJPE and the posture read from the root's roll against the label's.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

from pressurepose.data.dataset import DEFAULT_COLUMNS, PressurePoseDataset
from pressurepose.data.pmatdata import distinct_frames, load_images, load_index
from pressurepose.eval.real import posture_of, roll_deg
from pressurepose.net.model import NetInputs
from pressurepose.samples import resolve_pmatdata
from pressurepose.train.augment import speckle_batch
from pressurepose.train.checkpoint import load_network

SMALL_SHARE = 0.02  # a component under this share of the frame's force counts as detached


def detached(images: np.ndarray) -> None:
    """Print the detached components' statistics of (N, 64, 27) images."""
    counts, sizes, means, rows = [], [], [], []
    for p in images:
        lab, n = ndimage.label(p > 0, structure=np.ones((3, 3)))
        if n == 0:
            counts.append(0)
            continue
        ids = range(1, n + 1)
        force = np.asarray(ndimage.sum(p, lab, ids))
        size = np.asarray(ndimage.sum(np.ones_like(p), lab, ids))
        small = force < SMALL_SHARE * p.sum()
        counts.append(int(small.sum()))
        sizes += size[small].tolist()
        means += (force[small] / size[small]).tolist()
        rows += [ndimage.center_of_mass(p, lab, i)[0] for i in np.nonzero(small)[0] + 1]
    q = lambda a: np.round(np.percentile(a, [10, 50, 90]), 1) if a else "-"  # noqa: E731
    print(
        f"  {len(images)} frames: {np.mean(counts):.2f} per frame (>= 1 in {np.mean(np.array(counts) > 0):.0%}); "
        f"p10/50/90 size {q(sizes)} taxels, mean reading {q(means)} mmHg, row {q(rows)}"
    )


def read(net, pressure: torch.Tensor, joints: torch.Tensor, height: np.ndarray, posture: list[str]) -> str:
    heights, est_joints, rolls = [], [], []
    with torch.no_grad():
        for lo in range(0, len(pressure), 32):
            x = pressure[lo : lo + 32]
            est = net(NetInputs(pressure_mmhg=x, gender=torch.full((len(x),), 0.5)), mesh=False)[-1]
            heights.append(net.body.measure(est.params.shape).height_m)
            est_joints.append(est.joints.float())
            rolls.append(roll_deg(est.params.root_rotation.double()))
    err = torch.cat(heights).numpy() - height
    mpjpe = float((torch.cat(est_joints) - joints).norm(dim=-1).mean())
    right = np.mean([a == b for a, b in zip(posture_of(torch.cat(rolls)), posture)])
    return (
        f"height median {np.median(err) * 100:+.1f} cm, MAE {np.abs(err).mean() * 100:.1f} cm, "
        f"MPJPE {mpjpe * 1000:.1f} mm, posture {right:.1%}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, required=True, help="a generated dataset folder")
    ap.add_argument("--model", default=None, help='a run folder or "default"')
    ap.add_argument("--n", type=int, default=640)
    args = ap.parse_args()
    torch.set_num_threads(1)
    records = [r for r in distinct_frames(load_index(resolve_pmatdata("pmatdata"))) if r.group in "BCD"]
    images = load_images(records)
    for mattress in ("air", "sponge"):
        print(f"PmatData {mattress}:")
        detached(images[[r.mattress == mattress for r in records]])
    test = PressurePoseDataset(args.data, split="test", columns=DEFAULT_COLUMNS)
    items = [test[i] for i in range(min(len(test), args.n))]
    pressure = torch.stack([it["pressure_mmhg"] for it in items]).float()
    print(f"{args.data} (test split):")
    detached(pressure.numpy())
    if args.model is None:
        return
    net, _ = load_network(Path(args.model))
    joints = torch.stack([it["joints_m"] for it in items]).float()
    height = np.array([float(it["height_m"]) for it in items])
    posture = posture_of(roll_deg(torch.stack([it["root_rotation"] for it in items]).double()))
    noisy = speckle_batch(NetInputs(pressure_mmhg=pressure), 1.0, torch.Generator().manual_seed(0)).pressure_mmhg
    print(f"{args.model} on the first {len(items)} test images:")
    print("  as generated:  " + read(net, pressure, joints, height, posture))
    print("  with --speckle: " + read(net, noisy, joints, height, posture))


if __name__ == "__main__":
    main()
