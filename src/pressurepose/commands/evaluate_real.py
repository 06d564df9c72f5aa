"""`pressurepose evaluate-real`: estimation on real recordings: PmatData experiment II
(issue 9, seed A.8); with `--data`, an imported real set with point clouds (3DVPE per
participant).

Real frames have no 3D labels, but PmatData knows each subject's posture (supine / left / right lateral),
height and weight. The command runs a trained network on the frames and reports, per mattress (air,
sponge): posture accuracy - the posture read from the estimated root orientation (`eval.real.posture_of`)
- and the estimated height and mass against the subjects' values, with a confusion matrix and scatter
plots; for a heatmap network, how sharply its heatmaps pin the head and torso (`eval.real.spread_summary`).

Frames are normalised as the data's README says (empty level removed, noise threshold, summed force = the
subject's weight, mmHg; `data.pmatdata.normalise`), clipped at 100 mmHg as the sensor model does. Gender
is unknown to PmatData (given as 0.5); height and weight are given when the network takes them.

With `--data FILE.npz` (written by `import-pressurepose-real`, or any .npz with
pressure_mmhg, subject, cloud_points, cloud_offsets): the network estimates each frame's body
(gender, height and mass from the file when the network takes them), and
`metrics.vpe_to_cloud` compares its camera-facing vertices with the frame's cloud (1 cm voxel
downsampled, in the mat frame). As released, the error is averaged per participant and then
over participants; the mean over frames is reported too. Height and mass estimated from the
body shape are compared with the participants' values.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch

from pressurepose.body.joints import TRUNK_JOINTS
from pressurepose.commands.netopts import options_label, with_inference_options
from pressurepose.commands.outputs import Written, flat_config
from pressurepose.data.pmatdata import load_images, load_index, repeated_frames
from pressurepose.errors import UserError
from pressurepose.eval.metrics import CAMERA_M, vpe_to_cloud
from pressurepose.eval.real import (
    GROUP_POSTURE,
    POSTURES,
    height_by_load_ends,
    load_ends,
    load_ends_table,
    read_bodies,
    spread_lines,
    spread_summary,
    subject_interval,
)
from pressurepose.eval.real_cloud import load_cloud_file
from pressurepose.files import atomic_write, write_text
from pressurepose.net.inputs import check_images
from pressurepose.net.model import GENDER_UNKNOWN, NetInputs
from pressurepose.samples import resolve_pmatdata
from pressurepose.train.checkpoint import load_network
from pressurepose.viz.real import plot_real, plot_real_cloud


@dataclasses.dataclass(frozen=True)
class RealEvalConfig:
    """Run a trained network on PmatData experiment II and compare with what is known."""

    model: Path = Path("default")
    """Run folder of `pressurepose train`; "default" = the packaged model."""
    pmatdata: Path = Path("pmatdata")
    """PmatData folder (index.csv, experiment-ii/); "pmatdata" = the packaged copy of experiment II."""
    out: Path = Path("out/evaluate-real")
    """Report folder: real.md, real.json, real.png."""
    groups: str = "BCD"
    """PmatData posture groups: B supine, C right, D left (flat bed)."""
    threshold: float = 20.0
    """Raw noise threshold of the frames' normalisation (data README)."""
    batch: int = 32
    ik_steps: int | None = None
    """Arch heatmap: IK steps instead of the model's own (predict --ik-steps)."""
    flip_test: bool = False
    """Arch heatmap: localise on the mirror image too and average (predict --flip-test)."""
    data: Path | None = None
    """An imported real-data .npz with point clouds (`import-pressurepose-real`): instead of
    PmatData, report 3DVPE against the clouds per participant and height / mass errors."""
    voxel_m: float = 0.01
    """Voxel size of the clouds' downsampling before 3DVPE (--data; 1 cm as released)."""
    camera_m: tuple[float, float, float] = CAMERA_M
    """Camera position in the mat frame for the camera-facing vertices (--data; metrics.CAMERA_M)."""


