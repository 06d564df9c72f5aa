"""Training and prediction: data adapters, a 32-sample overfit, checkpoints and resume,
Mod2 on a frozen Mod1, and the `train` / `predict` commands on good and bad inputs."""

import json
import math

import numpy as np
import pytest
import torch

from pressurepose.cli import main
from pressurepose.commands.predict import read_mesh
from pressurepose.commands.train import run_train as train  # the loop + metrics.png
from pressurepose.eval.real import LOAD_ENDS, load_ends, posture_of, roll_deg
from pressurepose.net import NetConfig, NetInputs, PressureNet
from pressurepose.train.checkpoint import load_network, save_model
from pressurepose.train.config import TrainConfig
from pressurepose.train.data import (
    KEYS,
    NpzDataset,
    TensorDictDataset,
    collate,
    open_dataset,
    standardise,
    synthetic_arrays,
    write_npz,
)
from pressurepose.train.loop import build_network


@pytest.fixture(scope="module")
def data32(anny64, tmp_path_factory):
    """32 labelled samples from the generator's pipeline (sampler + sim #2), in a .npz folder."""
    arrays = synthetic_arrays(36, seed=1, body=anny64)
    assert len(arrays["pressure_mmhg"]) >= 32
    arrays = {k: v[:32] for k, v in arrays.items()}
    folder = tmp_path_factory.mktemp("data32")
    write_npz(folder / "train.npz", arrays)
    return folder


def _metrics(run):
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]


def test_standardise_accepts_shard_names_and_rejects_missing_keys(data32):
    item = dict(NpzDataset(data32 / "train.npz")[0])
    shard_like = {
        **item,
        "joints_m": item.pop("joints").double(),
        "gender": "female",
        "contact": item["contact"].byte(),
    }
    std = standardise(shard_like)
    assert set(std) == set(KEYS) and all(v.dtype == torch.float32 for v in std.values())
    assert float(std["gender"]) == 1.0
    del shard_like["depth_mm"]
    with pytest.raises(ValueError, match="depth_mm"):
        standardise(shard_like)
    with pytest.raises(ValueError, match="pose"):
        standardise({**item, "joints": item["pressure_mmhg"][:24, :3], "pose": torch.zeros(24, 3)})
    batch = collate([NpzDataset(data32 / "train.npz")[i] for i in range(4)])
    assert batch["pressure_mmhg"].shape == (4, 64, 27) and batch["pose"].shape == (4, 23, 3)


def test_npz_dataset_round_trip(data32, tmp_path):
    ds = open_dataset(data32)
    assert len(ds) == 32
    write_npz(tmp_path / "copy.npz", ds.arrays)
    again = open_dataset(tmp_path / "copy.npz")
    for k in KEYS:
        assert torch.equal(again.arrays[k], ds.arrays[k])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="neither"):
        open_dataset(tmp_path / "empty")
    np.savez(tmp_path / "bad.npz", pressure_mmhg=np.zeros((2, 64, 27)))
    with pytest.raises(ValueError, match="lacks arrays"):
        NpzDataset(tmp_path / "bad.npz")


@pytest.mark.slow
def test_overfit_32_samples(data32, tmp_path):
    """arch=fast learns 32 samples by heart: the loss falls by more than 90%."""
    cfg = TrainConfig.smoke(
        out=tmp_path / "run",
        epochs=110,
        batch_size=32,
        lr=2e-3,
        augment=False,
        dropout=0.0,
        val_fraction=0.0,
        progress=False,
        save_every=1000,
    )
    train(cfg, NpzDataset(data32 / "train.npz"))
    rows = _metrics(tmp_path / "run")
    assert len(rows) == 110
    first, last = rows[0]["loss"], min(r["loss"] for r in rows[-5:])
    assert last < 0.1 * first, (first, last)
    assert rows[-1]["train_mpjpe_mm"] < 0.2 * rows[0]["train_mpjpe_mm"]


def _small(data32, n=8):
    return TensorDictDataset({k: v[:n] for k, v in NpzDataset(data32 / "train.npz").arrays.items()})


def test_checkpoint_round_trip(anny32, tmp_path):
    torch.manual_seed(0)
    net = PressureNet(NetConfig(arch="fast", modules=2), body=anny32).eval()
    with torch.no_grad():
        for p in net.mod2.parameters():
            p.normal_(0, 0.01)
    record = {"train": {}, "net": dict(net.config.__dict__)}
    save_model(tmp_path, net, record)
    loaded, rec = load_network(tmp_path, body=anny32)
    assert rec == json.loads(json.dumps(record))
    p = torch.rand(2, 64, 27) * 40
    with torch.no_grad():
        a, b = net(NetInputs(p))[-1], loaded(NetInputs(p))[-1]
    assert torch.equal(a.raw, b.raw) and torch.equal(a.vertices, b.vertices)
    # Files are plain safetensors: no pickles anywhere.
    assert (tmp_path / "model.safetensors").read_bytes()[8:9] == b"{"


def test_resume_equals_an_uninterrupted_run(data32, tmp_path):
    ds = _small(data32)
    common = dict(batch_size=4, val_fraction=0.0, progress=False, seed=7, lr_gamma=0.5)
    train(TrainConfig.smoke(out=tmp_path / "a", epochs=3, **common), ds)
    train(TrainConfig.smoke(out=tmp_path / "b", epochs=2, **common), ds)
    assert len(_metrics(tmp_path / "b")) == 2
    train(TrainConfig.smoke(out=tmp_path / "b", epochs=3, **common), ds)  # resumes after epoch 2
    rows_a, rows_b = _metrics(tmp_path / "a"), _metrics(tmp_path / "b")
    assert [r["epoch"] for r in rows_b] == [1, 2, 3]
    assert [r["lr"] for r in rows_b] == pytest.approx([1e-3, 5e-4, 2.5e-4])  # decays per epoch, across the resume
    assert rows_a[2]["loss"] == pytest.approx(rows_b[2]["loss"], rel=1e-5)
    wa, _ = load_network(tmp_path / "a")
    wb, _ = load_network(tmp_path / "b")
    for (k, va), vb in zip(wa.trainable_state().items(), wb.trainable_state().values()):
        assert torch.allclose(va.float(), vb.float(), atol=1e-6), k
    for name in ("metrics.csv", "metrics.png", "config.json", "checkpoint.safetensors"):
        assert (tmp_path / "b" / name).is_file()
    with pytest.raises(ValueError, match="different settings"):
        train(TrainConfig.smoke(out=tmp_path / "b", epochs=4, lr=1e-2, **{**common}), ds)
    with pytest.raises(ValueError, match="different settings.*width"):
        train(TrainConfig.smoke(out=tmp_path / "b", epochs=4, width=2, **common), ds)
    # A run saved before a field existed resumes with that field at its default.
    path = tmp_path / "b" / "config.json"
    record = json.loads(path.read_text())
    del record["train"]["width"]
    path.write_text(json.dumps(record))
    train(TrainConfig.smoke(out=tmp_path / "b", epochs=4, **common), ds)
    assert [r["epoch"] for r in _metrics(tmp_path / "b")] == [1, 2, 3, 4]


