"""What a command's `run_*` returns: the files it wrote and the record it wrote with them, so
the command line prints its summary from memory instead of reading its own JSON back."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping
from pathlib import Path

from pressurepose.sampling.partitions import SamplingConfig


@dataclasses.dataclass(frozen=True)
class Written(Mapping):
    """name -> path of every file written (a read-only mapping), and the JSON record."""

    paths: dict[str, Path]
    record: dict

    def __getitem__(self, name: str) -> Path:
        return self.paths[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self.paths)

    def __len__(self) -> int:
        return len(self.paths)


def flat_config(cfg) -> dict:
    """A command's config as the flat JSON record it writes: the nested SamplingConfig's
    partition, gender, over_bed and seed in place of it, paths as strings."""
    out = {}
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if isinstance(v, SamplingConfig):
            out.update({k: getattr(v, k) for k in ("partition", "gender", "over_bed", "seed")})
        else:
            out[f.name] = str(v) if isinstance(v, Path) else v
    return out


__all__ = ["Written", "flat_config"]
