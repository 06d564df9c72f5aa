"""`pressurepose evaluate-real`: estimation on real recordings: PmatData experiment II
(issue 9, seed A.8); with `--data`, an imported real set with point clouds (3DVPE per
participant).

Real frames have no 3D labels, but PmatData knows each subject's posture (supine / left / right lateral),
height and weight. The command runs a trained network on the frames and reports, per mattress (air,
sponge): posture accuracy - the posture read from the estimated root orientation (`eval.real.posture_of`)
- and the estimated height and mass against the subjects' values, with a confusion matrix and scatter
plots; for a heatmap network, how sharply its heatmaps pin the head and torso (`eval.real.spread_summary`).
Group E's tilted bodies (20 or 40 deg on wedges or a pillow) are judged apart, by the roll read
against the documented one (`eval.real.tilt_summary`: real.md's tilt table, tilt.png); group F's
supine bodies on a bed whose head is raised 0-60 deg (outside the network's flat-bed scope) apart
too: the share read supine and the height error, per mattress and per angle.

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
from pressurepose.commands.evaluate_cloud import run_evaluate_cloud
from pressurepose.commands.evaluate_real_tables import flat_lines, raised_lines, tilt_lines
from pressurepose.commands.netopts import recorded_options_label, with_inference_options
from pressurepose.commands.outputs import Written, flat_config
from pressurepose.data.pmatdata import load_images, load_index, repeated_frames
from pressurepose.errors import UserError
from pressurepose.eval.metrics import CAMERA_M
from pressurepose.eval.real import (
    GROUP_POSTURE,
    POSTURES,
    RAISED_GROUPS,
    RAISED_POSTURE,
    TILTED_GROUPS,
    documented_roll,
    height_by_load_ends,
    load_ends,
    read_bodies,
    spread_summary,
    subject_interval,
    tilt_summary,
)
from pressurepose.files import atomic_write, write_text
from pressurepose.samples import resolve_pmatdata
from pressurepose.train.checkpoint import load_network
from pressurepose.viz.real import plot_real, plot_tilt


@dataclasses.dataclass(frozen=True)
class RealEvalConfig:
    """Run a trained network on PmatData experiment II and compare with what is known."""

    model: Path = Path("default")
    """Run folder of `pressurepose train`; "default" = the packaged model."""
    pmatdata: Path = Path("pmatdata")
    """PmatData folder (index.csv, experiment-ii/); "pmatdata" = the packaged copy of experiment II."""
    out: Path = Path("out/evaluate-real")
    """Report folder: real.md, real.json, real.png (groups B-D), tilt.png (group E)."""
    groups: str = "BCDEF"
    """PmatData posture groups: B supine, C right, D left (flat bed: the posture table); E lateral
    on wedges or a pillow at 20 or 40 deg of roll (the tilt table: the roll read against it); F
    supine, the head of the bed raised 0-60 deg (the raised-bed table)."""
    threshold: float = 20.0
    """Raw noise threshold of the frames' normalisation (data README)."""
    batch: int = 32
    ik_steps: int | None = None
    """Arch heatmap: IK steps instead of the model's own (predict --ik-steps)."""
    flip_test: bool = False
    """Arch heatmap: localise on the mirror image too and average (predict --flip-test)."""
    shift_test: bool = False
    """Arch heatmap: also read the image moved +-2 and +-4 rows along the bed and average (predict --shift-test)."""
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

    known = "".join(GROUP_POSTURE) + TILTED_GROUPS + RAISED_GROUPS
    if not cfg.groups or any(g not in known for g in cfg.groups):
        raise UserError(
            f"groups must be letters of {known} (B supine, C right, D left, E tilted on wedges, "
            f"F head of the bed raised), got {cfg.groups!r}"
        )
    records = [r for r in load_index(cfg.pmatdata) if r.group in cfg.groups]
    if not records:
        raise UserError(f"no PmatData frames of groups {cfg.groups} under {cfg.pmatdata}")
    # A frame that repeats another record's byte for byte is left out (not a new measurement).
    repeats = repeated_frames(records)
    left_out = {id(r) for r, _ in repeats}
    records = [r for r in records if id(r) not in left_out]
    flat = [r for r in records if r.group in GROUP_POSTURE]
    tilted = [r for r in records if r.group in TILTED_GROUPS]
    raised = [r for r in records if r.group in RAISED_GROUPS]
    documented = [_documented(r, cfg) for r in tilted]  # a row without its roll stops the run before the network
    for r in raised:  # likewise a raised bed's row that is not a supine body on a bed raised 0-90 deg
        _check_raised(r, cfg)
    net = with_inference_options(load_network(cfg.model)[0], cfg.ik_steps, cfg.flip_test, cfg.shift_test)
    t0 = time.perf_counter()
    rows, summary, variants = _flat_report(net, flat, cfg) if flat else ([], {}, {})
    tilt = _tilted_report(net, tilted, documented, cfg) if tilted else None
    bed = _raised_report(net, raised, cfg) if raised else None
    seconds = time.perf_counter() - t0
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
        **({} if tilt is None else {"tilted": tilt}),
        **({} if bed is None else {"raised": bed}),
    }
    paths = {}
    figures = {"figure": ("real.png", rows, lambda tmp: plot_real(tmp, rows, summary))}
    figures["tilt_figure"] = ("tilt.png", tilt, lambda tmp: plot_tilt(tmp, tilt["per_frame"]))
    for key, (name, present, plot) in figures.items():
        if present:
            paths[key] = atomic_write(cfg.out / name, plot)
        else:  # an earlier run's figure would not show this report's frames
            (cfg.out / name).unlink(missing_ok=True)
    paths["json"] = write_text(cfg.out / "real.json", json.dumps(record, indent=1))
    paths["markdown"] = write_text(cfg.out / "real.md", _markdown(record))
    return Written(paths, record)


