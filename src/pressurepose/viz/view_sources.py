"""Where `pressurepose view` reads samples from: a dataset folder, a `.npz` of images, the
dataset an evaluation report or a training run points to (`viz.view_data`)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import torch

from pressurepose.body.params import BodyParams
from pressurepose.errors import UserError

PARAM_KEYS = tuple(f.name for f in dataclasses.fields(BodyParams))
LABEL_KEYS = ("split", "partition", "gender", "over_bed", "index")
SCALAR_KEYS = ("mass_kg", "height_m", "head_angle_deg", "settle_steps", "sink_mm")
IMAGES = ("metrics.png", "cases.png", "failures.png", "contact_sheet.png")  # shown when present
HINT = (
    "give a dataset folder (manifest.json), a `pressurepose evaluate` report folder (report.json), "
    "a training run folder (config.json) or a .npz of pressure images"
)


class NpzImages(torch.utils.data.Dataset):
    """A .npz of pressure images (`import-pmatdata` output, or the training .npz format):
    `pressure_mmhg` (N, 64, 27) mmHg plus any per-image arrays (N,) shown as labels, and the
    body (shape, root_rotation, root_translation, pose) when all four are there. Loaded
    whole without pickles: these files hold thousands of images, not 200K."""

    def __init__(self, path: Path) -> None:
        try:
            with np.load(path, allow_pickle=False) as f:
                arrays = {k: f[k] for k in f.files}
        except (OSError, ValueError, EOFError) as exc:
            raise UserError(f"{path} is not a readable .npz ({exc}); {HINT}") from None
        p = arrays.get("pressure_mmhg")
        if p is None or p.ndim != 3 or p.shape[1:] != (64, 27):
            raise UserError(f"{path} holds no pressure_mmhg array of shape (N, 64, 27); {HINT}")
        n = len(p)
        self.arrays = {k: v for k, v in arrays.items() if v.ndim >= 1 and len(v) == n}
        self.n = n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> dict:
        return {k: (v[i] if v[i].ndim else v[i].item()) for k, v in self.arrays.items()}


def open_samples(data: Path, split: str | None):
    """The samples of a dataset folder (shards, verified lazily: a bad shard is reported
    when read), a folder of training .npz files, or one .npz - in the order
    `train.data.open_dataset` lists them, so report indices match."""
    from pressurepose.data.dataset import PressurePoseDataset
    from pressurepose.train.data import open_dataset

    if (data / "manifest.json").is_file():
        from pressurepose.data.manifest import load_manifest
        from pressurepose.data.shards import verify_shard

        # A missing or truncated shard is named now (a stat per shard); the sha256 of every byte
        # is not checked here - that reads the whole dataset (`pressurepose info` does it).
        for r in load_manifest(data, verify=False)["shards"]:
            verify_shard(data, r, contents=False)
        columns = ("pressure_mmhg", *PARAM_KEYS, "joints_m", *SCALAR_KEYS, *LABEL_KEYS)
        return PressurePoseDataset(data, split=split, columns=columns, verify=False, cache_row_groups=4)
    if data.is_file() and data.suffix == ".npz":
        return NpzImages(data)
    return open_dataset(data, split=split or "train")


def json_number(v):
    """A JSON-ready scalar: 4 decimals, NaN and infinities as None."""
    v = v.item() if isinstance(v, (torch.Tensor, np.ndarray, np.generic)) else v
    if isinstance(v, float):
        return round(v, 4) if math.isfinite(v) else None
    return v


__all__ = [
    "HINT",
    "IMAGES",
    "LABEL_KEYS",
    "PARAM_KEYS",
    "SCALAR_KEYS",
    "NpzImages",
    "json_number",
    "open_samples",
]