def test_shift_moves_images_and_labels_as_the_physics_does(anny64):
    from pressurepose.body import BodyParams
    from pressurepose.mat import MatSpec
    from pressurepose.net.losses import Targets
    from pressurepose.sim.foundation import simulate_pressure
    from pressurepose.sim.sensor import sensing_area, taxel_reading
    from pressurepose.train.augment import shift_batch

    a = synthetic_arrays(1, seed=5, body=anny64)
    inputs = NetInputs(pressure_mmhg=a["pressure_mmhg"])
    targets = Targets(joints=a["joints"], shape=a["shape"], depth_mm=a["depth_mm"], contact=a["contact"])
    mat = MatSpec()
    gen = torch.Generator().manual_seed(0)
    while True:  # a draw that moves both ways
        moved_in, moved = shift_batch(inputs, targets, 4, 3, gen)
        step = (moved.joints - targets.joints)[0, 0]
        dr, dc = round(float(step[0]) / mat.pitch_row_m), round(float(step[1]) / mat.pitch_col_m)
        if dr and dc:
            break
    # labels: every joint lands exactly (dr, dc) taxels further; the shape does not change
    rc = lambda j: torch.as_tensor(mat.to_taxel(j[0, :, :2].double()))  # noqa: E731
    assert torch.allclose(
        rc(moved.joints) - rc(targets.joints), torch.tensor([float(dr), float(dc)]).double(), atol=1e-4
    )
    assert torch.equal(moved.shape, targets.shape)
    # naive reference of the image move, with zeros entering
    ref = torch.zeros(64, 27)
    for r in range(64):
        for c in range(27):
            if 0 <= r - dr < 64 and 0 <= c - dc < 27:
                ref[r, c] = a["pressure_mmhg"][0, r - dr, c - dc]
    assert torch.equal(moved_in.pressure_mmhg[0], ref)
    assert float(moved.contact[0].sum()) <= float(targets.contact[0].sum())
    # physics: sim #2 on the body moved by the same whole taxels gives the same image moved
    # (both solved here from the same start, so only the move differs)
    move = torch.tensor([[0.0, 0.0, 0.0], [dr * mat.pitch_row_m, dc * mat.pitch_col_m, 0.0]], dtype=torch.float64)
    two = lambda x: x.double().expand(2, *x.shape[1:])  # noqa: E731
    params = BodyParams(
        shape=two(a["shape"]),
        pose=two(a["pose"]),
        root_rotation=two(a["root_rotation"]),
        root_translation=two(a["root_translation"]) + move,
    )
    out = anny64(params)
    with torch.no_grad():
        pressed = simulate_pressure(out.vertices, out.faces, anny64.measure(params.shape).mass_kg)
    here, there = taxel_reading(sensing_area(pressed.pressure_pa)).float()
    moved_here, _ = shift_batch(NetInputs(pressure_mmhg=here[None]), targets, 0, 0, None)
    ref = torch.zeros(64, 27)
    ref[max(dr, 0) : 64 + min(dr, 0), max(dc, 0) : 27 + min(dc, 0)] = here[
        max(-dr, 0) : 64 + min(-dr, 0), max(-dc, 0) : 27 + min(-dc, 0)
    ]
    rows, cols = slice(max(dr, 0), 64 + min(dr, 0)), slice(max(dc, 0), 27 + min(dc, 0))
    assert torch.equal(moved_here.pressure_mmhg[0], here) and float(here.sum()) > 100
    diff = (there[rows, cols] - ref[rows, cols]).abs()
    assert float(diff.max()) < 0.02 * float(ref.max()), float(diff.max())


def test_init_starts_from_another_runs_weights(data32, tmp_path):
    ds = _small(data32)
    common = dict(batch_size=4, val_fraction=0.0, progress=False, seed=3, epochs=1)
    a = train(TrainConfig.smoke(out=tmp_path / "a", **common), ds)
    b = train(TrainConfig.smoke(out=tmp_path / "b", init=a, lr=1e-12, **common), ds)  # ~no step
    na, _ = load_network(a)
    nb, _ = load_network(b)
    fresh = train(TrainConfig.smoke(out=tmp_path / "c", lr=1e-12, **common), ds)
    nc, _ = load_network(fresh)
    pa, pb, pc = ([p.detach() for p in n.parameters()] for n in (na, nb, nc))
    assert all(torch.allclose(x, y, atol=1e-9) for x, y in zip(pa, pb))
    assert not all(torch.allclose(x, y, atol=1e-6) for x, y in zip(pa, pc))  # without init: other weights
    with pytest.raises(ValueError, match="different network.*width"):
        train(TrainConfig.smoke(out=tmp_path / "d", init=a, width=2, **common), ds)
    with pytest.raises(ValueError, match="lr_gamma"):
        train(TrainConfig.smoke(out=tmp_path / "e", lr_gamma=0.0, **common), ds)


def test_init_keeps_how_the_other_network_is_read(data32, tmp_path):
    """A fine-tune reads its images as the network it started from: the inference settings
    (INFERENCE_FIELDS: IK steps, flip test, the height's blend with the localised skeleton) of the
    --init run's model are the fine-tune's, in its saved model too; a fresh run has the defaults."""
    from pressurepose.train.checkpoint import read_model
    from pressurepose.train.loop import INFERENCE_FIELDS

    ds = _small(data32)
    common = dict(arch="heatmap", gender_input=False, batch_size=4, val_fraction=0.0, progress=False, epochs=1)
    a = train(TrainConfig.smoke(out=tmp_path / "a", **common), ds)
    weights, rec = read_model(a)
    read_as = {"ik_steps": 7, "flip_test": True, "shift_test": True, "stature_weight": 0.25, "stature_head": False}
    net_a, _ = load_network(a)
    save_model(tmp_path / "a2", net_a, dict(rec, net=dict(rec["net"], **read_as)), state=weights)
    b = train(TrainConfig.smoke(out=tmp_path / "b", init=tmp_path / "a2", **common), ds)
    nb, rec_b = load_network(b)
    for key, value in read_as.items():
        assert getattr(nb.config, key) == value and rec_b["net"][key] == value, key
    assert set(read_as) < set(INFERENCE_FIELDS)
    fresh, _ = load_network(a)
    assert (fresh.config.ik_steps, fresh.config.flip_test, fresh.config.stature_weight) == (3, False, 0.0)


def test_stature_weight_is_given_to_a_new_network_and_overrides_init(data32, tmp_path):
    """--stature-weight: a line from random weights is read with the packaged model's height blend
    without editing its files; given with --init it replaces the other network's; a resumed run
    may change it (it says how the network is read, not how it trains) and keeps it when not given;
    a bad value is refused."""
    ds = _small(data32)
    common = dict(arch="heatmap", gender_input=False, batch_size=4, val_fraction=0.0, progress=False, epochs=1)
    a = train(TrainConfig.smoke(out=tmp_path / "a", stature_weight=0.194, **common), ds)
    net_a, rec_a = load_network(a)
    assert net_a.config.stature_weight == 0.194 and rec_a["net"]["stature_weight"] == 0.194
    b = train(TrainConfig.smoke(out=tmp_path / "b", init=a, stature_weight=0.5, **common), ds)
    assert load_network(b)[0].config.stature_weight == 0.5
    c = train(TrainConfig.smoke(out=tmp_path / "c", init=a, **common), ds)
    assert load_network(c)[0].config.stature_weight == 0.194  # carried when not given
    # resumed to a second epoch with another weight: the run goes on, read the new way
    a2 = train(TrainConfig.smoke(out=tmp_path / "a", stature_weight=0.3, **dict(common, epochs=2)), ds)
    assert len(_metrics(a2)) == 2 and load_network(a2)[0].config.stature_weight == 0.3
    a3 = train(TrainConfig.smoke(out=tmp_path / "a", **dict(common, epochs=3)), ds)  # not given: the run's
    assert len(_metrics(a3)) == 3 and load_network(a3)[0].config.stature_weight == 0.3
    for bad, match in ((1.5, "stature_weight must lie"), (0.2, "--arch heatmap")):
        with pytest.raises(ValueError, match=match):
            TrainConfig.smoke(stature_weight=bad, **(common if bad > 1 else dict(common, arch="fast")))


