"""Speed of the physics (issue 4): sim #1 settling, sim #2 pressure, both, and rejections.

One core (torch and MuJoCo single-threaded). Per partition: N initial poses (half female,
half male, seed 0) are settled in MuJoCo (sim #1, `--batch` bodies stepped together, a slot
refilled as soon as its body is done), posed and pressed (sim #2, batched), read by the
sensor and labelled. Prints per-stage ms per sample (wall clock, and for sim #1 also this
process's CPU time, which a busy shared machine disturbs less), sim #1 steps and rejection
reasons per partition, and the ratio to the seed's 35,000 images per day.

    .venv/bin/python benchmarks/sim.py [--n 16] [--batch 16] [--partitions supine,general]
"""

from __future__ import annotations

import argparse
import collections
import time

import numpy as np
import torch

from pressurepose.body import load_body_model
from pressurepose.body.capsules import build_capsule_body
from pressurepose.mat import MatSpec
from pressurepose.sampling.partitions import PARTITIONS, SamplingConfig
from pressurepose.sampling.sampler import InitialPoses, PoseSampler
from pressurepose.sim.foundation import simulate_pressure
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.run import settle_config_for
from pressurepose.sim.sensor import label_maps, sensing_area, taxel_reading
from pressurepose.sim.settle import settle
from pressurepose.sim.settle_config import SIM_VOLUME_POINTS

SEED_PER_DAY = 35_000


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=16, help="samples per partition")
    ap.add_argument("--batch", type=int, default=16, help="bodies stepped together in sim #1")
    ap.add_argument("--partitions", default="", help="comma-separated subset (default: all)")
    args = ap.parse_args()
    names = sorted(PARTITIONS) if not args.partitions else args.partitions.split(",")
    torch.set_num_threads(1)
    model = load_body_model("anny", dtype=torch.float64)
    mat, params = MatSpec(), MattressParams()
    rows = []
    totals = collections.Counter()
    all_ms = collections.defaultdict(list)
    cpu_ms = []
    for name in names:
        over = name in ("hands_behind_head", "prone_hands_up")
        parts = [
            PoseSampler(model, SamplingConfig(partition=name, gender=g, over_bed=over, seed=0)).sample(
                range(args.n // 2)
            )
            for g in ("female", "male")
        ]
        poses = InitialPoses.cat(parts)
        initial = poses.params
        n = initial.batch_size
        # Samples on the same bed are simulated together (half_sitting draws a bed per sample).
        groups = collections.defaultdict(list)
        for i, bed in enumerate(poses.beds()):
            groups[bed].append(i)
        t_body = t_sim1 = t_mesh = t_sim2 = cpu = 0.0
        steps, reason_list = [], []
        for bed, rows_ in groups.items():
            idx = torch.tensor(rows_)
            sub = initial.index(idx)
            t0 = time.perf_counter()
            body = build_capsule_body(model, sub.shape, volume_points=SIM_VOLUME_POINTS)
            t1, c1 = time.perf_counter(), time.process_time()
            res = settle(model, sub, params, mat, config=settle_config_for(name), body=body, batch=args.batch, bed=bed)
            t2, c2 = time.perf_counter(), time.process_time()
            out = model(res.params)
            mass = model.measure(res.params.shape).mass_kg
            t3 = time.perf_counter()
            pressed = simulate_pressure(out.vertices, out.faces, mass, params, mat, bed=bed)
            taxel_reading(sensing_area(pressed.pressure_pa, mat), params, mat)
            label_maps(pressed.vertices, out.faces, mat, bed)
            t4 = time.perf_counter()
            t_body, t_sim1, t_mesh, t_sim2 = t_body + t1 - t0, t_sim1 + t2 - t1, t_mesh + t3 - t2, t_sim2 + t4 - t3
            cpu += c2 - c1
            steps += list(res.steps)
            reason_list += res.reason
        cpu_ms.append(cpu * 1e3 / n)
        reasons = collections.Counter(r or "ok" for r in reason_list)
        for r, c in reasons.items():
            totals[r] += c
        stage = {"capsule body": t_body, "sim #1": t_sim1, "pose mesh": t_mesh, "sim #2 + sensor + labels": t_sim2}
        for k, v in stage.items():
            all_ms[k].append(v * 1e3 / n)
        rej = 1 - reasons["ok"] / n
        rows.append((name, n, stage, float(np.median(steps)), rej, reasons))
        print(
            f"{name:18s} n={n:3d}  "
            + "  ".join(f"{k} {v * 1e3 / n:6.1f}" for k, v in stage.items())
            + f"  ms/sample; sim #1 CPU {cpu_ms[-1]:.1f} ms, median steps {np.median(steps):.0f}; rejected {rej:.0%} "
            + str({k: v for k, v in reasons.items() if k != "ok"}),
            flush=True,
        )
    # sim #2 alone at several batch sizes, on settled supine poses.
    print("\nsim #2 alone (mesh at rest given), one core:")
    supine = InitialPoses.cat(
        [PoseSampler(model, SamplingConfig(partition="supine", gender="male", seed=1)).sample(range(32))]
    ).params
    rest = settle(model, supine, params, mat, batch=args.batch)
    rest_params = rest.params
    for B in (1, 8, 32):
        initial = rest_params.index(slice(0, B))
        out = model(initial)
        mass = model.measure(initial.shape).mass_kg
        simulate_pressure(out.vertices[:1], out.faces, mass[:1], params, mat)  # warm-up
        reps = max(1, 32 // B)
        t = time.perf_counter()
        for _ in range(reps):
            simulate_pressure(out.vertices, out.faces, mass, params, mat)
        ms = (time.perf_counter() - t) * 1e3 / (reps * B)
        print(f"  batch {B:3d}: {ms:6.1f} ms/sample")
    per_sample = sum(np.mean(v) for v in all_ms.values())
    accepted = totals["ok"] / sum(totals.values())
    per_day = 86400 / (per_sample / 1e3) * accepted
    print(f"\nsim #1 CPU time, mean over partitions: {np.mean(cpu_ms):.1f} ms per initial pose")
    print(
        "mean over partitions, ms per initial pose: "
        + ", ".join(f"{k} {np.mean(v):.1f}" for k, v in all_ms.items())
        + f"; total {per_sample:.0f}"
    )
    print(f"rejected overall: {1 - accepted:.1%} {dict((k, v) for k, v in totals.items() if k != 'ok')}")
    print(
        f"accepted samples per day: {per_day:,.0f} on one core, {2 * per_day:,.0f} on 2 cores "
        f"(seed: {SEED_PER_DAY:,} per day on 32 cores + GPU; ratio {2 * per_day / SEED_PER_DAY:.1f}x on 2 cores)"
    )


if __name__ == "__main__":
    main()
