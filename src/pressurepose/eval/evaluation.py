"""A trained network on a dataset: per-sample metrics and two baselines (seed B.4, Table 5).

Per sample: 3DVPE (as released), per-vertex error, MPJPE, PA-MPJPE, root position and
orientation error, height and mass error, and the joint error per body region; the baselines
give every number its context - the training set's mean body, and the body of the nearest
training pressure image. The estimated bodies go to predictions.npz (`write_predictions`,
re-posed by `pressurepose view`). The report: `commands.evaluate`.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from pressurepose.body.joints import J24_NAMES, J24_REGIONS, TRUNK_JOINTS
from pressurepose.body.params import BodyParams
from pressurepose.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from pressurepose.errors import UserError
from pressurepose.eval import metrics as M
from pressurepose.eval.real import load_ends, spread_summary
from pressurepose.files import atomic_write
from pressurepose.net.model import NetInputs
from pressurepose.train.data import open_dataset, standardise

# Seed Table 5, synthetic test sets: 3DVPE (cm) of the best network.
SEED_SYNTH_VPE_CM = {
    "straight_limbs": 2.68,
    "supine": 3.40,
    "crossed_legs": 3.41,
    "prone_hands_up": 4.24,
    "general": 4.30,
    "hands_behind_head": 4.40,
    "female": 3.85,
    "male": 4.04,
}
REGIONS = J24_REGIONS
METRICS = ("vpe_m", "v2v_m", "mpjpe_m", "pa_mpjpe_m", "root_pos_m", "root_rot_deg", "height_err_m", "mass_err_kg")
PARAM_KEYS = tuple(f.name for f in dataclasses.fields(BodyParams))
PREDICTIONS = "predictions.npz"  # the estimated BodyParams per sample (write_predictions)


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
    """(labels, tensor batch) over the dataset in order; labels (partition, gender, the
    generator's sampler index or None) per sample."""
    n = len(dataset) if limit is None else min(limit, len(dataset))
    for lo in range(0, n, batch):
        items = [dataset[i] for i in range(lo, min(lo + batch, n))]
        labels = [
            (
                _item_label(it, "partition", "unknown"),
                _item_label(it, "gender", "unknown"),
                int(it["index"]) if "index" in it else None,
            )
            for it in items
        ]
        std = [standardise(it) for it in items]
        yield labels, {k: torch.stack([s[k] for s in std]) for k in std[0]}


def open_split(data: Path, split: str):
    """A split of a generated dataset (with its partition labels and sampler indices) or .npz files."""
    return open_dataset(data, split=split, extra_columns=("partition", "index"))


def sample_ids(dataset, indices: list[int | None]) -> list[dict | None]:
    """Where each of the first len(indices) samples of an `open_split` dataset lives - its dataset
    folder, shard and row - and what the generator made it from: the dataset's seed, the shard's
    partition, gender and over_bed, its body model and the sampler index (`indices`, from
    `_batches`), so that `pressurepose sample --seed SEED --partition P --gender G [--over-bed]
    --start INDEX --n 1` draws its initial pose again. None for samples of .npz files; seed and
    index None for a dataset `generate` did not make (an imported one: no seed in its manifest)."""
    parts = dataset.datasets if isinstance(dataset, torch.utils.data.ConcatDataset) else [dataset]
    ids: list[dict | None] = []
    for part in parts:
        if len(ids) >= len(indices):
            break
        take = min(len(part), len(indices) - len(ids))  # 0 for a part without samples in the split
        if not hasattr(part, "locate"):  # .npz: no shards, no generator's coordinates
            ids += [None] * take
            continue
        config = part.manifest.get("config", {})
        seed = None if "source" in config else config.get("seed")  # imported data name their source
        for i in range(take):
            s, row = part.locate(i)
            shard = part.shards[s]
            ids.append(
                {
                    "dataset": str(part.root),
                    "shard": shard["id"],
                    "row": row,
                    "seed": seed,
                    "partition": shard["partition"],
                    "gender": shard["gender"],
                    "over_bed": bool(shard["over_bed"]),
                    "backend": config.get("backend", "anny"),
                    "index": None if seed is None else indices[len(ids)],
                }
            )
    return ids


def check_backend(net, dataset, data: Path) -> None:
    """A network and a dataset from different body models cannot be compared (UserError)."""
    shape_dim = next(_batches(dataset, 1, 1))[1]["shape"].shape[-1]
    manifest = getattr(dataset, "manifest", None)  # generated datasets record their body model
    backend = manifest.get("config", {}).get("backend") if isinstance(manifest, dict) else None
    if backend is not None and backend != net.config.backend:
        raise UserError(
            f"the network estimates {net.config.backend} bodies but {data} holds {backend} bodies; "
            f"evaluate on a dataset generated with --backend {net.config.backend}"
        )
    if shape_dim != len(net.body.shape_names):
        raise UserError(
            f"the dataset's shapes have {shape_dim} parameters but the network's {net.config.backend} "
            f"model has {len(net.body.shape_names)}: a dataset of another body model"
        )


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
    mean = BodyParams(
        shape=bodies.shape.mean(0, keepdim=True),
        root_rotation=matrix_to_axis_angle(R[None]),
        root_translation=bodies.root_translation.mean(0, keepdim=True),
        pose=bodies.pose.mean(0, keepdim=True),
    )
    return mean, torch.cat(imgs), bodies


def _normalised(p: torch.Tensor) -> torch.Tensor:
    flat = p.reshape(p.shape[0], -1).to(torch.float32)
    return flat / flat.sum(1, keepdim=True).clamp_min(1e-6)


def _sample_metrics(
    body,
    est: BodyParams,
    true: BodyParams,
    true_joints: torch.Tensor,
    true_out,
    true_measure,
    true_facing: M.FacingMeshes | None = None,
) -> dict[str, torch.Tensor]:
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
        "height_signed_m": meas.height_m - true_measure.height_m,
        "mass_err_kg": (meas.mass_kg - true_measure.mass_kg).abs(),
    }
    for region, names in REGIONS.items():
        res[f"joints_{region}_m"] = joint_err[:, [J24_NAMES.index(n) for n in names]].mean(-1)
    return res