def test_mod2_trains_on_a_frozen_mod1(data32, tmp_path):
    ds = _small(data32)
    common = dict(batch_size=4, val_fraction=0.0, progress=False)
    run1 = train(TrainConfig.smoke(out=tmp_path / "m1", epochs=1, **common), ds)
    run2 = train(TrainConfig.smoke(out=tmp_path / "m2", module=2, mod1=run1, epochs=1, **common), ds)
    row = _metrics(run2)[0]
    assert {"joints", "shape", "depth", "contact"} <= set(row)
    net1, _ = load_network(run1)
    net2, _ = load_network(run2)
    for k, v in net1.mod1.state_dict().items():
        assert torch.equal(v, net2.mod1.state_dict()[k]), k
    assert any(not torch.equal(p, torch.zeros_like(p)) for p in net2.mod2.fc[-1].parameters())
    with pytest.raises(ValueError, match="--mod1"):
        TrainConfig.smoke(module=2)
    # With the analysis-by-synthesis loss (sim #2 on the estimated meshes).
    run3 = train(
        TrainConfig.smoke(out=tmp_path / "m3", module=2, mod1=run1, epochs=1, synthesis_weight=0.1, **common),
        _small(data32, 4),
    )
    row = _metrics(run3)[0]
    assert "synthesis" in row and np.isfinite(row["synthesis"]) and row["synthesis"] > 0


@pytest.fixture(scope="module")
def trained_run(data32, tmp_path_factory):
    run = tmp_path_factory.mktemp("run")
    code = main(
        [
            "train",
            "--data",
            str(data32),
            "--out",
            str(run),
            "--module",
            "1",
            "--preset",
            "smoke",
            "--epochs",
            "1",
            "--batch-size",
            "8",
            "--no-progress",
        ]
    )
    assert code == 0
    return run


def test_predict_writes_params_meshes_and_figures(trained_run, data32, tmp_path, anny32):
    images = NpzDataset(data32 / "train.npz").arrays["pressure_mmhg"][:3].numpy()
    np.save(tmp_path / "one.npy", images[0])
    np.save(tmp_path / "stack.npy", images)
    # A PmatData-like frame: raw units, row 0 at the FOOT end, commas.
    raw = 40 + 30 * images[0][::-1]
    np.savetxt(tmp_path / "frame.csv", raw, delimiter=",", fmt="%.0f")
    _shard(tmp_path / "shard.parquet", images[:2])
    out = tmp_path / "out"
    files = [str(tmp_path / n) for n in ("one.npy", "stack.npy", "frame.csv", "shard.parquet")]
    assert (
        main(
            [
                "predict",
                "--model",
                str(trained_run),
                "--out",
                str(out),
                "--gender",
                "female",
                "--batch-size",
                "4",
                *files,
            ]
        )
        == 0
    )
    names = ["one", "stack_0000", "stack_0001", "stack_0002", "frame", "shard_0000", "shard_0001"]
    for n in names:
        record = json.loads((out / f"{n}.json").read_text())
        assert len(record["pose_axis_angle"]) == 23 and len(record["joints_m"]) == 24
        assert record["shape"]["gender"] == 1.0 and 30 < record["mass_kg"] < 160
        assert record["load_ends"] in LOAD_ENDS
        assert "joint_spread_m" not in record  # a network without heatmaps has no spreads to report
        rr = torch.tensor([record["root_rotation_axis_angle"]], dtype=torch.float64)
        assert record["roll_deg"] == pytest.approx(float(roll_deg(rr)[0]), abs=1e-6)
        assert record["posture"] == posture_of(torch.tensor([record["roll_deg"]]))[0]
        v, f = read_mesh(out / f"{n}.ply")
        assert v.shape == (anny32.num_vertices, 3) and f.shape == tuple(anny32.faces.shape)
        assert (out / f"{n}.png").stat().st_size > 10_000
    # One row per image, in input order: the JSONs' posture, height, mass and where the load lies.
    table = (out / "predictions.csv").read_text().splitlines()
    assert table[0] == "image,posture,roll_deg,height_m,mass_kg,load_ends" and len(table) == 1 + len(names)
    for n, line in zip(names, table[1:]):
        record = json.loads((out / f"{n}.json").read_text())
        cells = line.split(",")
        assert cells[:2] == [n, record["posture"]] and cells[5] == record["load_ends"]
        assert float(cells[3]) == pytest.approx(record["height_m"], abs=1e-4)
    # The same image gives the same answer whatever file and batch it came in.
    a, b = (json.loads((out / f"{n}.json").read_text()) for n in ("one", "stack_0000"))
    assert a["root_translation_m"] == pytest.approx(b["root_translation_m"], abs=1e-6)
    # Where the load lies is computed from each image as read, and follows a load put on the head row.
    assert [json.loads((out / f"{n}.json").read_text())["load_ends"] for n in names[1:4]] == load_ends(images)
    cut = images[:1].copy()
    cut[0, 0, 10:14] = cut[0].max()  # a load on the head row
    np.save(tmp_path / "cut.npy", cut[0])
    assert (
        main(["predict", "--model", str(trained_run), "--out", str(out), "--no-figures", str(tmp_path / "cut.npy")])
        == 0
    )
    assert json.loads((out / "cut.json").read_text())["load_ends"] in ("head only", "both")


def _shard(path, images):
    import pyarrow as pa
    import pyarrow.parquet as pq

    flat = pa.array(list(images.reshape(len(images), -1).astype(np.float32)), type=pa.list_(pa.float32(), 64 * 27))
    pq.write_table(pa.table({"pressure_mmhg": flat}), path)


