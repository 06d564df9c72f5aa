"""The realism report's raised beds: PmatData group F (supine, the head of the bed at 0-60 deg)
against bodies half-sitting on the same bed in the articulated rest (docs/realism.md "Raised
beds").

One simulated body per real frame, of that frame's subject's height and weight, in the home pose
half-sitting on the frame's bed (`sampling.sitting.half_sitting_params`), on the frame's
mattress preset. Where its hips lie is the frame's: each body rests twice, the second time with
its hips moved along the bed by what put its image's centre of pressure on the frame's (the flat
report's bodies stand over each frame's centre of pressure; a half-sitting body's place along the
bed decides how much of it the raised section carries). Per angle and mattress: the along- and
across-bed profile similarity, the contact area ratio and the share of the force on the rows above
the hinge, real and simulated.
"""

from __future__ import annotations

import numpy as np
import torch

from pressurepose.eval import realism as R

FIRST_HIP_OFFSET_M = 0.35  # the first rest's hips past the hinge (the middle of group F's)
HIP_OFFSET_RANGE_M = (0.0, 0.6)  # the second rest's hips stay within this


def load_raised(root, threshold: float) -> dict:
    """Real frames of raised beds per (angle, mattress): images (N, 64, 27) mmHg, heights (N,) m,
    masses (N,) kg. Empty when the folder has none (PmatData: group F, 0-60 deg)."""
    from pressurepose.data.pmatdata import distinct_frames, load_images, load_index
    from pressurepose.samples import resolve_pmatdata

    root = resolve_pmatdata(root)
    records = distinct_frames([r for r in load_index(root) if r.group == "F" or r.bed_incline_deg > 0])
    out = {}
    for key in sorted({(float(r.bed_incline_deg), r.mattress) for r in records}):
        rs = [r for r in records if (float(r.bed_incline_deg), r.mattress) == key]
        out[key] = (
            load_images(rs, threshold),
            np.array([r.height_cm / 100 for r in rs]),
            np.array([float(r.weight_kg) for r in rs]),
        )
    return out


def raised_share(images: np.ndarray, hinge_row: int) -> float:
    """The median over frames of the share of the force on the rows above the hinge."""
    return float(np.median(images[:, :hinge_row].sum((1, 2)) / images.sum((1, 2)).clip(min=1e-12)))


def twin_setup(cfg):
    """What the report's per-frame twins (raised and tilted rows) are made with, for a
    `RealismConfig`: the mat on its simulated mattress, its pitch (row, col) m, the float64 body
    model, the `--params` bed or None (each set's own preset)."""
    from pressurepose.body import load_body_model
    from pressurepose.mat import MatSpec
    from pressurepose.sim.mattress import MattressParams

    mat = MatSpec(covered_cols=cfg.bed_width_cols)
    fixed = MattressParams.load(cfg.params) if cfg.params else None
    return mat, (mat.pitch_row_m, mat.pitch_col_m), load_body_model("anny", dtype=torch.float64), fixed


def subject_shapes(model, heights: np.ndarray, masses: np.ndarray) -> torch.Tensor:
    """The body shapes of subjects of these heights (m) and masses (kg), male phenotype."""
    from pressurepose.body.fit_shape import shape_for_height_mass

    h, m = torch.from_numpy(heights).double(), torch.from_numpy(masses).double()
    return shape_for_height_mass(model, h, m, female=0.0)[0]


def raised_rows(real: dict, cfg) -> list[dict]:
    """The report's rows for the raised beds (module doc); cfg a `RealismConfig`."""
    from pressurepose.bed import BedShape
    from pressurepose.commands.realism import frame_placement, set_mattress
    from pressurepose.sampling.sitting import half_sitting_params
    from pressurepose.sim.run import simulate_poses

    mat, pitch, model, fixed = twin_setup(cfg)
    rows = []
    for (angle, mattress), (imgs, heights, masses) in real.items():
        bed = BedShape(angle)
        hinge_row = mat.rows - bed.hinge_row_from_foot
        bed_params = set_mattress(cfg, mattress, fixed)
        shape = subject_shapes(model, heights, masses)
        floor = R.reading_floor(imgs) if cfg.match_floor else 0.0
        offset = np.full(len(imgs), FIRST_HIP_OFFSET_M)
        for rest in range(2):
            params = half_sitting_params(model, shape, bed, mat, hip_offset_m=torch.from_numpy(offset))
            sim = simulate_poses(model, params, bed_params, mat, bed=bed, settle="articulated")
            images = sim.pressure_mmhg.numpy()
            if floor > 0:
                images = R.read_with_floor(images, floor)
            ok = np.array([not r for r in sim.reason])
            if rest == 0:  # move each body's hips by its image's miss of the frame's centre of pressure
                miss = frame_placement(imgs, *pitch)[0][:, 0] - frame_placement(images, *pitch)[0][:, 0]
                offset = np.clip(np.where(ok, offset + miss, offset), *HIP_OFFSET_RANGE_M)
        row = {
            "angle_deg": angle,
            "mattress": mattress,
            "frames": int(len(imgs)),
            "simulated_bodies": int(ok.sum()),
            "rejected": [r for r in sim.reason if r],
            "hips_past_hinge_m": round(float(np.median(offset[ok])), 3) if ok.any() else None,
            "raised_share": {"real": round(raised_share(imgs, hinge_row), 4)},
        }
        if ok.any():
            c = R.compare(R.summarise(imgs, heights, *pitch), R.summarise(images[ok], sim.height_m.numpy()[ok], *pitch))
            row["comparison"] = {"along": c.along, "across": c.across, "area_ratio": c.area_ratio}
            row["raised_share"]["simulated"] = round(raised_share(images[ok], hinge_row), 4)
        rows.append(row)
    return rows


def raised_markdown(rows: list[dict]) -> list[str]:
    """The report's table of the raised beds (`raised_rows`)."""
    if not rows:
        return []
    lines = [
        "",
        "## Raised head of the bed (PmatData group F; the bodies' hips placed from each frame's centre of pressure)",
        "",
        "| angle | mattress | along | across | area sim/real | raised section's share sim (real) | hips past the hinge | bodies |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        c = r.get("comparison")
        sim = r["raised_share"].get("simulated")
        cells = (
            [
                f"{c['along']:.3f}",
                f"{c['across']:.3f}",
                f"{c['area_ratio']:.2f}",
                f"{sim:.2f} ({r['raised_share']['real']:.2f})",
            ]
            if c
            else ["-", "-", "-", f"- ({r['raised_share']['real']:.2f})"]
        )
        hips = "-" if r["hips_past_hinge_m"] is None else f"{r['hips_past_hinge_m']:.2f} m"
        lines.append(
            f"| {r['angle_deg']:g} | {r['mattress']} | "
            + " | ".join(cells)
            + f" | {hips} | {r['simulated_bodies']} of {r['frames']} |"
        )
    return lines


__all__ = ["load_raised", "raised_markdown", "raised_rows", "raised_share", "subject_shapes", "twin_setup"]