def _flat_report(net, records: list, cfg: RealEvalConfig) -> tuple[list[dict], dict, dict]:
    """Per-frame rows, per-mattress summary and per-variant counts of the flat groups (B-D), or of
    group F's raised beds (their posture supine, each row with its bed's angle)."""
    images = torch.from_numpy(load_images(records, cfg.threshold))
    heights = [r.height_cm / 100 for r in records]
    masses = [r.weight_kg for r in records]
    read = read_bodies(net, images, torch.tensor(heights), torch.tensor(masses), cfg.batch)
    predicted = read.postures
    ends = load_ends(images.numpy())
    trunk = None if read.spread_m is None else read.spread_m[:, list(TRUNK_JOINTS)]  # heatmap networks
    rows = [
        {
            "file": _rel(r, cfg),
            "subject": r.subject,
            "mattress": r.mattress,
            "variant": f"{r.group}{r.index}",
            "posture": GROUP_POSTURE.get(r.group, RAISED_POSTURE),
            **({"bed_incline_deg": r.bed_incline_deg} if r.group in RAISED_GROUPS else {}),
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
    return rows, summary, variants


def _raised_report(net, records: list, cfg: RealEvalConfig) -> dict:
    """Group F's frames: the flat report's rows and per-mattress summary (read supine = right),
    and per bed angle and mattress the postures read and the median signed height error."""
    rows, summary, _ = _flat_report(net, records, cfg)
    by_angle = []
    for key in sorted({(r["bed_incline_deg"], r["variant"], r["mattress"]) for r in rows}):
        sel = [r for r in rows if (r["bed_incline_deg"], r["variant"], r["mattress"]) == key]
        estimated = {e: sum(r["estimated_posture"] == e for r in sel) for e in POSTURES}
        error = [r["estimated_height_m"] - r["height_m"] for r in sel]
        by_angle.append(
            {
                "bed_incline_deg": key[0],
                "variant": key[1],
                "mattress": key[2],
                "frames": len(sel),
                "estimated": {e: n for e, n in estimated.items() if n},
                "height_median_signed_m": float(np.median(error)),
            }
        )
    return {"frames": len(rows), "by_mattress": summary, "by_angle": by_angle, "per_frame": rows}


def _tilted_report(net, records: list, documented: list[float], cfg: RealEvalConfig) -> dict:
    """Group E's frames against their documented rolls (`documented`, one per record;
    `eval.real.tilt_summary`): per mattress, per variant and mattress, and per frame."""
    images = torch.from_numpy(load_images(records, cfg.threshold))
    heights = torch.tensor([r.height_cm / 100 for r in records])
    read = read_bodies(net, images, heights, torch.tensor([r.weight_kg for r in records]), cfg.batch)
    rows = [
        {
            "file": _rel(r, cfg),
            "subject": r.subject,
            "mattress": r.mattress,
            "variant": f"{r.group}{r.index}",
            "posture": r.posture,
            "documented_roll_deg": d,
            "roll_deg": float(a),
            "estimated_posture": e,
        }
        for r, d, a, e in zip(records, documented, read.roll_deg, read.postures)
    ]

    def summary(sel: list[dict]) -> dict:
        doc, got = [r["documented_roll_deg"] for r in sel], [r["roll_deg"] for r in sel]
        return tilt_summary(doc, got, [r["subject"] for r in sel])

    mattresses = sorted({r["mattress"] for r in rows})
    keys = sorted({(r["variant"], r["mattress"]) for r in rows}, key=lambda k: (int(k[0][1:]), k[1]))
    by_variant = {}
    for v, m in keys:
        sel = [r for r in rows if r["variant"] == v and r["mattress"] == m]
        by_variant[f"{v} {m}"] = {"documented_roll_deg": sel[0]["documented_roll_deg"], **summary(sel)}
    return {
        "frames": len(rows),
        "by_mattress": {m: summary([r for r in rows if r["mattress"] == m]) for m in mattresses},
        "by_variant": by_variant,
        "per_frame": rows,
    }


def _documented(record, cfg: RealEvalConfig) -> float:
    """A group E record's documented roll (+ right), or a one-line error naming its index row."""
    try:
        return documented_roll(record.posture, record.body_roll_deg)
    except ValueError as exc:
        raise UserError(f"{cfg.pmatdata / 'index.csv'}: {_rel(record, cfg)}: {exc}") from None


def _check_raised(record, cfg: RealEvalConfig) -> None:
    """A group F record is a supine body on a bed raised 0 to < 90 deg, or a one-line error."""
    angle = record.bed_incline_deg
    if not (np.isfinite(angle) and 0 <= angle < 90) or record.posture != RAISED_POSTURE:
        raise UserError(
            f"{cfg.pmatdata / 'index.csv'}: {_rel(record, cfg)}: group F is supine on a bed raised 0 to < 90 deg; "
            f"this row says {record.posture!r} at {angle} deg"
        )


def _rel(record, cfg: RealEvalConfig) -> str:
    return str(record.path.relative_to(Path(cfg.pmatdata)))


def _counts(r: dict, flat: str) -> list[str]:
    """How many frames a report read: the flat groups' (unless none while others were read), then
    the tilted and raised ones'."""
    others = [f"{r[k]['frames']} {k}" for k in ("tilted", "raised") if k in r]
    return ([f"{r['frames']} frames{flat}"] if r["frames"] or not others else []) + others


def _markdown(r: dict) -> str:
    left_out = len(r["repeats_left_out"])
    note = f"{left_out} frame(s) left out (all groups): each repeats another record's file byte for byte (`repeats_left_out`)"
    tilted, raised = r.get("tilted"), r.get("raised")
    counts = ", ".join(_counts(r, " flat" if tilted or raised else ""))
    lines = [
        f"# {r['config']['model']}{recorded_options_label(r['config'])} on PmatData experiment II ({counts}, groups {r['config']['groups']})",
        "",
        *([note, ""] if left_out else []),
    ]
    if r["by_mattress"]:
        lines += flat_lines(r)
    if tilted:
        lines += tilt_lines(tilted)
    if raised:
        lines += raised_lines(raised)
    lines += [
        "",
        "Intervals: 95%, resampling whole subjects with replacement (a subject's frames are not "
        "independent); a difference between two networks smaller than them is not shown by these frames.",
    ]
    lines += [f"\n![{name}]({name}.png)" for name, part in (("real", r["by_mattress"]), ("tilt", tilted)) if part]
    return "\n".join(lines + [""])


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
    if "tilted" in record:
        parts += [
            f"tilted ({k}): {v['share_turned'] * 100:.0f}% turned toward their side, roll error {v['abs_error_median_deg']:.0f} deg"
            for k, v in record["tilted"]["by_mattress"].items()
        ]
    if "raised" in record:
        parts += [
            f"raised beds ({k}): {v['posture_accuracy'] * 100:.0f}% read supine, height error "
            f"{v['height_median_signed_m'] * 100:+.1f} cm"
            for k, v in record["raised"]["by_mattress"].items()
        ]
    print(" + ".join(_counts(record, "")) + "; " + "; ".join(parts) + f" -> {written['markdown']}")


__all__ = ["RealEvalConfig", "evaluate_real", "run_evaluate_real"]