@pytest.mark.parametrize(
    "case",
    [
        "wrong_size",
        "nan",
        "negative",
        "empty_image",
        "empty_file",
        "words",
        "not_an_array",
        "pickled",
        "unknown_suffix",
        "missing",
    ],
)
def test_predict_bad_files_exit_2_with_one_line(case, trained_run, tmp_path, capsys):
    path = tmp_path / "bad.npy"
    good = np.zeros((64, 27), np.float32)
    good[20:30, 10:15] = 30
    if case == "wrong_size":
        np.save(path, np.ones((32, 27)))
    elif case == "nan":
        good[0, 0] = np.nan
        np.save(path, good)
    elif case == "negative":
        good[0, 0] = -5
        np.save(path, good)
    elif case == "empty_image":
        np.save(path, np.zeros((64, 27)))
    elif case == "empty_file":
        path.write_bytes(b"")
    elif case == "words":
        path = tmp_path / "bad.txt"
        path.write_text("\n".join(" ".join(["hello"] * 27) for _ in range(64)))
    elif case == "not_an_array":
        path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(200))
    elif case == "pickled":
        np.save(path, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    elif case == "unknown_suffix":
        path = tmp_path / "bad.png"
        path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(200))
    else:
        path = tmp_path / "missing.npy"
    capsys.readouterr()
    out = tmp_path / "out"
    assert main(["predict", "--model", str(trained_run), "--out", str(out), str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pressurepose: error:") and path.name in err[0]
    assert not out.exists()  # nothing written before every input was checked


def test_train_cli_errors_exit_2(tmp_path, capsys):
    assert main(["train", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "run"), "--preset", "smoke"]) == 2
    assert "no dataset" in capsys.readouterr().err
    assert main(["predict", "--model", str(tmp_path), str(tmp_path / "x.npy")]) == 2
    assert "no such file" in capsys.readouterr().err


def _blur_reference(image, sigma, radius):
    """Naive 2-D convolution with the truncated, normalised separable Gaussian, zero padded."""
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    k = torch.exp(-0.5 * (x / sigma) ** 2) if sigma > 0 else (x == 0).double()
    k = k / k.sum()
    out = torch.zeros_like(image, dtype=torch.float64)
    H, W = image.shape
    for r in range(H):
        for c in range(W):
            for dr in range(-radius, radius + 1):
                for dc in range(-radius, radius + 1):
                    if 0 <= r + dr < H and 0 <= c + dc < W:
                        out[r, c] += k[dr + radius] * k[dc + radius] * float(image[r + dr, c + dc])
    return out


def test_augmentations_read_from_the_generators_floor():
    """Images the augmentations re-read start where the generator's do: the default bed's sensor
    floor (a lower threshold would give them the fringe that no real mat reads)."""
    from pressurepose.sim.run import default_mattress
    from pressurepose.train.augment import REPRESS_THRESHOLD_MMHG

    assert REPRESS_THRESHOLD_MMHG == default_mattress("articulated").floor_mmhg > 3.0


def test_repress_augmentation_against_a_naive_reference(data32, monkeypatch):
    """Re-pressing from the depth label: a per-image loop with a naive 2-D blur gives the same
    images; the force is kept; a deeper sink covers more taxels; the off images are untouched."""
    from pressurepose.train import augment
    from pressurepose.train.augment import REPRESS_THRESHOLD_MMHG, repress_batch

    arrays = NpzDataset(data32 / "train.npz").arrays
    p, Q = arrays["pressure_mmhg"][:6].double(), arrays["depth_mm"][:6].double()
    inputs = NetInputs(pressure_mmhg=p)
    assert torch.equal(repress_batch(inputs, Q, 0.0, torch.Generator().manual_seed(0)).pressure_mmhg, p)
    out = repress_batch(inputs, Q, 0.5, torch.Generator().manual_seed(4)).pressure_mmhg
    u = torch.rand(4, 6, generator=torch.Generator().manual_seed(4)).double()  # the same draws
    on = u[0] < 0.5
    assert 0 < int(on.sum()) < 6, "pick a seed that re-presses some images and not others"
    delta, gamma, sigma = 40 * u[1], 0.5 + u[2], 0.3 + 0.7 * u[3]
    radius = max(1, int(np.ceil(3 * float(sigma.max()))))
    for i in range(6):
        if not on[i]:
            assert torch.equal(out[i], p[i])
            continue
        c = (float(delta[i]) - Q[i]).clamp(min=0)
        ref = _blur_reference(torch.where(c > 0, c ** float(gamma[i]), torch.zeros_like(c)), float(sigma[i]), radius)
        ref = ref * float(p[i].sum()) / float(ref.sum())
        ref = torch.where(ref >= REPRESS_THRESHOLD_MMHG, ref, torch.zeros_like(ref)).clamp(max=100)
        assert torch.allclose(out[i], ref, atol=1e-9), i
        # the load is kept, less what the threshold and the 100 mmHg ceiling take
        assert abs(float(out[i].sum()) / float(p[i].sum()) - 1) < 0.1
    # a softer bed (deeper sink) loads more taxels, with everything else the same
    monkeypatch.setattr(augment, "REPRESS_EXPONENT", (1.0, 1.0))
    monkeypatch.setattr(augment, "REPRESS_SPREAD_TAXELS", (0.5, 0.5))
    area = []
    for d in (0.0, 20.0, 40.0):
        monkeypatch.setattr(augment, "REPRESS_EXTRA_SINK_MM", (d, d))
        area.append((repress_batch(inputs, Q, 1.0, None).pressure_mmhg > 0).sum((1, 2)))
    assert bool((area[0] <= area[1]).all() and (area[1] <= area[2]).all() and (area[2] > area[0]).all())
    with pytest.raises(ValueError, match="repress"):
        TrainConfig.smoke(repress=1.5)


def test_mirror_flips_images_and_labels_as_the_physics_does(anny64):
    from pressurepose.body import BodyParams
    from pressurepose.body.joints import J24_MIRROR
    from pressurepose.mat import MatSpec
    from pressurepose.net.losses import Targets
    from pressurepose.sim.foundation import simulate_pressure
    from pressurepose.sim.sensor import sensing_area, taxel_reading
    from pressurepose.train.augment import mirror_batch

    a = synthetic_arrays(3, seed=6, body=anny64)
    B = len(a["pressure_mmhg"])
    inputs = NetInputs(pressure_mmhg=a["pressure_mmhg"])
    targets = Targets(joints=a["joints"], shape=a["shape"], depth_mm=a["depth_mm"], contact=a["contact"])
    same_in, same = mirror_batch(inputs, targets, 0.0, torch.Generator().manual_seed(0))
    assert same_in is inputs and same is targets
    W = MatSpec().sensing_width_m
    m_in, m = mirror_batch(inputs, targets, 1.0, None)
    for b in range(B):  # naive reference
        for r in range(0, 64, 7):
            for c in range(27):
                assert m_in.pressure_mmhg[b, r, c] == inputs.pressure_mmhg[b, r, 26 - c]
                assert m.depth_mm[b, r, c] == targets.depth_mm[b, r, 26 - c]
        for j in range(24):
            src = targets.joints[b, J24_MIRROR[j]]
            assert torch.allclose(m.joints[b, j], torch.stack([src[0], W - src[1], src[2]]), atol=1e-6)
    assert torch.equal(m.shape, targets.shape)
    back_in, back = mirror_batch(m_in, m, 1.0, None)  # an involution
    assert torch.equal(back_in.pressure_mmhg, inputs.pressure_mmhg) and torch.allclose(
        back.joints, targets.joints, atol=1e-6
    )
    part_in, part = mirror_batch(inputs, targets, 0.5, torch.Generator().manual_seed(2))
    on = torch.rand(B, generator=torch.Generator().manual_seed(2)) < 0.5
    for b in range(B):
        ref_in, ref = (m_in, m) if on[b] else (inputs, targets)
        assert torch.equal(part_in.pressure_mmhg[b], ref_in.pressure_mmhg[b]) and torch.equal(
            part.joints[b], ref.joints[b]
        )
    # physics: sim #2 on the mirrored mesh reads the mirrored image
    params = BodyParams(
        shape=a["shape"][:1].double(),
        pose=a["pose"][:1].double(),
        root_rotation=a["root_rotation"][:1].double(),
        root_translation=a["root_translation"][:1].double(),
    )
    out = anny64(params)
    mass = anny64.measure(params.shape).mass_kg
    mirrored = out.vertices.clone()
    mirrored[..., 1] = W - mirrored[..., 1]
    with torch.no_grad():
        here = taxel_reading(sensing_area(simulate_pressure(out.vertices, out.faces, mass).pressure_pa)).float()
        there = taxel_reading(sensing_area(simulate_pressure(mirrored, out.faces.flip(-1), mass).pressure_pa)).float()
    flipped, _ = mirror_batch(
        NetInputs(pressure_mmhg=here), Targets(joints=out.joints.float(), shape=params.shape), 1.0, None
    )
    assert float(here.sum()) > 100
    assert float((flipped.pressure_mmhg - there).abs().max()) < 1e-3 * float(here.max())


def _read_as_the_sensor(ref, p):
    """A reference image scaled to p's total, then the sensor's threshold and ceiling."""
    from pressurepose.train.augment import REPRESS_THRESHOLD_MMHG

    ref = ref * float(p.sum()) / float(ref.sum())
    return torch.where(ref >= REPRESS_THRESHOLD_MMHG, ref, torch.zeros_like(ref)).clamp(max=100)


def _drawn_half(batch, p, draws, seed):
    """Run an augmentation `batch(inputs, share, generator)` that draws `draws` uniforms per image
    first: share 0 leaves the images as they are; at share 0.5 some images are drawn and some
    not, and those not drawn are untouched. Returns the output, the uniforms and the drawn
    images' indices."""
    inputs = NetInputs(pressure_mmhg=p)
    assert torch.equal(batch(inputs, 0.0, torch.Generator().manual_seed(0)).pressure_mmhg, p)
    out = batch(inputs, 0.5, torch.Generator().manual_seed(seed)).pressure_mmhg
    u = torch.rand(draws, len(p), generator=torch.Generator().manual_seed(seed)).double()
    on = u[0] < 0.5
    assert 0 < int(on.sum()) < len(p)
    for i in range(len(p)):
        if not on[i]:
            assert torch.equal(out[i], p[i])
    return out, u, [i for i in range(len(p)) if on[i]]


def test_bands_against_a_naive_reference(data32):
    """Air-cell bands: a per-row loop gives the same images, the force is kept, rows of the same
    phase get the same gain, and the off images are untouched."""
    from pressurepose.train.augment import bands_batch

    p = NpzDataset(data32 / "train.npz").arrays["pressure_mmhg"][:6].double()
    out, u, drawn = _drawn_half(bands_batch, p, 4, 4)
    for i in drawn:
        T, a = 2 + 2 * float(u[1, i]), 0.3 + 0.7 * float(u[2, i])
        phi = T * float(u[3, i])
        ref = p[i].clone()
        for r in range(64):
            ref[r] *= max(0.0, 1 + a * math.cos(2 * math.pi * (r - phi) / T))
        ref = _read_as_the_sensor(ref, p[i])
        assert torch.allclose(out[i], ref, atol=1e-9), i
        assert abs(float(out[i].sum()) / float(p[i].sum()) - 1) < 0.1
    with pytest.raises(ValueError, match="bands"):
        TrainConfig.smoke(bands=-0.1)


def test_texture_against_a_per_taxel_reference(data32):
    """Uneven gain: the same draws applied taxel by taxel give the same images, the force is kept
    (before the sensor's threshold and ceiling), the loaded outline can only shrink, and the off
    images are untouched."""
    from pressurepose.train.augment import texture_batch

    p = NpzDataset(data32 / "train.npz").arrays["pressure_mmhg"][:6].double()
    inputs = NetInputs(pressure_mmhg=p)
    assert torch.equal(texture_batch(inputs, 0.0, torch.Generator().manual_seed(0)).pressure_mmhg, p)
    out = texture_batch(inputs, 0.5, torch.Generator().manual_seed(5)).pressure_mmhg
    g = torch.Generator().manual_seed(5)
    u = torch.rand(3, 6, generator=g).double()
    z_row = torch.randn(6, 64, 1, generator=g).double()
    z_taxel = torch.randn(6, 64, 27, generator=g).double()
    on = u[0] < 0.5
    assert 0 < int(on.sum()) < 6
    for i in range(6):
        if not on[i]:
            assert torch.equal(out[i], p[i])
            continue
        s_row, s_taxel = 0.05 + 0.30 * float(u[1, i]), 0.05 + 0.25 * float(u[2, i])
        ref = p[i].clone()
        for r in range(64):
            for c in range(27):
                ref[r, c] *= math.exp(s_row * float(z_row[i, r, 0]) + s_taxel * float(z_taxel[i, r, c]))
        ref = _read_as_the_sensor(ref, p[i])
        assert torch.allclose(out[i], ref, atol=1e-9), i
        assert bool(((out[i] > 0) <= (p[i] > 0)).all())  # no taxel starts to read
        assert abs(float(out[i].sum()) / float(p[i].sum()) - 1) < 0.1
    with pytest.raises(ValueError, match="texture"):
        TrainConfig.smoke(texture=1.5)


def test_occlude_against_a_per_row_reference(data32, tmp_path):
    """Occlusion: the same draws applied row by row zero the same band - k in [2, 8]
    consecutive rows starting on a loaded row (cut by the mat's end) - and leave every other
    taxel, the images not drawn and an empty image untouched."""
    from pressurepose.train.augment import occlude_batch

    p = NpzDataset(data32 / "train.npz").arrays["pressure_mmhg"][:8].double()
    p[7] = 0.0  # an empty image
    inputs = NetInputs(pressure_mmhg=p)
    assert torch.equal(occlude_batch(inputs, 0.0, torch.Generator().manual_seed(0)).pressure_mmhg, p)
    out = occlude_batch(inputs, 0.6, torch.Generator().manual_seed(3)).pressure_mmhg
    u = torch.rand(3, 8, generator=torch.Generator().manual_seed(3)).double()
    drawn = 0
    for i in range(8):
        loaded = [r for r in range(64) if float(p[i, r].sum()) > 0]
        if not (float(u[0, i]) < 0.6 and loaded):
            assert torch.equal(out[i], p[i]), i
            continue
        drawn += 1
        first, last = loaded[0], loaded[-1]
        start = first + math.floor(float(u[1, i]) * (last - first + 1))
        k = 2 + math.floor(float(u[2, i]) * 7)
        assert first <= start <= last and 2 <= k <= 8
        ref = p[i].clone()
        ref[start : start + k] = 0.0
        assert torch.equal(out[i], ref), i
        assert float(out[i].sum()) <= float(p[i].sum())
    assert drawn >= 2
    with pytest.raises(ValueError, match="occlude"):
        TrainConfig.smoke(occlude=1.5)
    with pytest.raises(ValueError, match="--occlude and --synthesis-weight do not combine"):
        TrainConfig.smoke(occlude=0.5, module=2, mod1=tmp_path, synthesis_weight=0.1)


def test_speckle_against_a_per_taxel_reference(data32):
    """Stray readings: the same draws applied taxel by taxel give the same spots - a spot starts
    where its draw is under n / (rows x cols), a share reaches the next row or column, its
    readings lie in SPECKLE_MMHG and a taxel keeps the larger of the body's and the spot's - and
    the images not drawn are untouched; the labels are not an input, so nothing else moves."""
    from pressurepose.train.augment import SPECKLE_MMHG, SPECKLE_PAIR, SPECKLE_PER_IMAGE, speckle_batch

    p = NpzDataset(data32 / "train.npz").arrays["pressure_mmhg"][:8].double()
    inputs = NetInputs(pressure_mmhg=p)
    assert torch.equal(speckle_batch(inputs, 0.0, torch.Generator().manual_seed(0)).pressure_mmhg, p)
    out = speckle_batch(inputs, 0.7, torch.Generator().manual_seed(4)).pressure_mmhg
    g = torch.Generator().manual_seed(4)
    u = torch.rand(2, 8, generator=g).double()
    draws = torch.rand(3, 8, 64, 27, generator=g).double()
    lo, hi = SPECKLE_MMHG
    drawn = 0
    for i in range(8):
        if not float(u[0, i]) < 0.7:
            assert torch.equal(out[i], p[i]), i
            continue
        drawn += 1
        rate = (SPECKLE_PER_IMAGE[0] + (SPECKLE_PER_IMAGE[1] - SPECKLE_PER_IMAGE[0]) * float(u[1, i])) / (64 * 27)
        spot = [[False] * 27 for _ in range(64)]
        for r in range(64):
            for c in range(27):
                if float(draws[0, i, r, c]) < rate:
                    spot[r][c] = True
                    d = float(draws[1, i, r, c])
                    if d < SPECKLE_PAIR / 2 and r + 1 < 64:
                        spot[r + 1][c] = True
                    elif SPECKLE_PAIR / 2 <= d < SPECKLE_PAIR and c + 1 < 27:
                        spot[r][c + 1] = True
        ref = p[i].clone()
        for r in range(64):
            for c in range(27):
                if spot[r][c]:
                    reading = lo * (hi / lo) ** float(draws[2, i, r, c])
                    assert lo <= reading <= hi
                    ref[r, c] = max(float(p[i, r, c]), reading)
        assert torch.allclose(out[i], ref, rtol=1e-12, atol=0), i
        assert bool((out[i] >= p[i]).all())  # readings only rise, and only off the body's load
    assert drawn >= 3
    # over many images the number of spots follows the drawn rate: mean n = 4 starts per image
    many = torch.zeros(400, 64, 27, dtype=torch.float64)
    noisy = speckle_batch(NetInputs(pressure_mmhg=many), 1.0, torch.Generator().manual_seed(1)).pressure_mmhg
    taxels = float((noisy > 0).sum(dim=(1, 2)).double().mean())
    expected = sum(SPECKLE_PER_IMAGE) / 2 * (1 + SPECKLE_PAIR)  # a pair adds one taxel (rarely off the mat)
    assert abs(taxels - expected) < 0.1 * expected, (taxels, expected)
    with pytest.raises(ValueError, match="speckle"):
        TrainConfig.smoke(speckle=1.5)


def test_predict_ik_steps_and_flip_test_only_for_the_heatmap_arch(trained_run, tmp_path, capsys):
    path = tmp_path / "one.npy"
    np.save(path, np.full((64, 27), 5.0, dtype=np.float32))
    for flags, said in ((["--ik-steps", "5"], "--ik-steps applies"), (["--flip-test"], "--flip-test applies")):
        capsys.readouterr()
        args = ["predict", "--model", str(trained_run), "--out", str(tmp_path / "o"), *flags, str(path)]
        assert main(args) == 2
        err = capsys.readouterr().err
        assert said in err and "arch heatmap" in err and "Traceback" not in err
    capsys.readouterr()
    args = ["evaluate", "--model", str(trained_run), "--data", str(tmp_path), "--flip-test"]
    assert main(args) == 2
    assert "--flip-test applies to arch heatmap" in capsys.readouterr().err


def _weights(run):
    net, _ = load_network(run)
    return net.trainable_state()


def test_weight_average_is_the_mean_of_the_epochs_and_resumes(data32, tmp_path):
    """--average-from 2 over 3 epochs: model.safetensors is the mean of the weights after epochs
    2 and 3 (batch-norm statistics included), last/ holds epoch 3's, and a run resumed in the
    middle of the averaging ends with the same average."""
    ds = _small(data32, n=24)  # 20 or more: a validation split
    common = dict(batch_size=6, val_fraction=0.25, progress=False, seed=3, lr_gamma=0.7, save_every=1)
    train(TrainConfig.smoke(out=tmp_path / "e2", epochs=2, **common), ds)
    train(TrainConfig.smoke(out=tmp_path / "e3", epochs=3, **common), ds)
    train(TrainConfig.smoke(out=tmp_path / "avg", epochs=3, average_from=2, **common), ds)
    e2, e3, avg = _weights(tmp_path / "e2"), _weights(tmp_path / "e3"), _weights(tmp_path / "avg")
    last = _weights(tmp_path / "avg" / "last")
    moved = 0
    for k, v in avg.items():
        if v.is_floating_point():
            mean = (e2[k].double() + e3[k].double()) / 2
            assert torch.allclose(v.double(), mean, atol=1e-5, rtol=1e-4), k
            assert torch.allclose(last[k], e3[k], atol=1e-6), k
            moved += int(not torch.allclose(e2[k], e3[k], atol=1e-4))
        else:  # batch norm's counters: the latest epoch's
            assert torch.equal(v, e3[k]), k
    assert moved > 10  # the epochs differ, so the mean is not one of them
    rows = _metrics(tmp_path / "avg")
    assert "average_val_mpjpe_mm" not in rows[0] and rows[1]["average_val_mpjpe_mm"] == pytest.approx(
        rows[1]["val_mpjpe_mm"], rel=1e-5
    )  # one epoch averaged: the network itself
    assert rows[2]["average_val_mpjpe_mm"] != pytest.approx(rows[2]["val_mpjpe_mm"], rel=1e-6)
    # Interrupted after epoch 2 (the average holds one epoch), resumed to 3.
    train(TrainConfig.smoke(out=tmp_path / "res", epochs=2, average_from=2, **common), ds)
    train(TrainConfig.smoke(out=tmp_path / "res", epochs=3, average_from=2, **common), ds)
    for k, v in _weights(tmp_path / "res").items():
        assert torch.allclose(v.float(), avg[k].float(), atol=1e-5), k


def test_weight_average_bad_settings_and_checkpoints(data32, tmp_path):
    from safetensors import safe_open
    from safetensors.torch import save_file

    ds = _small(data32)
    common = dict(batch_size=4, val_fraction=0.0, progress=False, seed=3)
    with pytest.raises(ValueError, match="average_from must lie in"):
        TrainConfig.smoke(out=tmp_path / "x", epochs=2, average_from=3)
    train(TrainConfig.smoke(out=tmp_path / "run", epochs=2, average_from=1, **common), ds)
    with pytest.raises(ValueError, match="different settings.*average_from"):
        train(TrainConfig.smoke(out=tmp_path / "run", epochs=3, average_from=2, **common), ds)
    path = tmp_path / "run" / "checkpoint.safetensors"
    with safe_open(str(path), "pt") as f:
        meta, tensors = f.metadata(), {k: f.get_tensor(k) for k in f.keys()}
    save_file({k: v for k, v in tensors.items() if not k.startswith("average")}, str(path), metadata=meta)
    with pytest.raises(ValueError, match="weight average of 0 epochs.*needs 2"):
        train(TrainConfig.smoke(out=tmp_path / "run", epochs=3, average_from=1, **common), ds)
    save_file({k: v for k, v in tensors.items() if k != "average_count"}, str(path), metadata=meta)
    with pytest.raises(ValueError, match="average_count"):
        train(TrainConfig.smoke(out=tmp_path / "run", epochs=3, average_from=1, **common), ds)
    assert main(["train", "--data", str(tmp_path), "--out", str(tmp_path / "r2"), "--preset", "smoke",
                 "--epochs", "2", "--average-from", "5"]) == 2  # fmt: skip


def test_posture_readout_trains_jointly_and_alone(data32, tmp_path):
    """--posture-weight: a heatmap network with a posture readout, its validation share
    recorded; --posture-only: the readout trained on another run's frozen network (one without
    a readout), every other weight kept to the bit."""
    ds = _small(data32, n=24)
    common = dict(arch="heatmap", batch_size=6, val_fraction=0.25, progress=False, seed=5, gender_input=False)
    train(TrainConfig.smoke(out=tmp_path / "joint", epochs=2, posture_weight=0.1, **common), ds)
    rows = _metrics(tmp_path / "joint")
    assert all(0 <= r["val_posture_accuracy"] <= 1 and r["posture"] > 0 for r in rows)
    joint, _ = load_network(tmp_path / "joint")
    assert joint.config.posture_head
    train(TrainConfig.smoke(out=tmp_path / "plain", epochs=1, **common), ds)
    train(TrainConfig.smoke(out=tmp_path / "alone", epochs=3, lr=1e-2, posture_only=True, init=tmp_path / "plain", **common), ds)  # fmt: skip
    plain, alone = _weights(tmp_path / "plain"), _weights(tmp_path / "alone")
    assert set(alone) - set(plain) == {"mod1.posture.layers.1.weight", "mod1.posture.layers.1.bias"}
    for k, v in plain.items():
        assert torch.equal(v, alone[k]), k  # frozen: weights and batch-norm statistics
    rows = _metrics(tmp_path / "alone")
    assert rows[-1]["loss"] == pytest.approx(rows[-1]["posture"]) and rows[-1]["loss"] < rows[0]["loss"]
    # What the optimizer gets and which modules run in training mode.
    net = build_network(TrainConfig.smoke(posture_only=True, init=tmp_path / "plain", **common), torch.device("cpu"))
    trained = {n for n, p in net.named_parameters() if p.requires_grad}
    assert trained == {"mod1.posture.layers.1.weight", "mod1.posture.layers.1.bias"}
    net.train()
    assert not net.mod1.training and net.mod1.posture.training and not net.mod1.enc1.training
    # A network with a readout fine-tunes into one without (the readout left out), and a
    # different input smoothing is refused.
    train(TrainConfig.smoke(out=tmp_path / "ft", epochs=1, init=tmp_path / "alone", **common), ds)
    assert not load_network(tmp_path / "ft")[0].config.posture_head
    with pytest.raises(ValueError, match="texture_sigma_taxels"):
        train(
            TrainConfig.smoke(out=tmp_path / "ts", epochs=1, init=tmp_path / "plain", texture_sigma=1.0, **common), ds
        )
    for bad, match in (
        (dict(posture_only=True), "give --init"),
        (dict(posture_weight=0.1, arch="fast"), "for --arch heatmap; this run is --arch fast"),
        (dict(posture_weight=-1.0), "posture_weight must be >= 0"),
    ):
        with pytest.raises(ValueError, match=match):
            TrainConfig.smoke(out=tmp_path / "x", **{**common, **bad})


def test_spread_against_a_direct_convolution(data32):
    """Spread: each drawn image equals a direct 2-D convolution with its own Gaussian (zero
    padded, truncated at the batch's radius), floored at its own reading floor and scaled back to its force; the
    spread image is wider and no higher; off images are untouched; bad shares are refused."""
    from pressurepose.train.augment import MAX_MMHG, SPREAD_FLOOR_MMHG, SPREAD_TAXELS, spread_batch

    p = NpzDataset(data32 / "train.npz").arrays["pressure_mmhg"][:8].double()
    out, u, drawn = _drawn_half(spread_batch, p, 3, 5)
    for i in drawn:
        sigma = SPREAD_TAXELS[0] + (SPREAD_TAXELS[1] - SPREAD_TAXELS[0]) * float(u[1, i])
        floor = SPREAD_FLOOR_MMHG[0] + (SPREAD_FLOOR_MMHG[1] - SPREAD_FLOOR_MMHG[0]) * float(u[2, i])
        # the batch's kernels share one radius, 3 x its largest sigma (blur.gaussian_blur)
        r = math.ceil(3 * (SPREAD_TAXELS[0] + (SPREAD_TAXELS[1] - SPREAD_TAXELS[0]) * float(u[1].max())))
        g = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=torch.float64) / sigma) ** 2)
        kernel = (g[:, None] * g[None, :]) / g.sum() ** 2
        ref = torch.nn.functional.conv2d(p[i][None, None], kernel[None, None], padding=r)[0, 0]
        ref = torch.where(ref >= floor, ref, torch.zeros_like(ref))
        ref = (ref * float(p[i].sum()) / float(ref.sum())).clamp(max=MAX_MMHG)
        assert torch.allclose(out[i], ref, atol=1e-9), i
        assert int((out[i] > 0).sum()) > int((p[i] > 0).sum()) and float(out[i].max()) <= float(p[i].max())
        assert float(out[i].sum()) == pytest.approx(float(p[i].sum()), rel=1e-9)
    with pytest.raises(ValueError, match="spread"):
        TrainConfig.smoke(spread=1.5)


