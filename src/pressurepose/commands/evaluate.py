"""`pressurepose evaluate`: a trained network on a dataset's test split -> a report.

Tables per partition and per gender in the layout of seed Table 5 with the seed's synthetic
3DVPE beside ours, overall numbers, the two baselines (`eval.evaluation`), and figures of the
best, median and worst cases plus a gallery of failures. Written as report.md, report.json,
PNGs and predictions.npz (the estimated body parameters, re-posed by `pressurepose view`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from pressurepose.body.params import BodyParams
from pressurepose.commands.netopts import recorded_options_label, with_inference_options
from pressurepose.commands.outputs import Written, flat_config
from pressurepose.errors import UserError
from pressurepose.eval import evaluation as E
from pressurepose.eval.evaluation import METRICS, PREDICTIONS, REGIONS, SEED_SYNTH_VPE_CM, write_predictions
from pressurepose.eval.real import height_by_load_ends, load_ends_table, spread_lines
from pressurepose.files import atomic_write, write_text
from pressurepose.train.checkpoint import load_network
from pressurepose.viz.evaluation import plot_cases


@dataclasses.dataclass(frozen=True)
class EvaluateConfig:
    """Evaluate a trained network (seed B.4, Table 5) on a dataset."""

    data: Path
    """Dataset folder (generated shards with manifest.json, or .npz files)."""
    model: Path = Path("default")
    """Run folder of `pressurepose train` (model.safetensors + config.json); "default" = the packaged model."""
    out: Path = Path("out/evaluate")
    """Report folder: report.md, report.json, cases.png, failures.png, predictions.npz."""
    split: str = "test"
    """Split evaluated (generated datasets); the train split feeds the baselines."""
    batch: int = 32
    limit: int | None = None
    """Evaluate at most this many samples (the first ones)."""
    train_data: Path | None = None
    """Training set for the baselines (default: the train split of --data when it is a
    generated dataset; .npz data have no split, so no baselines without this)."""
    baseline_samples: int = 4096
    """Training samples read for the baselines (mean body, nearest pressure image)."""
    failures: int = 8
    """Worst cases drawn in failures.png."""
    ik_steps: int | None = None
    """Arch heatmap: IK steps instead of the model's own (predict --ik-steps)."""
    flip_test: bool = False
    """Arch heatmap: localise on the mirror image too and average (predict --flip-test)."""
    shift_test: bool = False
    """Arch heatmap: also read the image moved +-2 and +-4 rows along the bed and average (predict --shift-test)."""


def run_evaluate(cfg: EvaluateConfig) -> Written:
    if cfg.batch < 1:
        raise UserError(f"batch must be >= 1, got {cfg.batch}")
    net = with_inference_options(load_network(cfg.model)[0], cfg.ik_steps, cfg.flip_test, cfg.shift_test)
    test = E.open_split(cfg.data, cfg.split)
    n = len(test) if cfg.limit is None else min(cfg.limit, len(test))
    if n == 0:
        raise UserError(f"{cfg.data} has no {cfg.split} samples to evaluate")
    E.check_backend(net, test, cfg.data)
    train = None
    if cfg.train_data is not None:
        train = E.open_split(cfg.train_data, "train")
    elif (cfg.data / "manifest.json").is_file():
        train = E.open_split(cfg.data, "train")
    if train is not None and len(train) == 0:
        train = None
    t0 = time.perf_counter()
    columns = (
        TextColumn("evaluating"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[rate]}"),
        TimeRemainingColumn(),
    )
    with Progress(*columns, transient=True) as bar:
        task = bar.add_task("eval", total=n, rate="")
        result = E.evaluate_network(
            net,
            test,
            n,
            cfg.batch,
            train,
            cfg.baseline_samples,
            on_batch=lambda done: bar.update(
                task, completed=done, rate=f"{done / (time.perf_counter() - t0):.1f} img/s"
            ),
        )
    return _write_report(
        cfg,
        result.rows,
        result.baselines,
        lambda i: E.case_meshes(net.body, test, result.estimates, i),
        net.body.faces.numpy(),
        result.seconds,
        result.estimates,
        result.trunk_spread,
    )


def _summary(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=np.float64)
    return {"mean": float(a.mean()), "median": float(np.median(a)), "p90": float(np.quantile(a, 0.9))}


def mean_interval(values: np.ndarray, floor: float | None = None) -> list[float] | None:
    """A 95% interval for the mean of per-sample values: the mean +- t standard errors (the
    sample standard deviation over sqrt(n); t Student's 97.5% quantile with n - 1 degrees of
    freedom, 1.96 for large n, so the small groups of the tiny presets are not overstated);
    None for fewer than 2 values; `floor` clips its lower end (a mean that cannot be below it, as
    an error's cannot be below 0). It covers our own sampling noise only, not the seed's."""
    from scipy.stats import t as student_t

    values = np.asarray(values, dtype=np.float64)
    if values.size < 2:
        return None
    half = float(student_t.ppf(0.975, values.size - 1)) * values.std(ddof=1) / math.sqrt(values.size)
    lo = float(values.mean() - half)
    return [lo if floor is None else max(lo, float(floor)), float(values.mean() + half)]


