"""The realism report's tilted bodies: PmatData group E (turned 20 or 40 deg toward a side on one
or two wedges or a pillow) against bodies turned the same way on a wedge in the articulated rest
(docs/realism.md "Tilted bodies on a wedge").

One simulated body per real frame, of that frame's subject's height and weight, in the home pose
(arms at the sides, legs straight) turned by the frame's documented roll, its centre of mass over
the frame's centre of pressure and its long axis along the frame's (as the flat report's twins),
resting on the wedge of the generator's `tilted` partition (`sim.wedge`; the pillow frames E5-E6
too: the simulator has no pillow under a back). Per documented roll and mattress: the along- and
across-bed profile similarity, the contact area ratio, the roll the twins rest at, and with the
report's network (`--model`) how it reads the real frames and the twins (the share read 10-135
deg toward the documented side, `eval.real.tilt_summary`).
"""

from __future__ import annotations

import numpy as np
import torch

from pressurepose.eval import realism as R


def load_tilted(root, threshold: float) -> dict:
    """Real frames of group E per (documented roll (+ right, deg), mattress): images (N, 64, 27)
    mmHg, heights (N,) m, masses (N,) kg. Empty when the folder has none; a row without its roll
    is a one-line error."""
    from pressurepose.data.pmatdata import distinct_frames, load_images, load_index
    from pressurepose.errors import UserError
    from pressurepose.eval.real import TILTED_GROUPS, documented_roll
    from pressurepose.samples import resolve_pmatdata

    root = resolve_pmatdata(root)
    records = distinct_frames([r for r in load_index(root) if r.group in TILTED_GROUPS and r.bed_incline_deg == 0])
    rolls = []
    for r in records:
        try:
            rolls.append(documented_roll(r.posture, r.body_roll_deg))
        except ValueError as exc:
            raise UserError(
                f"{root / 'index.csv'}: {r.path.relative_to(root)}: {exc} (column body_roll_deg); or --no-tilted"
            ) from None
    out = {}
    for key in sorted({(roll, r.mattress) for roll, r in zip(rolls, records)}):
        rs = [r for roll, r in zip(rolls, records) if (roll, r.mattress) == key]
        out[key] = (
            load_images(rs, threshold),
            np.array([r.height_cm / 100 for r in rs]),
            np.array([float(r.weight_kg) for r in rs]),
        )
    return out


def tilted_rows(real: dict, cfg, reader=None) -> list[dict]:
    """The report's rows for the tilted bodies (module doc); cfg a `RealismConfig`; `reader`:
    images (N, 64, 27) -> roll read (N,) deg by the report's network, or None."""
    from pressurepose.body.capsules import home_pose
    from pressurepose.body.params import BodyParams, root_roll
    from pressurepose.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle
    from pressurepose.commands.realism import frame_placement, set_mattress
    from pressurepose.commands.realism_raised import subject_shapes, twin_setup
    from pressurepose.eval.real import tilt_summary
    from pressurepose.maps import mesh_centroid
    from pressurepose.sim.articulated import ArticulatedConfig
    from pressurepose.sim.run import simulate_poses
    from pressurepose.sim.wedge import Wedge

    mat, pitch, model, fixed = twin_setup(cfg)
    rows = []
    for (roll_deg, mattress), (imgs, heights, masses) in real.items():
        B = len(imgs)
        shape = subject_shapes(model, heights, masses)
        centres, angles = frame_placement(imgs, *pitch)
        turn = axis_angle_to_matrix(torch.tensor([[np.radians(roll_deg), 0.0, 0.0]] * B, dtype=torch.float64))
        yaw = axis_angle_to_matrix(torch.from_numpy(np.stack([np.zeros(B), np.zeros(B), angles], 1)))
        params = BodyParams.zeros(B, shape).replace(pose=home_pose(B), root_rotation=matrix_to_axis_angle(yaw @ turn))
        com = mesh_centroid(model(params).vertices, model.faces)
        params = params.replace(
            root_translation=torch.cat(
                [torch.from_numpy(centres) - com[:, :2], torch.full((B, 1), 0.3, dtype=torch.float64)], 1
            )
        )
        sim = simulate_poses(
            model,
            params,
            set_mattress(cfg, mattress, fixed),
            mat,
            settle="articulated",
            articulated=ArticulatedConfig(wedge=Wedge()),
        )
        ok = np.array([not r for r in sim.reason])
        images = sim.pressure_mmhg.numpy()[ok]
        if cfg.match_floor and len(images):
            images = R.read_with_floor(images, R.reading_floor(imgs))
        rest = np.degrees(root_roll(sim.params.root_rotation).numpy())[ok]
        row = {
            "roll_deg": roll_deg,
            "mattress": mattress,
            "frames": int(B),
            "simulated_bodies": int(ok.sum()),
            "rejected": [r for r in sim.reason if r],
            "rest_roll_deg": round(float(np.median(rest)), 1) if ok.any() else None,
        }
        if ok.any():
            c = R.compare(R.summarise(imgs, heights, *pitch), R.summarise(images, sim.height_m.numpy()[ok], *pitch))
            row["comparison"] = {"along": c.along, "across": c.across, "area_ratio": c.area_ratio}
        if reader is not None:
            row["turned"] = {"real": tilt_summary([roll_deg] * B, reader(imgs))["share_turned"]}
            if ok.any():
                row["turned"]["simulated"] = tilt_summary([roll_deg] * len(images), reader(images))["share_turned"]
        rows.append(row)
    return rows


def tilted_markdown(rows: list[dict]) -> list[str]:
    """The report's table of the tilted bodies (`tilted_rows`)."""
    if not rows:
        return []
    with_reads = any("turned" in r for r in rows)
    lines = [
        "",
        "## Tilted bodies (PmatData group E; twins in the home pose turned by the documented roll on the "
        "`tilted` partition's wedge, placed over each frame's centre of pressure)",
        "",
        "| roll | mattress | along | across | area sim/real | twins rest at | bodies |"
        + (" read turned real / twins |" if with_reads else ""),
        "| --- | --- | --- | --- | --- | --- | --- |" + (" --- |" if with_reads else ""),
    ]
    for r in rows:
        c = r.get("comparison")
        cells = [f"{c['along']:.3f}", f"{c['across']:.3f}", f"{c['area_ratio']:.2f}"] if c else ["-", "-", "-"]
        rest = "-" if r["rest_roll_deg"] is None else f"{r['rest_roll_deg']:+.0f} deg"
        line = f"| {r['roll_deg']:+.0f} | {r['mattress']} | " + " | ".join(cells)
        line += f" | {rest} | {r['simulated_bodies']} of {r['frames']} |"
        if with_reads:
            t = r.get("turned", {})
            sim = "-" if "simulated" not in t else f"{t['simulated'] * 100:.0f}%"
            line += f" {t['real'] * 100:.0f}% / {sim} |" if t else " - |"
        lines.append(line)
    return lines


__all__ = ["load_tilted", "tilted_markdown", "tilted_rows"]
