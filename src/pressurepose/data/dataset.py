"""A torch Dataset over a generated dataset's shards that never loads the whole dataset.

The manifest says how many rows each shard holds; the Parquet footer of a shard says how many
rows each row group holds. `__getitem__` finds the row group of a row and reads only that
row group, only the requested columns, keeping the last few row groups in a small LRU cache
(sequential or shard-local access reads each row group once). Memory stays at a few row
groups whatever the dataset's size (the original needed 64 GB of RAM for its training set).

Selections (split, partitions, genders, over_bed) are applied to the manifest's shard list,
so they cost nothing: every shard holds one (split, partition, gender, over_bed) group.
"""

from __future__ import annotations

import bisect
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch

from pressurepose.data.manifest import load_manifest
from pressurepose.data.schema import FIELD_BY_NAME, NAMES, from_table
from pressurepose.data.shards import CorruptShardError
from pressurepose.errors import UserError

DEFAULT_COLUMNS = (
    "pressure_mmhg",
    "depth_mm",
    "contact",
    "shape",
    "root_rotation",
    "root_translation",
    "pose",
    "joints_m",
    "mass_kg",
    "height_m",
    "head_angle_deg",
)


class PressurePoseDataset(torch.utils.data.Dataset):
    """Samples of a generated dataset as dicts of tensors (numbers) and strings (labels).

    Args:
        root: dataset folder (manifest.json, shards/).
        split: "train", "test" or None (both).
        partitions, genders: keep only these (None: all).
        over_bed: keep only samples with this flag (None: both).
        columns: fields to load (schema.FIELDS); string fields come as str.
        cache_row_groups: row groups kept in memory (per Dataset copy / DataLoader worker).
        verify: check every shard's sha256 when opening (reads every byte once).

    Items: {"pressure_mmhg": (64, 27) float32, ..., "joints_m": (24, 3) float64, ...}.
    """

    def __init__(
        self,
        root: str | Path,
        split: str | None = None,
        partitions=None,
        genders=None,
        over_bed: bool | None = None,
        columns=DEFAULT_COLUMNS,
        cache_row_groups: int = 8,
        verify: bool = True,
    ) -> None:
        self.root = Path(root)
        manifest = load_manifest(self.root, verify=verify)
        self.manifest = manifest
        unknown = [c for c in columns if c not in FIELD_BY_NAME]
        if unknown:
            raise UserError(f"unknown columns {unknown}; columns: {', '.join(NAMES)}")
        if split not in (None, "train", "test"):
            raise UserError(f"split must be 'train', 'test' or None, got {split!r}")
        self.columns = tuple(columns)
        self.cache_row_groups = max(1, int(cache_row_groups))
        keep = []
        for r in manifest["shards"]:
            if split is not None and r["split"] != split:
                continue
            if partitions is not None and r["partition"] not in partitions:
                continue
            if genders is not None and r["gender"] not in genders:
                continue
            if over_bed is not None and r["over_bed"] != over_bed:
                continue
            keep.append(r)
        self.shards = keep
        self._starts = np.cumsum([0] + [r["count"] for r in keep]).tolist()
        self._groups: dict[int, list[int]] = {}  # shard -> row-group start rows (lazy, from the footer)
        self._cache: OrderedDict = OrderedDict()

    def __len__(self) -> int:
        return self._starts[-1]

    def locate(self, i: int) -> tuple[int, int]:
        """(shard number in this selection, row within the shard) of item i."""
        if not -len(self) <= i < len(self):
            raise IndexError(f"index {i} out of range for a dataset of {len(self)} samples")
        i %= len(self)
        s = bisect.bisect_right(self._starts, i) - 1
        return s, i - self._starts[s]

    def _file(self, s: int):
        import pyarrow as pa
        import pyarrow.parquet as pq

        path = self.root / self.shards[s]["file"]
        try:
            return pq.ParquetFile(path)
        except (OSError, pa.ArrowException) as exc:  # ArrowInvalid for a damaged footer
            raise CorruptShardError(
                f"shard {path} cannot be read ({exc}); re-run `pressurepose generate` "
                "with the same arguments to regenerate it"
            ) from None

    def _row_group(self, s: int, row: int) -> tuple[dict, int]:
        starts = self.row_groups(s)
        g = bisect.bisect_right(starts, row) - 1
        key = (s, g)
        if key in self._cache:
            self._cache.move_to_end(key)
        else:
            table = self._file(s).read_row_group(g, columns=list(self.columns))
            self._cache[key] = from_table(table, self.columns)
            while len(self._cache) > self.cache_row_groups:
                self._cache.popitem(last=False)
        return self._cache[key], row - starts[g]

    def row_groups(self, s: int) -> list[int]:
        """Start rows of shard s's row groups, plus its row count at the end (footer only)."""
        if s not in self._groups:
            meta = self._file(s).metadata
            starts = np.cumsum([0] + [meta.row_group(g).num_rows for g in range(meta.num_row_groups)]).tolist()
            if starts[-1] != self.shards[s]["count"]:
                raise CorruptShardError(
                    f"shard {self.root / self.shards[s]['file']} holds {starts[-1]} rows but the "
                    f"manifest records {self.shards[s]['count']}; re-run `pressurepose generate` "
                    "with the same arguments to regenerate the dataset"
                )
            self._groups[s] = starts
        return self._groups[s]

    def __getitem__(self, i: int) -> dict:
        s, row = self.locate(int(i))
        arrays, r = self._row_group(s, row)
        item = {}
        for name in self.columns:
            v = arrays[name][r]
            item[name] = v if FIELD_BY_NAME[name].dtype == "str" else torch.as_tensor(np.array(v))
        return item

    def __getstate__(self):
        # DataLoader workers get the selection, not the cache.
        state = dict(self.__dict__)
        state["_cache"] = OrderedDict()
        return state


class BlockShuffleSampler(torch.utils.data.Sampler):
    """Random order that reads every row group once per epoch: the row groups (blocks) are
    shuffled, then taken `blocks_in_memory` at a time and their rows shuffled together. With
    the Dataset's `cache_row_groups >= blocks_in_memory`, an epoch reads each row group once
    (plain `shuffle=True` reads about one row group per item). Call `set_epoch` for a new order."""

    def __init__(self, dataset: PressurePoseDataset, blocks_in_memory: int = 8, seed: int = 0) -> None:
        if blocks_in_memory < 1:
            raise UserError(f"blocks_in_memory must be >= 1, got {blocks_in_memory}")
        self.dataset, self.blocks_in_memory, self.seed, self.epoch = dataset, blocks_in_memory, seed, 0
        self.blocks = []  # (first item, end item) of every row group, in dataset order
        for s in range(len(dataset.shards)):
            starts = dataset.row_groups(s)
            base = dataset._starts[s]
            self.blocks += [(base + a, base + b) for a, b in zip(starts[:-1], starts[1:])]

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.dataset)

    def __iter__(self):
        rng = np.random.default_rng([self.seed, self.epoch])
        order = rng.permutation(len(self.blocks))
        for k in range(0, len(order), self.blocks_in_memory):
            rows = np.concatenate([np.arange(*self.blocks[b]) for b in order[k : k + self.blocks_in_memory]])
            yield from rng.permutation(rows).tolist()


__all__ = ["BlockShuffleSampler", "DEFAULT_COLUMNS", "PressurePoseDataset"]
