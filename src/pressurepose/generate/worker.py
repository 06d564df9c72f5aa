"""Make one shard: sample initial poses, simulate them, keep the accepted ones, encode Parquet.

Runs in whatever process the engine picks (this one, a pool worker, a Ray worker); it reads
no files but the optional mattress JSON's content (passed in as a dict) and writes nothing, and
returns the shard's bytes and its record to the one process that writes.
Torch uses one thread here, whatever the engine, so every engine runs the same arithmetic.
"""

from __future__ import annotations

import dataclasses
import logging
import time
import zlib
from collections import Counter

import numpy as np
import torch

from pressurepose.data.schema import SampleBatch, to_table
from pressurepose.data.shards import table_bytes
from pressurepose.errors import UserError
from pressurepose.generate.plan import ShardSpec

log = logging.getLogger(__name__)
REASON_UNREACHABLE = "sampling: constraints unreachable within the attempt limits"
REASON_NONFINITE = "non-finite output"
MAX_REJECTED_FRACTION = 0.9  # give up on a shard (clear error) when physics rejects more than this


@dataclasses.dataclass(frozen=True)
class WorkContext:
    """What every shard of a run needs besides its spec (small and picklable)."""

    seed: int
    batch: int
    backend: str
    smpl_dir: str | None
    mattress: dict  # MattressParams.to_dict()
    sim2: str = "rigid"  # sim #2: "rigid" or "articulated" (sim.run.simulate_poses)
    settle: str = "mujoco"  # "mujoco" or "articulated" (sim.run.simulate_poses)
    pillow: float = 0.0  # share of samples whose head rests on a pillow (`pillow_thickness`)


_MODELS: dict = {}


def _model(ctx: WorkContext):
    key = (ctx.backend, ctx.smpl_dir)
    if key not in _MODELS:
        from pressurepose.body import load_body_model

        options = {"model_dir": ctx.smpl_dir} if ctx.backend == "smpl" else {}
        _MODELS[key] = load_body_model(ctx.backend, dtype=torch.float64, **options)
    return _MODELS[key]


def noise_seed(seed: int, shard_id: str, chunk: int) -> int:
    """Sensor-noise seed of one simulated chunk of a shard."""
    return int(np.random.SeedSequence([seed, zlib.crc32(shard_id.encode()), chunk]).generate_state(1)[0])


