"""Where a network's limb errors come from: joints the mat sees against joints it does not (issue 22).

    PYTHONPATH=src .venv/bin/python benchmarks/limb_visibility.py --model RUN --data DATASET [--n N]

A joint counts as *seen* when the image loads a taxel within one taxel of it (its 3 x 3
neighbourhood on the mat grid) and the joint lies less than --height-m (6 cm) above the undeformed
mattress top; otherwise it is *unseen* - lifted off the bed, or outside the sensing area. For the
arm and leg joints of the test split (J24: shoulder, elbow, wrist, hand; hip, knee, ankle, foot),
prints the mean error per region split by visibility, the share of the region's summed error
that comes from unseen joints, and the same per joint and per partition. The measure behind
docs/network.md "Where the arm error comes from"; "default" is the packaged model.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from pressurepose.body.joints import J24_NAMES
from pressurepose.eval.evaluation import REGIONS, _batches, open_split
from pressurepose.mat import MatSpec
from pressurepose.net.model import NetInputs
from pressurepose.train.checkpoint import load_network

LIMBS = ("arms", "legs")


def seen_joints(pressure: torch.Tensor, joints: torch.Tensor, height_m: float, mat: MatSpec) -> torch.Tensor:
    """(B, J) bool: the joint (B, J, 3; mat frame) lies above a taxel whose 3 x 3 neighbourhood
    is loaded in the (B, rows, cols) image, and less than height_m above the mattress top."""
    loaded = F.max_pool2d((pressure > 0).float()[:, None], 3, 1, 1)[:, 0] > 0
    r = torch.floor(joints[..., 0] / mat.pitch_row_m).long()
    c = torch.floor(joints[..., 1] / mat.pitch_col_m).long()
    inside = (r >= 0) & (r < mat.rows) & (c >= 0) & (c < mat.cols)
    b = torch.arange(len(pressure))[:, None].expand_as(r)
    on_load = loaded[b, r.clamp(0, mat.rows - 1), c.clamp(0, mat.cols - 1)]
    return inside & on_load & (joints[..., 2] < height_m)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default="default")
    ap.add_argument("--data", type=Path, required=True, help="a generated dataset folder (its test split)")
    ap.add_argument("--n", type=int, default=None, help="the first N test samples (default: all)")
    ap.add_argument("--height-m", type=float, default=0.06)
    args = ap.parse_args()
    torch.set_num_threads(1)
    net, _ = load_network(Path(args.model))
    test = open_split(args.data, "test")
    mat = MatSpec()
    names = [n for region in LIMBS for n in REGIONS[region]]
    idx = [J24_NAMES.index(n) for n in names]
    errs, seen, parts = [], [], []
    with torch.no_grad():
        for labels, b in _batches(test, 64, args.n):
            inputs = NetInputs(
                pressure_mmhg=b["pressure_mmhg"], gender=b["gender"], height_m=b["height_m"], mass_kg=b["mass_kg"]
            )
            est = net(inputs, mesh=False)[-1].params
            true = b["joints"].float()[:, idx]
            errs.append((net.body(est).joints[:, idx] - true).norm(dim=-1))
            seen.append(seen_joints(b["pressure_mmhg"], true, args.height_m, mat))
            parts += [label[0] for label in labels]
    E, S, parts = torch.cat(errs).numpy() * 100, torch.cat(seen).numpy(), np.array(parts)
    print(f"{len(E)} test samples of {args.data}, model {args.model}; errors in cm")
    print("| region | mean | seen joints | mean seen (median) | mean unseen (median) | unseen share of the error |")
    print("| --- | --- | --- | --- | --- | --- |")
    for region in LIMBS:
        cols = [names.index(n) for n in REGIONS[region]]
        e, s = E[:, cols], S[:, cols]
        print(
            f"| {region} | {e.mean():.1f} | {s.mean() * 100:.0f}% | {e[s].mean():.1f} ({np.median(e[s]):.1f}) | "
            f"{e[~s].mean():.1f} ({np.median(e[~s]):.1f}) | {e[~s].sum() / e.sum() * 100:.0f}% |"
        )
    print("\n| joint | seen | mean seen | mean unseen |\n| --- | --- | --- | --- |")
    for j, n in enumerate(names):
        s = S[:, j]
        unseen = f"{E[~s, j].mean():.1f}" if (~s).any() else "-"
        print(f"| {n} | {s.mean() * 100:.0f}% | {E[s, j].mean():.1f} | {unseen} |")
    print("\n| partition | arms: mean / seen / mean seen / mean unseen | legs: the same |\n| --- | --- | --- |")
    for part in sorted(set(parts)):
        m = parts == part
        cells = []
        for region in LIMBS:
            cols = [names.index(n) for n in REGIONS[region]]
            e, s = E[m][:, cols], S[m][:, cols]
            cells.append(f"{e.mean():.1f} / {s.mean() * 100:.0f}% / {e[s].mean():.1f} / {e[~s].mean():.1f}")
        print(f"| {part} | {cells[0]} | {cells[1]} |")


if __name__ == "__main__":
    main()
