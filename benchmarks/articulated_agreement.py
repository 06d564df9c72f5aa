"""Agreement of two runs of the articulated rest (`benchmarks/articulated_speed.py --save`).

    python benchmarks/articulated_agreement.py DIR_A DIR_B [--partitions supine,general,lateral_straight]

Over the bodies both runs kept: per body the largest J24 joint distance (mm) and the foam
pressure field's relative L1 difference (sum |a - b| / sum |a|), each as median / p95; and
how many bodies were rejected by one run and not the other. The bar for a change that should
compute the same rest (docs/benchmarks.md): the old code against itself with every body moved
by 1e-12 m (`--jitter 1e-12`), the rest being chaotic at round-off level.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch


def compare(a: dict, b: dict) -> dict:
    kept = torch.tensor([not x and not y for x, y in zip(a["failure"], b["failure"])])
    changed = sum(bool(x) != bool(y) for x, y in zip(a["failure"], b["failure"]))
    ja, jb = a["joints"][kept].double(), b["joints"][kept].double()
    dist = (ja - jb).norm(dim=-1).amax(-1) * 1e3
    fa, fb = a["foundation_pa"][kept].double().flatten(1), b["foundation_pa"][kept].double().flatten(1)
    l1 = (fa - fb).abs().sum(1) / fa.abs().sum(1).clamp(min=1e-12)
    q = torch.tensor([0.5, 0.95], dtype=torch.float64)
    return {
        "joint_mm": torch.quantile(dist, q).tolist(),
        "image_l1": torch.quantile(l1, q).tolist(),
        "changed": changed,
        "n": len(a["failure"]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--partitions", default="supine,general,lateral_straight")
    args = ap.parse_args()
    print(
        "| partition | per-body max joint distance median / p95 mm | image rel. L1 median / p95 | rejections changed |"
    )
    print("| --- | --- | --- | --- |")
    for part in args.partitions.split(","):
        r = compare(torch.load(Path(args.a) / f"{part}.pt"), torch.load(Path(args.b) / f"{part}.pt"))
        j, l1 = r["joint_mm"], r["image_l1"]
        print(f"| {part} | {j[0]:.1f} / {j[1]:.0f} | {l1[0]:.3f} / {l1[1]:.2f} | {r['changed']} of {r['n']} |")


if __name__ == "__main__":
    main()