def make_shard(spec: ShardSpec, ctx: WorkContext, on_chunk=None) -> tuple[bytes, dict]:
    """(Parquet bytes, record) of a shard with exactly spec.count accepted samples;
    `on_chunk(kept, rejected)` is called after every simulated chunk (progress)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _make_shard(spec, ctx, on_chunk)
    finally:
        torch.set_num_threads(threads)


def _make_shard(spec: ShardSpec, ctx: WorkContext, on_chunk=None) -> tuple[bytes, dict]:
    from pressurepose.sampling import PoseSampler, SamplingConfig
    from pressurepose.sim.mattress import MattressParams

    t0 = time.perf_counter()
    model = _model(ctx)
    g = spec.group
    sampler = PoseSampler(
        model, SamplingConfig(partition=g.partition, gender=g.gender, over_bed=g.over_bed, seed=ctx.seed)
    )
    mattress = MattressParams(**ctx.mattress)
    kept: list[SampleBatch] = []
    rejections: Counter = Counter()
    sampling_rejections: Counter = Counter()
    primary = list(spec.primary_indices())
    ahead = PosesAhead(sampler, primary, ctx.batch)
    n_kept = candidates = replacements = chunk = 0
    while n_kept < spec.count:
        todo = spec.count - n_kept
        drawn = None
        if candidates < len(primary):
            indices = primary[candidates : candidates + min(ctx.batch, len(primary) - candidates)]
            drawn = ahead.rows(candidates, indices)
        else:  # replacements for rejected samples: exactly as many as missing, from this shard's stream
            indices = [spec.replacement_index(replacements + r) for r in range(min(ctx.batch, todo))]
            replacements += len(indices)
        candidates += len(indices)
        batch, reasons, counts = simulate_indices(
            model,
            sampler,
            indices,
            mattress,
            noise_seed(ctx.seed, spec.id, chunk),
            g.split,
            ctx.sim2,
            ctx.settle,
            pillow=ctx.pillow,
            drawn=drawn,
        )
        chunk += 1
        sampling_rejections.update(counts)
        rejections.update(r for r in reasons if r)
        if batch is not None:
            kept.append(batch)
            n_kept += len(batch)
        if on_chunk is not None:
            on_chunk(0 if batch is None else len(batch), sum(1 for r in reasons if r))
        if candidates - n_kept > MAX_REJECTED_FRACTION * candidates and candidates >= max(4 * ctx.batch, 32):
            raise UserError(
                f"shard {spec.id}: {candidates - n_kept} of {candidates} samples rejected "
                f"({dict(rejections)}); check the mattress parameters (--params)"
            )
    data = SampleBatch.concat(kept)
    record = {
        "split": g.split,
        "partition": g.partition,
        "gender": g.gender,
        "over_bed": g.over_bed,
        "number": spec.number,
        "first_slot": spec.first_slot,
        "count": len(data),
        "candidates": candidates,
        "rejections": dict(sorted(rejections.items())),
        "sampling_rejections": {k: int(v) for k, v in sorted(sampling_rejections.items())},
    }
    log.debug("shard %s: %d samples in %.1f s", spec.id, len(data), time.perf_counter() - t0)
    return table_bytes(to_table(data)), record


def _sample(sampler, indices: list[int]):
    """InitialPoses of the indices that the sampler can satisfy, and the unreachable ones."""
    from pressurepose.sampling import UnreachableConstraints

    try:
        return sampler.sample(indices), []
    except UnreachableConstraints:
        # One sample gave up; a sample does not depend on its batch, so redo them one by one.
        ok, bad = [], []
        for i in indices:
            try:
                sampler.sample([i])
                ok.append(i)
            except UnreachableConstraints:
                bad.append(i)
        return (sampler.sample(ok) if ok else None), bad


# Primary poses drawn in one sampler call at most (whole chunks): the sampler's per-round work
# (the capsule fits of shapes drawn anew, limb windows) is shared by a block (21-35% less
# sampling CPU for 128 than for 4 x 32, docs/benchmarks.md "Session 50") while its memory (~0.3
# MB per pose) stays bounded whatever --shard-size.
AHEAD_POSES = 128


class PosesAhead:
    """A shard's primary initial poses drawn ahead in blocks of whole chunks, handed out chunk
    by chunk. A pose does not depend on its batch, so the chunks get the poses they would draw
    themselves."""

    def __init__(self, sampler, primary: list[int], batch: int):
        self.sampler, self.primary = sampler, primary
        self.block = batch * max(1, AHEAD_POSES // batch)
        self.start, self.poses, self.where = -1, None, {}

    def rows(self, first: int, indices: list[int]) -> tuple | None:
        """`_sample(sampler, indices)`'s result (poses, no unreachable ones) for the chunk of
        primary indices starting at position `first`, or None when a pose of its block is
        unreachable (the chunk then draws its own and finds which, `_sample`; rare, and the
        block's draw is lost)."""
        from pressurepose.sampling import UnreachableConstraints

        start = first - first % self.block
        if start != self.start:
            self.start = start
            try:
                self.poses = self.sampler.sample(self.primary[start : start + self.block])
            except UnreachableConstraints:
                self.poses = None
            self.where = {} if self.poses is None else {int(i): r for r, i in enumerate(self.poses.index)}
        if self.poses is None:
            return None
        return self.poses.take([self.where[i] for i in indices]), []


_PILLOW_STREAM = 0x9111  # keeps the pillows' draws apart from any other stream of the sample


def pillow_thickness(config, index, share: float) -> np.ndarray:
    """Each sample's pillow (m; 0: none) for a `SamplingConfig` and sampler indices: with
    probability `share` a thickness uniform in sim.pillow.PILLOW_THICKNESS_M, a function of
    (seed, partition, gender, over_bed, index) like the sample itself."""
    from pressurepose.sim.pillow import PILLOW_THICKNESS_M

    lo, hi = PILLOW_THICKNESS_M
    key = [config.seed, zlib.crc32(config.partition.encode()), zlib.crc32(config.gender.encode()), int(config.over_bed)]
    out = np.zeros(len(index))
    for k, i in enumerate(index):
        u = np.random.default_rng([*key, int(i), _PILLOW_STREAM]).random(2)
        out[k] = lo + (hi - lo) * u[1] if u[0] < share else 0.0
    return out


def simulate_indices(
    model,
    sampler,
    indices: list[int],
    mattress,
    seed: int,
    split: str,
    sim2: str = "rigid",
    settle: str = "mujoco",
    pillow: float = 0.0,
    drawn: tuple | None = None,
):
    """Sample and simulate `indices`; (SampleBatch of the accepted ones or None, reason per
    index ("" = kept), summed sampling rejection counts). `pillow`: the share of samples whose
    head rests on a pillow (`pillow_thickness`; the articulated rest only). `drawn`: their
    poses drawn already (`PosesAhead.rows`), else drawn here."""
    from pressurepose.sim.run import articulated_config_for, settle_config_for, simulate_poses

    initial, unreachable = drawn if drawn is not None else _sample(sampler, indices)
    reasons = {i: REASON_UNREACHABLE for i in unreachable}
    if initial is None:
        return None, [reasons[i] for i in indices], {}
    B = initial.batch_size
    # Each sample rests on its own bed (raised head section for half_sitting, flat otherwise).
    cfg = sampler.config
    sim = simulate_poses(
        model,
        initial.params,
        mattress,
        seed=seed,
        bed=initial.beds(),
        settle_config=settle_config_for(cfg.partition),
        settle=settle,
        sim2=sim2,
        articulated=articulated_config_for(cfg.partition),
        pillow_m=torch.from_numpy(pillow_thickness(cfg, initial.index, pillow)) if pillow > 0 else None,
    )
    height = sim.height_m.detach().numpy()  # measured with the mass, in float64
    p = sim.params
    arrays = dict(
        split=np.array([split] * B, dtype=object),
        partition=np.array([cfg.partition] * B, dtype=object),
        gender=np.array([cfg.gender] * B, dtype=object),
        over_bed=np.full(B, cfg.over_bed),
        index=np.asarray(initial.index, dtype=np.int64),
        pressure_mmhg=sim.pressure_mmhg.detach().numpy().astype(np.float32),
        depth_mm=sim.depth_mm.detach().numpy().astype(np.float32),
        contact=(sim.contact.detach().numpy() > 0.5).astype(np.uint8),
        shape=p.shape.detach().numpy(),
        root_rotation=p.root_rotation.detach().numpy(),
        root_translation=p.root_translation.detach().numpy(),
        pose=p.pose.detach().numpy(),
        joints_m=sim.joints.detach().numpy(),
        mass_kg=sim.mass_kg.detach().numpy().astype(np.float64),
        height_m=height.astype(np.float64),
        head_angle_deg=np.asarray(sim.head_angle_deg, dtype=np.float64),
        settle_steps=np.asarray(sim.settle_steps, dtype=np.int32),
        sink_mm=(np.asarray(sim.sink_m, dtype=np.float64) * 1e3).astype(np.float32),
    )
    good = []
    for b in range(B):
        reason = sim.reason[b]
        if not reason and not all(np.isfinite(v[b]).all() for v in arrays.values() if v.dtype.kind == "f"):
            reason = REASON_NONFINITE  # never store NaN; such a sample is replaced like any rejection
        reasons[int(initial.index[b])] = reason
        if not reason:
            good.append(b)
    counts = {k: int(np.asarray(v).sum()) for k, v in initial.rejections.items()}
    batch = SampleBatch(**{k: v[good] for k, v in arrays.items()}) if good else None
    return batch, [reasons[i] for i in indices], counts


__all__ = ["WorkContext", "make_shard", "noise_seed", "pillow_thickness", "simulate_indices"]