def test_flatten_against_a_per_taxel_reference(data32, monkeypatch):
    """Flattened contrast: the power applied taxel by taxel gives the same images, flatter; g = 0
    (the range's end) leaves one pressure over the same outline with the same force; the off
    images are untouched."""
    from pressurepose.train import augment
    from pressurepose.train.augment import FLATTEN_GAMMA, flatten_batch

    p = NpzDataset(data32 / "train.npz").arrays["pressure_mmhg"][:8].double()
    inputs = NetInputs(pressure_mmhg=p)
    out, u, drawn = _drawn_half(flatten_batch, p, 2, 3)
    for i in drawn:
        g = FLATTEN_GAMMA[0] + (FLATTEN_GAMMA[1] - FLATTEN_GAMMA[0]) * float(u[1, i])
        ref = p[i].clone()
        for r in range(64):
            for c in range(27):
                ref[r, c] = float(p[i, r, c]) ** g if p[i, r, c] > 0 else 0.0
        ref = _read_as_the_sensor(ref, p[i])
        assert torch.allclose(out[i], ref, atol=1e-9), i
        spread = lambda a: float(a[a > 0].std() / a[a > 0].mean())  # noqa: E731
        assert spread(out[i]) < spread(p[i])  # flatter
    monkeypatch.setattr(augment, "FLATTEN_GAMMA", (0.0, 0.0))
    flat = augment.flatten_batch(inputs, 1.0, torch.Generator().manual_seed(3)).pressure_mmhg
    for i in range(8):  # one pressure over the same outline, the force kept
        assert torch.equal(flat[i] > 0, p[i] > 0)
        assert torch.allclose(flat[i][p[i] > 0], flat[i][p[i] > 0].mean(), rtol=1e-9)
        assert float(flat[i].sum()) == pytest.approx(float(p[i].sum()), rel=1e-9)
    with pytest.raises(ValueError, match="flatten"):
        TrainConfig.smoke(flatten=2.0)


