"""Where sim #1's time goes, and the floor MuJoCo's own stepping sets (issue 4's 20 ms target).

Per partition: N initial poses (half female, half male, seed 0) settled as `generate` settles
them (`settle`, 16 bodies stepped together, the partition's `SettleConfig`), under cProfile.
Prints per sample: sim #1 CPU time; the time inside MuJoCo's stepping (`mj_step1` +
`mj_step2`) and model building (`MjModel.from_xml_string`); the mattress forces; the steps.
MuJoCo's stepping at these step counts is a floor for any loop around MuJoCo on this CPU,
however the forces and the bookkeeping are computed (numpy, C, or a compiled callback).

    taskset -c 1 .venv/bin/python benchmarks/sim1_floor.py [--n 16] [--partitions supine,general]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time

import numpy as np
import torch

from pressurepose.body import load_body_model
from pressurepose.body.capsules import build_capsule_body
from pressurepose.sampling.partitions import PARTITIONS, SamplingConfig
from pressurepose.sampling.sampler import InitialPoses, PoseSampler
from pressurepose.sim.run import settle_config_for
from pressurepose.sim.settle import settle
from pressurepose.sim.settle_config import SIM_VOLUME_POINTS


def _seconds(stats: pstats.Stats, *names: str) -> float:
    """Total time (s) of the functions whose name contains any of `names`, own time only."""
    total = 0.0
    for (_, _, func), (_, _, tottime, _, _) in stats.stats.items():
        if any(n in func for n in names):
            total += tottime
    return total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=16, help="samples per partition")
    ap.add_argument("--partitions", default="", help="comma-separated subset (default: all flat-bed ones)")
    args = ap.parse_args()
    names = (
        [p for p in sorted(PARTITIONS) if not PARTITIONS[p].raised]
        if not args.partitions
        else args.partitions.split(",")
    )
    torch.set_num_threads(1)
    model = load_body_model("anny", dtype=torch.float64)
    print(
        "partition          | sim #1 CPU | MuJoCo step | MuJoCo build | forces | rest | median steps | us/body-step (MuJoCo)"
    )
    floors = []
    for name in names:
        over = name in ("hands_behind_head", "prone_hands_up")
        params = InitialPoses.cat(
            [
                PoseSampler(model, SamplingConfig(partition=name, gender=g, over_bed=over, seed=0)).sample(
                    range(args.n // 2)
                )
                for g in ("female", "male")
            ]
        ).params
        n = params.batch_size
        body = build_capsule_body(model, params.shape, volume_points=SIM_VOLUME_POINTS)
        prof = cProfile.Profile(time.process_time)
        c0 = time.process_time()
        prof.enable()
        res = settle(model, params, config=settle_config_for(name), body=body)
        prof.disable()
        cpu = (time.process_time() - c0) * 1e3 / n
        st = pstats.Stats(prof)
        step = _seconds(st, "mj_step1", "mj_step2") * 1e3 / n
        build = _seconds(st, "from_xml_string") * 1e3 / n
        forces = sum(v[3] for (_, _, f), v in st.stats.items() if f in ("forces",)) * 1e3 / n  # cumulative
        body_steps = int(res.steps.sum())
        floors.append(step)
        print(
            f"{name:18s} | {cpu:7.1f} ms | {step:8.1f} ms | {build:9.1f} ms | {forces:5.1f} ms | "
            f"{cpu - step - build - forces:5.1f} ms | {np.median(res.steps):12.0f} | "
            f"{step * n * 1e3 / max(body_steps, 1):.1f}",
            flush=True,
        )
    print(
        f"\nMuJoCo stepping alone, mean over partitions: {np.mean(floors):.1f} ms per sample "
        "(the floor for any loop around MuJoCo at these steps; target 20 ms for all of sim #1)"
    )


if __name__ == "__main__":
    main()
