"""What `pressurepose view` shows: one `Browser` over a dataset folder, an evaluation report,
a training run or a .npz of pressure images, read lazily.

A Browser answers four questions for the web viewer (`viz.viewer`): what is this folder
(`info`), which samples are there (`labels`, cheap: from the manifest's shard list or the
report's per-sample table, never from the samples themselves), what is sample i (`sample`:
pressure image, labels, metrics, joints) and what are its meshes (`meshes`: the true and
the estimated body re-posed with the body model, float32 vertices). Datasets of 200K samples
are fine: a sample costs one Parquet row-group read (PressurePoseDataset) and one or two
body-model passes; the last few results are kept in a small LRU cache.

Estimated bodies come from a report's `predictions.npz` (written by `pressurepose evaluate`)
or, for a training run, from its network run on the sample's pressure image on demand.
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch

from pressurepose.body.joints import J24_NAMES
from pressurepose.body.params import BodyParams
from pressurepose.errors import UserError
from pressurepose.validate import resolve_recorded
from pressurepose.viz.view_sources import (
    HINT,
    IMAGES,
    LABEL_KEYS,
    PARAM_KEYS,
    SCALAR_KEYS,
    NpzImages,
    json_number,
    open_samples,
)


class Browser:
    """The samples and predictions behind one PATH (see the module docstring)."""

    def __init__(
        self,
        path: Path,
        data: Path | None = None,
        backend: str | None = None,
        smpl_dir: Path | None = None,
        model: Path | None = None,
        cache: int = 8,
    ) -> None:
        path = Path(path)
        if not path.exists():
            raise UserError(f"{path} does not exist; {HINT}")
        self.path, self.kind, self.note = path, "", ""
        self.dataset = None
        self.split: str | None = None
        self.per_sample: dict[str, list] = {}
        self.summary: dict = {}
        self.metrics_rows: list[dict] = []
        self.estimates: BodyParams | None = None
        self.net = None
        self._net_run: Path | None = None  # a run's network, loaded on the first prediction
        self._limit: int | None = None  # a report shows only the samples it evaluated
        self.backend = backend
        self.smpl_dir = smpl_dir
        self._body = None
        self._lock = threading.RLock()  # one body-model / network pass (or load) at a time
        self._cache: OrderedDict = OrderedDict()
        self._cache_size = cache
        if path.is_file():
            if path.suffix != ".npz":
                raise UserError(f"{path} is a file but not a .npz; {HINT}")
            self.kind, self.dataset = "images", NpzImages(path)
        elif (path / "manifest.json").is_file():
            self.kind, self.dataset = "dataset", open_samples(path, None)
        elif (path / "report.json").is_file():
            self._open_report(path, data)
        elif (path / "config.json").is_file() and (
            (path / "metrics.jsonl").is_file() or (path / "model.safetensors").is_file()
        ):
            self._open_run(path, data)
        elif path.is_dir() and any(path.glob("*.npz")):
            self.kind, self.dataset = "dataset", open_samples(path, None)
        elif path.is_dir() and (path / "real.json").is_file():
            raise UserError(
                f"{path} is an `evaluate-real` report (no bodies to show); view the PmatData images with "
                "`pressurepose import-pmatdata --out pmat.npz` and `pressurepose view pmat.npz --model RUN`"
            )
        elif path.is_dir() and (path / "generate.json").is_file():
            raise UserError(
                f"{path} holds an unfinished dataset (no manifest.json); re-run the same "
                "`pressurepose generate` command to finish it"
            )
        else:
            empty = path.is_dir() and not any(path.iterdir())
            raise UserError(f"{path} is {'an empty folder' if empty else 'none of what the viewer reads'}; {HINT}")
        if model is not None:
            from pressurepose.models import resolve_model
            from pressurepose.train.checkpoint import read_model

            if self.kind == "report":
                raise UserError("--model is for datasets, runs and .npz images; a report has its own estimates")
            run = resolve_model(model)  # "default": the packaged network
            if not (run / "model.safetensors").is_file():
                raise UserError(f"--model {model} is not a training run folder (no model.safetensors)")
            self._net_run = run
            self.backend = self.backend or read_model(run)[1].get("net", {}).get("backend")
        if self.backend is None:
            manifest = getattr(self.dataset, "manifest", None)
            self.backend = (manifest or {}).get("config", {}).get("backend") or "anny"

    # --- opening -------------------------------------------------------------------------------

    def _open_report(self, path: Path, data: Path | None) -> None:
        from pressurepose.eval.evaluation import PREDICTIONS, read_predictions
        from pressurepose.validate import read_json

        record = read_json(path / "report.json", "report")
        if not isinstance(record, dict) or "per_sample" not in record or "config" not in record:
            raise UserError(f"{path / 'report.json'} is not a `pressurepose evaluate` report; {HINT}")
        self.kind = "report"
        self.split = record["config"].get("split", "test")
        self.per_sample = record["per_sample"]
        self.summary = {k: v.get("mean") for k, v in record.get("overall", {}).items()}
        root = data or resolve_recorded(record["config"].get("data"), path)
        if root is None:
            raise UserError(
                f"the report's dataset {record['config'].get('data')!r} is not found; give it with --data DIR"
            )
        self.dataset = open_samples(Path(root), self.split)
        n = len(self.per_sample.get("vpe_m", []))
        if len(self.dataset) < n:
            raise UserError(
                f"{root} has {len(self.dataset)} {self.split} samples but the report evaluated {n}: "
                "not the report's dataset; give the right one with --data DIR"
            )
        if (path / PREDICTIONS).is_file():
            index, params = read_predictions(path / PREDICTIONS)
            if not np.array_equal(index, np.arange(len(index))) or len(index) != n:
                raise UserError(f"{path / PREDICTIONS} does not match report.json; re-run `pressurepose evaluate`")
            self.estimates = params
        else:
            self.note = f"no {PREDICTIONS} in the report (made before the viewer existed): true bodies only"
        self._limit = n

    def _open_run(self, path: Path, data: Path | None) -> None:
        from pressurepose.validate import read_json

        record = read_json(path / "config.json", "run config")
        self.kind = "run"
        metrics = path / "metrics.jsonl"
        if metrics.is_file():
            for line in metrics.read_text().splitlines():
                try:
                    self.metrics_rows.append(json.loads(line))
                except ValueError:
                    continue  # a line cut by a killed run: the rows before it still show
        train = record.get("train", {}) if isinstance(record, dict) else {}
        self.backend = self.backend or train.get("backend")
        root = data or resolve_recorded(train.get("data"), path)
        if root is None:
            self.note = f"the run's dataset {train.get('data')!r} is not found (give it with --data DIR): curves only"
            return
        self.dataset = open_samples(Path(root), None)
        if (path / "model.safetensors").is_file():
            self._net_run = path

    # --- the body model ----------------------------------------------------------------------

    @property
    def body(self):
        with self._lock:
            if self._body is None:
                from pressurepose.body import load_body_model

                options = {"model_dir": self.smpl_dir} if self.backend == "smpl" and self.smpl_dir else {}
                self._body = load_body_model(self.backend or "anny", **options)
            return self._body

    # --- answers -----------------------------------------------------------------------------

    def __len__(self) -> int:
        if self.dataset is None:
            return 0
        return len(self.dataset) if self._limit is None else self._limit

    @property
    def has_truth(self) -> bool:
        if self.dataset is None:
            return False
        if isinstance(self.dataset, NpzImages):
            return all(k in self.dataset.arrays for k in PARAM_KEYS)
        return True

    @property
    def has_estimate(self) -> bool:
        return self.estimates is not None or self._net_run is not None

    def info(self) -> dict:
        from pressurepose.mat import MatSpec

        mat = MatSpec()
        images = [n for n in IMAGES if (self.path / n).is_file()] if self.path.is_dir() else []
        return {
            "kind": self.kind,
            "path": str(self.path),
            "count": len(self),
            "backend": self.backend,
            "has_truth": self.has_truth,
            "has_estimate": self.has_estimate,
            "note": self.note,
            "joint_names": list(J24_NAMES),
            "images": images,
            "metrics": self.metrics_rows,
            "summary": self.summary,
            "split": self.split,
            "mat": {
                "rows": mat.rows,
                "cols": mat.cols,
                "pitch_row_m": mat.pitch_row_m,
                "pitch_col_m": mat.pitch_col_m,
                "max_pressure_mmhg": mat.max_pressure_mmhg,
            },
        }

    def labels(self, lo: int, hi: int) -> list[dict]:
        """List entries of samples lo..hi-1 without reading them."""
        n = len(self)
        out = []
        shards = getattr(self.dataset, "shards", None)
        for i in range(max(0, lo), min(n, hi)):
            e = {"i": i}
            if shards is not None:
                s, row = self.dataset.locate(i)
                r = shards[s]
                e.update(split=r["split"], partition=r["partition"], gender=r["gender"])
            elif isinstance(self.dataset, NpzImages):
                for k in ("posture", "subject", "mattress", "partition", "gender"):
                    if k in self.dataset.arrays:
                        e[k] = json_number(self.dataset.arrays[k][i])
            for k in ("partition", "gender", "vpe_m", "mpjpe_m"):
                if k in self.per_sample:
                    e[k] = json_number(self.per_sample[k][i])
            out.append(e)
        return out

    def order(self, key: str) -> list[int]:
        """Sample numbers sorted by a per-sample metric, worst first ("index": as stored)."""
        if key in self.per_sample and all(isinstance(v, (int, float)) for v in self.per_sample[key]):
            return np.argsort(-np.asarray(self.per_sample[key], dtype=np.float64), kind="stable").tolist()
        return list(range(len(self)))

    def _check(self, i: int) -> None:
        if not 0 <= i < len(self):
            raise IndexError(f"sample {i} is out of range (0..{len(self) - 1})")

    def _computed(self, i: int) -> dict:
        """Sample i read and posed once (LRU cached): item, true / estimated params, outputs."""
        self._check(i)
        with self._lock:
            if i in self._cache:
                self._cache.move_to_end(i)
                return self._cache[i]
            item = self.dataset[i]
            res = {"item": item, "true": None, "est": None}
            with torch.no_grad():
                if self.has_truth:
                    res["true"] = BodyParams(
                        **{k: torch.as_tensor(np.asarray(item[k]), dtype=torch.float32)[None] for k in PARAM_KEYS}
                    )
                if self.estimates is not None:
                    res["est"] = self.estimates.index([i])
                elif self._net_run is not None:
                    res["est"] = self._predict(item)
                posed = [p for p in (res["true"], res["est"]) if p is not None]
                if posed:
                    out = self.body(BodyParams.cat(posed))
                    k = 0
                    for name in ("true", "est"):
                        if res[name] is not None:
                            res[f"{name}_vertices"] = out.vertices[k].numpy().astype(np.float32)
                            res[f"{name}_joints"] = out.joints[k].numpy().astype(np.float64)
                            k += 1
            self._cache[i] = res
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
            return res

    def _predict(self, item: dict) -> BodyParams:
        from pressurepose.net.model import NetInputs
        from pressurepose.train.checkpoint import load_network
        from pressurepose.train.data import _gender

        if self.net is None:
            self.net, _ = load_network(self._net_run, body=self._body)
            if self._body is None:  # the network's own body model poses the meshes too
                self._body = self.net.body

        def scalar(key, default):
            return torch.tensor(
                [float(_gender(item[key]) if key == "gender" else item[key]) if key in item else default],
                dtype=torch.float32,
            )

        inputs = NetInputs(
            pressure_mmhg=torch.as_tensor(np.asarray(item["pressure_mmhg"]), dtype=torch.float32)[None],
            gender=scalar("gender", 0.5),
            height_m=scalar("height_m", 1.7),
            mass_kg=scalar("mass_kg", 70.0),
        )
        return self.net(inputs, mesh=False)[-1].params.to(torch.float32)

    def sample(self, i: int) -> dict:
        """Pressure image (row-major 64 x 27, mmHg), labels, metrics, joints and per-joint errors."""
        res = self._computed(i)
        item = res["item"]
        pressure = np.asarray(item["pressure_mmhg"], dtype=np.float32)
        meta = {"sample": i}
        for k in (*LABEL_KEYS, *SCALAR_KEYS):
            if k in item and not isinstance(item[k], (list, dict)):
                meta[k] = json_number(item[k])
        if isinstance(self.dataset, NpzImages):
            for k, v in item.items():
                if k not in meta and np.ndim(v) == 0:
                    meta[k] = json_number(v)
        for k, vals in self.per_sample.items():
            if isinstance(vals[i], dict):  # evaluate's sample_id: shown as where the sample lives
                meta.setdefault("shard, row", f"{vals[i].get('shard')}, {vals[i].get('row')}")
            elif not isinstance(vals[i], list):
                meta.setdefault(k, json_number(vals[i]))
        true_joints = None
        if res["true"] is not None:
            stored = item.get("joints_m", item.get("joints"))
            true_joints = np.asarray(stored, dtype=np.float64) if stored is not None else res["true_joints"]
        est_joints = res.get("est_joints")
        errors = (
            np.linalg.norm(est_joints - true_joints, axis=-1)
            if est_joints is not None and true_joints is not None
            else None
        )
        if errors is not None and "mpjpe_m" not in meta:
            meta["mpjpe_m"] = round(float(errors.mean()), 4)
        return {
            "i": i,
            "meta": meta,
            "rows": int(pressure.shape[0]),
            "cols": int(pressure.shape[1]),
            "pressure": np.round(pressure.reshape(-1), 2).tolist(),
            "joints_true": None if true_joints is None else np.round(true_joints, 4).tolist(),
            "joints_est": None if est_joints is None else np.round(est_joints, 4).tolist(),
            "joint_errors_m": None if errors is None else np.round(errors, 5).tolist(),
        }

    def meshes(self, i: int) -> tuple[list[str], bytes]:
        """(layer names, float32 little-endian vertices of each layer one after the other)."""
        res = self._computed(i)
        layers = [
            (name, res[f"{key}_vertices"])
            for name, key in (("true", "true"), ("estimated", "est"))
            if f"{key}_vertices" in res
        ]
        return [n for n, _ in layers], b"".join(v.astype("<f4").tobytes() for _, v in layers)

    def faces(self) -> bytes:
        """The body model's triangles, uint32 little-endian (F, 3)."""
        return self.body.faces.numpy().astype("<u4").tobytes()


__all__ = ["Browser", "HINT", "NpzImages"]
