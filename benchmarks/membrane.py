"""The mat's membrane's cost (`MattressParams.membrane_m`, `sim.membrane`): `taxel_pressure` on a
batch of covered-grid pressure fields (2 cells per taxel, float64) with and without it, and over
the air preset's tubes with the mat bridging their seams (`membrane_support_pa_per_m`) or on
their stiffness wave (`membrane_wave`); the passes of those two fixed points depend on the load,
so they load a body-sized patch, 0.5-1.5 kPa.

    OMP_NUM_THREADS=1 PYTHONPATH=src python benchmarks/membrane.py [--batch 32] [--repeats 20]
"""

from __future__ import annotations

import argparse
import time

import torch

from pressurepose.mat import MatSpec
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.reading import taxel_pressure


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args()
    torch.set_num_threads(1)
    mat = MatSpec()
    rows, cols = mat.covered_shape
    field = torch.rand(args.batch, 2 * rows, 2 * cols, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    sponge = MattressParams.preset("sponge")
    for length in (0.0, 0.02, 0.03):
        mp = sponge.replace(membrane_m=length)
        taxel_pressure(field * 1e3, mp, mat, 2)  # warm-up
        t0 = time.perf_counter()
        for _ in range(args.repeats):
            taxel_pressure(field * 1e3, mp, mat, 2)
        ms = (time.perf_counter() - t0) / args.repeats / args.batch * 1e3
        print(f"membrane_m {length:.3f} m: {ms:.3f} ms per image (batch {args.batch}, one thread)")
    patch = torch.zeros_like(field)
    patch[:, 16:112, 14:42] = 500 + 1000 * field[:, 16:112, 14:42]
    air = MattressParams.preset("air").replace(membrane_m=0.02, membrane_wave=0.0)  # the preset's tubes
    for name, mp in (
        ("air, flat membrane 2 cm", air),
        ("air, membrane 2 cm over the seams", air.replace(membrane_support_pa_per_m=9e4)),
        ("air, membrane 2 cm on a stiffness wave 0.4", air.replace(membrane_wave=0.4)),
        ("the air preset as it is", MattressParams.preset("air")),
    ):
        taxel_pressure(patch, mp, mat, 2)
        t0 = time.perf_counter()
        for _ in range(args.repeats):
            taxel_pressure(patch, mp, mat, 2)
        ms = (time.perf_counter() - t0) / args.repeats / args.batch * 1e3
        print(f"{name}: {ms:.3f} ms per image (batch {args.batch}, one thread)")


if __name__ == "__main__":
    main()
