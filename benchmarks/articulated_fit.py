"""Fit the bed (foam k1, k3; soft tissue; the mat/cover's spread; the taxel threshold) and the
neck's relaxation to PmatData experiment II through the articulated sim #2 (issue 20, item 3).

CMA-ES (the `cma` package) on log-scaled parameters; loss per posture (supine, left, right)
on one mattress: (1 - along) + (1 - across) similarity + |log area ratio| + 0.5 |log coverage
ratio| (docs/realism.md's measures), mean over postures; the simulated images read with the real
set's reading floor (`eval.realism.read_with_floor`, since session 39). Reduced as stated in docs/realism.md:
sim #1 is skipped (settle none: the report's resting poses are already lying down), so each
evaluation is 24 articulated rests (~10-20 s on one core). Every evaluation is appended to
<out>/evals.jsonl; the best parameters go to <out>/<mattress>.json (MattressParams file).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/articulated_fit.py --mattress sponge --out out/fit
        [--bed-only] [--from-preset] [--tissue 98300]
    ... --mattress air --air-support [--tissue 98300] [--fit-travel]
        # the air support (P0, kappa), the cells' depth and the tissue (unless held); with
        # --fit-travel also the tubes' travel (thickness_m; else the preset's)
    ... --drawn 16   # also rest 16 drawn poses of each of DRAWN_PARTITIONS on every candidate bed:
        # the share sinking through the mattress adds SINK_WEIGHT x share to the loss (the report's
        # home poses never reach the foam's travel; a knee or an elbow of a drawn pose does)
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from pressurepose.commands.realism import POSTURES, RealismConfig, load_real, real_scenes, simulate_subjects
from pressurepose.eval import realism as R
from pressurepose.mat import MatSpec
from pressurepose.sim.articulated import FAIL_BOTTOM, ArticulatedConfig, rest_articulated
from pressurepose.sim.mattress import MattressParams

# name, start, low, high (searched in log space)
SPACE = (
    ("k1_pa_per_m", 2.77e4, 5e3, 1.5e5),
    ("k3_pa_per_m3", 5.89e7, 1e6, 1e9),
    ("tissue_pa_per_m", 3e5, 3e4, 3e6),
    ("spread_m", 0.008, 0.001, 0.02),
    ("neck", 0.1, 0.01, 1.0),
    ("spine", 1.0, 0.1, 10.0),
    ("belly", 0.3, 0.05, 1.5),
)

# The air support (`sim.air_law`) and the air cells' depth, on the preset's other fields.
AIR_SPACE = (
    ("air_pressure_pa", 3500.0, 500.0, 2e4),
    ("air_stiffness_pa_per_m3", 6e5, 2e4, 2e7),
    ("cell_depth_m", 0.015, 0.003, 0.04),
)
AIR_TRAVEL = ("thickness_m", 0.06, 0.015, 0.15)  # the tubes' travel before the base (--fit-travel)
TISSUE = ("tissue_pa_per_m", 2.5e5, 3e4, 3e6)
DENSIFY = ("densify_pa", 1e5, 1e4, 1e6)  # the foam's densification (--densify)
MEMBRANE = ("membrane_m", 0.02, 0.003, 0.1)  # the mat's membrane length (--membrane)
# the tubes' stiffness under the membrane, which then bridges their seams (--seam-support, with --air-support)
SEAM_SUPPORT = ("membrane_support_pa_per_m", 5e5, 5e4, 1e7)
WAVE = ("membrane_wave", 0.3, 0.02, 0.9)  # the tubes' stiffness wave under the mat (--wave, with --membrane)
DRAWN_PARTITIONS = ("supine", "general", "lateral_straight")
SINK_WEIGHT = 10.0  # loss per unit share of drawn bodies sinking through (one of 48 -> +0.21)


def drawn_poses(n: int):
    """The body model and n drawn poses (seed 1, female) per partition of DRAWN_PARTITIONS,
    as `benchmarks/articulated_speed.py` draws them (another seed, so its figures stay a check)."""
    from pressurepose.body import load_body_model
    from pressurepose.sampling.partitions import SamplingConfig
    from pressurepose.sampling.sampler import PoseSampler

    model = load_body_model("anny", dtype=torch.float64)
    poses = {
        part: PoseSampler(model, SamplingConfig(partition=part, gender="female", seed=1)).sample(range(n)).params
        for part in DRAWN_PARTITIONS
    }
    return model, poses


def sink_share(model, poses, mp: MattressParams) -> float:
    """The share of the drawn bodies the articulated rest rejects as sunk through the mattress."""
    from pressurepose.sim.run import articulated_config_for

    sank = total = 0
    for part, params in poses.items():
        rest = rest_articulated(model, params, mattress=mp, config=articulated_config_for(part))
        sank += sum(f == FAIL_BOTTOM for f in rest.failure)
        total += len(rest.failure)
    return sank / total


def decode(x, space=SPACE):
    out = {name: float(np.exp(np.clip(xi, np.log(lo), np.log(hi)))) for (name, _, lo, hi), xi in zip(space, x)}
    d = ArticulatedConfig()
    belly = dict(d.tissue_by_part).get("spine1", 1.0)
    out.setdefault("neck", d.neck_stiffness_scale)
    out.setdefault("spine", d.spine_stiffness_scale)
    out.setdefault("belly", belly)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mattress", default="sponge", choices=("sponge", "air"))
    ap.add_argument("--out", type=Path, default=Path("out/articulated_fit"))
    ap.add_argument("--popsize", type=int, default=8)
    ap.add_argument("--max-iter", type=int, default=6)
    ap.add_argument("--frames", type=int, default=24, help="real frames simulated per posture (evenly picked)")
    ap.add_argument(
        "--bed-only",
        action="store_true",
        help="fit the bed (k1, k3, tissue, spread) alone, the body's factors at ArticulatedConfig's defaults",
    )
    ap.add_argument("--from-preset", action="store_true", help="start at the mattress's preset (sigma 0.25)")
    ap.add_argument(
        "--tissue",
        type=float,
        default=None,
        help="hold the soft tissue's modulus (Pa/m; the body's, shared by every mattress) and fit k1, k3, spread",
    )
    ap.add_argument(
        "--air-support",
        action="store_true",
        help="fit the air support's P0 and kappa, the cells' depth and the tissue (unless --tissue holds it) on the preset",
    )
    ap.add_argument("--fit-travel", action="store_true", help="with --air-support: fit the tubes' travel too")
    ap.add_argument(
        "--start", type=Path, default=None, help="with --from-preset: start at this MattressParams file instead"
    )
    ap.add_argument("--eval-only", action="store_true", help="with --from-preset: the preset's loss alone, no search")
    ap.add_argument(
        "--drawn",
        type=int,
        default=0,
        help="drawn poses per partition rested on every candidate; the share sinking through adds to the loss",
    )
    ap.add_argument(
        "--set", default="", help="ArticulatedConfig overrides for every rest, e.g. spine_stiffness_scale=0.5"
    )
    ap.add_argument("--densify", action="store_true", help="with --bed-only: fit the foam's densification too")
    ap.add_argument("--membrane", action="store_true", help="fit the mat's membrane length (sim.membrane) too")
    ap.add_argument(
        "--seam-support",
        action="store_true",
        help="and the tubes' stiffness under it: the membrane bridges their seams",
    )
    ap.add_argument(
        "--wave",
        action="store_true",
        help="and the tubes' stiffness wave under the mat (with --air-support --membrane)",
    )
    ap.add_argument(
        "--bands",
        type=float,
        default=0.0,
        help="weight of |log| of the transverse bands' amplitude ratio (air tubes, eval.realism.fit_bands) per posture",
    )
    args = ap.parse_args()
    overrides = {k: ast.literal_eval(v) for k, v in (kv.split("=", 1) for kv in args.set.split(",") if kv)}
    if args.densify and args.air_support:
        raise SystemExit("--densify fits a foam's densification: not with --air-support")
    if (args.eval_only or args.start) and not args.from_preset:
        raise SystemExit("--eval-only and --start work from a starting bed: give --from-preset")
    import cma

    torch.set_num_threads(1)
    mat = MatSpec()
    pitch = (mat.pitch_row_m, mat.pitch_col_m)
    real, subjects = load_real(Path("pmatdata"), 20.0)
    real_sets = {p: R.summarise(real[(p, args.mattress)][0], real[(p, args.mattress)][1], *pitch) for p in POSTURES}
    floors = {p: R.reading_floor(real[(p, args.mattress)][0]) for p in POSTURES}
    real_bands = {p: R.fit_bands(real[(p, args.mattress)][0], pitch[0]) for p in POSTURES} if args.bands > 0 else {}
    # One simulated body per real frame, where that frame's load lies (docs/realism.md).
    scenes = {}
    for k, (ids, centres, angles) in real_scenes(real, RealismConfig()).items():
        if k[1] == args.mattress:
            pick = np.linspace(0, len(ids) - 1, min(args.frames, len(ids))).round().astype(int)
            scenes[k] = (ids[pick], centres[pick], angles[pick])
    args.out.mkdir(parents=True, exist_ok=True)
    log = (args.out / "evals.jsonl").open("a")
    drawn = drawn_poses(args.drawn) if args.drawn > 0 else None
    best = (float("inf"), None)

    def loss(x):
        nonlocal best
        v = decode(x, space)
        if args.tissue is not None:
            v["tissue_pa_per_m"] = args.tissue
        if args.air_support:
            bed = {k: v[k] for k, *_ in space}
            if "tissue_pa_per_m" in v:
                bed["tissue_pa_per_m"] = v["tissue_pa_per_m"]
            mp = MattressParams.preset(args.mattress).replace(**bed)
        else:
            mp = MattressParams(
                k1_pa_per_m=v["k1_pa_per_m"],
                k3_pa_per_m3=v["k3_pa_per_m3"],
                tissue_pa_per_m=v["tissue_pa_per_m"],
                spread_m=v["spread_m"],
                densify_pa=v.get("densify_pa", 0.0),
                membrane_m=v.get("membrane_m", 0.0),
            )
        t0 = time.perf_counter()
        sims = simulate_subjects(
            subjects,
            RealismConfig(settle="none"),
            mp,
            dataclasses.replace(
                ArticulatedConfig(
                    neck_stiffness_scale=v["neck"],
                    spine_stiffness_scale=v["spine"],
                    tissue_by_part=(("spine1", v["belly"]), ("spine2", v["belly"])),
                ),
                **overrides,
            ),
            scenes=scenes,
        )
        total, parts = 0.0, {}
        for p in POSTURES:
            imgs, hts = sims[(p, args.mattress)][0], sims[(p, args.mattress)][1]
            if len(imgs) < len(scenes[(p, args.mattress)][0]) // 2:
                total += 4.0
                continue
            imgs = R.read_with_floor(imgs, floors[p])  # read as the real frames are (docs/realism.md)
            sim_set = R.summarise(imgs, hts, *pitch)
            c = R.compare(real_sets[p], sim_set)
            regions = sum(abs(sim_set.regions[k] - real_sets[p].regions[k]) for k in R.REGION_NAMES)
            loss = (
                (1 - c.along)
                + (1 - c.across)
                + abs(math.log(c.area_ratio))
                + 0.5 * abs(math.log(c.coverage_ratio))
                + 0.5 * regions
            )
            if args.bands > 0:
                amp = R.fit_bands(imgs, pitch[0], real_bands[p].period_m).amplitude
                loss += args.bands * abs(math.log(max(amp, 1e-3) / real_bands[p].amplitude))
            parts[p] = {
                "bands": round(amp, 3) if args.bands > 0 else None,
                "along": round(c.along, 3),
                "across": round(c.across, 3),
                "area": round(c.area_ratio, 3),
                "coverage": round(c.coverage_ratio, 3),
                "regions": round(regions, 3),
            }
            total += loss
        total /= len(POSTURES)
        if drawn is not None:
            parts["sank"] = round(sink_share(*drawn, mp), 3)
            total += SINK_WEIGHT * parts["sank"]
        log.write(json.dumps({"loss": total, "params": v, "parts": parts, "seconds": time.perf_counter() - t0}) + "\n")
        log.flush()
        if total < best[0]:
            best = (total, v)
            mp.save(args.out / f"{args.mattress}.json")
            (args.out / f"{args.mattress}_best.json").write_text(
                json.dumps({"loss": total, "params": v, "parts": parts}, indent=1)
            )
        print(f"loss {total:.4f} {parts} {v}", flush=True)
        return total

    space = SPACE[:4] if args.bed_only else SPACE
    if args.tissue is not None:  # the body's tissue held: the bed's foam and cover alone
        space = tuple(d for d in SPACE[:4] if d[0] != "tissue_pa_per_m")
    if args.densify:
        space = space + (DENSIFY,)
    if args.air_support:  # with the tissue unless it is held
        space = AIR_SPACE + ((AIR_TRAVEL,) if args.fit_travel else ()) + (() if args.tissue is not None else (TISSUE,))
    if args.membrane:
        space = space + (MEMBRANE,)
    if args.seam_support:
        if not (args.air_support and args.membrane):
            raise SystemExit("--seam-support needs --air-support and --membrane")
        space = space + (SEAM_SUPPORT,)
    if args.wave:
        if not (args.air_support and args.membrane) or args.seam_support:
            raise SystemExit("--wave needs --air-support and --membrane, and not --seam-support")
        space = space + (WAVE,)
    x0 = [math.log(s) for _, s, _, _ in space]
    sigma = 0.5
    if args.from_preset:  # start at the mattress's preset, a narrower search around it
        preset = MattressParams.load(args.start) if args.start else MattressParams.preset(args.mattress)
        x0 = [
            math.log(getattr(preset, name)) if getattr(preset, name, 0) > 0 else x for (name, *_), x in zip(space, x0)
        ]
        sigma = 0.25
    if args.eval_only:
        loss(x0)
        return
    es = cma.CMAEvolutionStrategy(
        x0, sigma, {"popsize": args.popsize, "maxiter": args.max_iter, "seed": 1, "verbose": -9}
    )
    while not es.stop():
        xs = es.ask()
        es.tell(xs, [loss(x) for x in xs])
    print("best", best)


if __name__ == "__main__":
    main()
