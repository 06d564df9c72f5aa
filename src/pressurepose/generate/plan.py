"""What a dataset holds: presets (seed Table 4), the generation config, and its shards.

A dataset is a list of groups (split, partition, gender, over_bed, count), each cut into
shards of `shard_size` samples. A shard is the unit of work, and a pure function of the
config: shard k of a group fills its slots k*S .. k*S+S-1 with the sampler indices of those
slots (test indices are offset by TEST_INDEX_BASE so they never meet the training ones); a
sample rejected by the physics is replaced by the next index of a stream that belongs to that
shard alone (REPLACEMENT_BASE + shard number * REPLACEMENT_SPAN + r). So no two shards share
a sample, any shard can be (re)made alone, in any order, on any machine.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Literal

from pressurepose.errors import UserError
from pressurepose.sampling.partitions import PARTITIONS, get_partition

SPLITS = ("train", "test")
TEST_INDEX_BASE = 1 << 32
REPLACEMENT_BASE = 1 << 40
REPLACEMENT_SPAN = 1 << 20  # replacement indices per shard (far more than a shard ever needs)

# Seed Table 4: (partition, gender, over_bed) -> (train, test) images. Crossed legs and
# straight limbs have no test images without the over-the-bed flag.
PAPER_TABLE4: dict[tuple[str, str, bool], tuple[int, int]] = {}
for _part, _rows in (
    ("general", {False: (26000, 3000), True: (26000, 3000)}),
    ("supine", {False: (13000, 1500), True: (13000, 1500)}),
    ("hands_behind_head", {True: (2000, 500)}),
    ("prone_hands_up", {True: (4000, 500)}),
    ("crossed_legs", {False: (2000, 0), True: (2000, 500)}),
    ("straight_limbs", {False: (2000, 0), True: (2000, 500)}),
):
    for _over, _n in _rows.items():
        for _g in ("female", "male"):
            PAPER_TABLE4[(_part, _g, _over)] = _n

PRESETS = ("paper", "small", "tiny")


@dataclasses.dataclass(frozen=True)
class Group:
    split: str
    partition: str
    gender: str
    over_bed: bool
    count: int

    @property
    def key(self) -> str:
        return f"{self.split}-{self.partition}-{self.gender}-{'overbed' if self.over_bed else 'free'}"


@dataclasses.dataclass(frozen=True)
class ShardSpec:
    """One unit of work: `count` samples of a group, slots first_slot .. first_slot + count - 1."""

    group: Group
    number: int  # shard number within its group
    first_slot: int
    count: int

    @property
    def id(self) -> str:
        return f"{self.group.key}-{self.number:05d}"

    def primary_indices(self) -> range:
        base = TEST_INDEX_BASE if self.group.split == "test" else 0
        return range(base + self.first_slot, base + self.first_slot + self.count)

    def replacement_index(self, r: int) -> int:
        if r >= REPLACEMENT_SPAN:
            raise UserError(f"shard {self.id} needed more than {REPLACEMENT_SPAN} replacement samples")
        split = 0 if self.group.split == "train" else 1
        return REPLACEMENT_BASE * (1 + split) + self.number * REPLACEMENT_SPAN + r


@dataclasses.dataclass(frozen=True)
class GenerateConfig:
    """Generate a dataset: sampling -> sim #1 -> sim #2 -> sensor -> Parquet shards.

    Re-running the same command in the same folder resumes an interrupted run; the result is
    identical to an uninterrupted one."""

    out: Path = Path("out/dataset")
    """Dataset folder (created): shards/, manifest.json when done."""
    preset: Literal["paper", "small", "tiny"] = "small"
    """paper: seed Table 4 (184,000 train + 22,000 test); small: the same mix at 1/100
    (1,840 + 220); tiny: one sample per Table 4 row and split (36)."""
    partition: str | None = None
    """Only this partition (its preset rows; a partition outside the preset gets equal rows
    over genders and its over-the-bed choices, train split)."""
    n: int | None = None
    """Total samples, spread over the selected rows in the preset's proportions (exact total)."""
    seed: int = 0
    """Dataset seed: every sample is a function of (seed, partition, gender, over_bed, index)."""
    workers: int = 1
    """Parallel simulation processes (local engine) or Ray tasks in flight."""
    engine: Literal["local", "ray"] = "local"
    """local: a process pool on this machine; ray: Ray tasks (pip install 'pressurepose[ray]')."""
    ray_address: str | None = None
    """Ray cluster to join ('auto' after `ray start`); default: a local Ray instance."""
    params: Path | None = None
    """Mattress/sensor parameters (MattressParams JSON, e.g. from `pressurepose calibrate`)."""
    shard_size: int = 128
    """Samples per shard (the unit of work and of resume)."""
    batch: int = 32
    """Samples simulated together inside a shard (part of the dataset's definition; 16 before
    session 28 - such datasets resume with --batch 16)."""
    backend: Literal["anny", "smpl"] = "anny"
    smpl_dir: Path | None = None
    settle: Literal["articulated", "mujoco"] = "articulated"
    """How a drawn pose comes to rest: `articulated` (default): one batched quasi-static engine
    settles the mesh part by part on the soft bed (joint springs, self-contact, friction, soft
    tissue; no MuJoCo) and gives the image, on flat and raised beds (docs/physics.md);
    `mujoco`: the seed's procedure, sim #1 (MuJoCo, capsule body) then sim #2 - the generator's
    default before 2026-11-25, so older datasets resume with it."""
    sim2: Literal["rigid", "articulated"] | None = None
    """Sim #2 after MuJoCo (`--settle mujoco`): the whole mesh at rigid rest, or every body part on
    its own contact with compliant joints and soft tissue.
    Default: rigid after MuJoCo; the articulated engine makes the image itself (and allows nothing
    else)."""
    pillow: float = 0.0
    """Share of the samples whose head rests on a pillow (the articulated engine; a soft layer
    5-12 cm thick under the head whose load the mat reads spread over its footprint, `sim.pillow`,
    docs/physics.md "Pillow"); 0: none, as before."""

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise UserError(f"unknown preset {self.preset!r}; presets: {', '.join(PRESETS)}")
        if self.partition is not None:
            get_partition(self.partition)
        if self.n is not None and self.n < 1:
            raise UserError(f"n must be >= 1, got {self.n}")
        for name in ("workers", "shard_size", "batch"):
            if getattr(self, name) < 1:
                raise UserError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.seed < 0:
            raise UserError(f"seed must be >= 0, got {self.seed}")
        if not 0.0 <= self.pillow <= 1.0:
            raise UserError(f"pillow is a share of the samples, in [0, 1]; got {self.pillow}")
        if self.pillow > 0 and self.sim2_engine != "articulated":
            raise UserError("--pillow needs the articulated engine (the default --settle articulated)")
        if self.partition is not None and get_partition(self.partition).wedge and self.settle != "articulated":
            raise UserError(
                f"partition {self.partition} rests on wedges: it needs the articulated engine (the default --settle articulated)"
            )
        if self.settle == "articulated" and self.sim2 == "rigid":
            raise UserError(
                "--sim2 rigid needs --settle mujoco (the articulated engine, the default, makes the image itself)"
            )

    @property
    def sim2_engine(self) -> str:
        """The sim #2 in effect: `sim2`, or its default for the settling engine."""
        return self.sim2 or ("articulated" if self.settle == "articulated" else "rigid")

    def identity(self) -> dict:
        """The fields that define the dataset's content (not how fast it is made)."""
        keep = ("preset", "partition", "n", "seed", "shard_size", "batch", "backend")
        ident = {k: getattr(self, k) for k in keep}
        if self.sim2_engine != "rigid":  # absent for the rigid rest, so datasets made before it resume
            ident["sim2"] = self.sim2_engine
        if self.settle != "mujoco":
            ident["settle"] = self.settle
        if self.pillow > 0:  # absent without pillows, so datasets made before them resume
            ident["pillow"] = self.pillow
        return ident


