"""Estimation on real recordings: PmatData experiment II (issue 9, seed A.8); with `data`, an
imported real set with point clouds (3DVPE per participant, `eval.real_cloud`).

Real frames have no 3D labels, but PmatData knows each subject's posture (supine / left /
right lateral), height and weight. `pressurepose evaluate-real` runs a trained network on
the frames and reports, per mattress (air, sponge): posture accuracy - the posture read from
the estimated root orientation - and the estimated height and mass against the subjects'
values, with a confusion matrix and scatter plots.

Posture from the root: the heights of the body's left and front axes in the mat frame give
the roll about the bed's long axis, roll = atan2(left_z, front_z) whatever the yaw (0 supine,
-90 deg on the left side, +90 deg on the right, +-180 prone; the convention of `sampling` and `benchmarks/sim_realism.py`, which
put PmatData's group D "left" at roll -90 deg). |roll| <= 45 deg: supine; >= 135: prone;
otherwise left or right by its sign.

Frames are normalised as the data's README says (empty level removed, noise threshold, summed
force = the subject's weight, mmHg; `data.pmatdata.normalise`), clipped at 100 mmHg as the
sensor model does. Gender is unknown to PmatData (given as 0.5); height and weight are given
when the network takes them.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch

from pressurepose.errors import UserError
from pressurepose.eval.metrics import CAMERA_M
from pressurepose.files import atomic_write, save_figure

POSTURES = ("supine", "left", "right", "prone")
GROUP_POSTURE = {"B": "supine", "C": "right", "D": "left"}  # PmatData groups (README)


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
    data: Path | None = None
    """An imported real-data .npz with point clouds (`import-pressurepose-real`): instead of
    PmatData, report 3DVPE against the clouds per participant and height / mass errors."""
    voxel_m: float = 0.01
    """Voxel size of the clouds' downsampling before 3DVPE (--data; 1 cm as released)."""
    camera_m: tuple[float, float, float] = CAMERA_M
    """Camera position in the mat frame for the camera-facing vertices (--data; metrics.CAMERA_M)."""


def roll_deg(root_rotation: torch.Tensor) -> torch.Tensor:
    """(B,) roll (deg) of the body about the bed's long axis from root rotations (B, 3)."""
    from pressurepose.body.params import root_matrix

    R = root_matrix(root_rotation)  # body axes (x left, y head, z front) -> mat frame
    # Heights of the body's left and front axes: sin and cos of the roll, whatever the yaw.
    return torch.rad2deg(torch.atan2(R[:, 2, 0], R[:, 2, 2]))


def posture_of(roll: torch.Tensor) -> list[str]:
    out = []
    for r in roll.tolist():
        a = abs(r)
        out.append("supine" if a <= 45 else "prone" if a >= 135 else ("left" if r < 0 else "right"))
    return out


