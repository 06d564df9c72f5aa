"""`pressurepose generate`: plan the shards, make the missing ones on an engine, write the manifest.

Resume: the folder's `generate.json` pins what the dataset is (config fields that define its
content, mattress parameters, package version). A re-run with the same settings skips every
shard whose record exists and whose bytes match its sha256, remakes the others (a shard is a
pure function of the settings, so a remade shard equals the lost one), and writes the
manifest when all are there. Only this process writes files; workers return bytes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import time
from collections.abc import Iterator
from pathlib import Path

from pressurepose.data.manifest import MANIFEST, write_manifest
from pressurepose.data.shards import (
    SHARD_DIR,
    CorruptShardError,
    explain_os_error,
    read_record,
    verify_shard,
    write_shard,
)
from pressurepose.errors import UserError
from pressurepose.files import atomic_write
from pressurepose.generate.plan import (
    REPLACEMENT_BASE,
    REPLACEMENT_SPAN,
    TEST_INDEX_BASE,
    GenerateConfig,
    ShardSpec,
    plan_groups,
    plan_shards,
)
from pressurepose.generate.worker import WorkContext, make_shard
from pressurepose.sampling.partitions import get_partition

log = logging.getLogger(__name__)
SETTINGS = "generate.json"
TIMING = "timing.json"


# The articulated engine's settings a dataset pins (`generate.json`), beside the mattress.
ARTICULATED_JOINT_FIELDS = ("stiffness_scale", "neck_stiffness_scale", "spine_stiffness_scale", "self_contact_sink_m")


def _settings(cfg: GenerateConfig, mattress: dict) -> dict:
    from pressurepose import __version__
    from pressurepose.sampling.partitions import SAMPLING_LAW, SamplingConfig

    sampling = SamplingConfig()
    settings = {
        "pressurepose_version": __version__,
        "config": cfg.identity(),
        "mattress": mattress,
        "sampling_limits": {k: getattr(sampling, k) for k in ("max_failures", "max_shapes", "max_limb_draws")},
        "sampling_law": SAMPLING_LAW,
    }
    if cfg.sim2_engine == "articulated":
        from pressurepose.sim.articulated import ENGINE_REVISION, ArticulatedConfig

        # The body's joint springs define the rest as much as the bed does (docs/realism.md
        # "Relaxed joints"): a dataset rested with other springs does not resume. Nor does one
        # rested by another revision of the engine's numerics (its rests differ from these, so
        # a remade shard would not equal the lost one).
        joints = ArticulatedConfig()
        settings["articulated_joints"] = {k: getattr(joints, k) for k in ARTICULATED_JOINT_FIELDS}
        if joints.lying_extension:  # pinned only when set, so datasets made without it resume
            settings["articulated_joints"]["lying_extension"] = [list(e) for e in joints.lying_extension]
        settings["articulated_engine"] = ENGINE_REVISION
    if any(get_partition(g.partition).wedge for g in plan_groups(cfg)):  # so do the wedges (`sim.wedge`)
        from pressurepose.sim.wedge import Wedge

        settings["wedge"] = dataclasses.asdict(Wedge())
    if cfg.pillow > 0:  # the pillows' size and material define the images as much as the bed
        from pressurepose.sim.pillow import PILLOW_THICKNESS_M, Pillow

        settings["pillow"] = {**dataclasses.asdict(Pillow()), "thickness_m": list(PILLOW_THICKNESS_M)}
    return settings


def _prepare_folder(cfg: GenerateConfig, settings: dict) -> None:
    out = Path(cfg.out)
    try:
        (out / SHARD_DIR).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OSError(
            f"cannot create the dataset folder {out} ({exc.strerror or exc}); choose a writable --out"
        ) from None
    path = out / SETTINGS
    text = json.dumps(settings, indent=1, sort_keys=True)
    if path.exists():
        try:
            old = json.loads(path.read_text())
        except ValueError:
            old = None
        if old != settings:
            diff = sorted(
                k
                for k in set(settings["config"]) | set((old or {}).get("config", {}))
                if settings["config"].get(k) != (old or {}).get("config", {}).get(k)
            )
            what = ", ".join(diff) if diff else "mattress parameters or package version"
            hint = ""
            if "settle" in diff and "settle" not in (old or {}).get("config", {}):
                hint = " (it was made with MuJoCo, the default before the articulated engine: add --settle mujoco)"
            elif not diff and settings["sampling_law"] != (law := (old or {}).get("sampling_law", 1)):
                what = "the pose sampler's law"
                hint = (
                    " (drawn before face-down bodies stopped kneeling on the bed, docs/sampling.md)"
                    if law == 1
                    else f" (drawn under law {law}, this version draws law {settings['sampling_law']}: docs/generation.md)"
                )
            elif not diff and settings.get("articulated_joints") != (old or {}).get("articulated_joints"):
                what = "the articulated engine's joint springs"
                hint = (
                    " (rested with other joints than today's: springs relaxed to 0.8 x the seed's and a 5 cm"
                    " self-contact since session 42, 0.5 x and 2 cm before; docs/realism.md)"
                )
            elif not diff and settings.get("articulated_engine") != (old or {}).get("articulated_engine"):
                what = "the articulated engine's revisions"
                hint = " (made by another revision of the engine, whose rests differ: docs/benchmarks.md)"
            raise UserError(
                f"{out} holds a dataset made with other settings ({what} differ, see {path}){hint}; "
                "re-run with the same settings to resume, or choose another --out"
            )
        return
    if any((out / SHARD_DIR).iterdir()) or (out / MANIFEST).exists():
        raise UserError(f"{out} is not empty and has no {SETTINGS}; choose another --out")
    try:
        atomic_write(path, lambda tmp: Path(tmp).write_text(text))
    except OSError as exc:
        raise OSError(f"cannot write to {out} ({exc.strerror or exc}); choose a writable --out") from None


def _finished(out: Path, spec: ShardSpec) -> dict | None:
    """The shard's record if it is complete and intact; None (and a warning when it was
    damaged) otherwise."""
    record = read_record(out, spec.id)
    if record is None:
        return None
    if record.get("count") != spec.count or record.get("first_slot") != spec.first_slot:
        log.warning("shard %s: record does not match the plan; remaking it", spec.id)
        return None
    try:
        verify_shard(out, record)
    except CorruptShardError as exc:
        log.warning("%s - remaking it", exc)
        return None
    return record


def run_generate(cfg: GenerateConfig, progress: bool = True) -> dict:
    """Generate (or finish) the dataset in cfg.out; returns the manifest's summary."""
    from pressurepose.sim.mattress import MattressParams
    from pressurepose.sim.run import default_mattress

    if cfg.params is not None:
        mattress = MattressParams.load(cfg.params).to_dict()
    else:
        mattress = default_mattress(cfg.settle, cfg.sim2_engine).to_dict()
    if cfg.sim2_engine == "rigid":
        # The rigid rest has no soft tissue; leaving the field out keeps the settings of datasets
        # made before it existed, so they resume.
        mattress.pop("tissue_pa_per_m")
    settings = _settings(cfg, mattress)
    out = Path(cfg.out)
    _prepare_folder(cfg, settings)
    with _exclusive(out):
        return _generate(cfg, out, settings, mattress, progress)


