"""Do half-sitting samples stay sitting through sim #1? (issue 4; docs/physics.md)

Draws N samples of the half_sitting partition, runs both simulations on their beds and prints
per sample: the head angle, how far the hips slid along the bed in sim #1, the head's height
before and after, the share of the pressure on the rows above the hinge, and sim #1's steps.

    .venv/bin/python benchmarks/half_sitting.py [--n 12] [--gender male] [--friction 0.5]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from pressurepose.bed import BedShape
from pressurepose.body import load_body_model
from pressurepose.body.joints import J24_NAMES
from pressurepose.mat import MatSpec
from pressurepose.sampling.partitions import SamplingConfig
from pressurepose.sampling.sampler import PoseSampler
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.run import simulate_poses

HIPS = [J24_NAMES.index("left_hip"), J24_NAMES.index("right_hip")]
HEAD = J24_NAMES.index("head")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=12)
    ap.add_argument("--gender", default="male", choices=("female", "male"))
    ap.add_argument("--friction", type=float, default=MattressParams().friction)
    args = ap.parse_args()
    model = load_body_model("anny", dtype=torch.float64)
    poses = PoseSampler(model, SamplingConfig(partition="half_sitting", gender=args.gender)).sample(range(args.n))
    sim = simulate_poses(model, poses.params, MattressParams(friction=args.friction), bed=poses.beds())
    hinge_row = MatSpec().rows - BedShape().hinge_row_from_foot
    slide = (sim.joints[:, HIPS, 0].mean(1) - poses.joints[:, HIPS, 0].mean(1)).numpy()
    share = (sim.pressure_mmhg[:, :hinge_row].sum((1, 2)) / sim.pressure_mmhg.sum((1, 2)).clamp_min(1e-9)).numpy()
    print("angle  slide (m)  head z before -> after (m)  load above the hinge  sim #1 steps  rejected")
    for i in range(args.n):
        print(
            f"{poses.head_angle_deg[i]:5.0f}  {slide[i]:+9.3f}  {float(poses.joints[i, HEAD, 2]):13.2f} -> "
            f"{float(sim.joints[i, HEAD, 2]):.2f}  {share[i]:20.2f}  {sim.settle_steps[i]:12d}  {sim.reason[i] or '-'}"
        )
    ok = np.array([not r for r in sim.reason])
    print(
        f"slide |median| {np.median(np.abs(slide[ok])) * 100:.2f} cm, max {np.abs(slide[ok]).max() * 100:.1f} cm; "
        f"load above the hinge {share[ok].min():.2f}-{share[ok].max():.2f}"
    )


if __name__ == "__main__":
    main()
