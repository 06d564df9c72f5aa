"""`pressurepose evaluate-real --data FILE.npz`: a real set with point clouds (issue 9, seed A.8).

The file is written by `import-pressurepose-real`, or is any .npz with pressure_mmhg, subject,
cloud_points, cloud_offsets. The network estimates each frame's body (gender, height and mass from
the file when the network takes them), and `metrics.vpe_to_cloud` compares its camera-facing
vertices with the frame's cloud (1 cm voxel downsampled, in the mat frame). As released, the error
is averaged per participant and then over participants; the mean over frames is reported too.
Height and mass estimated from the body shape are compared with the participants' values.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from pressurepose.commands.netopts import recorded_options_label, with_inference_options
from pressurepose.commands.outputs import Written, flat_config
from pressurepose.errors import UserError
from pressurepose.eval.metrics import vpe_to_cloud
from pressurepose.eval.real_cloud import load_cloud_file
from pressurepose.files import atomic_write, write_text
from pressurepose.net.inputs import check_images
from pressurepose.net.model import GENDER_UNKNOWN, NetInputs
from pressurepose.train.checkpoint import load_network
from pressurepose.viz.real import plot_real_cloud


def run_evaluate_cloud(cfg) -> Written:
    """Report (real.md, real.json, real.png in cfg.out) of a RealEvalConfig with `data`."""
    arrays = load_cloud_file(cfg.data)
    images = torch.from_numpy(check_images(arrays["pressure_mmhg"], Path(cfg.data)))
    n = len(images)
    net = with_inference_options(load_network(cfg.model)[0], cfg.ik_steps, cfg.flip_test, cfg.shift_test)
    genders = arrays.get("gender")
    gender = torch.tensor(
        [{"female": 1.0, "male": 0.0}.get(str(g), GENDER_UNKNOWN) for g in genders]
        if genders is not None
        else [GENDER_UNKNOWN] * n
    )
    height = torch.tensor(arrays["height_m"], dtype=torch.float32) if "height_m" in arrays else None
    mass = torch.tensor(arrays["mass_kg"], dtype=torch.float32) if "mass_kg" in arrays else None
    if net.config.height_weight and (height is None or mass is None):
        raise UserError(f"{cfg.data}: this network takes height and mass; the file has no height_m / mass_kg")
    faces = net.faces
    t0 = time.perf_counter()
    vpes, est_h, est_m = [], [], []
    with torch.no_grad():
        for lo in range(0, n, cfg.batch):
            sl = slice(lo, lo + cfg.batch)
            inputs = NetInputs(
                pressure_mmhg=images[sl],
                gender=gender[sl],
                height_m=None if height is None else height[sl],
                mass_kg=None if mass is None else mass[sl],
            )
            est = net(inputs, mesh=True, maps=False)[-1]
            meas = net.body.measure(est.params.shape)
            est_h.append(meas.height_m)
            est_m.append(meas.mass_kg)
            for j, verts in enumerate(est.vertices):
                i = lo + j
                cloud = torch.from_numpy(
                    arrays["cloud_points"][arrays["cloud_offsets"][i] : arrays["cloud_offsets"][i + 1]]
                )
                vpes.append(
                    float(vpe_to_cloud(verts, faces, cloud.to(verts.dtype), camera=cfg.camera_m, voxel_m=cfg.voxel_m))
                )
    seconds = time.perf_counter() - t0
    est_h, est_m = torch.cat(est_h).tolist(), torch.cat(est_m).tolist()
    rows = []
    for i in range(n):
        r = {
            "subject": str(arrays["subject"][i]),
            "vpe_m": vpes[i],
            "estimated_height_m": est_h[i],
            "estimated_mass_kg": est_m[i],
        }
        for k in ("pose_set", "pose_type", "index", "height_m", "mass_kg"):
            if k in arrays:
                v = arrays[k][i]
                r[k] = v.item() if hasattr(v, "item") else v
        rows.append(r)
    by_subject = {}
    for s in sorted({r["subject"] for r in rows}):
        sel = [r for r in rows if r["subject"] == s]
        e = {"frames": len(sel), "vpe_m": float(np.mean([r["vpe_m"] for r in sel]))}
        if "height_m" in sel[0]:
            e["height_error_m"] = float(np.mean([r["estimated_height_m"] - r["height_m"] for r in sel]))
            e["mass_error_kg"] = float(np.mean([r["estimated_mass_kg"] - r["mass_kg"] for r in sel]))
        by_subject[s] = e
    overall = {
        "participants": len(by_subject),
        "vpe_m": float(np.mean([e["vpe_m"] for e in by_subject.values()])),
        "vpe_m_over_frames": float(np.mean(vpes)),
    }
    if "height_m" in arrays:
        overall["height_mae_m"] = float(np.mean([abs(r["estimated_height_m"] - r["height_m"]) for r in rows]))
        overall["mass_mae_kg"] = float(np.mean([abs(r["estimated_mass_kg"] - r["mass_kg"]) for r in rows]))
    cfg.out.mkdir(parents=True, exist_ok=True)
    record = {
        "command": "evaluate-real",
        "kind": "point-cloud",
        "config": flat_config(cfg),
        "frames": n,
        "seconds": round(seconds, 2),
        "overall": overall,
        "by_participant": by_subject,
        "per_frame": rows,
    }
    paths = {"figure": atomic_write(cfg.out / "real.png", lambda tmp: plot_real_cloud(tmp, rows, by_subject))}
    paths["json"] = write_text(cfg.out / "real.json", json.dumps(record, indent=1))
    paths["markdown"] = write_text(cfg.out / "real.md", _cloud_markdown(record))
    return Written(paths, record)


def _cloud_markdown(r: dict) -> str:
    o = r["overall"]
    lines = [
        f"# {r['config']['model']}{recorded_options_label(r['config'])} on {r['config']['data']} ({r['frames']} frames, {o['participants']} participants)",
        "",
        f"3DVPE against the point clouds: **{o['vpe_m'] * 100:.2f} cm** (mean of the participants' means, as "
        f"released; {o['vpe_m_over_frames'] * 100:.2f} cm over frames).",
        "",
    ]
    if "height_mae_m" in o:
        lines += [f"Height MAE {o['height_mae_m'] * 100:.1f} cm, mass MAE {o['mass_mae_kg']:.1f} kg.", ""]
    has_hw = all("height_error_m" in e for e in r["by_participant"].values())
    head = "| participant | frames | 3DVPE (cm) |" + (" height error (cm) | mass error (kg) |" if has_hw else "")
    lines += [head, "| --- | --- | --- |" + (" --- | --- |" if has_hw else "")]
    for s, e in r["by_participant"].items():
        line = f"| {s} | {e['frames']} | {e['vpe_m'] * 100:.2f} |"
        if has_hw:
            line += f" {e['height_error_m'] * 100:+.1f} | {e['mass_error_kg']:+.1f} |"
        lines.append(line)
    lines += ["", "![real](real.png)", ""]
    return "\n".join(lines)


__all__ = ["run_evaluate_cloud"]
