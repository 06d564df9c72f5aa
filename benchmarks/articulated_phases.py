"""Where the articulated rest's CPU goes, and how its bodies converge re-posing by re-posing
(issues 20, 21).

    OMP_NUM_THREADS=1 python benchmarks/articulated_phases.py [--partitions general] [--n 64]
        [--batch 32] [--bed sponge] [--set coarse_inner=4] [--trace]

N drawn poses per partition (seed 0, female, as `articulated_speed.py`), rested in batches.
Prints the CPU time per body split by grid (the coarse grid's re-posings, the image's) into the
lowest points (`ContactGrid.heights`), the linearisations' set-up (`Linearised`), the Newton
solves (`minimise`; the rests' own solves apart) and everything else (set-up, skinning,
kinematics, springs, friction, bookkeeping). `--trace` also prints, per re-posing of the first
batch: how many bodies still move, the median over the batch of each body's largest motion over
its settled tolerance, the unknowns per body that swing damping holds back, and the median
height of the centre of mass above where the coarse re-posings leave it (docs/benchmarks.md
"Session 51": the coarse phase is mostly a fall; blank once bodies have left the batch, or
without a coarse grid). It instruments the engine by wrapping its module-level functions: the
figures of a diagnostic run; `articulated_speed.py` times the engine alone, and
`articulated_settling_diag.py` follows single bodies' energies solve by solve.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from articulated_speed import partition_config, rest_options  # noqa: E402  (the same options)

from pressurepose.body import load_body_model  # noqa: E402
from pressurepose.sampling.partitions import SamplingConfig  # noqa: E402
from pressurepose.sampling.sampler import PoseSampler  # noqa: E402
from pressurepose.sim import articulated  # noqa: E402
from pressurepose.sim.contact_grid import ContactGrid  # noqa: E402
from pressurepose.sim.mattress import MattressParams  # noqa: E402


class Probe:
    """Wraps the engine's heights, set-up, solves, swing damping and motion while installed."""

    def __init__(self, config):
        self.config, self.cpu, self.grid, self.trace, self.on = config, Counter(), None, [], True
        self.originals = (ContactGrid.heights, articulated.minimise, articulated.Linearised)
        self.originals += (articulated.damp_swings, articulated.apply_motion)

    def _timed(self, label, fn, *a, **k):
        t = time.process_time()
        out = fn(*a, **k)
        self.cpu[label] += time.process_time() - t
        return out

    def install(self):
        heights, minimise, linearised, damp, motion = self.originals
        probe = self

        def heights_w(grid, *a, **k):
            probe.grid = "coarse" if grid.sub == probe.config.coarse_sub and probe.config.coarse_sub else "image"
            return probe._timed(f"{probe.grid}: lowest points", heights, grid, *a, **k)

        def minimise_w(lin, q, *a, **k):
            # the rests' own solves: the rest's step count and no re-posing stop (step_tol 0)
            rest = k.get("max_steps") == probe.config.inner and k.get("step_tol", 0.0) == 0.0
            return probe._timed(f"{probe.grid}: Newton{' (the rests)' if rest else ''}", minimise, lin, q, *a, **k)

        def damp_w(q, last_q, share, streak, cap, tol):
            step, new, st = damp(q, last_q, share, streak, cap, tol)
            if probe.on:
                probe.trace.append({"ratio": (step.abs() / tol).amax(1), "held": (new < 1).sum(1).double()})
            return step, new, st

        def motion_w(cur, step, dofs, rot, joints, body_com):
            if probe.on and probe.trace:
                probe.trace[-1]["com_z"] = body_com[:, 2].clone()
            return motion(cur, step, dofs, rot, joints, body_com)

        ContactGrid.heights = heights_w
        articulated.minimise = minimise_w
        articulated.Linearised = lambda *a, **k: self._timed(f"{self.grid}: set-up", linearised, *a, **k)
        articulated.damp_swings, articulated.apply_motion = damp_w, motion_w

    def remove(self):
        ContactGrid.heights, articulated.minimise, articulated.Linearised = self.originals[:3]
        articulated.damp_swings, articulated.apply_motion = self.originals[3:]


def print_trace(trace, coarse: int, tol_note: str) -> None:
    ends = [t["com_z"] for t in trace if "com_z" in t]
    # where the coarse re-posings leave the bodies: the posing the first image-grid one starts from
    end = ends[coarse] if coarse and len(ends) > coarse else None
    print(f"  per re-posing (first batch): moving bodies, median largest motion / tolerance ({tol_note}),")
    print("  unknowns held back by swing damping per body, median centre of mass above its height after")
    print("  the coarse re-posings (mm)")
    for k, t in enumerate(trace):
        above = ""
        if end is not None and "com_z" in t and len(t["com_z"]) == len(end):
            above = f"{1e3 * float((t['com_z'] - end).median()):8.1f}"
        moving = int((t["ratio"] >= 1).sum())
        print(
            f"  {k:3d}  {moving:4d}/{len(t['ratio']):<4d} {float(t['ratio'].median()):8.1f} "
            f"{float(t['held'].mean()):6.1f} {above}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    rest_options(ap, "general", 32)
    ap.add_argument("--trace", action="store_true", help="per re-posing figures of the first batch")
    args = ap.parse_args()
    torch.set_num_threads(1)
    model = load_body_model("anny", dtype=torch.float64)
    mattress = MattressParams.load(args.bed)
    for part in args.partitions.split(","):
        poses = PoseSampler(model, SamplingConfig(partition=part, gender="female", seed=0)).sample(range(args.n)).params
        config = partition_config(part, args.set)
        articulated.rest_articulated(
            model, poses.index(torch.arange(min(4, args.n))), mattress=mattress, config=config
        )  # warm-up
        probe = Probe(config)
        probe.install()
        try:
            t0, reposings = time.process_time(), []
            for b0 in range(0, args.n, args.batch):
                probe.on = args.trace and b0 == 0
                rest = articulated.rest_articulated(
                    model, poses.index(torch.arange(b0, min(b0 + args.batch, args.n))), mattress=mattress, config=config
                )
                reposings += rest.reposings.tolist()
            total = time.process_time() - t0
        finally:
            probe.remove()
        n = args.n
        print(f"{part} B={args.batch}: {total / n * 1e3:.1f} CPU ms per body, re-posings mean {sum(reposings) / n:.1f}")
        for label, cpu in sorted(probe.cpu.items()):
            print(f"  {label:<28} {cpu / n * 1e3:6.1f} ms ({cpu / total:4.0%})")
        rest_cpu = total - sum(probe.cpu.values())
        print(f"  {'everything else':<28} {rest_cpu / n * 1e3:6.1f} ms ({rest_cpu / total:4.0%})")
        if args.trace:
            print_trace(
                probe.trace,
                config.coarse_reposings,
                f"{config.settled_rotation_rad * 1e3:g} mrad, {config.settled_shift_m * 1e3:g} mm",
            )


if __name__ == "__main__":
    main()