def run_evaluate_real(cfg: RealEvalConfig) -> dict[str, Path]:
    if cfg.data is not None:
        from pressurepose.eval.real_cloud import run_evaluate_cloud

        if not cfg.voxel_m > 0:
            raise UserError(f"voxel size must be > 0 m, got {cfg.voxel_m}")
        return run_evaluate_cloud(cfg)
    from pressurepose.data.pmatdata import load_images, load_index
    from pressurepose.net.model import GENDER_UNKNOWN, NetInputs
    from pressurepose.samples import resolve_pmatdata
    from pressurepose.train.checkpoint import load_network

    cfg = dataclasses.replace(cfg, pmatdata=resolve_pmatdata(cfg.pmatdata))

    groups = [g for g in cfg.groups if g in GROUP_POSTURE]
    if not groups or len(groups) != len(cfg.groups):
        raise UserError(f"groups must be letters of {''.join(GROUP_POSTURE)} (B supine, C right, D left), "
                         f"got {cfg.groups!r}")
    records = [r for r in load_index(cfg.pmatdata) if r.group in groups]
    if not records:
        raise UserError(f"no PmatData frames of groups {cfg.groups} under {cfg.pmatdata}")
    net, _ = load_network(cfg.model)
    images = torch.from_numpy(load_images(records, cfg.threshold))
    heights = [r.height_cm / 100 for r in records]
    masses = [r.weight_kg for r in records]
    t0 = time.perf_counter()
    rolls, est_h, est_m = [], [], []
    with torch.no_grad():
        for lo in range(0, len(records), cfg.batch):
            sl = slice(lo, lo + cfg.batch)
            p = images[sl]
            inputs = NetInputs(pressure_mmhg=p, gender=torch.full((p.shape[0],), GENDER_UNKNOWN),
                               height_m=torch.tensor(heights[sl]), mass_kg=torch.tensor(masses[sl]))
            est = net(inputs, mesh=False)[-1].params
            meas = net.body.measure(est.shape)
            rolls.append(roll_deg(est.root_rotation.to(torch.float64)))
            est_h.append(meas.height_m)
            est_m.append(meas.mass_kg)
    seconds = time.perf_counter() - t0
    roll = torch.cat(rolls)
    predicted = posture_of(roll)
    rows = [{"file": str(r.path.relative_to(Path(cfg.pmatdata))), "subject": r.subject, "mattress": r.mattress,
             "posture": GROUP_POSTURE[r.group], "estimated_posture": e, "roll_deg": float(a),
             "height_m": r.height_cm / 100, "estimated_height_m": float(h), "mass_kg": r.weight_kg,
             "estimated_mass_kg": float(m)}
            for r, e, a, h, m in zip(records, predicted, roll, torch.cat(est_h), torch.cat(est_m))]
    summary = {}
    for mattress in sorted({r["mattress"] for r in rows}):
        sel = [r for r in rows if r["mattress"] == mattress]
        confusion = {t: {e: sum(1 for r in sel if r["posture"] == t and r["estimated_posture"] == e) for e in POSTURES}
                     for t in ("supine", "left", "right")}
        summary[mattress] = {
            "frames": len(sel),
            "posture_accuracy": sum(r["posture"] == r["estimated_posture"] for r in sel) / len(sel),
            "confusion": confusion,
            "height_mae_m": float(np.mean([abs(r["estimated_height_m"] - r["height_m"]) for r in sel])),
            "mass_mae_kg": float(np.mean([abs(r["estimated_mass_kg"] - r["mass_kg"]) for r in sel])),
        }
    cfg.out.mkdir(parents=True, exist_ok=True)
    record = {"command": "evaluate-real",
              "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(cfg).items()},
              "frames": len(rows), "seconds": round(seconds, 2), "by_mattress": summary, "per_frame": rows}
    paths = {"figure": atomic_write(cfg.out / "real.png", lambda tmp: _plot(tmp, rows, summary))}
    paths["json"] = atomic_write(cfg.out / "real.json", lambda tmp: Path(tmp).write_text(json.dumps(record, indent=1)))
    paths["markdown"] = atomic_write(cfg.out / "real.md", lambda tmp: Path(tmp).write_text(_markdown(record)))
    return paths


def _markdown(r: dict) -> str:
    lines = [f"# {r['config']['model']} on PmatData experiment II ({r['frames']} frames, groups "
             f"{r['config']['groups']})", "",
             "| mattress | frames | posture accuracy | height MAE (cm) | mass MAE (kg) |", "| --- | --- | --- | --- | --- |"]
    for name, s in r["by_mattress"].items():
        lines.append(f"| {name} | {s['frames']} | {s['posture_accuracy'] * 100:.1f}% | {s['height_mae_m'] * 100:.1f} | "
                     f"{s['mass_mae_kg']:.1f} |")
    for name, s in r["by_mattress"].items():
        lines += ["", f"Confusion ({name}; rows: true, columns: estimated)", "",
                  "| | " + " | ".join(POSTURES) + " |", "| --- |" + " --- |" * len(POSTURES)]
        for t, row in s["confusion"].items():
            lines.append(f"| {t} | " + " | ".join(str(row[e]) for e in POSTURES) + " |")
    lines += ["", "![real](real.png)", ""]
    return "\n".join(lines)


def _plot(path, rows: list[dict], summary: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mattresses = list(summary)
    fig, axes = plt.subplots(len(mattresses), 3, figsize=(12, 3.6 * len(mattresses)), squeeze=False)
    for row, name in zip(axes, mattresses):
        sel = [r for r in rows if r["mattress"] == name]
        conf = np.array([[summary[name]["confusion"][t][e] for e in POSTURES] for t in ("supine", "left", "right")])
        row[0].imshow(conf, cmap="Blues")
        for (i, j), v in np.ndenumerate(conf):
            row[0].text(j, i, str(v), ha="center", va="center")
        row[0].set(xticks=range(len(POSTURES)), xticklabels=POSTURES, yticks=range(3),
                   yticklabels=["supine", "left", "right"], xlabel="estimated", ylabel="true",
                   title=f"{name}: posture {summary[name]['posture_accuracy'] * 100:.0f}%")
        for ax, key, unit in ((row[1], "height_m", "m"), (row[2], "mass_kg", "kg")):
            t = [r[key] for r in sel]
            e = [r[f"estimated_{key}"] for r in sel]
            ax.scatter(t, e, s=12)
            lo, hi = min(t + e), max(t + e)
            ax.plot([lo, hi], [lo, hi], "k--", lw=0.8)
            ax.set(xlabel=f"subject ({unit})", ylabel=f"estimated ({unit})", title=f"{name}: {key.split('_')[0]}")
    fig.tight_layout()
    save_figure(fig, path, format="png", dpi=80)
    plt.close(fig)


__all__ = ["RealEvalConfig", "posture_of", "roll_deg", "run_evaluate_real"]
