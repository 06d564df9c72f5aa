"""Data layer: shard schema round trips, manifest and checksums, the lazy Dataset, info, and
the importer of original pickles (restricted unpickler)."""

import json
import os
import pickle
from collections import OrderedDict

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from pressurepose.cli import main
from pressurepose.commands.info import dataset_info
from pressurepose.data.dataset import BlockShuffleSampler, PressurePoseDataset
from pressurepose.data.importer import import_original, infer_labels, load_restricted, read_original
from pressurepose.data.manifest import load_manifest, write_manifest
from pressurepose.data.schema import NAMES, SampleBatch, from_table, to_table
from pressurepose.data.shards import CorruptShardError, read_record, table_bytes, verify_shard, write_shard


def random_batch(n, rng, split="train", partition="supine", gender="female", over_bed=False, first=0):
    return SampleBatch(
        split=np.array([split] * n, dtype=object),
        partition=np.array([partition] * n, dtype=object),
        gender=np.array([gender] * n, dtype=object),
        over_bed=np.full(n, over_bed),
        index=np.arange(first, first + n, dtype=np.int64),
        pressure_mmhg=rng.uniform(0, 100, (n, 64, 27)).astype(np.float32),
        depth_mm=rng.normal(0, 10, (n, 64, 27)).astype(np.float32),
        contact=(rng.random((n, 64, 27)) > 0.5).astype(np.uint8),
        shape=rng.random((n, 6)),
        root_rotation=rng.normal(size=(n, 3)),
        root_translation=rng.normal(size=(n, 3)),
        pose=rng.normal(size=(n, 23, 3)),
        joints_m=rng.normal(size=(n, 24, 3)),
        mass_kg=rng.uniform(40, 120, n),
        height_m=rng.uniform(1.4, 2.0, n),
        head_angle_deg=np.zeros(n),
        settle_steps=rng.integers(0, 900, n).astype(np.int32),
        sink_mm=rng.uniform(0, 80, n).astype(np.float32),
    )


def make_fake_dataset(root, groups, seed=0):
    """Write shards of random samples + a manifest (no simulation). groups: [(split, partition,
    gender, count)]. Returns {shard id: SampleBatch}."""
    rng = np.random.default_rng(seed)
    records, batches = [], {}
    for k, (split, part, gender, n) in enumerate(groups):
        batch = random_batch(n, rng, split, part, gender)
        sid = f"{split}-{part}-{gender}-{k:05d}"
        rec = {
            "split": split,
            "partition": part,
            "gender": gender,
            "over_bed": False,
            "number": k,
            "first_slot": 0,
            "count": n,
            "candidates": n + 1,
            "rejections": {"sim #1: fake": 1},
            "sampling_rejections": {"collisions": 2},
        }
        records.append(write_shard(root, sid, table_bytes(to_table(batch)), rec))
        batches[sid] = batch
    write_manifest(root, {"config": {"preset": "fake"}}, records)
    return batches


GROUPS = [("train", "supine", "female", 70), ("train", "general", "male", 33), ("test", "supine", "male", 5)]


def test_schema_round_trip_and_deterministic_bytes():
    batch = random_batch(7, np.random.default_rng(1))
    data = table_bytes(to_table(batch))
    assert data == table_bytes(to_table(batch))
    import io

    back = from_table(pq.read_table(io.BytesIO(data)))
    for name in NAMES:
        a, b = getattr(batch, name), back[name]
        assert a.shape == b.shape, name
        assert (a == b).all(), name


def test_sample_batch_rejects_nan_and_bad_shapes():
    rng = np.random.default_rng(0)
    batch = random_batch(2, rng)
    fields = {n: getattr(batch, n) for n in NAMES}
    bad = dict(fields, pressure_mmhg=np.full((2, 64, 27), np.nan, np.float32))
    with pytest.raises(ValueError, match="pressure_mmhg holds NaN"):
        SampleBatch(**bad)
    with pytest.raises(ValueError, match=r"joints_m must have shape \(2, 24, 3\)"):
        SampleBatch(**dict(fields, joints_m=np.zeros((2, 23, 3))))