def test_predict_leaves_no_table_when_a_run_stops(trained_run, data32, tmp_path, monkeypatch):
    """predictions.csv is written last: a run that stops on its second image leaves none, not an
    earlier run's table that no longer matches the files."""
    import pressurepose.commands.predict as P

    images = NpzDataset(data32 / "train.npz").arrays["pressure_mmhg"][:2].numpy()
    np.save(tmp_path / "two.npy", images)
    out = tmp_path / "out"
    args = ["predict", "--model", str(trained_run), "--out", str(out), "--no-figures", "--no-meshes"]
    assert main([*args, str(tmp_path / "two.npy")]) == 0 and (out / "predictions.csv").is_file()
    written = P._write_one

    def stop_at_the_second(*a, **k):
        if a[1].endswith("0001"):
            raise RuntimeError("disk full")
        return written(*a, **k)

    monkeypatch.setattr(P, "_write_one", stop_at_the_second)
    with pytest.raises(RuntimeError, match="disk full"):
        P.run_predict(P.PredictConfig(files=(tmp_path / "two.npy",), model=trained_run, out=out, figures=False))
    assert not (out / "predictions.csv").exists()


def test_predict_without_meshes_or_figures_skips_the_mesh(trained_run, data32, tmp_path, monkeypatch):
    """With neither meshes nor figures asked for, predict poses no mesh (the joints come from the
    skeleton alone) and writes the same JSON numbers as a run that writes the meshes."""
    import pressurepose.body.model as body_model

    images = NpzDataset(data32 / "train.npz").arrays["pressure_mmhg"][:3].numpy()
    np.save(tmp_path / "three.npy", images)
    base = ["predict", "--model", str(trained_run), "--no-figures", str(tmp_path / "three.npy")]
    assert main([*base, "--out", str(tmp_path / "with")]) == 0
    assert (tmp_path / "with" / "three_0000.ply").is_file()
    posed = []
    forward = body_model.BodyModel.forward
    monkeypatch.setattr(body_model.BodyModel, "forward", lambda self, p: posed.append(p) or forward(self, p))
    assert main([*base, "--no-meshes", "--out", str(tmp_path / "without")]) == 0
    assert not posed and not list((tmp_path / "without").glob("*.ply"))
    for k in range(3):
        a, b = (json.loads((tmp_path / d / f"three_{k:04d}.json").read_text()) for d in ("with", "without"))
        assert a.keys() == b.keys() and a["posture"] == b["posture"]
        for joint, xyz in a["joints_m"].items():
            np.testing.assert_allclose(b["joints_m"][joint], xyz, atol=1e-5)
        assert b["height_m"] == pytest.approx(a["height_m"], abs=1e-5)
        assert b["mass_kg"] == pytest.approx(a["mass_kg"], rel=1e-5)
    assert (tmp_path / "without" / "predictions.csv").read_text() == (tmp_path / "with" / "predictions.csv").read_text()


