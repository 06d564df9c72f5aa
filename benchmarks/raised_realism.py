"""The raised bed against PmatData group F (issue 20 item 4): the articulated rest (`sim.raised`)
and the older MuJoCo + rigid rest, per head angle and mattress (each engine on the bed `pressurepose
realism` gives it: the articulated rest on the set's preset, the rigid rest on its own fit).

For group F's subjects (their heights and weights, male Anny bodies) half-sitting in the home
pose on the raised bed (`sampling.sitting.half_sitting_params`, hips 15 cm foot-ward of the
hinge), each engine rests them on the set's mattress preset; the images are read with the real
frames' floor, as `pressurepose realism` reads them, and compared with the frames of that angle
and mattress: along-bed and across-bed profile similarity (best over shifts), contact area
ratio, and the share of the force on the rows above the hinge (median over frames).

    OMP_NUM_THREADS=1 python benchmarks/raised_realism.py [--angles 0,10,20,30,40,50,60] [--engines articulated,rigid]
        [--hip-offset 0.15]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from pressurepose.bed import BedShape
from pressurepose.body import load_body_model
from pressurepose.body.fit_shape import shape_for_height_mass
from pressurepose.commands.realism import frame_placement
from pressurepose.commands.realism_raised import raised_share
from pressurepose.data.pmatdata import distinct_frames, load_images, load_index, subjects_of
from pressurepose.eval import realism as R
from pressurepose.mat import MatSpec
from pressurepose.samples import resolve_pmatdata
from pressurepose.sampling.sitting import half_sitting_params
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.run import default_mattress, simulate_poses

ENGINES = {"articulated": {"settle": "articulated"}, "rigid": {"settle": "mujoco", "sim2": "rigid"}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--angles", default="0,10,20,30,40,50,60")
    ap.add_argument("--engines", default="articulated,rigid")
    ap.add_argument("--threshold", type=float, default=20.0)
    ap.add_argument("--hip-offset", type=float, default=0.15, help="hips this far foot-ward of the hinge (m)")
    ap.add_argument(
        "--place-cop",
        action="store_true",
        help="rest twice: the second time with the hips moved by what puts the images' median centre "
        "of pressure along the bed on the real frames' (per engine, angle and mattress)",
    )
    args = ap.parse_args()
    torch.set_num_threads(1)
    root = resolve_pmatdata("pmatdata")
    recs = distinct_frames([r for r in load_index(root) if r.group == "F"])
    subjects = subjects_of(recs)
    model = load_body_model("anny", dtype=torch.float64)
    shape, _, _ = shape_for_height_mass(model, [s[1] for s in subjects], [s[2] for s in subjects])
    mat = MatSpec()
    pitch = (mat.pitch_row_m, mat.pitch_col_m)
    print(f"PmatData group F: {len(recs)} frames, {len(subjects)} subjects")
    print(
        "| angle | mattress | real frames | engine | along | across | area sim/real | head section sim (real) | kept | s |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for angle in [float(a) for a in args.angles.split(",")]:
        bed = BedShape(angle)
        hinge_row = mat.rows - bed.hinge_row_from_foot
        for mattress in ("air", "sponge"):
            rs = [r for r in recs if r.bed_incline_deg == angle and r.mattress == mattress]
            if not rs:
                continue
            real = load_images(rs, args.threshold)
            real_set = R.summarise(real, np.array([r.height_cm / 100 for r in rs]), *pitch)
            floor = R.reading_floor(real)
            for engine in args.engines.split(","):
                t0 = time.perf_counter()
                # Each engine on the bed `pressurepose realism` gives it: the articulated rest on the
                # set's preset, the rigid rest on its own fit (the class defaults).
                bed_params = MattressParams.preset(mattress) if engine == "articulated" else default_mattress("mujoco")
                offset = args.hip_offset
                for _ in range(2 if args.place_cop else 1):
                    used = offset
                    params = half_sitting_params(model, shape, bed, mat, hip_offset_m=used)
                    sim = simulate_poses(model, params, bed_params, mat, bed=bed, **ENGINES[engine])
                    ok = [i for i, r in enumerate(sim.reason) if not r]
                    if not ok:
                        break
                    drawn = R.read_with_floor(sim.pressure_mmhg[ok].numpy(), floor)
                    miss = np.median(frame_placement(real, *pitch)[0][:, 0]) - np.median(
                        frame_placement(drawn, *pitch)[0][:, 0]
                    )
                    offset = float(np.clip(offset + miss, 0.0, 0.5))
                if not ok:  # noqa: SIM102
                    print(
                        f"| {angle:.0f} | {mattress} | {len(rs)} | {engine} | - | - | - | - | 0/{len(params.pose)} | |"
                    )
                    continue
                images = R.read_with_floor(sim.pressure_mmhg[ok].numpy(), floor)
                sim_set = R.summarise(images, sim.height_m[ok].numpy(), *pitch)
                c = R.compare(real_set, sim_set)
                print(
                    f"| {angle:.0f} | {mattress} | {len(rs)} | {engine} | {c.along:.3f} | {c.across:.3f} | "
                    f"{c.area_ratio:.2f} | {raised_share(images, hinge_row):.2f} ({raised_share(real, hinge_row):.2f}) | "
                    f"{len(ok)}/{len(sim.reason)} | {time.perf_counter() - t0:.0f} |"
                    + (f" hips {used:.2f} m |" if args.place_cop else ""),
                    flush=True,
                )


if __name__ == "__main__":
    main()
