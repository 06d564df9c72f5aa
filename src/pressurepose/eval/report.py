"""`pressurepose evaluate`: a trained network on a dataset's test split -> a report.

Per sample: 3DVPE (as released), per-vertex error, MPJPE, PA-MPJPE, root position and
orientation error, height and mass error, and the joint error per body region. Tables per
partition and per gender in the layout of seed Table 5 with the seed's synthetic 3DVPE beside
ours, overall numbers, two baselines that give every number its context - the training set's
mean body, and the body of the nearest training pressure image - and figures of the best,
median and worst cases plus a gallery of failures. Written as report.md, report.json, PNGs and
predictions.npz (the estimated body parameters, re-posed by `pressurepose view`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from pressurepose.body.joints import J24_NAMES
from pressurepose.body.params import BodyParams
from pressurepose.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from pressurepose.errors import UserError
from pressurepose.eval import metrics as M
from pressurepose.files import atomic_write

# Seed Table 5, synthetic test sets: 3DVPE (cm) of the best network.
SEED_SYNTH_VPE_CM = {"straight_limbs": 2.68, "supine": 3.40, "crossed_legs": 3.41, "prone_hands_up": 4.24,
                     "general": 4.30, "hands_behind_head": 4.40, "female": 3.85, "male": 4.04}
REGIONS = {
    "head": ("neck", "head"),
    "torso": ("pelvis", "spine1", "spine2", "spine3", "left_collar", "right_collar"),
    "arms": tuple(f"{s}_{n}" for s in ("left", "right") for n in ("shoulder", "elbow", "wrist", "hand")),
    "legs": tuple(f"{s}_{n}" for s in ("left", "right") for n in ("hip", "knee", "ankle", "foot")),
}
METRICS = ("vpe_m", "v2v_m", "mpjpe_m", "pa_mpjpe_m", "root_pos_m", "root_rot_deg", "height_err_m", "mass_err_kg")
PARAM_KEYS = tuple(f.name for f in dataclasses.fields(BodyParams))
PREDICTIONS = "predictions.npz"  # the estimated BodyParams per sample (write_predictions)


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


def _as_params(batch: dict, dtype) -> BodyParams:
    return BodyParams(**{k: batch[k].to(dtype) for k in PARAM_KEYS})


def _item_label(item: dict, key: str, default: str) -> str:
    v = item.get(key, default)
    if isinstance(v, torch.Tensor):
        v = v.item() if v.numel() == 1 else default
    if key == "gender" and not isinstance(v, str):
        return "female" if float(v) >= 0.5 else "male"
    return str(v)


def _batches(dataset, batch: int, limit: int | None):
    """(labels, tensor batch) over the dataset in order."""
    from pressurepose.train.data import standardise

    n = len(dataset) if limit is None else min(limit, len(dataset))
    for lo in range(0, n, batch):
        items = [dataset[i] for i in range(lo, min(lo + batch, n))]
        labels = [(_item_label(it, "partition", "unknown"), _item_label(it, "gender", "unknown")) for it in items]
        std = [standardise(it) for it in items]
        yield labels, {k: torch.stack([s[k] for s in std]) for k in std[0]}


def _open(data: Path, split: str):
    """A split of a generated dataset (with its partition labels) or .npz files."""
    from pressurepose.train.data import open_dataset

    return open_dataset(data, split=split, extra_columns=("partition",))


def _check_backend(net, dataset, data: Path, shape_dim: int) -> None:
    """A network and a dataset from different body models cannot be compared."""
    manifest = getattr(dataset, "manifest", None)  # generated datasets record their body model
    backend = manifest.get("config", {}).get("backend") if isinstance(manifest, dict) else None
    if backend is not None and backend != net.config.backend:
        raise UserError(f"the network estimates {net.config.backend} bodies but {data} holds {backend} bodies; "
                         f"evaluate on a dataset generated with --backend {net.config.backend}")
    if shape_dim != len(net.body.shape_names):
        raise UserError(f"the dataset's shapes have {shape_dim} parameters but the network's {net.config.backend} "
                         f"model has {len(net.body.shape_names)}: a dataset of another body model")


def _baseline_data(train, n: int, dtype) -> tuple[BodyParams, torch.Tensor, BodyParams]:
    """From one pass over up to n training samples: the mean body (mean shape, pose
    (axis-angle) and pelvis position, chordal mean of the root rotations), and the (N, 1728)
    sum-normalised images with their bodies for the nearest-image baseline."""
    imgs, parts = [], []
    for _, b in _batches(train, 256, n):
        imgs.append(_normalised(b["pressure_mmhg"]))
        parts.append(_as_params(b, dtype))
    bodies = BodyParams.cat(parts)
    U, _, Vh = torch.linalg.svd(axis_angle_to_matrix(bodies.root_rotation).mean(0))
    R = U @ torch.diag(torch.tensor([1.0, 1.0, float(torch.linalg.det(U @ Vh))], dtype=dtype)) @ Vh
    mean = BodyParams(shape=bodies.shape.mean(0, keepdim=True), root_rotation=matrix_to_axis_angle(R[None]),
                      root_translation=bodies.root_translation.mean(0, keepdim=True),
                      pose=bodies.pose.mean(0, keepdim=True))
    return mean, torch.cat(imgs), bodies


def _normalised(p: torch.Tensor) -> torch.Tensor:
    flat = p.reshape(p.shape[0], -1).to(torch.float32)
    return flat / flat.sum(1, keepdim=True).clamp_min(1e-6)


def _sample_metrics(body, est: BodyParams, true: BodyParams, true_joints: torch.Tensor,
                    true_out, true_measure, true_facing: M.FacingMeshes | None = None) -> dict[str, torch.Tensor]:
    """Every per-sample metric of a batch; `true_facing` = the true meshes packed for 3DVPE
    (`M.facing_meshes`), when the caller compares them with other meshes too."""
    out = body(est)
    meas = body.measure(est.shape)
    joint_err = (out.joints - true_joints).norm(dim=-1)  # (B, 24)
    if true_facing is None:
        true_facing = M.facing_meshes(true_out.vertices, body.faces)
    res = {
        "vpe_m": M.vpe_between(M.facing_meshes(out.vertices, body.faces), true_facing),
        "v2v_m": M.per_vertex_error(out.vertices, true_out.vertices),
        "mpjpe_m": joint_err.mean(-1),
        "pa_mpjpe_m": M.pa_mpjpe(out.joints, true_joints),
        "root_pos_m": M.root_position_error(est.root_translation, true.root_translation),
        "root_rot_deg": torch.rad2deg(M.root_orientation_error(est.root_rotation, true.root_rotation)),
        "height_err_m": (meas.height_m - true_measure.height_m).abs(),
        "mass_err_kg": (meas.mass_kg - true_measure.mass_kg).abs(),
    }
    for region, names in REGIONS.items():
        res[f"joints_{region}_m"] = joint_err[:, [J24_NAMES.index(n) for n in names]].mean(-1)
    return res


def run_evaluate(cfg: EvaluateConfig) -> dict[str, Path]:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from pressurepose.net.model import NetInputs
    from pressurepose.train.checkpoint import load_network

    if cfg.batch < 1:
        raise UserError(f"batch must be >= 1, got {cfg.batch}")
    net, _ = load_network(cfg.model)
    body = net.body
    dtype = torch.float32
    test = _open(cfg.data, cfg.split)
    n = len(test) if cfg.limit is None else min(cfg.limit, len(test))
    if n == 0:
        raise UserError(f"{cfg.data} has no {cfg.split} samples to evaluate")
    first = next(_batches(test, 1, 1))[1]
    _check_backend(net, test, cfg.data, first["shape"].shape[-1])
    train = None
    if cfg.train_data is not None:
        train = _open(cfg.train_data, "train")
    elif (cfg.data / "manifest.json").is_file():
        train = _open(cfg.data, "train")
    if train is not None and len(train) == 0:
        train = None
    mean_body, train_imgs, train_bodies = (_baseline_data(train, cfg.baseline_samples, dtype) if train is not None
                                           else (None, None, None))
    with torch.no_grad():  # the mean body is one mesh for every sample: packed once
        mean_facing = None if mean_body is None else M.facing_meshes(body(mean_body).vertices, body.faces)

    rows: dict[str, list] = {"partition": [], "gender": []}
    base_rows: dict[str, list] = {"mean_body": [], "nearest_image": []}
    estimates = []  # BodyParams per batch: the figures re-pose the few samples they show
    t0 = time.perf_counter()
    columns = (TextColumn("evaluating"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[rate]}"),
               TimeRemainingColumn())
    with Progress(*columns, transient=True) as bar, torch.no_grad():
        task = bar.add_task("eval", total=n, rate="")
        done = 0
        for labels, b in _batches(test, cfg.batch, n):
            true = _as_params(b, dtype)
            true_out = body(true)
            true_facing = M.facing_meshes(true_out.vertices, body.faces)  # shared by the three 3DVPE
            true_measure = body.measure(true.shape)
            inputs = NetInputs(pressure_mmhg=b["pressure_mmhg"], gender=b["gender"], height_m=b["height_m"],
                               mass_kg=b["mass_kg"])
            est = net(inputs, mesh=False)[-1].params
            res = _sample_metrics(body, est, true, b["joints"].to(dtype), true_out, true_measure, true_facing)
            for k, v in res.items():
                rows.setdefault(k, []).extend(v.tolist())
            rows["partition"] += [p for p, _ in labels]
            rows["gender"] += [g for _, g in labels]
            estimates.append(est)
            B = len(labels)
            if mean_body is not None:
                base_rows["mean_body"] += M.vpe_between(mean_facing, true_facing).tolist()
                nearest = torch.cdist(_normalised(b["pressure_mmhg"]), train_imgs).argmin(1)
                nearest_out = body(train_bodies.index(nearest))
                base_rows["nearest_image"] += M.vpe_between(M.facing_meshes(nearest_out.vertices, body.faces),
                                                            true_facing).tolist()
            done += B
            bar.update(task, completed=done, rate=f"{done / (time.perf_counter() - t0):.1f} img/s")
    seconds = time.perf_counter() - t0
    estimates = BodyParams.cat(estimates)

    def case(i: int) -> tuple:
        """The pressure image and the true and estimated meshes of sample i."""
        _, b = next(_batches(torch.utils.data.Subset(test, [i]), 1, 1))
        with torch.no_grad():
            true_v = body(_as_params(b, dtype)).vertices[0]
            est_v = body(estimates.index([i])).vertices[0]
        return b["pressure_mmhg"][0].numpy(), true_v.numpy(), est_v.numpy()

    return _write_report(cfg, rows, base_rows, case, body.faces.numpy(), seconds, estimates)


def _summary(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=np.float64)
    return {"mean": float(a.mean()), "median": float(np.median(a)), "p90": float(np.quantile(a, 0.9))}


def _group_table(rows: dict, base: dict, key: str) -> list[dict]:
    labels = np.asarray(rows[key])
    out = []
    for g in sorted(set(labels.tolist())):
        sel = labels == g
        entry = {key: g, "count": int(sel.sum())}
        for m in METRICS:
            entry[m] = float(np.asarray(rows[m])[sel].mean())
        for name, vals in base.items():
            if vals:
                entry[f"baseline_{name}_vpe_m"] = float(np.asarray(vals)[sel].mean())
        entry["seed_synth_vpe_cm"] = SEED_SYNTH_VPE_CM.get(g)
        out.append(entry)
    return out


def write_predictions(path: Path, estimates: BodyParams) -> Path:
    """The estimated bodies of a report, for `pressurepose view` to re-pose: `index` (N,) the
    samples' positions in the evaluated split (as `train.data.open_dataset(data, split)` lists
    them; the first N when --limit is given), and the BodyParams fields as float32 arrays -
    `shape` (N, S), `root_rotation` (N, 3) rad, `root_translation` (N, 3) m, `pose`
    (N, 23, 3) rad. A plain .npz (no pickles)."""
    arrays = {"index": np.arange(estimates.batch_size, dtype=np.int64)}
    arrays.update({k: getattr(estimates, k).detach().cpu().numpy().astype(np.float32) for k in PARAM_KEYS})
    return atomic_write(Path(path), lambda tmp: np.savez_compressed(tmp, **arrays))


def read_predictions(path: Path) -> tuple[np.ndarray, BodyParams]:
    """(index (N,), BodyParams (N, ...) float32) of a `predictions.npz`; ValueError if it is
    not one."""
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except (OSError, ValueError, EOFError) as exc:
        raise UserError(f"{path} is not a readable predictions file ({exc}); re-run `pressurepose evaluate`") from None
    missing = [k for k in ("index", *PARAM_KEYS) if k not in arrays]
    if missing:
        raise UserError(f"{path} lacks arrays {missing}; re-run `pressurepose evaluate` to rewrite it")
    index = arrays["index"].astype(np.int64)
    params = BodyParams(**{k: torch.from_numpy(arrays[k].astype(np.float32)) for k in PARAM_KEYS})
    if len({len(index), *(len(getattr(params, k)) for k in PARAM_KEYS)}) != 1:
        raise UserError(f"{path}: arrays of different lengths; re-run `pressurepose evaluate` to rewrite it")
    return index, params


def _write_report(cfg: EvaluateConfig, rows: dict, base: dict, case, faces: np.ndarray,
                  seconds: float, estimates: BodyParams) -> dict[str, Path]:
    from pressurepose.viz.evaluation import plot_cases

    cfg.out.mkdir(parents=True, exist_ok=True)
    vpe = np.asarray(rows["vpe_m"])
    order = np.argsort(vpe)
    n = len(vpe)
    picks = {"best": int(order[0]), "median": int(order[n // 2]), "worst": int(order[-1])}
    failures = [int(i) for i in order[::-1][: cfg.failures]]
    record = {
        "command": "evaluate",
        "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(cfg).items()},
        "count": n,
        "seconds": round(seconds, 2),
        "overall": {m: _summary(rows[m]) for m in METRICS},
        "regions_m": {r: _summary(rows[f"joints_{r}_m"]) for r in REGIONS},
        "baselines_vpe_m": {k: _summary(v) for k, v in base.items() if v},
        "by_partition": _group_table(rows, base, "partition"),
        "by_gender": _group_table(rows, base, "gender"),
        "cases": {k: {"index": i, "vpe_m": float(vpe[i])} for k, i in picks.items()},
        "failures": [{"index": i, "vpe_m": float(vpe[i]), "partition": rows["partition"][i]} for i in failures],
        "per_sample": {k: v for k, v in rows.items()},
        "seed_reference": "Bodies at Rest, Table 5 (synthetic test sets, best network)",
    }
    paths = {}
    paths["cases"] = atomic_write(cfg.out / "cases.png", lambda tmp: plot_cases(
        tmp, [(f"{k}: 3DVPE {vpe[i] * 100:.1f} cm", *case(i)) for k, i in picks.items()], faces))
    paths["failures"] = atomic_write(cfg.out / "failures.png", lambda tmp: plot_cases(
        tmp, [(f"#{i} {rows['partition'][i]}: {vpe[i] * 100:.1f} cm", *case(i)) for i in failures], faces))
    paths["predictions"] = write_predictions(cfg.out / PREDICTIONS, estimates)
    paths["json"] = atomic_write(cfg.out / "report.json", lambda tmp: Path(tmp).write_text(json.dumps(record, indent=1)))
    paths["markdown"] = atomic_write(cfg.out / "report.md", lambda tmp: Path(tmp).write_text(_markdown(record)))
    return paths


def _cm(x: float | None) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x * 100:.2f}"


def _markdown(r: dict) -> str:
    has_base = bool(r["baselines_vpe_m"])
    lines = [f"# Evaluation: {r['config']['model']} on {r['config']['data']} ({r['config']['split']}, {r['count']} samples)",
             "", "All errors unaligned except PA-MPJPE; 3DVPE as released (camera-facing vertices, two-way, "
             "area-weighted). Seed = Bodies at Rest Table 5, synthetic, best network.", ""]
    for key, title in (("by_partition", "pose partition"), ("by_gender", "gender partition")):
        head = f"| {title} | test ct. | 3DVPE (cm) | seed 3DVPE (cm) | v2v (cm) | MPJPE (cm) | PA-MPJPE (cm) |"
        sep = "| --- | --- | --- | --- | --- | --- | --- |"
        if has_base:
            head += " mean body (cm) | nearest image (cm) |"
            sep += " --- | --- |"
        lines += [head, sep]
        for e in r[key]:
            name = e["partition" if key == "by_partition" else "gender"]
            seed = e["seed_synth_vpe_cm"]
            row = (f"| {name} | {e['count']} | {_cm(e['vpe_m'])} | {'-' if seed is None else f'{seed:.2f}'} | "
                   f"{_cm(e['v2v_m'])} | {_cm(e['mpjpe_m'])} | {_cm(e['pa_mpjpe_m'])} |")
            if has_base:
                row += (f" {_cm(e.get('baseline_mean_body_vpe_m'))} | {_cm(e.get('baseline_nearest_image_vpe_m'))} |")
            lines.append(row)
        lines.append("")
    o = r["overall"]
    lines += ["## Overall (mean / median / 90th percentile)", "", "| metric | mean | median | p90 |",
              "| --- | --- | --- | --- |"]
    labels = {"vpe_m": ("3DVPE", "cm", 100.0), "v2v_m": ("v2v", "cm", 100.0), "mpjpe_m": ("MPJPE", "cm", 100.0),
              "pa_mpjpe_m": ("PA-MPJPE", "cm", 100.0), "root_pos_m": ("root position", "cm", 100.0),
              "root_rot_deg": ("root orientation", "deg", 1.0), "height_err_m": ("height", "cm", 100.0),
              "mass_err_kg": ("mass", "kg", 1.0)}
    for m in METRICS:
        name, unit, scale = labels[m]
        s = o[m]
        lines.append(f"| {name} ({unit}) | {s['mean'] * scale:.2f} | {s['median'] * scale:.2f} | {s['p90'] * scale:.2f} |")
    lines += ["", "## Joint error per body region (cm, mean / median / p90)", "", "| region | mean | median | p90 |",
              "| --- | --- | --- | --- |"]
    for reg, s in r["regions_m"].items():
        lines.append(f"| {reg} | {s['mean'] * 100:.2f} | {s['median'] * 100:.2f} | {s['p90'] * 100:.2f} |")
    if has_base:
        lines += ["", "## Baselines (3DVPE, cm, mean / median)", ""]
        for k, s in r["baselines_vpe_m"].items():
            lines.append(f"- {k.replace('_', ' ')}: {s['mean'] * 100:.2f} / {s['median'] * 100:.2f}")
    else:
        lines += ["", "No training split in the dataset: baselines not computed."]
    lines += ["", "## Cases", "", "![best, median, worst](cases.png)", "", "## Failures", "",
              "![worst cases](failures.png)", ""]
    return "\n".join(lines)


__all__ = ["EvaluateConfig", "METRICS", "PREDICTIONS", "REGIONS", "SEED_SYNTH_VPE_CM", "read_predictions",
           "run_evaluate", "write_predictions"]
