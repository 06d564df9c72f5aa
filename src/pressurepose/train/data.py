"""Training data: any torch Dataset of sample dicts, one adapter, a small .npz format and a
synthetic in-memory set made by the generator's own pipeline.

Items must hold (per sample, SI, mat frame): pressure_mmhg (64, 27), depth_mm (64, 27),
contact (64, 27), shape (S,), root_rotation (3,), root_translation (3,), pose (23, 3),
joints (24, 3) (or `joints_m`, as the dataset shards name it), gender (1.0 female, 0.0 male,
or the strings "female" / "male"), mass_kg, height_m. `collate` turns a list of them into
float32 tensors.

The .npz format (`write_npz` / `NpzDataset`): one uncompressed or compressed .npz file whose
arrays are those keys with a leading sample axis N (gender as float), loaded without pickles.
`open_dataset(DIR)` reads the generator's Parquet shards when DIR holds a manifest.json (and
`pressurepose.data.dataset` exists), else every *.npz file in DIR, else every dataset folder
(with a manifest.json) directly inside DIR - e.g. links to the paper mix and a partition generated
apart (docs/model-history.md).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from pressurepose.errors import UserError

log = logging.getLogger(__name__)

KEYS = (
    "pressure_mmhg",
    "depth_mm",
    "contact",
    "shape",
    "root_rotation",
    "root_translation",
    "pose",
    "joints",
    "gender",
    "mass_kg",
    "height_m",
)
SHAPES = {
    "pressure_mmhg": (64, 27),
    "depth_mm": (64, 27),
    "contact": (64, 27),
    "root_rotation": (3,),
    "root_translation": (3,),
    "pose": (23, 3),
    "joints": (24, 3),
    "gender": (),
    "mass_kg": (),
    "height_m": (),
}
GENDER_VALUE = {"female": 1.0, "male": 0.0}


def _gender(value) -> float:
    if isinstance(value, str):
        if value not in GENDER_VALUE:
            raise UserError(f"gender must be 'female' or 'male', got {value!r}")
        return GENDER_VALUE[value]
    return float(value)


def standardise(item: dict) -> dict[str, torch.Tensor]:
    """One sample dict -> {KEYS: float32 tensors}, ValueError naming a missing or misshapen key."""
    item = dict(item)
    if "joints" not in item and "joints_m" in item:
        item["joints"] = item["joints_m"]
    missing = [k for k in KEYS if k not in item]
    if missing:
        raise UserError(f"training samples lack {missing}; a dataset item needs {', '.join(KEYS)}")
    out = {}
    for k in KEYS:
        v = torch.tensor(_gender(item[k])) if k == "gender" else torch.as_tensor(np.asarray(item[k]))
        v = v.to(torch.float32)
        want = SHAPES.get(k)
        if want is not None and tuple(v.shape) != want:
            raise UserError(f"sample field {k} must have shape {want}, got {tuple(v.shape)}")
        out[k] = v
    return out


def collate(items: list[dict]) -> dict[str, torch.Tensor]:
    """List of sample dicts -> batch dict of (B, ...) float32 tensors."""
    std = [standardise(it) for it in items]
    return {k: torch.stack([s[k] for s in std]) for k in KEYS}


class TensorDictDataset(torch.utils.data.Dataset):
    """Samples held in memory as {key: (N, ...) tensor}."""

    def __init__(self, arrays: dict[str, torch.Tensor]) -> None:
        sizes = {k: len(v) for k, v in arrays.items()}
        if len(set(sizes.values())) != 1:
            raise UserError(f"arrays have different sample counts: {sizes}")
        self.arrays = arrays
        self.n = next(iter(sizes.values()))

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return {k: v[i] for k, v in self.arrays.items()}


def in_memory(dataset: torch.utils.data.Dataset, chunk: int = 1024) -> TensorDictDataset:
    """Every sample of `dataset` decoded once, in index order, as a TensorDictDataset of the
    collated KEYS (what the training loop reads; item i equals collate([dataset[i]])). Read in
    order, a generated dataset decodes each Parquet row group once (~0.25 ms per sample; in the
    training's random order ~2.7 ms, as much as a training step; docs/benchmarks.md); held in
    memory, a sample takes ~21 KB (the pressure, depth and contact maps as float32). Data already
    in memory (.npz files) is returned as it is. A set that would not fit in the memory the
    system reports available is refused with one line naming `--no-in-memory` (UserError)."""
    parts = dataset.datasets if isinstance(dataset, torch.utils.data.ConcatDataset) else [dataset]
    if all(isinstance(p, TensorDictDataset) for p in parts):
        return dataset
    n = len(dataset)
    first = collate([dataset[0]])
    need = n * sum(v.numel() * v.element_size() for v in first.values())
    available = _available_memory_bytes()
    if available is not None and need > 0.8 * available:
        raise UserError(
            f"the {n} training samples need ~{need / 1e9:.1f} GB decoded, {available / 1e9:.1f} GB of memory is "
            "available: give --no-in-memory to read them from their files each epoch"
        )
    log.info("decoding %d training samples into memory (~%.2f GB)", n, need / 1e9)
    out = {k: torch.empty((n, *v.shape[1:]), dtype=v.dtype) for k, v in first.items()}
    for lo in range(0, n, chunk):
        batch = collate([dataset[i] for i in range(lo, min(lo + chunk, n))])
        for k in KEYS:
            out[k][lo : lo + len(batch[k])] = batch[k]
    return TensorDictDataset(out)


def _available_memory_bytes() -> int | None:
    """MemAvailable of /proc/meminfo (Linux), else None (no check)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def write_npz(path: str | Path, arrays: dict[str, torch.Tensor | np.ndarray]) -> Path:
    from pressurepose.files import atomic_write

    data = {k: np.asarray(arrays[k].cpu() if isinstance(arrays[k], torch.Tensor) else arrays[k]) for k in KEYS}
    return atomic_write(Path(path), lambda tmp: np.savez_compressed(tmp, **data))


class NpzDataset(TensorDictDataset):
    def __init__(self, path: str | Path) -> None:
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as f:
                arrays = {k: torch.from_numpy(f[k]) for k in f.files}
        except (OSError, ValueError) as exc:
            raise UserError(f"{path} is not a readable .npz dataset ({exc})") from None
        missing = [k for k in KEYS if k not in arrays and not (k == "joints" and "joints_m" in arrays)]
        if missing:
            raise UserError(f"{path} lacks arrays {missing}; a .npz dataset holds {', '.join(KEYS)}")
        super().__init__(arrays)


def open_dataset(
    root: str | Path, split: str = "train", extra_columns: tuple[str, ...] = ()
) -> torch.utils.data.Dataset:
    """The training samples under `root`: generated shards (manifest.json) or *.npz files.
    `extra_columns`: further shard columns to load (e.g. "partition"; .npz files have none)."""
    root = Path(root)
    if not root.exists():
        raise UserError(f"no dataset at {root}")
    if root.is_file() and root.suffix == ".npz":
        return NpzDataset(root)
    if (root / "manifest.json").is_file():
        try:
            from pressurepose.data.dataset import PressurePoseDataset
        except ImportError:
            raise UserError(
                f"{root} holds dataset shards, but this install cannot read them (pressurepose.data.dataset missing)"
            ) from None
        # The dataset's names for KEYS (its joints column is joints_m).
        columns = tuple("joints_m" if k == "joints" else k for k in KEYS) + tuple(extra_columns)
        return PressurePoseDataset(root, split=split, columns=columns)
    sets = [NpzDataset(f) for f in sorted(root.glob("*.npz"))]
    if not sets:
        # A folder of dataset folders (e.g. links to a generated set and a partition made apart):
        # all of them, in name order.
        sets = [
            open_dataset(d, split, extra_columns)
            for d in sorted(root.iterdir())
            if d.is_dir() and (d / "manifest.json").is_file()
        ]
    if not sets:
        raise UserError(
            f"{root} holds neither a manifest.json (generated shards), .npz files, nor dataset "
            "folders with a manifest.json"
        )
    return sets[0] if len(sets) == 1 else torch.utils.data.ConcatDataset(sets)


def synthetic_arrays(
    n: int, seed: int = 0, partition: str = "supine", sim1: bool = False, body=None
) -> dict[str, torch.Tensor]:
    """n labelled samples made by the generator's pipeline, for tests and quick runs.

    Poses from `PoseSampler` (both genders, alternating); with `sim1` they settle in sim #1
    and go through `simulate_poses` exactly as a dataset is generated (~0.3-1 s a sample);
    without, the initial pose is rested directly by sim #2 (rigid, ~20 ms a sample) - same
    sensor and labels, a pose that has not settled. Rejected samples are dropped, so fewer
    than n may come back."""
    from pressurepose.body import load_body_model
    from pressurepose.sampling import PoseSampler, SamplingConfig
    from pressurepose.sim import MattressParams
    from pressurepose.sim.run import simulate_poses

    body = body or load_body_model("anny", dtype=torch.float64)
    parts = []
    for g, gender in enumerate(("female", "male")):
        count = (n + 1 - g) // 2
        if count == 0:
            continue
        cfg = SamplingConfig(partition=partition, gender=gender, seed=seed)
        poses = PoseSampler(body, cfg).sample(range(count))
        params = poses.params.to(body.dtype)
        # The generator's own path (sim.run.simulate_poses): with sim #1 as a dataset is made,
        # without it the drawn pose rested directly by the rigid sim #2.
        sim = simulate_poses(body, params, MattressParams(), seed=seed, settle="mujoco" if sim1 else "none")
        ok = torch.tensor([not r for r in sim.reason])
        rest, joints, q, c, p, mass = (
            sim.params,
            sim.joints,
            sim.depth_mm,
            sim.contact,
            sim.pressure_mmhg,
            sim.mass_kg,
        )
        height = body.measure(rest.shape).height_m
        part = {
            "pressure_mmhg": p,
            "depth_mm": q,
            "contact": c,
            "shape": rest.shape,
            "root_rotation": rest.root_rotation,
            "root_translation": rest.root_translation,
            "pose": rest.pose,
            "joints": joints,
            "gender": torch.full((count,), GENDER_VALUE[gender]),
            "mass_kg": mass,
            "height_m": height,
        }
        parts.append({k: v.detach()[ok].to(torch.float32) for k, v in part.items()})
    return {k: torch.cat([p[k] for p in parts]) for k in KEYS}


__all__ = [
    "KEYS",
    "NpzDataset",
    "TensorDictDataset",
    "collate",
    "open_dataset",
    "standardise",
    "synthetic_arrays",
    "in_memory",
    "write_npz",
]
