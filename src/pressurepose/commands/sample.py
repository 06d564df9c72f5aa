"""`pressurepose sample`: draw N initial poses of one partition, write them and their figures.

Output folder:
- poses.npz   arrays (no pickles): shape, root_rotation, root_translation, pose (float64, the
              BodyParams layout), joints (B, 24, 3) mat frame, index, cells, root_draw, and
              one `rejections_<reason>` array per rejection reason;
- config.json the SamplingConfig, body backend, package version, counts and timing;
- cells.png   the ankles and wrists over their cells; bodies.png a grid of sampled bodies.
Files are written to temporary names and renamed, so a folder never holds a partial result
under a final name.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Literal

import numpy as np
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from pressurepose import __version__
from pressurepose.body import load_body_model
from pressurepose.commands.outputs import Written, flat_config
from pressurepose.errors import UserError
from pressurepose.files import atomic_write
from pressurepose.mat import MatSpec
from pressurepose.sampling.partitions import SAMPLING_LAW, SamplingConfig
from pressurepose.sampling.sampler import InitialPoses, PoseSampler
from pressurepose.viz.sampling import plot_bodies, plot_cells, posed_vertices

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class SampleConfig:
    """Draw initial poses (seed A.1) for one partition of seed Table 4."""

    out: Path = Path("out/sample")
    """Output folder (created)."""
    n: int = 200
    """Number of initial poses."""
    sampling: SamplingConfig = SamplingConfig()
    """Partition, gender, over_bed, seed and the sampler's attempt limits."""
    start: int = 0
    """First sample index (indices start .. start + n - 1)."""
    backend: Literal["anny", "smpl"] = "anny"
    """Body model backend."""
    smpl_dir: Path | None = None
    """Folder with SMPL_*.npz/.pkl for backend=smpl (default $PRESSUREPOSE_SMPL_DIR)."""
    batch: int = 256
    """Samples drawn together (speed only; results do not depend on it)."""
    figures: int = 24
    """Bodies drawn in bodies.png (0: no body figure)."""


def run_sample(cfg: SampleConfig) -> Written:
    if cfg.n < 1:
        raise UserError(f"n must be >= 1, got {cfg.n}")
    if cfg.batch < 1:
        raise UserError(f"batch must be >= 1, got {cfg.batch}")
    if cfg.start < 0:
        raise UserError(f"start must be >= 0, got {cfg.start}")
    sampling = cfg.sampling
    options = {"model_dir": cfg.smpl_dir} if cfg.backend == "smpl" else {}
    model = load_body_model(cfg.backend, **options)
    sampler = PoseSampler(model, sampling)
    cfg.out.mkdir(parents=True, exist_ok=True)
    parts: list[InitialPoses] = []
    t0 = time.perf_counter()
    columns = (
        TextColumn("sampling"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[rate]}"),
        TimeRemainingColumn(),
    )
    with Progress(*columns, transient=True) as bar:
        task = bar.add_task("sample", total=cfg.n, rate="")
        for lo in range(cfg.start, cfg.start + cfg.n, cfg.batch):
            hi = min(lo + cfg.batch, cfg.start + cfg.n)
            parts.append(sampler.sample(range(lo, hi)))
            done = hi - cfg.start
            bar.update(task, completed=done, rate=f"{done / (time.perf_counter() - t0):.0f}/s")
    seconds = time.perf_counter() - t0
    poses = InitialPoses.cat(parts)

    arrays = {
        "shape": poses.params.shape.numpy(),
        "root_rotation": poses.params.root_rotation.numpy(),
        "root_translation": poses.params.root_translation.numpy(),
        "pose": poses.params.pose.numpy(),
        "joints": poses.joints.numpy(),
        "index": poses.index,
        "cells": poses.cells,
        "root_draw": poses.root_draw,
        "head_angle_deg": poses.head_angle_deg,
    }
    arrays.update({f"rejections_{k}": v for k, v in poses.rejections.items()})
    npz = atomic_write(cfg.out / "poses.npz", lambda tmp: np.savez_compressed(tmp, **arrays))

    title = f"{sampling.partition}, {sampling.gender}, over_bed={sampling.over_bed}: {cfg.n} samples"
    paths = {"poses": npz}
    paths["cells"] = atomic_write(
        cfg.out / "cells.png",
        lambda tmp: plot_cells(
            poses.joints.numpy(), poses.root_draw, poses.cells, tmp, title=f"{title} - distal joints over the cells"
        ),
    )
    k = min(cfg.figures, cfg.n)
    if k > 0:
        sub = poses.params.index(slice(0, k))
        labels = [f"#{i} cells {c.tolist()}" for i, c in zip(poses.index[:k], poses.cells[:k])]
        vertices = posed_vertices(model, sub)
        paths["bodies"] = atomic_write(
            cfg.out / "bodies.png", lambda tmp: plot_bodies(vertices, MatSpec(), tmp, labels)
        )

    low, high = model.shape_bounds(sampling.gender, model.shape_names)
    record = {
        "command": "sample",
        "pressurepose_version": __version__,
        "config": flat_config(cfg),
        "sampling": dataclasses.asdict(sampling),
        "body_backend": model.name,
        "shape_names": list(model.shape_names),
        "shape_low": low.tolist(),
        "shape_high": high.tolist(),
        "shape_power": model.shape_powers(model.shape_names).tolist(),  # density ~ t^(p - 1) on [low, high]
        "sampling_law": SAMPLING_LAW,
        "count": cfg.n,
        "seconds": round(seconds, 3),
        "samples_per_second": round(cfg.n / seconds, 1),
        "cell_counts": {
            name: np.bincount(poses.cells[:, i], minlength=8 if "arm" in name else 4).tolist()
            for i, name in enumerate(("left_leg", "right_leg", "left_arm", "right_arm"))
        },
        "rejections_total": {k: int(v.sum()) for k, v in poses.rejections.items()},
        "files": {k: p.name for k, p in paths.items()},
    }
    paths["config"] = atomic_write(
        cfg.out / "config.json", lambda tmp: Path(tmp).write_text(json.dumps(record, indent=1))
    )
    log.info("%d poses in %.1f s (%.0f/s)", cfg.n, seconds, cfg.n / seconds)
    return Written(paths, record)


def sample(cfg: SampleConfig) -> None:
    """Draw initial poses for one partition (seed A.1) and write poses.npz, cells.png and
    bodies.png."""
    written = run_sample(cfg)
    record, paths = written.record, written.paths
    print(
        f"{record['count']} poses ({record['samples_per_second']:.0f}/s) -> {cfg.out}: "
        + ", ".join(p.name for p in paths.values())
    )


def load_poses(path: str | Path) -> dict[str, np.ndarray]:
    """Arrays of a poses.npz written by `pressurepose sample` (no pickles are loaded)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"no poses file at {path}; run `pressurepose sample --out DIR` first")
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError) as exc:
        raise UserError(
            f"{path} is not a readable poses file ({exc}); write it again with `pressurepose sample`"
        ) from None
