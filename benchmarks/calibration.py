"""Proof that calibration works (issue 5, item 4), timed.

Makes measurements of the seed's ten capsule-weight pairs (two scenes of five) with our own
simulator and hidden parameters plus sensor noise and compression-measurement noise, runs
`pressurepose calibrate` with the seed's CMA-ES settings from fixed start values, and
prints the recovered parameters against the hidden ones, the loss against the noise floor
(the loss of the hidden parameters themselves), the wall time, and the sim #1 / sim #2
sinking check. Then the loss surface: the loss along each free parameter around the result,
and along directions the measurements cannot see (mat stiffness with c1, c2 rescaled;
thickness; sim #1's damping and friction), written as loss_surface.png.

    .venv/bin/python benchmarks/calibration.py [--out out/bench_calibration] [--workers 2]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from pressurepose.calib.loss import CalibrationLoss, ParamSpace
from pressurepose.calib.measurements import synthetic_measurements
from pressurepose.calib.objects import seed_objects
from pressurepose.commands.calibrate import CalibrateConfig, run_calibrate
from pressurepose.sim.mattress import MattressParams

# The start: the built-in defaults before issue 5 (fixed here so that the benchmark does not
# move when the shipped defaults do).
START = MattressParams(
    k1_pa_per_m=2.0e4, k3_pa_per_m3=6.0e7, spread_m=0.008, c0_mmhg=-1.0, c1_mmhg_per_mm=1.0, c2_mmhg_per_mm2=0.0
)
HIDDEN = MattressParams(
    k1_pa_per_m=3.0e4, k3_pa_per_m3=4.0e7, spread_m=0.012, c0_mmhg=-2.0, c1_mmhg_per_mm=1.3, c2_mmhg_per_mm2=0.004
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/bench_calibration"))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--noise-mmhg", type=float, default=0.5)
    ap.add_argument("--compression-noise-m", type=float, default=0.0005)
    ap.add_argument("--popsize", type=int, default=50)
    ap.add_argument("--no-surface", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    meas = synthetic_measurements(
        seed_objects(), HIDDEN, noise_mmhg=args.noise_mmhg, compression_noise_m=args.compression_noise_m, seed=1
    )
    path = meas.save(args.out / "measurements.json")
    START.save(args.out / "start.json")
    cfg = CalibrateConfig(
        measurements=path,
        out=args.out,
        start=args.out / "start.json",
        workers=args.workers,
        popsize=args.popsize,
        restart=True,
    )
    t0 = time.perf_counter()
    paths = run_calibrate(cfg, progress=False)
    wall = time.perf_counter() - t0
    record = json.loads(paths["record"].read_text())
    space = ParamSpace(cfg.free, START)
    loss = CalibrationLoss(meas, space)
    floor = loss(space.encode(HIDDEN))
    print(
        f"measurements: {meas.n_objects} objects in {len(meas.scenes)} scenes, sensor noise {args.noise_mmhg} mmHg, "
        f"compression noise {args.compression_noise_m * 1000:.1f} mm"
    )
    print(
        f"calibration: {record['iterations']} generations, {record['evaluations']} evaluations, "
        f"{wall:.0f} s wall on {args.workers} workers (incl. the sim #1 check); stop: {record['stop']}"
    )
    print(
        f"loss: start {record['start_loss']:.4f}, result {record['best_loss']:.4f}, noise floor "
        f"(hidden parameters) {floor:.4f}"
    )
    print("| parameter | start | hidden | recovered | error |")
    print("| --- | --- | --- | --- | --- |")
    for name in cfg.free:
        h, r, s = getattr(HIDDEN, name), record["params"][name], getattr(START, name)
        print(f"| {name} | {s:.5g} | {h:.5g} | {r:.5g} | {100 * (r - h) / abs(h):+.2f}% |")
    print("sim #1 vs sim #2 sinking (calibrated parameters):")
    print("| object | sim #2 (mm) | sim #1 (mm) | difference |")
    print("| --- | --- | --- | --- |")
    for c in record["coupling"]:
        print(
            f"| {c['name']} | {1000 * c['sim2_sink_m']:.1f} | {1000 * c['sim1_sink_m']:.1f} | "
            f"{100 * c['relative_difference']:+.1f}% |"
        )
    if not args.no_surface:
        surface(loss, space, record["params"], floor, args.out / "loss_surface.png")


def surface(loss: CalibrationLoss, space: ParamSpace, fitted: dict, floor: float, path: Path) -> None:
    """1-D loss profiles through the result: each free parameter from 0.8x to 1.2x, and the
    directions the measurements cannot see."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    best = MattressParams(**fitted)
    print("loss profile through the result:")
    factors = np.linspace(0.8, 1.2, 17)  # holds 0.95 (index 6) and 1.05 (index 10)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for name in space.free:
        values = [loss.of_params(best.replace(**{name: getattr(best, name) * f})) for f in factors]
        axes[0].plot(factors, values, label=name)
        print(
            f"  {name}: loss at 0.95x {values[6]:.4f}, at 1.0x {values[8]:.4f}, at 1.05x {values[10]:.4f} "
            f"(noise floor {floor:.4f})"
        )
    axes[0].axhline(floor, color="k", ls=":", label="noise floor")
    axes[0].set_xlabel("parameter / calibrated value")
    axes[0].set_ylabel("loss")
    axes[0].set_title("free parameters")
    axes[0].legend(fontsize=7)
    hidden_dirs = {
        "mat_stiffness (c1, c2 rescaled)": lambda f: best.replace(
            mat_stiffness_pa_per_mm=best.mat_stiffness_pa_per_mm * f,
            c1_mmhg_per_mm=best.c1_mmhg_per_mm * f,
            c2_mmhg_per_mm2=best.c2_mmhg_per_mm2 * f * f,
        ),
        "thickness_m": lambda f: best.replace(thickness_m=best.thickness_m * f),
        "damping_s": lambda f: best.replace(damping_s=best.damping_s * f),
        "friction": lambda f: best.replace(friction=best.friction * f),
    }
    print("unidentifiable directions (loss range over 0.8x-1.2x):")
    for label, make in hidden_dirs.items():
        values = [loss.of_params(make(f)) for f in factors]
        axes[1].plot(factors, values, label=label)
        print(f"  {label}: {min(values):.6f} - {max(values):.6f}")
    axes[1].set_xlabel("factor")
    axes[1].set_title("directions the static measurements cannot see")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    print(f"loss surface -> {path}")


if __name__ == "__main__":
    main()
