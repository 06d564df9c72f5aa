"""The two settling engines against each other (issue 21): MuJoCo (sim #1, then the rigid
sim #2: today's default pipeline) and the articulated engine (one quasi-static mechanics, no
MuJoCo), on the same initial poses and the same bed (the sponge preset).

Per partition: N initial poses (seed 0, half female, half male). Each engine rests them, and
rests them again after a tiny perturbation (pose +- `--jitter-rad`, placement +- 1 mm): the
spread an engine shows under such a perturbation is the bar the other engine's difference is
judged against. Prints, per partition: rejections and reasons per engine; per-joint distance
(J24, mat frame) between the engines and within each engine under perturbation (median, p95);
image agreement per sample (along/across profile similarity, best shift within 2 rows/cols,
contact-area ratio; median); ms per sample per engine.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/engines.py [--n 100] [--partitions supine,general]
"""

from __future__ import annotations

import argparse
import collections
import time

import numpy as np
import torch

from pressurepose.body import load_body_model
from pressurepose.body.params import BodyParams
from pressurepose.eval.realism import profile_similarity
from pressurepose.sampling.partitions import PARTITIONS, SamplingConfig
from pressurepose.sampling.sampler import PoseSampler
from pressurepose.sim.articulated import ArticulatedConfig
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.run import settle_config_for, simulate_poses

ENGINES = {"mujoco": dict(settle="mujoco", sim2="rigid"), "articulated": dict(settle="articulated")}


def perturbed(p: BodyParams, jitter_rad: float, seed: int) -> BodyParams:
    g = torch.Generator().manual_seed(seed)
    noise = lambda t, s: t + s * torch.randn(t.shape, generator=g, dtype=t.dtype)  # noqa: E731
    return p.replace(pose=noise(p.pose, jitter_rad), root_translation=noise(p.root_translation, 1e-3))


def run(model, params, engine, partition, mattress, batch):
    outs, seconds = [], 0.0
    hold = settle_config_for(partition).hold_roll_m
    for b0 in range(0, params.batch_size, batch):
        chunk = params.index(torch.arange(b0, min(b0 + batch, params.batch_size)))
        t0 = time.perf_counter()
        outs.append(
            simulate_poses(
                model,
                chunk,
                mattress,
                settle_config=settle_config_for(partition),
                articulated=ArticulatedConfig(hold_roll_m=hold),
                **ENGINES[engine],
            )
        )
        seconds += time.perf_counter() - t0
    joints = torch.cat([o.joints for o in outs]).numpy()
    images = torch.cat([o.pressure_mmhg for o in outs]).numpy()
    reasons = [r for o in outs for r in o.reason]
    return joints, images, reasons, seconds


def agreement(ja, ia, ra, jb, ib, rb):
    """Per-joint distances (mm) and per-sample image measures over samples both engines kept."""
    keep = [i for i in range(len(ra)) if not ra[i] and not rb[i]]
    if not keep:
        return None
    d = np.linalg.norm(ja[keep] - jb[keep], axis=-1).ravel() * 1e3
    along, across, area = [], [], []
    for i in keep:
        a, b = ia[i], ib[i]
        if a.sum() <= 0 or b.sum() <= 0:
            continue
        along.append(profile_similarity(a.sum(1), b.sum(1), 2)[0])
        across.append(profile_similarity(a.sum(0), b.sum(0), 2)[0])
        area.append((b > 0).sum() / max((a > 0).sum(), 1))
    return dict(
        n=len(keep),
        joint_median_mm=float(np.median(d)),
        joint_p95_mm=float(np.percentile(d, 95)),
        along=float(np.median(along)),
        across=float(np.median(across)),
        area=float(np.median(area)),
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=100)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--jitter-rad", type=float, default=0.01)
    ap.add_argument("--partitions", default=",".join(p for p in PARTITIONS if p != "half_sitting"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    model = load_body_model("anny", dtype=torch.float64)
    mattress = MattressParams.preset("sponge")
    print(
        "| partition | engine | rejected (reasons) | ms/sample | within engine: joint median / p95 mm, along, across, area "
        "| mujoco vs articulated: joint median / p95 mm, along, across, area |"
    )
    print("| --- | --- | --- | --- | --- | --- |")
    for part in args.partitions.split(","):
        over_bed = PARTITIONS[part].over_bed_choices[0]  # the partition's first Table 4 row
        params = BodyParams.cat(
            [
                PoseSampler(model, SamplingConfig(partition=part, gender=g, seed=0, over_bed=over_bed))
                .sample(range(args.n // 2))
                .params
                for g in ("female", "male")
            ]
        )
        shaken = perturbed(params, args.jitter_rad, seed=1)
        res = {}
        for engine in ENGINES:
            res[engine] = run(model, params, engine, part, mattress, args.batch)
            res[engine + "'"] = run(model, shaken, engine, part, mattress, args.batch)
        between = agreement(*res["mujoco"][:3], *res["articulated"][:3])
        for engine in ENGINES:
            j, im, r, s = res[engine]
            within = agreement(j, im, r, *res[engine + "'"][:3])
            reasons = collections.Counter(x.split(":")[-1].strip()[:28] for x in r if x)
            fmt = lambda a: (
                "-"
                if a is None
                # noqa: E731
                else f"{a['joint_median_mm']:.0f} / {a['joint_p95_mm']:.0f}, {a['along']:.3f}, "
                f"{a['across']:.3f}, {a['area']:.2f} (n={a['n']})"
            )
            print(
                f"| {part} | {engine} | {sum(bool(x) for x in r)}/{len(r)} {dict(reasons) or ''} | "
                f"{s / len(r) * 1e3:.0f} | {fmt(within)} | {fmt(between) if engine == 'mujoco' else ''} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