def test_checksums_catch_corruption_and_truncation(tmp_path, capsys):
    make_fake_dataset(tmp_path, GROUPS)
    manifest = load_manifest(tmp_path)
    assert manifest["total"] == 108 and manifest["counts"]["train"]["supine"]["female"] == 70
    rec = manifest["shards"][0]
    path = tmp_path / rec["file"]
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(CorruptShardError, match="corrupted: its sha256 does not match"):
        load_manifest(tmp_path)
    path.write_bytes(bytes(data[:100]))
    with pytest.raises(CorruptShardError, match="truncated"):
        verify_shard(tmp_path, rec)
    assert main(["info", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "truncated" in err


def test_full_disk_leaves_written_shards_intact(tmp_path, monkeypatch):
    import errno
    from pathlib import Path

    rng = np.random.default_rng(0)
    data = table_bytes(to_table(random_batch(3, rng)))
    rec = write_shard(tmp_path, "a", data, {"count": 3})

    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_bytes", full)
    with pytest.raises(OSError, match="no space left on the device .* re-run the same command to resume"):
        write_shard(tmp_path, "b", data, {"count": 3})
    monkeypatch.undo()
    verify_shard(tmp_path, rec)
    assert read_record(tmp_path, "b") is None
    assert sorted(p.name for p in (tmp_path / "shards").iterdir()) == ["a.json", "a.parquet"]


def test_dataset_items_equal_the_shards_and_filters_select(tmp_path):
    batches = make_fake_dataset(tmp_path, GROUPS)
    everything = SampleBatch.concat(list(batches.values()))
    ds = PressurePoseDataset(tmp_path, columns=NAMES, cache_row_groups=2)
    assert len(ds) == len(everything) == 108
    for i in range(len(ds)):  # naive reference: the concatenated source batches
        item = ds[i]
        for name in ("pressure_mmhg", "joints_m", "pose", "contact", "mass_kg", "index"):
            assert np.array_equal(item[name].numpy(), getattr(everything, name)[i]), (i, name)
        assert item["partition"] == everything.partition[i]
        assert len(ds._cache) <= 2
    assert ds[-1]["index"] == everything.index[-1]
    with pytest.raises(IndexError):
        ds[108]
    train = PressurePoseDataset(tmp_path, split="train")
    assert len(train) == 103
    sup = PressurePoseDataset(
        tmp_path, partitions=["supine"], genders=["male"], columns=("gender", "partition", "split")
    )
    assert len(sup) == 5 and {sup[i]["split"] for i in range(5)} == {"test"}
    loader = torch.utils.data.DataLoader(PressurePoseDataset(tmp_path, split="train"), batch_size=16)
    first = next(iter(loader))
    assert first["pressure_mmhg"].shape == (16, 64, 27) and first["pressure_mmhg"].dtype == torch.float32
    with pytest.raises(ValueError, match="unknown columns"):
        PressurePoseDataset(tmp_path, columns=("pressure",))


def count_row_group_reads(monkeypatch) -> list:
    """From now on, every Parquet row-group read appends its row-group number to the list."""
    calls = []
    original = pq.ParquetFile.read_row_group

    def spy(self, i, *args, **kwargs):
        calls.append(i)
        return original(self, i, *args, **kwargs)

    monkeypatch.setattr(pq.ParquetFile, "read_row_group", spy)
    return calls


def test_dataset_reads_each_row_group_once_when_sequential(tmp_path, monkeypatch):
    make_fake_dataset(tmp_path, GROUPS)
    calls = count_row_group_reads(monkeypatch)
    ds = PressurePoseDataset(tmp_path, cache_row_groups=1)
    for i in range(len(ds)):
        ds[i]
    # row groups of 32 rows: 70 -> 3, 33 -> 2, 5 -> 1
    assert len(calls) == 6


def test_block_shuffle_reads_each_row_group_once_per_epoch(tmp_path, monkeypatch):
    make_fake_dataset(tmp_path, GROUPS)
    ds = PressurePoseDataset(tmp_path, cache_row_groups=2, columns=("index", "split"))
    sampler = BlockShuffleSampler(ds, blocks_in_memory=2, seed=1)
    first = list(sampler)
    assert sorted(first) == list(range(len(ds))) and first != sorted(first)
    assert list(sampler) == first
    sampler.set_epoch(1)
    assert list(sampler) != first
    calls = count_row_group_reads(monkeypatch)
    for i in sampler:
        ds[i]
    assert len(calls) == len(sampler.blocks) == 6


def test_info_counts_and_contact_sheet(tmp_path, capsys):
    make_fake_dataset(tmp_path, GROUPS)
    info = dataset_info(tmp_path, sheet=6)
    assert info["total"] == 108 and info["rejected"] == 3 and info["rejections"] == {"sim #1: fake": 3}
    assert info["pressure"]["supine"]["samples"] == 75 and info["pressure"]["supine"]["nan_values"] == 0
    png = (tmp_path / "contact_sheet.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["info", str(tmp_path), "--sheet", "0"]) == 0
    out = capsys.readouterr().out
    assert "108 samples in 3 shards" in out and "general" in out


def test_not_a_dataset_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="not a pressurepose dataset"):
        PressurePoseDataset(tmp_path)


# --- importer -----------------------------------------------------------------------------


def original_dict(n, rng, with_optional=True):
    d = {
        "images": [rng.uniform(0, 100, 1728) for _ in range(n)],
        "markers_xyz_m": [rng.normal(size=72) for _ in range(n)],
        "body_shape": [rng.uniform(-3, 3, 10) for _ in range(n)],
        "joint_angles": [rng.normal(size=72) for _ in range(n)],
        "root_xyz_shift": [rng.normal(size=3) for _ in range(n)],
    }
    if with_optional:
        d.update(
            {
                "mesh_depth": [rng.normal(size=(64, 27)) for _ in range(n)],
                "mesh_contact": [(rng.random((64, 27)) > 0.5).astype(np.float64) for _ in range(n)],
                "body_mass": [float(x) for x in rng.uniform(40, 100, n)],
                "body_height": [np.float64(x) for x in rng.uniform(1.5, 1.9, n)],
            }
        )
    return d


def test_importer_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    d1, d2 = original_dict(4, rng), original_dict(3, rng, with_optional=False)
    f1 = tmp_path / "train_roll0_xl_f_lay_set2both_4000.p"
    f2 = tmp_path / "test_roll0_m_lay_set1_500.p"
    f1.write_bytes(pickle.dumps(d1, protocol=2))
    f2.write_bytes(pickle.dumps(d2, protocol=4))
    out = tmp_path / "ds"
    import_original([f1, f2], out)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["counts"] == {"train": {"crossed_legs": {"female": 4}}, "test": {"supine": {"male": 3}}}
    assert manifest["import"]["files"][1]["missing"] == [
        "mesh_depth",
        "mesh_contact",
        "body_mass",
        "body_height",
        "bed_angle_deg",
    ]
    ds = PressurePoseDataset(out, columns=NAMES)
    assert len(ds) == 7
    for i in range(4):
        item = ds[i]
        assert np.allclose(item["pressure_mmhg"].numpy().ravel(), d1["images"][i], atol=1e-4)
        assert np.array_equal(item["joints_m"].numpy().ravel(), d1["markers_xyz_m"][i])
        assert np.array_equal(item["root_rotation"].numpy(), d1["joint_angles"][i][:3])
        assert np.array_equal(item["pose"].numpy().ravel(), d1["joint_angles"][i][3:])
        assert np.array_equal(item["shape"].numpy(), d1["body_shape"][i])
        assert item["mass_kg"].item() == d1["body_mass"][i]
        assert np.array_equal(item["contact"].numpy(), d1["mesh_contact"][i].astype(np.uint8))
    assert ds[5]["gender"] == "male" and ds[5]["mass_kg"].item() == 0.0


def test_restricted_unpickler_accepts_numpy_and_containers():
    values = {
        "a": np.arange(6, dtype=np.int16).reshape(2, 3),
        "b": [np.float32(1.5), (1, 2.0, "x")],
        b"k": {1, 2},
        "c": np.array([1.0, 2.0]).T,
        "d": np.bool_(True),
        "e": frozenset([3]),
        "f": 2 + 1j,
    }
    for protocol in (2, 4, 5):
        back = load_restricted(pickle.dumps(values, protocol=protocol))
        assert np.array_equal(back["a"], values["a"]) and back["a"].dtype == np.int16
        assert back["b"][0] == np.float32(1.5) and back["b"][1] == (1, 2.0, "x")
        assert back[b"k"] == {1, 2} and back["e"] == frozenset([3]) and back["f"] == 2 + 1j


class _Evil:
    def __reduce__(self):
        return (os.system, ("touch pwned_by_pickle",))


@pytest.mark.parametrize(
    "payload, name",
    [
        (OrderedDict(a=1), "collections.OrderedDict"),
        ({"images": [_Evil()]}, "system"),
        ({"x": [np.random.default_rng(0)]}, "numpy.random"),
    ],
)
def test_restricted_unpickler_refuses_other_objects(tmp_path, payload, name, monkeypatch):
    monkeypatch.chdir(tmp_path)
    data = pickle.dumps(payload, protocol=2)
    with pytest.raises(ValueError, match=f"refusing to load the global .*{name}"):
        load_restricted(data)
    path = tmp_path / "train_f_bad.p"
    path.write_bytes(data)
    with pytest.raises(ValueError, match="refusing"):
        read_original(path)
    assert not (tmp_path / "pwned_by_pickle").exists()


def test_importer_bad_inputs(tmp_path):
    rng = np.random.default_rng(0)
    d = original_dict(2, rng)
    del d["joint_angles"]
    path = tmp_path / "train_f_x.p"
    path.write_bytes(pickle.dumps(d, protocol=2))
    with pytest.raises(ValueError, match="missing keys"):
        read_original(path)
    d = original_dict(2, rng)
    path = tmp_path / "train_roll0_x.p"
    path.write_bytes(pickle.dumps(d, protocol=2))
    with pytest.raises(ValueError, match="--gender"):
        read_original(path)
    d["images"][1] = np.full(1728, np.nan)
    path.write_bytes(pickle.dumps(d, protocol=2))
    with pytest.raises(ValueError, match="NaN"):
        read_original(path, gender="male")
    (tmp_path / "junk.p").write_bytes(b"not a pickle")
    with pytest.raises(ValueError, match="not a readable pickle|refusing"):
        read_original(tmp_path / "junk.p", gender="male")
    assert infer_labels(path.with_name("test_roll180_m_lay_set1_500.p")) == {
        "split": "test",
        "gender": "male",
        "partition": "prone_hands_up",
    }


def test_import_original_cli(tmp_path, capsys):
    path = tmp_path / "test_roll0_m_lay_set1_2.p"
    path.write_bytes(pickle.dumps(original_dict(2, np.random.default_rng(5)), protocol=2))
    assert main(["import-original", str(path), "--out", str(tmp_path / "ds"), "--partition", "general"]) == 0
    assert "2 samples from 1 files" in capsys.readouterr().out
    assert load_manifest(tmp_path / "ds")["counts"] == {"test": {"general": {"male": 2}}}
    bad = tmp_path / "train_f_evil.p"
    bad.write_bytes(pickle.dumps({"images": [_Evil()]}, protocol=2))
    assert main(["import-original", str(bad), "--out", str(tmp_path / "ds2")]) == 2
    assert "refusing to load the global" in capsys.readouterr().err


def test_open_dataset_reads_a_folder_of_dataset_folders(tmp_path):
    """train's --data may name a folder holding several generated sets (e.g. the paper mix and a
    partition made apart): their train samples in name order, the test ones left out."""
    from pressurepose.train.data import open_dataset

    a = make_fake_dataset(tmp_path / "mix" / "a_paper", GROUPS, seed=1)
    b = make_fake_dataset(tmp_path / "mix" / "b_lateral", [("train", "lateral", "male", 9)], seed=2)
    (tmp_path / "mix" / "notes").mkdir()  # a folder without a manifest is not a dataset
    ds = open_dataset(tmp_path / "mix")
    assert len(ds) == 103 + 9
    train_a = [x for sid, x in a.items() if sid.startswith("train")]
    expected = np.concatenate([x.pressure_mmhg for x in train_a] + [x.pressure_mmhg for x in b.values()])
    for i in (0, 102, 103, 111):
        assert np.array_equal(ds[i]["pressure_mmhg"].numpy(), expected[i]), i
    (tmp_path / "none").mkdir()
    (tmp_path / "none" / "empty").mkdir()
    with pytest.raises(ValueError, match="neither a manifest.json"):
        open_dataset(tmp_path / "none")


def test_training_data_decoded_once_into_memory_equals_the_shards(tmp_path, monkeypatch):
    """`train` decodes a generated dataset into memory before its first epoch (`in_memory`):
    each row group is read once, every item equals the collated shard sample, and an epoch
    trained from memory gives the same weights as one reading the shards."""
    import torch

    from pressurepose.train.config import TrainConfig
    from pressurepose.train.data import collate, in_memory, open_dataset
    from pressurepose.train.loop import train

    make_fake_dataset(tmp_path / "ds", GROUPS, seed=3)
    ds = open_dataset(tmp_path / "ds")
    reads = count_row_group_reads(monkeypatch)
    mem = in_memory(ds, chunk=16)
    assert len(mem) == len(ds) == 103 and len(reads) == 5  # row groups of 32: 70 -> 3, 33 -> 2
    for i in (0, 15, 16, 70, 102):
        one = collate([ds[i]])
        for k, v in mem[i].items():
            assert torch.equal(v, one[k][0]), (i, k)
    assert in_memory(mem) is mem
    both = torch.utils.data.ConcatDataset([mem, mem])  # e.g. a folder of .npz files: kept as it is
    assert in_memory(both) is both
    import pressurepose.train.data as data_module

    monkeypatch.setattr(data_module, "_available_memory_bytes", lambda: 100_000)  # 100 kB free
    with pytest.raises(ValueError, match="give --no-in-memory"):
        in_memory(ds)
    monkeypatch.setattr(data_module, "_available_memory_bytes", lambda: None)  # unknown: no check
    assert len(in_memory(ds)) == 103
    weights = []
    for flag in (True, False):
        cfg = TrainConfig.smoke(
            data=tmp_path / "ds", out=tmp_path / f"run_{flag}", epochs=1, in_memory=flag, progress=False
        )
        run = train(cfg)
        weights.append((run / "model.safetensors").read_bytes())
    from safetensors.torch import load

    a, b = (load(w) for w in weights)
    assert a.keys() == b.keys()
    for k in a:  # the same batches through the same operations: equal up to float round-off
        torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-6)