def test_realism_refuses_a_network_without_heatmaps(trained_run):
    from pressurepose.commands.realism import _readers
    from pressurepose.errors import UserError

    with pytest.raises(UserError, match="must be a heatmap network without height and mass inputs"):
        _readers(trained_run)


def test_predict_head_end_auto_turns_a_reversed_file(tmp_path, capsys):
    """`--head-end auto` with the packaged heatmap network: PmatData's frames as imported (head at
    row 0) read the first row as the head end; the same frames turned end for end read the last,
    and are read turned back (the same estimates); `last-row` turns a file without asking; a
    network without heatmaps cannot tell."""
    from pathlib import Path

    from pressurepose.data.pmatdata import load_images, load_index

    pmat = Path(__file__).resolve().parent / "data" / "pmatdata"
    frames = load_images(load_index(pmat))
    np.save(tmp_path / "given.npy", frames)
    np.save(tmp_path / "turned.npy", np.ascontiguousarray(frames[:, ::-1]))
    out = tmp_path / "auto"
    flags = ["--no-figures", "--no-meshes", "--out", str(out)]
    assert (
        main(["predict", "--head-end", "auto", *flags, str(tmp_path / "given.npy"), str(tmp_path / "turned.npy")]) == 0
    )
    n = len(frames)
    given = [json.loads((out / f"given_{k:04d}.json").read_text()) for k in range(n)]
    turned = [json.loads((out / f"turned_{k:04d}.json").read_text()) for k in range(n)]
    assert {r["head_end"] for r in given} == {"first row"} and {r["head_end"] for r in turned} == {"last row"}
    spreads = given[0]["head_end_trunk_spread_m"]
    assert (
        spreads["first row"] < spreads["last row"]
        and turned[0]["head_end_trunk_spread_m"]["last row"] < spreads["last row"]
    )
    for a, b in zip(given, turned):  # the same images once turned back: the same bodies
        np.testing.assert_allclose(a["joints_m"]["head"], b["joints_m"]["head"], atol=1e-4)
        assert a["posture"] == b["posture"]
    rows = (out / "predictions.csv").read_text().splitlines()
    assert rows[0].split(",")[:7] == ["image", "posture", "roll_deg", "height_m", "mass_kg", "load_ends", "head_end"]
    assert sum(r.split(",")[6] == "last row" for r in rows[1:]) == n
    # last-row: turned without asking; the default leaves the file as it is (and says nothing).
    assert main(["predict", "--head-end", "last-row", *flags, str(tmp_path / "turned.npy")]) == 0
    last = json.loads((out / "turned_0000.json").read_text())
    assert last["head_end"] == "last row" and "head_end_trunk_spread_m" not in last
    np.testing.assert_allclose(last["joints_m"]["head"], given[0]["joints_m"]["head"], atol=1e-4)
    assert main(["predict", *flags, str(tmp_path / "given.npy")]) == 0
    assert "head_end" not in json.loads((out / "given_0000.json").read_text())


def test_predict_head_end_auto_needs_heatmaps(trained_run, tmp_path, capsys):
    path = tmp_path / "one.npy"
    np.save(path, np.full((64, 27), 5.0, dtype=np.float32))
    capsys.readouterr()
    args = ["predict", "--model", str(trained_run), "--head-end", "auto", "--out", str(tmp_path / "o"), str(path)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "--head-end auto reads the head end from heatmaps" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()