def _group_table(rows: dict, base: dict, key: str) -> list[dict]:
    labels = np.asarray(rows[key])
    out = []
    for g in sorted(set(labels.tolist())):
        sel = labels == g
        entry = {key: g, "count": int(sel.sum())}
        for m in METRICS:
            entry[m] = float(np.asarray(rows[m])[sel].mean())
        entry["vpe_m_ci95"] = mean_interval(np.asarray(rows["vpe_m"])[sel], floor=0.0)
        for name, vals in base.items():
            if vals:
                entry[f"baseline_{name}_vpe_m"] = float(np.asarray(vals)[sel].mean())
        entry["seed_synth_vpe_cm"] = SEED_SYNTH_VPE_CM.get(g)
        out.append(entry)
    return out


def _write_report(
    cfg: EvaluateConfig,
    rows: dict,
    base: dict,
    case,
    faces: np.ndarray,
    seconds: float,
    estimates: BodyParams,
    trunk_spread: dict | None = None,
) -> Written:
    cfg.out.mkdir(parents=True, exist_ok=True)
    vpe = np.asarray(rows["vpe_m"])
    order = np.argsort(vpe)
    n = len(vpe)
    picks = {"best": int(order[0]), "median": int(order[n // 2]), "worst": int(order[-1])}
    failures = [int(i) for i in order[::-1][: cfg.failures]]
    record = {
        "command": "evaluate",
        "config": flat_config(cfg),
        "count": n,
        "seconds": round(seconds, 2),
        "overall": {m: _summary(rows[m]) for m in METRICS},
        "regions_m": {r: _summary(rows[f"joints_{r}_m"]) for r in REGIONS},
        "baselines_vpe_m": {k: _summary(v) for k, v in base.items() if v},
        "by_partition": _group_table(rows, base, "partition"),
        "by_gender": _group_table(rows, base, "gender"),
        # the signed height error by whether the image's load reaches the mat's ends, as
        # evaluate-real reports it for real frames: a reading of the body or of where it lies
        "height_by_load_ends": height_by_load_ends(rows["height_signed_m"], rows["load_ends"]),
        "trunk_spread": trunk_spread,  # heatmap networks: how sharply the heatmaps pin the head and torso
        "cases": {k: {"index": i, "vpe_m": float(vpe[i])} for k, i in picks.items()},
        "failures": [
            {"index": i, "vpe_m": float(vpe[i]), "partition": rows["partition"][i], "sample_id": rows["sample_id"][i]}
            for i in failures
        ],
        "per_sample": {k: v for k, v in rows.items()},
        "seed_reference": "Bodies at Rest, Table 5 (synthetic test sets, best network)",
    }
    paths = {}
    paths["cases"] = atomic_write(
        cfg.out / "cases.png",
        lambda tmp: plot_cases(tmp, [(f"{k}: 3DVPE {vpe[i] * 100:.1f} cm", *case(i)) for k, i in picks.items()], faces),
    )
    paths["failures"] = atomic_write(
        cfg.out / "failures.png",
        lambda tmp: plot_cases(
            tmp, [(f"#{i} {rows['partition'][i]}: {vpe[i] * 100:.1f} cm", *case(i)) for i in failures], faces
        ),
    )
    paths["predictions"] = write_predictions(cfg.out / PREDICTIONS, estimates)
    paths["json"] = write_text(cfg.out / "report.json", json.dumps(record, indent=1))
    paths["markdown"] = write_text(cfg.out / "report.md", _markdown(record))
    return Written(paths, record)


def _cm(x: float | None) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x * 100:.2f}"


def _markdown(r: dict) -> str:
    has_base = bool(r["baselines_vpe_m"])
    lines = [
        f"# Evaluation: {r['config']['model']}{recorded_options_label(r['config'])} on {r['config']['data']} ({r['config']['split']}, {r['count']} samples)",
        "",
        "All errors unaligned except PA-MPJPE; 3DVPE as released (camera-facing vertices, two-way, "
        "area-weighted). Seed = Bodies at Rest Table 5, synthetic, best network.",
        "",
    ]
    for key, title in (("by_partition", "pose partition"), ("by_gender", "gender partition")):
        head = (
            f"| {title} | test ct. | 3DVPE (cm) | 3DVPE 95% interval (cm) | seed 3DVPE (cm) | v2v (cm) | MPJPE (cm) "
            "| PA-MPJPE (cm) |"
        )
        sep = "| --- | --- | --- | --- | --- | --- | --- | --- |"
        if has_base:
            head += " mean body (cm) | nearest image (cm) |"
            sep += " --- | --- |"
        lines += [head, sep]
        for e in r[key]:
            name = e["partition" if key == "by_partition" else "gender"]
            seed = e["seed_synth_vpe_cm"]
            ci = e.get("vpe_m_ci95")
            row = (
                f"| {name} | {e['count']} | {_cm(e['vpe_m'])} | "
                f"{'-' if ci is None else f'{_cm(ci[0])} - {_cm(ci[1])}'} | {'-' if seed is None else f'{seed:.2f}'} | "
                f"{_cm(e['v2v_m'])} | {_cm(e['mpjpe_m'])} | {_cm(e['pa_mpjpe_m'])} |"
            )
            if has_base:
                row += f" {_cm(e.get('baseline_mean_body_vpe_m'))} | {_cm(e.get('baseline_nearest_image_vpe_m'))} |"
            lines.append(row)
        lines.append("")
    o = r["overall"]
    lines += [
        "## Overall (mean / median / 90th percentile)",
        "",
        "| metric | mean | median | p90 |",
        "| --- | --- | --- | --- |",
    ]
    labels = {
        "vpe_m": ("3DVPE", "cm", 100.0),
        "v2v_m": ("v2v", "cm", 100.0),
        "mpjpe_m": ("MPJPE", "cm", 100.0),
        "pa_mpjpe_m": ("PA-MPJPE", "cm", 100.0),
        "root_pos_m": ("root position", "cm", 100.0),
        "root_rot_deg": ("root orientation", "deg", 1.0),
        "height_err_m": ("height", "cm", 100.0),
        "mass_err_kg": ("mass", "kg", 1.0),
    }
    for m in METRICS:
        name, unit, scale = labels[m]
        s = o[m]
        lines.append(
            f"| {name} ({unit}) | {s['mean'] * scale:.2f} | {s['median'] * scale:.2f} | {s['p90'] * scale:.2f} |"
        )
    lines += [
        "",
        "## Joint error per body region (cm, mean / median / p90)",
        "",
        "| region | mean | median | p90 |",
        "| --- | --- | --- | --- |",
    ]
    for reg, s in r["regions_m"].items():
        lines.append(f"| {reg} | {s['mean'] * 100:.2f} | {s['median'] * 100:.2f} | {s['p90'] * 100:.2f} |")
    lines += [
        "",
        "## Height error by where the load lies (median signed, cm; samples)",
        "",
        "Whether the load (the rows holding >= 0.2% of the force) reaches the mat's head or foot row, "
        "as `evaluate-real` reports it for real frames.",
        "",
        *load_ends_table({r["config"]["split"]: r["height_by_load_ends"]}, "split"),
        *spread_lines({r["config"]["split"]: r["trunk_spread"]} if r.get("trunk_spread") else {}),
    ]
    if has_base:
        lines += ["", "## Baselines (3DVPE, cm, mean / median)", ""]
        for k, s in r["baselines_vpe_m"].items():
            lines.append(f"- {k.replace('_', ' ')}: {s['mean'] * 100:.2f} / {s['median'] * 100:.2f}")
    else:
        lines += ["", "No training split in the dataset: baselines not computed."]
    lines += [
        "",
        "## Cases",
        "",
        "![best, median, worst](cases.png)",
        "",
        "## Failures",
        "",
        "![worst cases](failures.png)",
        "",
        *_failure_table(r["failures"]),
    ]
    return "\n".join(lines)


def _failure_table(failures: list[dict]) -> list[str]:
    """Where the worst samples live and how to draw their initial poses again (generated data)."""
    if not any(f.get("sample_id") for f in failures):
        return []
    lines = [
        "| # (in the split) | 3DVPE (cm) | shard, row | initial pose again |",
        "| --- | --- | --- | --- |",
    ]
    for f in failures:
        s = f.get("sample_id")
        if s is None:
            lines.append(f"| {f['index']} | {f['vpe_m'] * 100:.2f} | - | - |")
            continue
        again = "-"  # a sample `generate` did not make (imported) has no initial pose to draw
        if s.get("seed") is not None and s.get("index") is not None:
            backend = "" if s.get("backend", "anny") == "anny" else f" --backend {s['backend']} --smpl-dir DIR"
            again = (
                f"`pressurepose sample --seed {s['seed']} --partition {s['partition']} --gender {s['gender']}"
                f"{' --over-bed' if s['over_bed'] else ''}{backend} --start {s['index']} --n 1`"
            )
        lines.append(f"| {f['index']} | {f['vpe_m'] * 100:.2f} | {s['shard']}, {s['row']} | {again} |")
    return [*lines, ""]


def evaluate(cfg: EvaluateConfig) -> None:
    """Evaluate a trained network on a dataset (seed Table 5): tables per partition and gender
    with the seed's numbers and two baselines, per-region errors, best/median/worst cases and
    failures; report.md, report.json and PNGs in --out."""
    written = run_evaluate(cfg)
    record = written.record
    o = record["overall"]
    print(
        f"{record['count']} samples: 3DVPE {o['vpe_m']['mean'] * 100:.2f} cm, MPJPE {o['mpjpe_m']['mean'] * 100:.2f} cm "
        f"-> {written['markdown']}"
    )


__all__ = ["EvaluateConfig", "evaluate", "run_evaluate"]