@contextlib.contextmanager
def _exclusive(out: Path):
    """Hold an advisory lock on the folder for the run (released by the OS if the process dies):
    two runs writing the same folder would share temporary file names."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock
        yield
        return
    fh = open(out / ".lock", "a")
    try:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise UserError(f"another `pressurepose generate` is writing {out}; wait for it or stop it first") from None
        yield
    finally:
        fh.close()


def _generate(cfg: GenerateConfig, out: Path, settings: dict, mattress: dict, progress: bool) -> dict:
    for stale in (out / SHARD_DIR).glob(".*.partial*"):  # left by a killed run
        stale.unlink(missing_ok=True)

    shards = plan_shards(cfg)
    records: dict[str, dict] = {}
    for spec in shards:
        record = _finished(out, spec)
        if record is not None:
            records[spec.id] = record
    pending = [s for s in shards if s.id not in records]
    total = sum(s.count for s in shards)
    resumed = sum(r["count"] for r in records.values())
    if resumed:
        log.info("resuming: %d of %d samples already in %s", resumed, total, out)
    ctx = WorkContext(
        seed=cfg.seed,
        batch=cfg.batch,
        backend=cfg.backend,
        smpl_dir=str(cfg.smpl_dir) if cfg.smpl_dir else None,
        mattress=mattress,
        sim2=cfg.sim2_engine,
        settle=cfg.settle,
        pillow=cfg.pillow,
    )

    t0 = time.perf_counter()
    made = 0
    in_process = cfg.engine == "local" and cfg.workers == 1
    with _Progress(total, resumed, enabled=progress) as bar:
        # In this process the bar moves per simulated chunk; otherwise per finished shard.
        for spec, data, record in _engine(cfg, pending, ctx, bar.advance if in_process else None):
            records[spec.id] = write_shard(out, spec.id, data, record)
            made += record["count"]
            if not in_process:
                bar.advance(record["count"], record["candidates"] - record["count"])
    seconds = time.perf_counter() - t0

    header = {
        **settings,
        "seeds": {
            "dataset": cfg.seed,
            "initial_pose": "PoseSampler(SamplingConfig(partition, gender, over_bed, seed)).sample([index])",
            "sensor_noise": "per simulated chunk of a shard: SeedSequence([seed, crc32(shard id), chunk])",
            "test_index_base": TEST_INDEX_BASE,
            "replacement_base": REPLACEMENT_BASE,
            "replacement_span": REPLACEMENT_SPAN,
        },
    }
    ordered = [records[s.id] for s in shards]
    timing = {
        "samples_made": made,
        "seconds": round(seconds, 2),
        "samples_per_second": round(made / seconds, 3) if made and seconds > 0 else None,
        "engine": cfg.engine,
        "workers": cfg.workers,
    }
    try:
        write_manifest(out, header, ordered)
        atomic_write(out / TIMING, lambda tmp: Path(tmp).write_text(json.dumps(timing, indent=1)))
    except OSError as exc:
        raise explain_os_error(exc, out / MANIFEST) from None
    return {
        "total": total,
        "made": made,
        "resumed": resumed,
        "seconds": seconds,
        "shards": len(shards),
        "rejected": sum(r["candidates"] - r["count"] for r in ordered),
    }


def _engine(cfg: GenerateConfig, pending: list[ShardSpec], ctx: WorkContext, on_chunk) -> Iterator[tuple]:
    if not pending:
        return iter(())
    if cfg.engine == "ray":
        from pressurepose.generate.ray_engine import run_ray

        return run_ray(pending, ctx, cfg.workers, cfg.ray_address)
    if cfg.workers == 1:
        return ((spec, *make_shard(spec, ctx, on_chunk)) for spec in pending)
    return _run_pool(pending, ctx, cfg.workers)


def _init_worker(parent: int | None = None) -> None:
    import torch

    from pressurepose.generate.allocator import tune_allocator

    tune_allocator()
    torch.set_num_threads(1)
    logging.basicConfig(level=logging.WARNING)
    if parent is not None:
        import threading

        threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True).start()


def _exit_with_parent(parent: int, every_s: float = 1.0) -> None:
    """A pool worker's watch: when the generate process is gone (killed, SIGTERM, SIGKILL -
    no chance to shut the pool down), the orphaned worker exits instead of finishing its shard
    for nobody and then waiting forever with a body model in memory."""
    import os

    while True:
        time.sleep(every_s)
        if os.getppid() != parent:
            os._exit(1)


def _run_pool(pending: list[ShardSpec], ctx: WorkContext, workers: int) -> Iterator[tuple]:
    """Shards on a pool of `workers` processes (spawned: no forked torch/MuJoCo state), at most
    2 per worker in flight so finished shards never pile up in memory."""
    import concurrent.futures as cf
    import multiprocessing as mp

    todo = list(pending)
    import os

    with cf.ProcessPoolExecutor(
        workers, mp_context=mp.get_context("spawn"), initializer=_init_worker, initargs=(os.getpid(),)
    ) as pool:
        running: dict = {}
        while todo or running:
            while todo and len(running) < 2 * workers:
                spec = todo.pop(0)
                running[pool.submit(make_shard, spec, ctx)] = spec
            done, _ = cf.wait(running, return_when=cf.FIRST_COMPLETED)
            for fut in done:
                spec = running.pop(fut)
                yield (spec, *fut.result())


class _Progress:
    """A rich progress bar: samples, samples/s (this run), rejections, ETA."""

    def __init__(self, total: int, done: int, enabled: bool) -> None:
        self.total, self.done, self.enabled = total, done, enabled
        self.start = time.perf_counter()
        self.made = self.rejected = 0

    def __enter__(self):
        if self.enabled:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            self.bar = Progress(
                TextColumn("generating"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[rate]}"),
                TextColumn("{task.fields[rejected]}"),
                TimeRemainingColumn(),
                transient=True,
            )
            self.bar.__enter__()
            self.task = self.bar.add_task("generate", total=self.total, completed=self.done, rate="", rejected="")
        return self

    def advance(self, kept: int, rejected: int) -> None:
        self.made += kept
        self.rejected += rejected
        if self.enabled:
            rate = self.made / max(time.perf_counter() - self.start, 1e-9)
            self.bar.update(self.task, advance=kept, rate=f"{rate:.2f} samples/s", rejected=f"{self.rejected} rejected")

    def __exit__(self, *exc):
        if self.enabled:
            self.bar.__exit__(*exc)
        return False


__all__ = ["run_generate"]
