"""CPU time per sample of the articulated rest on drawn poses (issues 20, 21).

    OMP_NUM_THREADS=1 python benchmarks/articulated_speed.py [--partitions supine,general] [--batch 16] [--n 64]

N initial poses per partition (seed 0, female), rested from the drawn pose on the sponge preset
in batches of B; prints CPU ms per sample (process time, so other jobs on the machine matter
less than for wall time), rejections with their reasons and the median Newton step count. Before/after a change:
run the same command with PYTHONPATH pointing at each source tree, interleaved (docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

import torch

from pressurepose.body import load_body_model
from pressurepose.sampling.partitions import SamplingConfig
from pressurepose.sampling.sampler import PoseSampler
from pressurepose.sim.articulated import rest_articulated
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.run import articulated_config_for


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--partitions", default="supine,general")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--n", type=int, default=64)
    args = ap.parse_args()
    torch.set_num_threads(1)
    model = load_body_model("anny", dtype=torch.float64)
    bed = MattressParams.preset("sponge")
    for part in args.partitions.split(","):
        poses = PoseSampler(model, SamplingConfig(partition=part, gender="female", seed=0)).sample(range(args.n)).params
        config = articulated_config_for(part)
        t0, reasons, steps = time.process_time(), Counter(), []
        for b0 in range(0, args.n, args.batch):
            chunk = poses.index(torch.arange(b0, min(b0 + args.batch, args.n)))
            rest = rest_articulated(model, chunk, mattress=bed, config=config)
            reasons.update(x for x in rest.failure if x)
            steps += rest.iterations.tolist()
        ms = (time.process_time() - t0) / args.n * 1e3
        print(
            f"{part} B={args.batch}: {ms:.1f} CPU ms/sample, rejected {sum(reasons.values())}/{args.n} "
            f"{dict(reasons)}, Newton steps median {sorted(steps)[len(steps) // 2]}",
            flush=True,
        )


if __name__ == "__main__":
    main()
