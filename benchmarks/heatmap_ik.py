"""arch=heatmap: how the IK settings move the joint error, on a run's own validation split.

    PYTHONPATH=src .venv/bin/python benchmarks/heatmap_ik.py --model RUN --data DIR [--n 512]
        [--split val|test] [--grid weights|damping]

Prints MPJPE (mm) of the localised joints, of the regression head's body (no IK) and of the
body after IK for a grid of (steps, joint sigma, prior sigma, damping), and the time per batch
of 128 for the IK. With `--split val` the samples are the ones `train` held out of DIR (same
seed and fraction); with `--split test`, DIR's test split - for a dataset the model never
trained on (a fresh seed) and that no report evaluates, a validation set too. Either way
choosing the defaults here does not look at the evaluation's test split. Grids: `weights`
(steps, joint sigma, prior sigma, spread weights; damping 1), `damping` (the LM damping and the
prior at the joint sigma and spread weights of IKConfig, 3-4 steps).
"""

from __future__ import annotations

import argparse
import itertools
import time
from pathlib import Path

import torch

from pressurepose.net.ik import IKConfig, fit_to_joints
from pressurepose.net.model import NetInputs
from pressurepose.train.checkpoint import load_network
from pressurepose.train.config import TrainConfig
from pressurepose.train.data import collate, open_dataset
from pressurepose.train.loop import _split


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--n", type=int, default=512)
    parser.add_argument(
        "--split",
        choices=("val", "test"),
        default="val",
        help="val: the run's held-out part of DIR; test: DIR's test split",
    )
    parser.add_argument("--grid", choices=("weights", "damping"), default="weights")
    args = parser.parse_args()
    data = Path(args.data)
    if args.split == "test" and (data.suffix == ".npz" or any(data.glob("*.npz"))):
        parser.error(f"--split test needs generated shards; {data} holds .npz files, which have no test split")
    torch.set_num_threads(1)
    net, record = load_network(args.model)
    cfg = TrainConfig.from_json(record["train"]).resolved()
    if args.split == "val":
        dataset = open_dataset(args.data)
        _, val = _split(len(dataset), cfg)
    else:
        dataset = open_dataset(args.data, split=args.split)
        val = list(range(len(dataset)))
    batch = collate([dataset[i] for i in val[: args.n]])
    inputs = NetInputs(batch["pressure_mmhg"], gender=batch["gender"])
    true = batch["joints"]
    err = lambda j: 1000 * float((j - true).norm(dim=-1).mean())  # noqa: E731
    with torch.no_grad():
        x = net.channels(inputs)
        raw, loc = net.mod1(x)
        params = net.head(raw, inputs.gender if net.config.gender_input else None)
        print(
            f"{len(val[: args.n])} samples ({args.split}): localised {err(loc.joints):.1f} mm, "
            f"head body {err(net.body.joints(params)):.1f} mm"
        )
        print("| steps | joint sigma (m) | prior sigma (rad) | damping | spread weights | MPJPE (mm) | ms per 128 |")
        print("| --- | --- | --- | --- | --- | --- | --- |")
        if args.grid == "weights":
            grid = itertools.product((1, 3, 5), (0.03, 0.1), (0.25, 0.5, 1.0, 2.0), (1.0,), (False, True))
        else:
            grid = itertools.product((3, 4), (IKConfig.joint_sigma_m,), (2.0, 4.0, 8.0), (0.3, 0.5, 1.0), (True,))
        for steps, js, ps, d, sw in grid:
            ik = IKConfig(steps, js, ps, d, sw)
            t0 = time.perf_counter()
            fitted = fit_to_joints(net.body, params, loc.joints, ik.weights(loc.spread_m2), ik)
            seconds = (time.perf_counter() - t0) * 128 / len(true)
            print(
                f"| {steps} | {js} | {ps} | {d} | {sw} | {err(net.body.joints(fitted)):.1f} | {1000 * seconds:.0f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
