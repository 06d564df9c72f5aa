"""Speed of the articulated sim #2 against the rigid one, on the generator's own inputs.

One core. Per partition: N initial poses (seed 0, half female, half male), settled by sim #1
(MuJoCo) once; then both sim #2 variants rest the same settled bodies in batches of B, and
the articulated rest also rests the initial poses directly (no sim #1: what a MuJoCo-free
generator would do). Prints ms per sample (wall, best of `--repeat`), re-posings/Newton steps,
and rejections.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/articulated.py [--n 16] [--batch 16]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from pressurepose.body import load_body_model
from pressurepose.body.params import BodyParams
from pressurepose.sampling.partitions import SamplingConfig
from pressurepose.sampling.sampler import PoseSampler
from pressurepose.sim.articulated import ArticulatedConfig, rest_articulated
from pressurepose.sim.foundation import simulate_pressure
from pressurepose.sim.run import settle_config_for
from pressurepose.sim.settle import settle


def timed(fn, repeat):
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=16)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--partitions", default="supine,general,lateral_straight")
    args = ap.parse_args()
    torch.set_num_threads(1)
    model = load_body_model("anny", dtype=torch.float64)
    print(
        "| partition | input | rigid ms/sample | articulated ms/sample | articulated steps (median) | rejected rigid / articulated |"
    )
    print("| --- | --- | --- | --- | --- | --- |")
    for part in args.partitions.split(","):
        params = []
        for gender in ("female", "male"):
            cfg = SamplingConfig(partition=part, gender=gender, seed=0)
            params.append(PoseSampler(model, cfg).sample(range(args.n // 2)).params)
        initial = BodyParams.cat(params)
        hold = settle_config_for(part).hold_roll_m
        settled = settle(model, initial, config=settle_config_for(part))
        ok = [i for i, r in enumerate(settled.reason) if not r]
        rest = settled.params.index(torch.tensor(ok))
        art_cfg = ArticulatedConfig(hold_roll_m=hold)
        for name, p in (("after sim #1", rest), ("initial pose", initial)):
            rigid_s, rigid_rej, art_s, art_rej, steps = 0.0, 0, 0.0, 0, []
            for b0 in range(0, p.batch_size, args.batch):
                chunk = p.index(torch.arange(b0, min(b0 + args.batch, p.batch_size)))
                if name == "after sim #1":

                    def rigid():
                        out = model(chunk)
                        return simulate_pressure(out.vertices, out.faces, model.measure(chunk.shape).mass_kg)

                    t, r = timed(rigid, args.repeat)
                    rigid_s += t
                    rigid_rej += sum(bool(x) for x in r.failure)
                t, a = timed(lambda: rest_articulated(model, chunk, config=art_cfg), args.repeat)
                art_s += t
                art_rej += sum(bool(x) for x in a.failure)
                steps += a.iterations.tolist()
            n = p.batch_size
            rigid_txt = f"{rigid_s / n * 1e3:.1f}" if name == "after sim #1" else "-"
            print(
                f"| {part} | {name} ({n}) | {rigid_txt} | {art_s / n * 1e3:.1f} | {int(np.median(steps))} | "
                f"{rigid_rej if name == 'after sim #1' else '-'} / {art_rej} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
