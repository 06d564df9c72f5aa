"""Plausibility of the simulated pressure images against real ones (issue 4, item 5).

For PmatData experiment II's subjects (their heights and weights, male Anny bodies fitted to
them) lying supine, on the left and on the right side on a flat bed in the home pose (arms at
the sides), run sim #1 + sim #2 + the sensor and compare with the real recordings, normalised
as ../shared/data/pmatdata/README.md says (empty level subtracted, noise threshold, summed
force = weight): contact area, mean contact pressure, peak pressure (medians over subjects),
and the force profile along the bed. Prints a table, writes a side-by-side figure per posture.
Then the same for PmatData group F (head of the bed raised 0-60 degrees) against half-sitting
bodies on the raised bed, with the share of the load on the head section.

    .venv/bin/python benchmarks/sim_realism.py [--params bed.json] [--out out/realism]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

from pressurepose.bed import BedShape
from pressurepose.body import load_body_model
from pressurepose.body.capsules import home_pose
from pressurepose.body.fit_shape import shape_for_height_mass
from pressurepose.body.params import BodyParams
from pressurepose.data.pmatdata import (
    PMAT_TAXEL_AREA_M2,
    distinct_frames,
    frame_stats,
    load_index,
    normalise,
    read_frame,
    subjects_of,
)
from pressurepose.mat import MatSpec
from pressurepose.sampling.sitting import half_sitting_params
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.run import simulate_poses

PMAT = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "pmatdata"
POSTURES = {"supine": ("B", 0.0), "left": ("D", -math.pi / 2), "right": ("C", math.pi / 2)}
PLAUSIBLE = {"area_m2": (0.30, 0.45), "mean_mmhg": (11.0, 20.0), "peak_mmhg": (60.0, 110.0)}


def real_stats(root: Path, threshold: float):
    recs = distinct_frames([r for r in load_index(root) if r.bed_incline_deg == 0])
    out = {}
    for posture, (group, _) in POSTURES.items():
        for mattress in ("air", "sponge"):
            frames = [
                normalise(read_frame(r.path), r.weight_kg, threshold)
                for r in recs
                if r.group == group and r.mattress == mattress
            ]
            out[(posture, mattress)] = frames
    return out, subjects_of(recs)


def simulate(subjects, params: MattressParams, mat: MatSpec):
    model = load_body_model("anny", dtype=torch.float64)
    heights = torch.tensor([s[1] for s in subjects], dtype=torch.float64)
    masses = torch.tensor([float(s[2]) for s in subjects], dtype=torch.float64)
    shape, h, m = shape_for_height_mass(model, heights, masses, female=0.0)
    B = shape.shape[0]
    out = {}
    for posture, (_, roll) in POSTURES.items():
        p = BodyParams.zeros(B, shape).replace(
            pose=home_pose(B),
            root_rotation=torch.tensor([[roll, 0.0, 0.0]] * B, dtype=torch.float64),
            root_translation=torch.tensor([[0.80, mat.sensing_width_m / 2, 0.3]] * B, dtype=torch.float64),
        )
        t0 = time.perf_counter()
        sim = simulate_poses(model, p, params, mat)
        out[posture] = sim
        print(
            f"  simulated {posture}: {B} bodies in {time.perf_counter() - t0:.1f} s; rejected: "
            f"{sum(bool(r) for r in sim.reason)} {[r for r in sim.reason if r]}",
            file=sys.stderr,
        )
    return out, h, m


def raised_bed(root: Path, threshold: float, params: MattressParams, mat: MatSpec) -> None:
    """PmatData group F (supine, head of the bed at 0-60 degrees) against half-sitting bodies."""
    recs = distinct_frames([r for r in load_index(root) if r.group == "F"])
    subjects = subjects_of(recs)
    model = load_body_model("anny", dtype=torch.float64)
    shape, _, _ = shape_for_height_mass(model, [s[1] for s in subjects], [s[2] for s in subjects])
    print("\nhead of the bed raised (PmatData group F vs simulated half-sitting):")
    print("| angle | source | contact area (m^2) | mean (mmHg) | peak (mmHg) | load on head section |")
    print("| --- | --- | --- | --- | --- | --- |")
    for angle in sorted({r.bed_incline_deg for r in recs}):
        bed = BedShape(angle)
        hinge_row = mat.rows - bed.hinge_row_from_foot
        for mattress in ("air", "sponge"):
            frames = [
                normalise(read_frame(r.path), r.weight_kg, threshold)
                for r in recs
                if r.bed_incline_deg == angle and r.mattress == mattress
            ]
            st = summary(frames, PMAT_TAXEL_AREA_M2)
            head = float(np.median([f[:hinge_row].sum() / f.sum() for f in frames]))
            print(
                f"| {angle:.0f} | PmatData {mattress} | {st['area_m2']:.3f} | {st['mean_mmhg']:.1f} | {st['peak_mmhg']:.0f} | {head:.0%} |"
            )
        sim = simulate_poses(model, half_sitting_params(model, shape, bed, mat), params, mat, bed=bed)
        ok = [i for i, r in enumerate(sim.reason) if not r]
        frames = [sim.pressure_mmhg[i].numpy() for i in ok]
        if frames:
            st = summary(frames, mat.taxel_area_m2)
            head = float(np.median([f[:hinge_row].sum() / f.sum() for f in frames]))
            print(
                f"| {angle:.0f} | simulated ({len(ok)}/{len(sim.reason)}) | {st['area_m2']:.3f} | {st['mean_mmhg']:.1f} "
                f"| {st['peak_mmhg']:.0f} | {head:.0%} |"
            )
        else:
            print(f"| {angle:.0f} | simulated (0/{len(sim.reason)}) | - | - | - | - |  {sorted(set(sim.reason))}")


def summary(frames, area):
    st = [frame_stats(f, area) for f in frames]
    return {k: float(np.median([s[k] for s in st])) for k in ("area_m2", "mean_mmhg", "peak_mmhg")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--params", type=Path, help="mattress parameter JSON (default: built-in)")
    ap.add_argument("--pmatdata", type=Path, default=PMAT)
    ap.add_argument("--threshold", type=float, default=20.0, help="raw noise threshold for the real frames")
    ap.add_argument("--out", type=Path, default=Path("out/realism"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    params = MattressParams.load(args.params) if args.params else MattressParams()
    mat = MatSpec()
    real, subjects = real_stats(args.pmatdata, args.threshold)
    sims, h, m = simulate(subjects, params, mat)
    print(
        f"subjects: {len(subjects)} (male Anny fits: height {h.min():.2f}-{h.max():.2f} m, "
        f"mass {m.min():.0f}-{m.max():.0f} kg); real threshold {args.threshold} raw units"
    )
    print("| posture | source | contact area (m^2) | mean (mmHg) | peak (mmHg) |")
    print("| --- | --- | --- | --- | --- |")
    rows = {}
    for posture in POSTURES:
        for mattress in ("air", "sponge"):
            s = summary(real[(posture, mattress)], PMAT_TAXEL_AREA_M2)
            print(
                f"| {posture} | PmatData {mattress} | {s['area_m2']:.3f} | {s['mean_mmhg']:.1f} | {s['peak_mmhg']:.0f} |"
            )
        sim = sims[posture]
        ok = [i for i, r in enumerate(sim.reason) if not r]
        frames = [sim.pressure_mmhg[i].numpy() for i in ok]
        s = summary(frames, mat.taxel_area_m2) if frames else dict.fromkeys(PLAUSIBLE, float("nan"))
        rows[posture] = s
        flags = " ".join("ok" if PLAUSIBLE[k][0] <= s[k] <= PLAUSIBLE[k][1] else "OUT" for k in PLAUSIBLE)
        print(
            f"| {posture} | simulated ({len(ok)}/{len(sim.reason)}) | {s['area_m2']:.3f} | {s['mean_mmhg']:.1f} "
            f"| {s['peak_mmhg']:.0f} |  supine targets: {flags if posture == 'supine' else '-'}"
        )
    args.out.mkdir(parents=True, exist_ok=True)
    _figure(args.out, real, sims, mat)
    print(f"figures in {args.out}")
    raised_bed(args.pmatdata, args.threshold, params, mat)


def _figure(out: Path, real, sims, mat: MatSpec) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for posture in POSTURES:
        sim = sims[posture]
        ok = [i for i, r in enumerate(sim.reason) if not r]
        fig, axes = plt.subplots(1, 5, figsize=(14, 5), gridspec_kw={"width_ratios": [1, 1, 1, 1, 1.6]})
        panels = [("PmatData air", real[(posture, "air")]), ("PmatData sponge", real[(posture, "sponge")])]
        panels += [(f"simulated #{i}", [sim.pressure_mmhg[i].numpy()]) for i in ok[:2]]
        for ax, (title, frames) in zip(axes, panels):
            ax.imshow(frames[0], vmin=0, vmax=100, cmap="viridis", aspect="auto")
            ax.set_title(title)
            ax.set_xticks([])
        for ax in axes[len(panels) : 4]:
            ax.axis("off")
        ax = axes[4]
        for title, frames in panels[:2]:
            prof = np.mean([f.sum(1) * PMAT_TAXEL_AREA_M2 * 133.322 for f in frames], 0)
            ax.plot(prof, label=title)
        if ok:
            prof = np.mean([sim.pressure_mmhg[i].numpy().sum(1) * mat.taxel_area_m2 * 133.322 for i in ok], 0)
            ax.plot(prof, label="simulated (mean)")
        ax.set_xlabel("row (head at 0)")
        ax.set_ylabel("force per row (N)")
        ax.legend()
        fig.suptitle(f"{posture}: real (first frame) vs simulated, and the force profile along the bed")
        fig.tight_layout()
        fig.savefig(out / f"realism_{posture}.png", dpi=80)
        plt.close(fig)


if __name__ == "__main__":
    main()
