"""CPU time per sample of the articulated rest on drawn poses (issues 20, 21).

    OMP_NUM_THREADS=1 python benchmarks/articulated_speed.py [--partitions supine,general] [--batch 16] [--n 64]
        [--save DIR] [--jitter 1e-12] [--set outer=8]

N initial poses per partition (seed 0, female), rested from the drawn pose on the sponge preset (`--bed`)
in batches of B (half_sitting, whose bodies each lie on their own raised bed: B = 1); prints CPU ms per sample (process time, so other jobs on the machine matter
less than for wall time), rejections with their reasons, the median Newton step and re-posing counts. Before/after a change:
run the same command with PYTHONPATH pointing at each source tree, interleaved (docs/benchmarks.md).
`--save DIR` writes each partition's rests (joints, foam pressure, failures) to DIR/<partition>.pt
for `benchmarks/articulated_agreement.py`; `--jitter D` moves every drawn body by D m first (the
engine's own round-off spread: the same code with and without it).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections import Counter
from pathlib import Path

import torch

from pressurepose.body import load_body_model
from pressurepose.sampling.partitions import SamplingConfig
from pressurepose.sampling.sampler import PoseSampler
from pressurepose.sim.articulated import rest_articulated
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.run import articulated_config_for


def rest_options(ap: argparse.ArgumentParser, partitions: str, batch: int) -> None:
    """The options the rest's benchmarks share (also `articulated_phases.py`)."""
    ap.add_argument("--partitions", default=partitions)
    ap.add_argument("--batch", type=int, default=batch)
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--set", default="", help="ArticulatedConfig overrides, e.g. outer=8,inner_reposing=6")
    ap.add_argument("--bed", default="sponge", help="mattress preset (sponge, air) or parameter file")


def partition_config(partition: str, overrides: str):
    """The partition's `ArticulatedConfig` with `--set`'s KEY=VALUE,... overrides."""
    over = {k: eval(v) for k, v in (kv.split("=") for kv in overrides.split(",") if kv)}  # noqa: S307
    return dataclasses.replace(articulated_config_for(partition), **over)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    rest_options(ap, "supine,general", 16)
    ap.add_argument("--save", default=None, help="directory for the rests (<partition>.pt)")
    ap.add_argument("--jitter", type=float, default=0.0, help="move every body by this many metres first")
    args = ap.parse_args()
    torch.set_num_threads(1)
    model = load_body_model("anny", dtype=torch.float64)
    mattress = MattressParams.load(args.bed)
    for part in args.partitions.split(","):
        drawn = PoseSampler(model, SamplingConfig(partition=part, gender="female", seed=0)).sample(range(args.n))
        poses, all_beds = drawn.params, drawn.beds()
        if args.jitter:
            poses = poses.replace(root_translation=poses.root_translation + args.jitter)
        config = partition_config(part, args.set)
        t0, reasons, steps, reposings, moving = time.process_time(), Counter(), [], [], 0
        saved = {"joints": [], "foundation_pa": [], "failure": []}
        for b0 in range(0, args.n, args.batch):
            idx = torch.arange(b0, min(b0 + args.batch, args.n))
            chunk = poses.index(idx)
            beds = [all_beds[i] for i in idx.tolist()]
            if len(set(beds)) > 1:  # half_sitting: each raised bed's bodies together
                raise SystemExit("one bed per batch: use --batch 1 for half_sitting, or a flat partition")
            rest = rest_articulated(model, chunk, mattress=mattress, config=config, bed=beds[0])
            reasons.update(x for x in rest.failure if x)
            steps += rest.iterations.tolist()
            reposings += rest.reposings.tolist()
            moving += int((~rest.settled).sum())
            if args.save:
                saved["joints"].append(rest.joints)
                saved["foundation_pa"].append(rest.foundation_pa)
                saved["failure"] += rest.failure
        ms = (time.process_time() - t0) / args.n * 1e3
        print(
            f"{part} B={args.batch}: {ms:.1f} CPU ms/sample, rejected {sum(reasons.values())}/{args.n} "
            f"{dict(reasons)}, Newton steps median {sorted(steps)[len(steps) // 2]}, re-posings median "
            f"{sorted(reposings)[len(reposings) // 2]} (at the cap {sum(r == config.outer for r in reposings)}, still moving there {moving})",
            flush=True,
        )
        if args.save:
            Path(args.save).mkdir(parents=True, exist_ok=True)
            torch.save(
                {k: v if k == "failure" else torch.cat(v) for k, v in saved.items()}, Path(args.save) / f"{part}.pt"
            )


if __name__ == "__main__":
    main()
