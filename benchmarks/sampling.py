"""Initial-pose sampling and capsulised-body benchmarks (issue 3).

    python benchmarks/sampling.py              # accepted poses/s per partition, one core
    python benchmarks/sampling.py --shapes     # height / mass / BMI ranges of the shape sampler
    python benchmarks/sampling.py --capsules   # capsule fit, volume (QMC vs 2 mm voxels), full body
    python benchmarks/sampling.py --stages --n 512   # CPU time per sampler stage, over the bed

Prints figures; record them in docs/benchmarks.md with the machine.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from pressurepose.body import load_body_model
from pressurepose.sampling import PARTITIONS, PoseSampler, SamplingConfig, UnreachableConstraints


def bench_sampling(n: int, threads: int, partitions: list[str] | None = None) -> None:
    torch.set_num_threads(threads)
    model = load_body_model("anny", dtype=torch.float32)
    print(f"accepted initial poses per second ({threads} thread(s), {n} samples, batch {min(n, 256)}, Anny)")
    print(
        f"{'partition':<18} {'over_bed':<8} {'poses/s':>8} {'cpu p/s':>8} {'draws rej.':>10} {'collisions':>10} "
        f"{'limb fail':>9} {'new shape':>9} {'new cell':>8} {'sit-up rej.':>11}"
    )
    for name, part in PARTITIONS.items():
        if partitions and name not in partitions:
            continue
        for over_bed in part.over_bed_choices:
            sampler = PoseSampler(model, SamplingConfig(partition=name, gender="male", over_bed=over_bed))
            sampler.sample([10**6])  # warm-up (and the float64 copy of the model)
            t, c = time.perf_counter(), time.process_time()
            try:
                out = [sampler.sample(range(lo, min(lo + 256, n))) for lo in range(0, n, 256)]
            except UnreachableConstraints as exc:
                print(f"{name:<18} {str(over_bed):<8} gave up: {exc}")
                continue
            dt, dc = time.perf_counter() - t, time.process_time() - c
            rej = {k: np.concatenate([o.rejections[k] for o in out]).mean() for k in out[0].rejections}
            print(
                f"{name:<18} {str(over_bed):<8} {n / dt:8.0f} {n / dc:8.0f} {rej['limb_draws_rejected']:10.0f} "
                f"{rej['collisions']:10.1f} {rej['limb_failures']:9.2f} {rej['shape_resamples']:9.2f} "
                f"{rej['cell_redraws']:8.3f} {rej['sit_up_rejections']:11.2f}"
            )


def bench_stages(n: int, partitions: list[str] | None) -> None:
    """CPU seconds per stage of the sampler over the bed (male, batches of 256): the capsule
    fit, the root's axis-angle, the reachable boxes, the proposals drawn in them, and the
    windows' float32 screen, exact float64 tests and collision tests (nested: a window's
    total includes its screen, exact tests and collisions)."""
    import collections
    import functools

    from pressurepose.sampling import limb_draws, sampler, support

    torch.set_num_threads(1)
    model = load_body_model("anny", dtype=torch.float32)
    spent = collections.Counter()

    def timed(owner, name, label):
        f = getattr(owner, name)

        @functools.wraps(f)
        def g(*a, **k):
            t = time.process_time()
            try:
                return f(*a, **k)
            finally:
                spent[label] += time.process_time() - t

        setattr(owner, name, g)
        return owner, name, f

    stages = [
        (sampler, "fit_capsules", "capsule fit"),
        (sampler, "root_axis_angles", "root axis-angle"),
        (limb_draws.LimbDraws, "_draw_limbs", "limb draws (all)"),
        (support.LimbGrid, "support", "  reachable boxes"),
        (support.LimbGrid, "propose_rows", "  proposals in the boxes"),
        (limb_draws.LimbDraws, "_window", "  windows"),
        (limb_draws.LimbDraws, "_screen", "    screen (float32)"),
        (limb_draws.LimbDraws, "_limb_survivors", "    exact tests"),
        (limb_draws.LimbDraws, "_collision_free", "    collisions"),
    ]
    labels = [label for _, _, label in stages]
    patches = [timed(*stage) for stage in stages]
    try:
        for name in partitions or ["hands_behind_head", "crossed_legs", "straight_limbs"]:
            sampler_ = sampler.PoseSampler(model, SamplingConfig(partition=name, gender="male", over_bed=True))
            sampler_.sample([10**6])
            spent.clear()
            c = time.process_time()
            for lo in range(0, n, 256):
                sampler_.sample(range(lo, min(lo + 256, n)))
            total = time.process_time() - c
            print(f"{name} over the bed: {total:.2f} CPU s for {n} samples ({n / total:.0f}/s)")
            for label in labels:
                print(f"  {label:<26} {spent[label]:6.2f} s  {100 * spent[label] / total:4.0f}%")
    finally:
        for owner, name, f in patches:
            setattr(owner, name, f)


def bench_shapes(n: int) -> None:
    from pressurepose.sampling.shapes import draw_shape, shape_bounds

    model = load_body_model("anny", dtype=torch.float64)
    power = model.shape_powers(model.shape_names)
    for gender in ("female", "male"):
        low, high = shape_bounds("anny", gender, model.shape_names)
        # the sampler's law and, from the same numbers, the uniform law (sampling laws 1-2)
        for law, pw in (("sampler's law", power), ("uniform weight (laws 1-2)", None)):
            rng = np.random.default_rng(0)
            shape = torch.tensor(np.stack([draw_shape(rng, low, high, pw) for _ in range(n)]))
            with torch.no_grad():
                m = model.measure(shape)
            h, w = m.height_m.numpy(), m.mass_kg.numpy()
            bmi = w / h**2
            q = lambda x: " / ".join(f"{v:.2f}" for v in np.quantile(x, [0, 0.01, 0.5, 0.99, 1]))  # noqa: E731
            print(f"{gender}, {law} (n={n}; min / 1% / median / 99% / max)")
            print(f"  height m : {q(h)}\n  mass kg  : {q(w)}\n  BMI      : {q(bmi)}")
            print(
                f"  BMI < 18.5: {np.mean(bmi < 18.5):.3f}, >= 25: {np.mean(bmi >= 25):.3f}, >= 30: {np.mean(bmi >= 30):.3f}"
            )


def bench_capsules() -> None:
    from pressurepose.body.capsules import build_capsule_body, capsule_volumes, fit_capsules

    torch.set_num_threads(1)
    model = load_body_model("anny", dtype=torch.float64)
    shape = torch.rand(64, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    shape[:, 1] = 0.8
    fit_capsules(model, shape[:2])
    t = time.perf_counter()
    caps = fit_capsules(model, shape)
    print(f"fit_capsules, B=64, float64, 1 thread: {(time.perf_counter() - t) / 64 * 1e3:.2f} ms/body")
    t = time.perf_counter()
    capsule_volumes(caps)
    print(f"capsule_volumes qmc (8192 pts), B=64: {(time.perf_counter() - t) / 64 * 1e3:.2f} ms/body")
    one = type(caps)(caps.start[:4], caps.end[:4], caps.radius[:4], caps.rest[:4])
    t = time.perf_counter()
    vox = capsule_volumes(one, method="voxel", resolution=0.002)
    dt = (time.perf_counter() - t) / 4
    fast = capsule_volumes(one)
    err = ((fast - vox).abs() / vox).max().item()
    print(f"capsule_volumes voxel 2 mm: {dt:.2f} s/body; max per-capsule |qmc - voxel| / voxel = {err * 100:.2f}%")
    t = time.perf_counter()
    build_capsule_body(model, shape)
    print(
        f"build_capsule_body (fit, volumes, masses, inertia, stiffness), B=64: "
        f"{(time.perf_counter() - t) / 64 * 1e3:.2f} ms/body"
    )


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=1024, help="samples per partition")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--partitions", nargs="*", help="only these partitions (default: all)")
    ap.add_argument("--shapes", action="store_true")
    ap.add_argument("--capsules", action="store_true")
    ap.add_argument("--stages", action="store_true", help="CPU time per sampler stage, over the bed")
    args = ap.parse_args()
    if args.stages:
        bench_stages(args.n, args.partitions)
    elif args.shapes:
        bench_shapes(1000)
    elif args.capsules:
        bench_capsules()
    else:
        bench_sampling(args.n, args.threads, args.partitions)