def preset_rows(preset: str) -> list[Group]:
    """Rows of a preset in Table 4's order, train then test; empty rows dropped."""
    scale = {"paper": 1.0, "small": 0.01, "tiny": None}[preset]
    rows = []
    for s, split in enumerate(SPLITS):
        for (part, gender, over), counts in PAPER_TABLE4.items():
            if counts[s] == 0:
                continue
            n = 1 if scale is None else int(round(counts[s] * scale))
            rows.append(Group(split, part, gender, over, n))
    return rows


def plan_groups(cfg: GenerateConfig) -> list[Group]:
    rows = preset_rows(cfg.preset)
    if cfg.partition is not None:
        rows = [g for g in rows if g.partition == cfg.partition]
        if not rows:  # a partition Table 4 does not have (e.g. half_sitting)
            spec = get_partition(cfg.partition)
            rows = [Group("train", cfg.partition, g, o, 1) for o in spec.over_bed_choices for g in ("female", "male")]
    if cfg.n is not None:
        rows = _spread(rows, cfg.n)
    return [g for g in rows if g.count > 0]


def _spread(rows: list[Group], total: int) -> list[Group]:
    """Counts proportional to the rows' counts that sum exactly to `total` (largest remainder,
    ties to the earlier row)."""
    weight = sum(g.count for g in rows)
    exact = [total * g.count / weight for g in rows]
    counts = [math.floor(x) for x in exact]
    order = sorted(range(len(rows)), key=lambda i: (-(exact[i] - counts[i]), i))
    for i in order[: total - sum(counts)]:
        counts[i] += 1
    return [dataclasses.replace(g, count=c) for g, c in zip(rows, counts)]


def plan_shards(cfg: GenerateConfig) -> list[ShardSpec]:
    shards = []
    for g in plan_groups(cfg):
        for k, lo in enumerate(range(0, g.count, cfg.shard_size)):
            shards.append(ShardSpec(g, k, lo, min(cfg.shard_size, g.count - lo)))
    return shards


__all__ = [
    "GenerateConfig",
    "Group",
    "PAPER_TABLE4",
    "PARTITIONS",
    "PRESETS",
    "ShardSpec",
    "plan_groups",
    "plan_shards",
    "preset_rows",
]