@dataclasses.dataclass(frozen=True)
class Evaluation:
    """Per-sample metrics of a network on a dataset: `rows[metric]` (N,) lists (METRICS, the
    joint error per region, the signed height error `height_signed_m`, the partition, gender
    and `load_ends` labels, and `sample_id`: where each sample lives and how it was made,
    `sample_ids`), `baselines[name]` the baselines' 3DVPE (N,) (empty without a
    training set), the estimated bodies and the seconds it took."""

    rows: dict[str, list]
    baselines: dict[str, list]
    estimates: BodyParams
    seconds: float
    trunk_spread: dict | None = None  # heatmap networks: `eval.real.spread_summary` of the head and torso


def evaluate_network(
    net,
    test,
    n: int,
    batch: int,
    train=None,
    baseline_samples: int = 4096,
    on_batch: Callable[[int], None] | None = None,
) -> Evaluation:
    """The first n samples of `test` through `net` (no gradients) against their true bodies;
    with `train`, the mean-body and nearest-image baselines. `on_batch(done)` reports progress."""
    body = net.body
    dtype = torch.float32
    mean_body, train_imgs, train_bodies = (
        _baseline_data(train, baseline_samples, dtype) if train is not None else (None, None, None)
    )
    with torch.no_grad():  # the mean body is one mesh for every sample: packed once
        mean_facing = None if mean_body is None else M.facing_meshes(body(mean_body).vertices, body.faces)

    rows: dict[str, list] = {"partition": [], "gender": [], "load_ends": []}
    indices: list[int | None] = []
    trunk_spreads = []  # (B, 8) per batch, heatmap networks
    base_rows: dict[str, list] = {"mean_body": [], "nearest_image": []}
    estimates = []  # BodyParams per batch: the figures re-pose the few samples they show
    t0 = time.perf_counter()
    with torch.no_grad():
        done = 0
        for labels, b in _batches(test, batch, n):
            true = _as_params(b, dtype)
            true_out = body(true)
            true_facing = M.facing_meshes(true_out.vertices, body.faces)  # shared by the three 3DVPE
            true_measure = body.measure(true.shape)
            inputs = NetInputs(
                pressure_mmhg=b["pressure_mmhg"], gender=b["gender"], height_m=b["height_m"], mass_kg=b["mass_kg"]
            )
            out = net(inputs, mesh=False)[-1]
            est = out.params
            if out.localisation is not None:  # how sharply the heatmaps pin the head and torso
                spread = out.localisation.spread_m[:, list(TRUNK_JOINTS)]
                rows.setdefault("trunk_spread_m", []).extend(spread.median(1).values.tolist())
                trunk_spreads.append(spread)
            res = _sample_metrics(body, est, true, b["joints"].to(dtype), true_out, true_measure, true_facing)
            for k, v in res.items():
                rows.setdefault(k, []).extend(v.tolist())
            rows["partition"] += [p for p, _, _ in labels]
            rows["gender"] += [g for _, g, _ in labels]
            indices += [i for _, _, i in labels]
            rows["load_ends"] += load_ends(b["pressure_mmhg"].numpy())
            estimates.append(est)
            if mean_body is not None:
                base_rows["mean_body"] += M.vpe_between(mean_facing, true_facing).tolist()
                nearest = torch.cdist(_normalised(b["pressure_mmhg"]), train_imgs).argmin(1)
                nearest_out = body(train_bodies.index(nearest))
                base_rows["nearest_image"] += M.vpe_between(
                    M.facing_meshes(nearest_out.vertices, body.faces), true_facing
                ).tolist()
            done += len(labels)
            if on_batch is not None:
                on_batch(done)
    rows["sample_id"] = sample_ids(test, indices)
    spread = spread_summary(torch.cat(trunk_spreads)) if trunk_spreads else None
    return Evaluation(rows, base_rows, BodyParams.cat(estimates), time.perf_counter() - t0, spread)


def case_meshes(body, test, estimates: BodyParams, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pressure image (64, 27) mmHg and the true and estimated meshes (V, 3) of sample i."""
    _, b = next(_batches(torch.utils.data.Subset(test, [i]), 1, 1))
    with torch.no_grad():
        true_v = body(_as_params(b, torch.float32)).vertices[0]
        est_v = body(estimates.index([i])).vertices[0]
    return b["pressure_mmhg"][0].numpy(), true_v.numpy(), est_v.numpy()


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


__all__ = [
    "METRICS",
    "PREDICTIONS",
    "REGIONS",
    "SEED_SYNTH_VPE_CM",
    "Evaluation",
    "case_meshes",
    "check_backend",
    "evaluate_network",
    "open_split",
    "read_predictions",
    "write_predictions",
]