def run_evaluate_real(cfg: RealEvalConfig) -> Written:
    if cfg.data is not None:
        if not cfg.voxel_m > 0:
            raise UserError(f"voxel size must be > 0 m, got {cfg.voxel_m}")
        return run_evaluate_cloud(cfg)
    cfg = dataclasses.replace(cfg, pmatdata=resolve_pmatdata(cfg.pmatdata))

    groups = [g for g in cfg.groups if g in GROUP_POSTURE]
    if not groups or len(groups) != len(cfg.groups):
        raise UserError(
            f"groups must be letters of {''.join(GROUP_POSTURE)} (B supine, C right, D left), got {cfg.groups!r}"
        )
    records = [r for r in load_index(cfg.pmatdata) if r.group in groups]
    if not records:
        raise UserError(f"no PmatData frames of groups {cfg.groups} under {cfg.pmatdata}")
    # A frame that repeats another record's byte for byte is left out (not a new measurement).
    repeats = repeated_frames(records)
    left_out = {id(r) for r, _ in repeats}
    records = [r for r in records if id(r) not in left_out]
    net = with_inference_options(load_network(cfg.model)[0], cfg.ik_steps, cfg.flip_test)
    images = torch.from_numpy(load_images(records, cfg.threshold))
    heights = [r.height_cm / 100 for r in records]
    masses = [r.weight_kg for r in records]
    t0 = time.perf_counter()
    read = read_bodies(net, images, torch.tensor(heights), torch.tensor(masses), cfg.batch)
    seconds = time.perf_counter() - t0
    predicted = read.postures
    ends = load_ends(images.numpy())
    trunk = None if read.spread_m is None else read.spread_m[:, list(TRUNK_JOINTS)]  # heatmap networks
    rows = [
        {
            "file": _rel(r, cfg),
            "subject": r.subject,
            "mattress": r.mattress,
            "variant": f"{r.group}{r.index}",
            "posture": GROUP_POSTURE[r.group],
            "estimated_posture": e,
            **({} if read.readout is None else {"readout_posture": read.readout[i]}),
            "roll_deg": float(a),
            "height_m": r.height_cm / 100,
            "estimated_height_m": float(h),
            "mass_kg": r.weight_kg,
            "estimated_mass_kg": float(m),
            "load_reaches": ends[i],
            **({} if trunk is None else {"trunk_spread_m": float(trunk[i].median())}),
        }
        for i, (r, e, a, h, m) in enumerate(zip(records, predicted, read.roll_deg, read.height_m, read.mass_kg))
    ]
    summary = {}
    for mattress in sorted({r["mattress"] for r in rows}):
        sel = [r for r in rows if r["mattress"] == mattress]
        confusion = {
            t: {e: sum(1 for r in sel if r["posture"] == t and r["estimated_posture"] == e) for e in POSTURES}
            for t in ("supine", "left", "right")
        }
        height_error = np.array([r["estimated_height_m"] - r["height_m"] for r in sel])
        correct = [float(r["posture"] == r["estimated_posture"]) for r in sel]
        subjects = [r["subject"] for r in sel]
        summary[mattress] = {
            "frames": len(sel),
            "subjects": len(set(subjects)),
            "posture_accuracy": sum(correct) / len(sel),
            # 95% intervals resampling whole subjects (eval.real.subject_interval): what another
            # 8 people on the same mattress could give, the scale a difference must beat
            "posture_accuracy_ci": subject_interval(correct, subjects, np.mean),
            "confusion": confusion,
            "height_mae_m": float(np.abs(height_error).mean()),
            "height_median_abs_m": float(np.median(np.abs(height_error))),
            "height_median_signed_m": float(np.median(height_error)),
            "height_median_signed_ci_m": subject_interval(height_error, subjects, np.median),
            "mass_mae_kg": float(np.mean([abs(r["estimated_mass_kg"] - r["mass_kg"]) for r in sel])),
            # The height error by whether the frame's load reaches the mat's ends (`load_ends`).
            "height_by_load_ends": height_by_load_ends(height_error, [r["load_reaches"] for r in sel]),
        }
        if trunk is not None:  # how sharply the heatmaps pin the head and torso
            summary[mattress]["trunk_spread"] = spread_summary(trunk[[r["mattress"] == mattress for r in rows]])
        if read.readout is not None:
            summary[mattress]["readout_accuracy"] = sum(r["posture"] == r["readout_posture"] for r in sel) / len(sel)
    variants = {}
    for r in rows:  # per posture variant (B1-B10, C1-C3, D1-D3), both mattresses
        v = variants.setdefault(r["variant"], {"posture": r["posture"], "frames": 0, "estimated": {}})
        v["frames"] += 1
        v["estimated"][r["estimated_posture"]] = v["estimated"].get(r["estimated_posture"], 0) + 1
    cfg.out.mkdir(parents=True, exist_ok=True)
    record = {
        "command": "evaluate-real",
        "config": flat_config(cfg),
        "frames": len(rows),
        "repeats_left_out": [{"file": _rel(r, cfg), "same_as": _rel(o, cfg)} for r, o in repeats],
        "seconds": round(seconds, 2),
        "by_mattress": summary,
        "by_variant": dict(sorted(variants.items(), key=lambda kv: (kv[0][0], int(kv[0][1:])))),
        "per_frame": rows,
    }
    paths = {"figure": atomic_write(cfg.out / "real.png", lambda tmp: plot_real(tmp, rows, summary))}
    paths["json"] = write_text(cfg.out / "real.json", json.dumps(record, indent=1))
    paths["markdown"] = write_text(cfg.out / "real.md", _markdown(record))
    return Written(paths, record)


def _rel(record, cfg: RealEvalConfig) -> str:
    return str(record.path.relative_to(Path(cfg.pmatdata)))


