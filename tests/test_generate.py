"""Dataset generation: presets and plans, exact counts, determinism, resume after SIGKILL
(finished on a process pool), damaged shards, the Ray engine agreeing with the in-process run."""

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from pressurepose.cli import main
from pressurepose.data.manifest import load_manifest
from pressurepose.data.schema import NAMES, SampleBatch, from_table
from pressurepose.generate import worker
from pressurepose.generate.plan import (
    PAPER_TABLE4,
    REPLACEMENT_BASE,
    TEST_INDEX_BASE,
    GenerateConfig,
    plan_groups,
    plan_shards,
    preset_rows,
)
from pressurepose.generate.run import run_generate
from pressurepose.sampling.partitions import PARTITIONS, SAMPLING_LAW
from pressurepose.sim.articulated import ENGINE_REVISION

# A tiny dataset: 6 supine samples spread over the preset's supine rows, shards of 2, chunks of 2.
SMALL = dict(preset="small", partition="supine", n=6, shard_size=2, batch=2, seed=3)
SMALL_ARGS = ["--partition", "supine", "--n", "6", "--shard-size", "2", "--batch", "2", "--seed", "3"]


def cli(*args, **kwargs):
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).parents[1] / "src"))
    return subprocess.Popen(
        [sys.executable, "-m", "pressurepose.cli", *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        **kwargs,
    )


def files_of(root: Path) -> dict[str, bytes]:
    """Every file that defines the dataset (shards, records, manifest), by relative path."""
    keep = [p for p in root.rglob("*") if p.is_file() and p.name not in ("timing.json", "contact_sheet.png")]
    return {str(p.relative_to(root)): p.read_bytes() for p in keep}


def read_all(root: Path) -> dict[str, np.ndarray]:
    manifest = load_manifest(root)
    parts = [from_table(pq.read_table(root / r["file"])) for r in manifest["shards"]]
    return {k: np.concatenate([p[k] for p in parts]) for k in NAMES}


def fake_batch(index, rng, split):
    n = len(index)
    f = dict(
        split=np.array([split] * n, dtype=object),
        partition=np.array(["supine"] * n, dtype=object),
        gender=np.array(["female"] * n, dtype=object),
        over_bed=np.zeros(n, bool),
        index=index,
        pressure_mmhg=rng.uniform(0, 100, (n, 64, 27)).astype(np.float32),
        depth_mm=np.zeros((n, 64, 27), np.float32),
        contact=np.zeros((n, 64, 27), np.uint8),
        shape=rng.random((n, 6)),
        root_rotation=np.zeros((n, 3)),
        root_translation=np.zeros((n, 3)),
        pose=np.zeros((n, 23, 3)),
        joints_m=np.zeros((n, 24, 3)),
        mass_kg=np.full(n, 70.0),
        height_m=np.full(n, 1.7),
        head_angle_deg=np.zeros(n),
        settle_steps=np.zeros(n, np.int32),
        sink_mm=np.zeros(n, np.float32),
    )
    return SampleBatch(**f)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("gen") / "ref"
    summary = run_generate(GenerateConfig(out=out, **SMALL), progress=False)
    return out, summary


# --- plans ------------------------------------------------------------------------------------


def test_paper_preset_is_seed_table4():
    rows = preset_rows("paper")
    assert sum(g.count for g in rows if g.split == "train") == 184_000
    assert sum(g.count for g in rows if g.split == "test") == 22_000
    per = {}
    for g in rows:
        per.setdefault(g.partition, [0, 0])[g.split == "test"] += g.count
    assert per == {
        "general": [104_000, 12_000],
        "supine": [52_000, 6_000],
        "hands_behind_head": [4_000, 1_000],
        "prone_hands_up": [8_000, 1_000],
        "crossed_legs": [8_000, 1_000],
        "straight_limbs": [8_000, 1_000],
    }
    # every row is a (partition, gender, over_bed) the sampler accepts
    for part, _, over in PAPER_TABLE4:
        assert over in PARTITIONS[part].over_bed_choices
    small = preset_rows("small")
    assert [g.count * 100 for g in small] == [g.count for g in rows]
    assert len(preset_rows("tiny")) == len(rows) and all(g.count == 1 for g in preset_rows("tiny"))


@pytest.mark.parametrize("n", [1, 7, 1000, 2063])
def test_n_is_spread_exactly(n):
    groups = plan_groups(GenerateConfig(preset="paper", n=n))
    assert sum(g.count for g in groups) == n
    if n >= 1000:  # proportions follow Table 4 within one sample per row
        paper = {(g.split, g.partition, g.gender, g.over_bed): g.count for g in preset_rows("paper")}
        for g in groups:
            assert abs(g.count - n * paper[(g.split, g.partition, g.gender, g.over_bed)] / 206_000) < 1
    only = plan_groups(GenerateConfig(preset="paper", partition="crossed_legs", n=n))
    assert sum(g.count for g in only) == n and {g.partition for g in only} == {"crossed_legs"}


def test_partition_outside_the_preset_gets_its_own_rows():
    extra = [p for p in PARTITIONS if p not in {k[0] for k in PAPER_TABLE4}]
    for name in extra:  # e.g. half_sitting
        groups = plan_groups(GenerateConfig(partition=name, n=10))
        assert sum(g.count for g in groups) == 10 and {g.partition for g in groups} == {name}
        assert {g.over_bed for g in groups} == set(PARTITIONS[name].over_bed_choices)


def test_shards_cover_slots_once_and_indices_never_collide():
    shards = plan_shards(GenerateConfig(preset="small", shard_size=7))
    by_group = {}
    for s in shards:
        by_group.setdefault(s.group, []).extend(range(s.first_slot, s.first_slot + s.count))
    for g, slots in by_group.items():
        assert sorted(slots) == list(range(g.count))
    seen = set()
    for s in shards:
        key = (s.group.partition, s.group.gender, s.group.over_bed)  # the sampler's stream
        idx = list(s.primary_indices()) + [s.replacement_index(r) for r in (0, 1, 999)]
        assert all((i >= TEST_INDEX_BASE) == (s.group.split == "test") for i in s.primary_indices())
        assert all(i >= REPLACEMENT_BASE for i in idx[-3:])
        for i in idx:
            assert (key, i) not in seen
            seen.add((key, i))
    assert len({s.id for s in shards}) == len(shards)


def test_bad_settings_are_clear(tmp_path, capsys):
    with pytest.raises(ValueError, match="unknown partition 'sitting'"):
        GenerateConfig(partition="sitting")
    for field, value in (("n", 0), ("workers", 0), ("shard_size", 0), ("seed", -1)):
        with pytest.raises(ValueError, match=field):
            GenerateConfig(**{field: value})
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["generate", "--out", str(blocker / "ds"), "--n", "1"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "cannot create the dataset folder" in err
    # A config that fails its own checks is one line too (not tyro's box naming its inner fields).
    assert main(["generate", "--out", str(tmp_path / "ds"), "--partition", "sitting"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown partition" in err[0] and "tyro" not in err[0]


# --- one shard ----------------------------------------------------------------------------


def test_rejected_samples_are_replaced_from_the_shards_own_stream(anny64, monkeypatch):
    """A shard keeps exactly `count` samples: rejected primary indices are replaced by
    replacement indices, the same ones every time."""

    handed = []

    def fake(model, sampler, indices, mattress, seed, split, sim2="rigid", settle="mujoco", pillow=0.0, drawn=None):
        handed.append((list(indices), None if drawn is None else list(drawn[0].index), drawn and drawn[1]))
        rng = np.random.default_rng(seed)
        keep = [i for i in indices if i % 3 != 0]  # index 0, 3, 6, ... and some replacements rejected
        n = len(keep)
        b = fake_batch(np.array(keep, dtype=np.int64), rng, split) if n else None
        return b, ["fake" if i % 3 == 0 else "" for i in indices], {"collisions": len(indices)}

    monkeypatch.setattr(worker, "simulate_indices", fake)
    monkeypatch.setitem(worker._MODELS, ("anny", None), anny64)
    ctx = worker.WorkContext(seed=0, batch=4, backend="anny", smpl_dir=None, mattress={})
    spec = plan_shards(GenerateConfig(partition="supine", n=200, shard_size=10))[1]
    data, record = worker.make_shard(spec, ctx)
    again, _ = worker.make_shard(spec, ctx)
    assert data == again
    import io

    rows = from_table(pq.read_table(io.BytesIO(data)))
    primary = list(spec.primary_indices())
    assert len(rows["index"]) == spec.count == record["count"] == 10
    assert len(set(rows["index"])) == 10
    kept_primary = [i for i in primary if i % 3 != 0]
    assert list(rows["index"][: len(kept_primary)]) == kept_primary
    assert all(i >= REPLACEMENT_BASE for i in rows["index"][len(kept_primary) :])
    assert record["rejections"] == {"fake": record["candidates"] - 10}
    assert record["sampling_rejections"] == {"collisions": record["candidates"]}
    # The primary chunks come with their poses drawn ahead (one sampler call per shard), in
    # order; the replacements are drawn chunk by chunk.
    primary_chunks = [h for h in handed[: len(handed) // 2] if h[0][0] < REPLACEMENT_BASE]
    assert [i for h in primary_chunks for i in h[0]] == primary
    assert all(h[1] == h[0] and h[2] == [] for h in primary_chunks)
    assert all(h[1] is None for h in handed[: len(handed) // 2] if h[0][0] >= REPLACEMENT_BASE)


@pytest.mark.parametrize("partition", ["general", "half_sitting"])  # half_sitting: a bed per pose
def test_poses_drawn_ahead_are_the_poses_drawn_per_chunk(anny64, partition):
    """A block's poses drawn in one call and handed out by chunk (`PosesAhead.rows`) are the
    ones each chunk would draw itself, every field in order."""
    from pressurepose.sampling import PoseSampler, SamplingConfig

    sampler = PoseSampler(anny64, SamplingConfig(partition=partition, gender="male", seed=3))
    primary = [5, 6, 7, 8, 9]
    ahead = worker.PosesAhead(sampler, primary, batch=2)
    for first in (0, 2, 4):
        chunk = primary[first : first + 2]
        poses, unreachable = ahead.rows(first, chunk)
        alone = sampler.sample(chunk)
        assert list(poses.index) == chunk and unreachable == []
        for name in ("shape", "pose", "root_rotation", "root_translation"):
            assert torch.equal(getattr(poses.params, name), getattr(alone.params, name))
        assert torch.equal(poses.joints, alone.joints)
        for name in ("cells", "root_draw", "head_angle_deg"):
            assert np.array_equal(getattr(poses, name), getattr(alone, name))
        assert all(np.array_equal(poses.rejections[k], alone.rejections[k]) for k in alone.rejections)
    if partition == "half_sitting":
        assert len(set(ahead.poses.head_angle_deg.tolist())) > 1  # the beds differ and were reordered with the poses


def test_a_shard_is_the_same_drawn_ahead_or_chunk_by_chunk(anny64, monkeypatch):
    """make_shard over several chunks and replacements: the poses each chunk simulates are the
    same bit for bit whether drawn ahead in blocks (one sampler call per block) or chunk by
    chunk (as when a block has an unreachable pose: `PosesAhead.rows` None)."""
    from pressurepose.sampling import PoseSampler

    calls, seen = [], []
    real_sample = PoseSampler.sample

    def counting(self, indices):
        calls.append(list(indices))
        return real_sample(self, indices)

    def fake(model, sampler, indices, mattress, seed, split, sim2="rigid", settle="mujoco", pillow=0.0, drawn=None):
        initial = drawn[0] if drawn is not None else worker._sample(sampler, indices)[0]
        seen.append((list(indices), initial.params.pose.clone(), initial.params.shape.clone()))
        keep = [i for i in indices if i % 4 != 1]  # some rejected: replacements follow
        rng = np.random.default_rng(seed)
        return (
            fake_batch(np.array(keep, dtype=np.int64), rng, split) if keep else None,
            ["fake" if i % 4 == 1 else "" for i in indices],
            {},
        )

    monkeypatch.setattr(PoseSampler, "sample", counting)
    monkeypatch.setattr(worker, "simulate_indices", fake)
    monkeypatch.setattr(worker, "AHEAD_POSES", 6)  # blocks of 2 chunks of 3
    monkeypatch.setitem(worker._MODELS, ("anny", None), anny64)
    ctx = worker.WorkContext(seed=0, batch=3, backend="anny", smpl_dir=None, mattress={})
    spec = plan_shards(GenerateConfig(partition="supine", n=200, shard_size=10))[1]
    ahead_data, _ = worker.make_shard(spec, ctx)
    ahead_seen, ahead_calls = list(seen), list(calls)
    seen.clear(), calls.clear()
    monkeypatch.setattr(worker.PosesAhead, "rows", lambda self, first, indices: None)
    chunk_data, _ = worker.make_shard(spec, ctx)
    assert ahead_data == chunk_data
    assert [s[0] for s in ahead_seen] == [s[0] for s in seen]
    assert all(torch.equal(a[1], b[1]) and torch.equal(a[2], b[2]) for a, b in zip(ahead_seen, seen))
    primary = list(spec.primary_indices())
    assert len(seen) > 4  # four primary chunks and at least one of replacements
    # Ahead: one call per block of primary indices, then the replacements chunk by chunk.
    assert ahead_calls[:2] == [primary[:6], primary[6:]]
    assert all(min(c) >= REPLACEMENT_BASE for c in ahead_calls[2:])
    assert calls[:4] == [primary[0:3], primary[3:6], primary[6:9], primary[9:]]


# --- whole runs ---------------------------------------------------------------------------


@pytest.mark.slow
def test_counts_exact_no_nan_and_labels_consistent(reference, anny64):
    out, summary = reference
    manifest = load_manifest(out)
    groups = plan_groups(GenerateConfig(**SMALL))
    assert manifest["total"] == summary["total"] == 6 == sum(g.count for g in groups)
    for g in groups:
        assert manifest["counts"][g.split][g.partition][g.gender] == sum(
            h.count for h in groups if (h.split, h.partition, h.gender) == (g.split, g.partition, g.gender)
        )
    assert manifest["rejected"] == sum(manifest["rejections"].values()) == manifest["candidates"] - 6
    data = read_all(out)
    assert len(data["index"]) == 6
    for name, value in data.items():
        if value.dtype.kind == "f":
            assert np.isfinite(value).all(), name
    for r in manifest["shards"]:
        assert pq.ParquetFile(out / r["file"]).metadata.num_rows == r["count"]
    keys = set(zip(data["split"], data["gender"], data["over_bed"], data["index"]))
    assert len(keys) == 6
    p = data["pressure_mmhg"]
    assert p.shape == (6, 64, 27) and p.min() >= 0 and p.max() <= 100 and (p.reshape(6, -1).max(1) > 0).all()
    assert set(np.unique(data["contact"])) <= {0, 1}
    assert (data["head_angle_deg"] == 0).all() and (data["mass_kg"] > 30).all()
    assert ((data["height_m"] > 1.3) & (data["height_m"] < 2.2)).all()
    # The stored parameters reproduce the stored joints through the body model.
    from pressurepose.body.params import BodyParams

    params = BodyParams(*(torch.from_numpy(data[k]) for k in ("shape", "root_rotation", "root_translation", "pose")))
    joints = anny64.joints(params).numpy()
    assert np.abs(joints - data["joints_m"]).max() < 1e-6
    # ... and the stored height and mass through its measure (one float64 measure of the shape).
    measured = anny64.measure(params.shape)
    np.testing.assert_allclose(data["height_m"], measured.height_m.numpy(), rtol=1e-9)
    np.testing.assert_allclose(data["mass_kg"], measured.mass_kg.numpy(), rtol=1e-6)
    # each sample's initial pose is the sampler's for its index (regenerable alone)
    from pressurepose.sampling import PoseSampler, SamplingConfig

    i = int(np.argmax(data["index"] < TEST_INDEX_BASE))
    cfg = SamplingConfig(partition="supine", gender=data["gender"][i], over_bed=bool(data["over_bed"][i]), seed=3)
    initial = PoseSampler(anny64, cfg).sample([int(data["index"][i])])
    assert np.allclose(initial.params.shape.numpy()[0], data["shape"][i])


@pytest.mark.slow
def test_resume_after_sigkill_equals_an_uninterrupted_run(reference, tmp_path):
    ref, _ = reference
    out = tmp_path / "ds"
    args = ["generate", "--out", str(out), *SMALL_ARGS]
    for kill_after in (1, 2):  # SIGKILL once the k-th new shard record lands (mid-run, writing the next)
        before = len(list((out / "shards").glob("*.json"))) if out.exists() else 0
        p = cli(*args)
        deadline = time.time() + 300
        while time.time() < deadline and p.poll() is None:
            if len(list((out / "shards").glob("*.json"))) >= before + kill_after if out.exists() else False:
                break
            time.sleep(0.01)
        assert p.poll() is None, "the run finished before it could be killed"
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
        assert not (out / "manifest.json").exists()
        with pytest.raises(ValueError, match="unfinished dataset"):
            load_manifest(out)
    p = cli(*args, "--workers", "2")  # the last run on a process pool: same shards as in-process
    stdout, stderr = p.communicate(timeout=300)
    assert p.returncode == 0, stderr
    assert "already there" in stdout
    assert files_of(out) == files_of(ref)


@pytest.mark.slow
def test_resume_remakes_damaged_and_half_written_shards(reference, tmp_path, caplog):
    ref, _ = reference
    out = tmp_path / "ds"
    shutil.copytree(ref, out)
    (out / "manifest.json").unlink()
    shards = sorted((out / "shards").glob("*.parquet"))
    data = bytearray(shards[0].read_bytes())
    data[200] ^= 0xFF
    shards[0].write_bytes(bytes(data))  # corrupted
    shards[1].with_suffix(".json").unlink()  # killed between the shard and its record
    (out / "shards" / ".x.partial.parquet").write_bytes(b"partial")  # killed inside a write
    summary = run_generate(GenerateConfig(out=out, **SMALL), progress=False)
    assert summary["made"] == sum(
        json.loads((ref / "shards" / f"{p.stem}.json").read_text())["count"] for p in shards[:2]
    )
    assert "sha256 does not match" in caplog.text
    assert files_of(out) == files_of(ref)
    with pytest.raises(ValueError, match="other settings .*seed"):
        run_generate(GenerateConfig(out=out, **dict(SMALL, seed=4)), progress=False)
    # A dataset made before the articulated default (no `settle` in its settings) names the fix.
    settings = json.loads((out / "generate.json").read_text())
    settings["config"].pop("settle", None)
    (out / "generate.json").write_text(json.dumps(settings))
    with pytest.raises(ValueError, match="add --settle mujoco"):
        run_generate(GenerateConfig(out=out, **dict(SMALL, settle="articulated")), progress=False)
    # One rested with the seed's full joint springs (before they were relaxed) does not resume.
    settings = json.loads((ref / "generate.json").read_text())
    assert settings["articulated_joints"]["stiffness_scale"] == 0.8
    settings["articulated_joints"]["stiffness_scale"] = 1.0
    (out / "generate.json").write_text(json.dumps(settings))
    with pytest.raises(ValueError, match="joint springs differ.*relaxed"):
        run_generate(GenerateConfig(out=out, **SMALL), progress=False)
    del settings["articulated_joints"]
    (out / "generate.json").write_text(json.dumps(settings))
    with pytest.raises(ValueError, match="joint springs differ"):
        run_generate(GenerateConfig(out=out, **SMALL), progress=False)
    # One drawn under the sampling law before face-down bodies stopped kneeling (no
    # `sampling_law` in its settings) does not resume either, and says why.
    settings = json.loads((ref / "generate.json").read_text())
    assert settings["sampling_law"] == SAMPLING_LAW
    del settings["sampling_law"]
    (out / "generate.json").write_text(json.dumps(settings))
    with pytest.raises(ValueError, match="sampler's law differ.*kneeling"):
        run_generate(GenerateConfig(out=out, **SMALL), progress=False)
    settings["sampling_law"] = SAMPLING_LAW - 1  # a later law: which one it was drawn under
    (out / "generate.json").write_text(json.dumps(settings))
    with pytest.raises(ValueError, match=f"drawn under law {SAMPLING_LAW - 1}, this version draws law {SAMPLING_LAW}"):
        run_generate(GenerateConfig(out=out, **SMALL), progress=False)
    # One rested by another revision of the engine's numerics (or before revisions were
    # pinned) does not resume either: a remade shard would not equal the lost one.
    settings = json.loads((ref / "generate.json").read_text())
    assert settings["articulated_engine"] == ENGINE_REVISION
    for revision in (ENGINE_REVISION - 1, None):
        if revision is None:
            del settings["articulated_engine"]
        else:
            settings["articulated_engine"] = revision
        (out / "generate.json").write_text(json.dumps(settings))
        with pytest.raises(ValueError, match="engine's revisions differ.*another revision"):
            run_generate(GenerateConfig(out=out, **SMALL), progress=False)


def _children(pid: int) -> list[int]:
    """Live processes whose parent is `pid` (Linux /proc)."""
    kids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            kids.append(int(stat.parent.name))
    return kids


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
def test_pool_workers_exit_when_the_generate_process_is_killed(tmp_path):
    p = cli(
        "generate",
        "--out",
        str(tmp_path / "ds"),
        "--partition",
        "supine",
        "--n",
        "64",
        "--shard-size",
        "2",
        "--batch",
        "2",
        "--workers",
        "2",
    )
    try:
        deadline = time.time() + 120
        workers: list[int] = []
        while time.time() < deadline and p.poll() is None:
            # the pool's two workers (besides multiprocessing's resource tracker) and a shard started
            workers = [c for c in _children(p.pid) if b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes()]
            if len(workers) == 2:
                break
            time.sleep(0.1)
        assert p.poll() is None and len(workers) == 2, "the pool did not start"
        time.sleep(2.0)  # mid-shard
        os.kill(p.pid, signal.SIGKILL)  # the main process only: no chance to shut the pool down
        p.wait()
        deadline = time.time() + 15
        while time.time() < deadline and any(Path(f"/proc/{w}").exists() for w in workers):
            time.sleep(0.1)
        alive = [
            w
            for w in workers
            if Path(f"/proc/{w}").exists() and Path(f"/proc/{w}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
        ]
        assert not alive, f"orphaned workers still running: {alive}"
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGKILL)


@pytest.mark.slow
def test_ray_engine_makes_the_same_dataset(reference, tmp_path):
    ref, _ = reference
    import ray  # noqa: F401  (the test extra installs it: the Ray engine is always tested)

    run_generate(GenerateConfig(out=tmp_path / "ray", workers=1, engine="ray", **SMALL), progress=False)
    assert files_of(tmp_path / "ray") == files_of(ref)


@pytest.mark.slow
def test_half_sitting_samples_keep_their_bed(tmp_path, anny64):
    """Samples of a partition on a raised bed are simulated on their own bed and store its angle."""
    out = tmp_path / "sit"
    run_generate(GenerateConfig(out=out, partition="half_sitting", n=2, shard_size=2, batch=2), progress=False)
    data = read_all(out)
    assert len(data["index"]) == 2 and (data["head_angle_deg"] > 0).all()
    from pressurepose.sampling import PoseSampler, SamplingConfig

    for k in range(2):
        cfg = SamplingConfig(partition="half_sitting", gender=data["gender"][k], over_bed=bool(data["over_bed"][k]))
        initial = PoseSampler(anny64, cfg).sample([int(data["index"][k])])
        assert data["head_angle_deg"][k] == initial.head_angle_deg[0]
    for name, value in data.items():
        if value.dtype.kind == "f":
            assert np.isfinite(value).all(), name


def test_a_second_run_on_the_same_folder_is_refused(tmp_path):
    import fcntl

    out = tmp_path / "ds"
    out.mkdir()
    with open(out / ".lock", "a") as held:  # what a running generate holds
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(ValueError, match="another `pressurepose generate` is writing"):
            run_generate(GenerateConfig(out=out, partition="supine", n=1), progress=False)
    assert not (out / "manifest.json").exists() and not list((out / "shards").iterdir())


def test_the_sampling_law_is_pinned(tmp_path):
    """Every dataset pins the sampling law (law 2: face-down bodies do not kneel, capped attempts
    over the bed); one drawn under law 1 (no pin) or another law is refused in one line before
    any work, and the same law resumes."""
    from pressurepose.generate.run import SETTINGS, _prepare_folder, _settings

    cfg = GenerateConfig(out=tmp_path / "ds", partition="straight_limbs", n=4)
    for c in (cfg, GenerateConfig(partition="supine", n=4), GenerateConfig(preset="paper")):
        assert _settings(c, {})["sampling_law"] == SAMPLING_LAW
    for old in (None, 1):
        (tmp_path / "ds" / "shards").mkdir(parents=True, exist_ok=True)
        made = dict(_settings(cfg, {}), mattress="unchanged")
        if old is None:
            del made["sampling_law"]
        else:
            made["sampling_law"] = old
        new = dict(_settings(cfg, {}), mattress="unchanged")
        (tmp_path / "ds" / SETTINGS).write_text(json.dumps(made))
        with pytest.raises(ValueError, match=r"sampler's law differ") as err:
            _prepare_folder(cfg, new)
        assert "\n" not in str(err.value)
        (tmp_path / "ds" / SETTINGS).write_text(json.dumps(new, indent=1, sort_keys=True))
        _prepare_folder(cfg, new)  # the same law resumes


def test_the_pillow_share_reaches_every_chunk(monkeypatch, anny64):
    """`generate --pillow` reaches the simulation of every chunk of a shard (WorkContext.pillow)."""
    seen = []

    def fake(model, sampler, indices, mattress, seed, split, sim2="rigid", settle="mujoco", pillow=0.0, drawn=None):
        seen.append(pillow)
        return (
            fake_batch(np.array(indices, dtype=np.int64), np.random.default_rng(seed), split),
            [""] * len(indices),
            {},
        )

    monkeypatch.setattr(worker, "simulate_indices", fake)
    monkeypatch.setitem(worker._MODELS, ("anny", None), anny64)
    ctx = worker.WorkContext(seed=0, batch=4, backend="anny", smpl_dir=None, mattress={}, pillow=0.7)
    spec = plan_shards(GenerateConfig(partition="supine", n=200, shard_size=10, pillow=0.7))[1]
    worker.make_shard(spec, ctx)
    assert len(seen) >= 3 and set(seen) == {0.7}


def test_rigid_dataset_settings_leave_out_the_tissue(tmp_path, monkeypatch, anny64):
    """The rigid rest (MuJoCo + rigid sim #2) ignores soft tissue and uses the class-default bed:
    its settings stay those of datasets made before these fields existed (they resume); the
    default engine's carry the tissue."""
    import json

    from pressurepose.sim.mattress import MattressParams

    def fake(model, sampler, indices, mattress, seed, split, sim2="rigid", settle="mujoco", pillow=0.0, drawn=None):
        return (
            fake_batch(np.array(indices, dtype=np.int64), np.random.default_rng(seed), split),
            [""] * len(indices),
            {},
        )

    monkeypatch.setattr(worker, "simulate_indices", fake)
    monkeypatch.setitem(worker._MODELS, ("anny", None), anny64)
    for name, settle, params in (
        ("rigid", "mujoco", None),
        ("default", "articulated", None),
        ("air", "articulated", "air"),
    ):
        run_generate(
            GenerateConfig(out=tmp_path / name, partition="supine", n=2, settle=settle, params=params), progress=False
        )
    rigid, default, air = (
        json.loads((tmp_path / n / "manifest.json").read_text()) for n in ("rigid", "default", "air")
    )
    expected = MattressParams().to_dict()
    expected.pop("tissue_pa_per_m")
    assert rigid["mattress"] == expected and "settle" not in rigid["config"]
    assert default["mattress"] == MattressParams.preset("sponge").to_dict()
    # Flat beds leave the air cells' fields out (datasets made before them resume); air keeps them.
    assert "cell_depth_m" not in default["mattress"] and "cell_depth_m" not in rigid["mattress"]
    assert air["mattress"] == MattressParams.preset("air").to_dict() and air["mattress"]["cell_depth_m"] > 0


def _assert_params_reproduce_joints(data):
    """The stored body parameters, through the body model, give the stored joints."""
    from pressurepose.body import load_body_model
    from pressurepose.body.params import BodyParams

    model = load_body_model("anny", dtype=torch.float64)
    params = BodyParams(
        shape=torch.from_numpy(data["shape"]),
        root_rotation=torch.from_numpy(data["root_rotation"]),
        root_translation=torch.from_numpy(data["root_translation"]),
        pose=torch.from_numpy(data["pose"]),
    )
    np.testing.assert_allclose(model.joints(params).numpy(), data["joints_m"], atol=1e-4)


def test_articulated_sim2_dataset(tmp_path):
    """`generate --sim2 articulated`: the manifest records it, images carry the weight, the
    stored parameters reproduce the stored joints; the rigid default's identity is unchanged."""
    out = tmp_path / "art"
    run_generate(
        GenerateConfig(out=out, partition="supine", n=2, shard_size=2, batch=2, settle="mujoco", sim2="articulated"),
        progress=False,
    )
    import json

    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["sim2"] == "articulated"
    assert manifest["mattress"]["tissue_pa_per_m"] > 0
    assert "sim2" not in GenerateConfig(partition="supine", n=2, settle="mujoco").identity()
    data = read_all(out)
    assert len(data["index"]) == 2
    assert (data["pressure_mmhg"].reshape(2, -1).max(1) > 5).all()
    _assert_params_reproduce_joints(data)


def test_articulated_settling_dataset_needs_no_mujoco(tmp_path, monkeypatch):
    """`generate --settle articulated`: no MuJoCo run (sim #1 is never called), the sponge bed,
    articulated images that carry the weight, labels consistent with the parameters; a rigid
    sim #2 with it is refused in one line."""
    import json

    import pressurepose.sim.run as sim_run

    def no_mujoco(*args, **kwargs):
        raise AssertionError("MuJoCo settling ran")

    monkeypatch.setattr(sim_run, "settle_bodies", no_mujoco)
    out = tmp_path / "one"
    cfg = GenerateConfig(out=out, partition="general", n=3, shard_size=3, batch=3)  # the default engine
    assert cfg.settle == "articulated" and cfg.sim2_engine == "articulated"
    assert cfg.identity()["settle"] == "articulated"
    run_generate(cfg, progress=False)
    manifest = json.loads((out / "manifest.json").read_text())
    from pressurepose.sim.mattress import MattressParams

    assert manifest["mattress"] == MattressParams.preset("sponge").to_dict()
    data = read_all(out)
    assert len(data["index"]) == 3
    assert (data["pressure_mmhg"].reshape(3, -1).max(1) > 5).all()
    # The sensor reads from the preset's floor, as PmatData's frames do: nothing in (0, floor).
    p = data["pressure_mmhg"]
    assert manifest["mattress"]["floor_mmhg"] == 3.31 and not ((p > 0) & (p < 3.31)).any()
    _assert_params_reproduce_joints(data)
    from pressurepose.errors import UserError

    with pytest.raises(UserError, match="--sim2 rigid needs --settle mujoco"):
        GenerateConfig(out=out, settle="articulated", sim2="rigid")


def test_a_lying_reference_posture_is_pinned_only_when_set(monkeypatch):
    """A dataset rested with the springs' lying reference posture pins it (and so does not resume
    into an engine without one); the default engine (none) writes the settings as before, so
    datasets made before the option resume."""
    import dataclasses

    import pressurepose.sim.articulated as articulated
    from pressurepose.generate.run import _settings

    cfg = GenerateConfig(preset="paper")
    assert "lying_extension" not in _settings(cfg, {})["articulated_joints"]
    base = articulated.ArticulatedConfig
    monkeypatch.setattr(
        articulated, "ArticulatedConfig", lambda: dataclasses.replace(base(), lying_extension=(("neck", 0.4),))
    )
    assert _settings(cfg, {})["articulated_joints"]["lying_extension"] == [["neck", 0.4]]


def test_evaluate_sample_ids_locate_and_redraw_the_samples(reference, anny64):
    """`eval.evaluation.sample_ids`: every sample's shard, row, seed, partition, gender, over_bed
    and sampler index, checked against the dataset, and the initial pose drawn again from them
    carries the sample's shape (the rest does not change the shape)."""
    from pressurepose.eval.evaluation import _batches, open_split, sample_ids
    from pressurepose.sampling.partitions import SamplingConfig
    from pressurepose.sampling.sampler import PoseSampler

    out, _ = reference
    data = open_split(out, "train")
    labels = [label for batch_labels, _ in _batches(data, 4, None) for label in batch_labels]
    ids = sample_ids(data, [index for _, _, index in labels])
    assert len(ids) == len(data) >= 2
    for i, (sid, (partition, gender, index)) in enumerate(zip(ids, labels)):
        shard, row = data.locate(i)
        assert sid["shard"] == data.shards[shard]["id"] and sid["row"] == row and sid["seed"] == SMALL["seed"]
        assert (sid["partition"], sid["gender"]) == (partition, gender)
        assert sid["index"] == index == int(data[i]["index"])
        sampler = PoseSampler(anny64, SamplingConfig(sid["partition"], sid["gender"], sid["over_bed"], sid["seed"]))
        redrawn = sampler.sample([sid["index"]])
        np.testing.assert_allclose(redrawn.params.shape[0].numpy(), data[i]["shape"].numpy(), rtol=0, atol=1e-12)
    # a folder of two datasets: each sample keeps its own dataset and rows
    both = out.parent / "both"
    both.mkdir(exist_ok=True)
    for name in ("a", "b"):
        if not (both / name).exists():
            (both / name).symlink_to(out, target_is_directory=True)
    two = open_split(both, "train")
    ids2 = sample_ids(two, list(range(2 * len(data))))
    assert [s["dataset"] for s in ids2] == [str(both / "a")] * len(data) + [str(both / "b")] * len(data)
    assert [(s["shard"], s["row"]) for s in ids2] == [(s["shard"], s["row"]) for s in ids] * 2
    assert [s["index"] for s in ids2] == list(range(2 * len(data)))  # each sample keeps its own index
    # a dataset without samples in the split, sorted first, is passed over (not the end of the list)
    from test_data import make_fake_dataset

    mixed = out.parent / "mixed"
    make_fake_dataset(mixed / "a_train_only", [("train", "supine", "male", 3)])
    if not (mixed / "b").exists():
        (mixed / "b").symlink_to(out, target_is_directory=True)
    ids3 = sample_ids(open_split(mixed, "train"), list(range(3 + len(data))))
    assert [s["dataset"] for s in ids3] == [str(mixed / "a_train_only")] * 3 + [str(mixed / "b")] * len(data)
    assert all(s["seed"] is None and s["index"] is None for s in ids3[:3])  # no generator's seed: no redraw
    test = open_split(mixed, "test")
    assert [s["dataset"] for s in sample_ids(test, [0] * len(test))] == [str(mixed / "b")] * len(test)