def _markdown(r: dict) -> str:
    left_out = len(r["repeats_left_out"])
    note = f"{left_out} frame(s) left out: each repeats another record's file byte for byte (`repeats_left_out`)"
    lines = [
        f"# {r['config']['model']}{options_label(r['config']['ik_steps'], r['config']['flip_test'])} on PmatData experiment II ({r['frames']} frames, groups {r['config']['groups']})",
        "",
        *([note, ""] if left_out else []),
        "| mattress | frames (subjects) | posture accuracy [95% CI] | height MAE (cm) "
        "| height error median: absolute / signed [95% CI] (cm) | mass MAE (kg) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for name, s in r["by_mattress"].items():
        lines.append(
            f"| {name} | {s['frames']} ({s['subjects']}) | {s['posture_accuracy'] * 100:.1f}% "
            f"[{s['posture_accuracy_ci'][0] * 100:.1f}, {s['posture_accuracy_ci'][1] * 100:.1f}] | "
            f"{s['height_mae_m'] * 100:.1f} | {s['height_median_abs_m'] * 100:.1f} / "
            f"{s['height_median_signed_m'] * 100:+.1f} [{s['height_median_signed_ci_m'][0] * 100:+.1f}, "
            f"{s['height_median_signed_ci_m'][1] * 100:+.1f}] | {s['mass_mae_kg']:.1f} |"
        )
    lines += spread_lines({k: s["trunk_spread"] for k, s in r["by_mattress"].items() if "trunk_spread" in s})
    for name, s in r["by_mattress"].items():
        lines += [
            "",
            f"Confusion ({name}; rows: true, columns: estimated)",
            "",
            "| | " + " | ".join(POSTURES) + " |",
            "| --- |" + " --- |" * len(POSTURES),
        ]
        for t, row in s["confusion"].items():
            lines.append(f"| {t} | " + " | ".join(str(row[e]) for e in POSTURES) + " |")
    lines += [
        "",
        "Height error (median signed, cm; frames) by where the load lies: a frame whose load (the rows "
        "holding >= 0.2% of its force) reaches the mat's head or foot row may run on beyond the mat",
        "",
        *load_ends_table({name: s["height_by_load_ends"] for name, s in r["by_mattress"].items()}, "mattress"),
    ]
    lines += [
        "",
        "Per posture variant (both mattresses; PmatData's groups: B supine variants, C right, D left)",
        "",
        "| variant | posture | frames | correct | " + " | ".join(f"read {e}" for e in POSTURES) + " |",
        "| --- | --- | --- | --- |" + " --- |" * len(POSTURES),
    ]
    for name, v in r["by_variant"].items():
        counts = [v["estimated"].get(e, 0) for e in POSTURES]
        lines.append(
            f"| {name} | {v['posture']} | {v['frames']} | {v['estimated'].get(v['posture'], 0)} | "
            + " | ".join(map(str, counts))
            + " |"
        )
    readout = {k: s["readout_accuracy"] for k, s in r["by_mattress"].items() if "readout_accuracy" in s}
    if readout:
        lines += [
            "",
            "The network's posture readout (net.posture; the posture above is its body's): "
            + ", ".join(f"{k} {v * 100:.1f}%" for k, v in readout.items()),
        ]
    lines += [
        "",
        "Intervals: 95%, resampling whole subjects with replacement (a subject's frames are not "
        "independent); a difference between two networks smaller than them is not shown by these frames.",
        "",
        "![real](real.png)",
        "",
    ]
    return "\n".join(lines)


def run_evaluate_cloud(cfg) -> Written:
    """Report (real.md, real.json, real.png in cfg.out) of a RealEvalConfig with `data`."""
    arrays = load_cloud_file(cfg.data)
    images = torch.from_numpy(check_images(arrays["pressure_mmhg"], Path(cfg.data)))
    n = len(images)
    net = with_inference_options(load_network(cfg.model)[0], cfg.ik_steps, cfg.flip_test)
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
        f"# {r['config']['model']}{options_label(r['config']['ik_steps'], r['config']['flip_test'])} on {r['config']['data']} ({r['frames']} frames, {o['participants']} participants)",
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


def evaluate_real(cfg: RealEvalConfig) -> None:
    """Run a trained network on PmatData's real recordings: posture accuracy from the estimated
    root, estimated height and mass against the subjects', per mattress (real.md, real.png);
    with --data FILE.npz (import-pressurepose-real), 3DVPE against its point clouds per
    participant."""
    written = run_evaluate_real(cfg)
    record = written.record
    if record.get("kind") == "point-cloud":
        o = record["overall"]
        extra = (
            f", height MAE {o['height_mae_m'] * 100:.1f} cm, mass MAE {o['mass_mae_kg']:.1f} kg"
            if "height_mae_m" in o
            else ""
        )
        print(
            f"{record['frames']} frames of {o['participants']} participants: 3DVPE {o['vpe_m'] * 100:.2f} cm"
            f"{extra} -> {written['markdown']}"
        )
        return
    parts = [
        f"{k}: posture {v['posture_accuracy'] * 100:.0f}%"
        + (f" (readout {v['readout_accuracy'] * 100:.0f}%)" if "readout_accuracy" in v else "")
        + f", height MAE {v['height_mae_m'] * 100:.1f} cm, mass MAE {v['mass_mae_kg']:.1f} kg"
        for k, v in record["by_mattress"].items()
    ]
    print(f"{record['frames']} frames; " + "; ".join(parts) + f" -> {written['markdown']}")


__all__ = ["RealEvalConfig", "evaluate_real", "run_evaluate_real"]
