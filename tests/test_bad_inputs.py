"""Bad inputs at every file boundary: one line naming the file and the field, exit 2, no
traceback (issue #24). Each case here failed before the fix it names; the property-based
versions (mutated files) are in test_fuzz.py."""

import json
import pickle
import shutil

import numpy as np
import pytest
import tyro
from test_data import GROUPS, make_fake_dataset

from pressurepose.cli import main
from pressurepose.errors import UserError


def one_line_error(capsys, *needles):
    """The CLI's stderr: exactly one line, starting as a user error, holding every needle."""
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("pressurepose: error:") and "Traceback" not in err[0], err
    for needle in needles:
        assert needle in err[0], (needle, err[0])
    return err[0]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds") / "ds"
    make_fake_dataset(root, GROUPS)
    return root


def edit_manifest(src, dst, change):
    shutil.copytree(src, dst)
    manifest = json.loads((dst / "manifest.json").read_text())
    manifest = change(manifest)
    (dst / "manifest.json").write_text(json.dumps(manifest) if not isinstance(manifest, str) else manifest)
    return dst


def _drop(key):
    def change(m):
        del m[key]
        return m

    return change


def _shard(key, value):
    def change(m):
        if value is KeyError:
            del m["shards"][0][key]
        else:
            m["shards"][0][key] = value
        return m

    return change


MANIFEST_CASES = {
    "list": (lambda m: [], "expected a JSON object"),
    "no_shards": (_drop("shards"), "'shards' is missing"),
    "shards_not_list": (lambda m: {**m, "shards": {"a": 1}}, "'shards' must be a JSON list"),
    "shard_without_file": (_shard("file", KeyError), "'shards[0].file' is missing"),
    "shard_file_escapes": (_shard("file", "../../../../etc/passwd"), "must be a relative path inside"),
    "shard_file_absolute": (_shard("file", "/etc/passwd"), "must be a relative path inside"),
    "shard_count_text": (_shard("count", "70"), "'shards[0].count' must be an integer >= 0"),
    "shard_count_wrong": (_shard("count", 71), "'total' is 108 but the shards hold 109"),
    "shard_sha_short": (_shard("sha256", "abc"), "'shards[0].sha256' must be a sha256"),
    "shard_split": (_shard("split", "val"), "'shards[0].split' must be one of train, test"),
    "broken_json": (lambda m: json.dumps(m)[:-20], "is not readable JSON"),
    "no_format": (_drop("format"), "not a pressurepose-dataset v1 manifest"),
}


@pytest.mark.parametrize("case", sorted(MANIFEST_CASES))
def test_malformed_manifest_is_one_line_for_info_train_evaluate(case, dataset, tmp_path, capsys):
    change, message = MANIFEST_CASES[case]
    bad = edit_manifest(dataset, tmp_path / "bad", change)
    for argv in (
        ["info", str(bad), "--sheet", "0"],
        ["train", "--data", str(bad), "--out", str(tmp_path / "run"), "--preset", "smoke"],
        ["evaluate", "--data", str(bad), "--out", str(tmp_path / "ev")],
    ):
        capsys.readouterr()
        assert main(argv) == 2, argv
        one_line_error(capsys, "manifest.json", message)
    assert not (tmp_path / "run" / "model.safetensors").exists()


def test_shard_path_outside_the_dataset_is_never_read(dataset, tmp_path, capsys, monkeypatch):
    import pressurepose.data.shards as shards

    secret = tmp_path / "secret.parquet"
    secret.write_bytes(b"not yours")
    bad = edit_manifest(dataset, tmp_path / "bad", _shard("file", "../secret.parquet"))
    opened = []
    monkeypatch.setattr(shards, "sha256_file", lambda p: opened.append(p) or "0" * 64)
    assert main(["info", str(bad), "--sheet", "0"]) == 2
    one_line_error(capsys, "must be a relative path inside")
    assert opened == []
    # A symlink inside the folder that leads out is refused too.
    (bad / "shards" / "link.parquet").symlink_to(secret)
    m = json.loads((bad / "manifest.json").read_text())
    m["shards"][0]["file"] = "shards/link.parquet"
    (bad / "manifest.json").write_text(json.dumps(m))
    assert main(["info", str(bad), "--sheet", "0"]) == 2
    one_line_error(capsys, "must be a relative path inside")
    assert opened == []


def test_shard_with_fewer_rows_than_its_record_is_corrupt(dataset, tmp_path):
    from pressurepose.data.dataset import PressurePoseDataset
    from pressurepose.data.shards import CorruptShardError

    m = json.loads((dataset / "manifest.json").read_text())
    m["shards"][0]["count"] += 1  # the manifest consistent with itself, but not with the shard's footer
    m["total"] += 1
    m["counts"]["train"]["supine"]["female"] += 1
    bad = edit_manifest(dataset, tmp_path / "bad", lambda _: m)
    with pytest.raises(CorruptShardError, match="holds 70 rows but the manifest records 71"):
        PressurePoseDataset(bad, verify=False)[0]


def test_user_error_is_one_line_but_internal_value_error_keeps_its_traceback(monkeypatch, capsys):
    import pressurepose.cli as cli

    def bug(path: tyro.conf.Positional[str]) -> None:
        raise ValueError("an internal bug")

    monkeypatch.setitem(cli.COMMANDS, "info", bug)
    with pytest.raises(ValueError, match="an internal bug"):
        main(["info", "x"])

    def user(path: tyro.conf.Positional[str]) -> None:
        raise UserError("x: field 'y' must be z")

    monkeypatch.setitem(cli.COMMANDS, "info", user)
    assert main(["info", "x"]) == 2
    one_line_error(capsys, "x: field 'y' must be z")


# --- network files and run folders ---------------------------------------------------------


def good_image(path):
    image = np.zeros((64, 27), np.float32)
    image[10:50, 8:19] = 30.0
    np.save(path, image)
    return path


def rewrite_model(src_run, dst_run, tensors=None, metadata=None):
    """A copy of a run's model.safetensors with some tensors or metadata replaced."""
    from safetensors import safe_open
    from safetensors.torch import save_file

    dst_run.mkdir(parents=True, exist_ok=True)
    with safe_open(str(src_run / "model.safetensors"), framework="pt") as f:
        found = {k: f.get_tensor(k) for k in f.keys()}
        meta = dict(f.metadata())
    found.update(tensors or {})
    meta.update(metadata or {})
    save_file({k: v.contiguous() for k, v in found.items()}, str(dst_run / "model.safetensors"), metadata=meta)
    return dst_run


@pytest.fixture(scope="module")
def default_run():
    from pressurepose.models import default_model_dir

    return default_model_dir()


def _first_weight(run):
    from pressurepose.train.checkpoint import read_model

    weights, _ = read_model(run)
    return next(k for k, v in weights.items() if v.ndim >= 2)


MODEL_CASES = {
    "wrong_shape": (lambda k, t: {"tensors": {f"model/{k}": t[:, :1].clone()}}, "has shape"),
    "nan_weight": (lambda k, t: {"tensors": {f"model/{k}": t * float("nan")}}, "NaN or infinite"),
    "missing_tensor": (None, "missing tensors"),
    "config_not_json": (lambda k, t: {"metadata": {"config": "{not json"}}, "'config' is not readable JSON"),
    "config_no_net": (lambda k, t: {"metadata": {"config": "{}"}}, "'config.net' is missing"),
    "width_text": (
        lambda k, t: {"metadata": {"config": json.dumps({"net": {"width": "2"}})}},
        "'config.net.width' must be an integer",
    ),
    "width_huge": (
        lambda k, t: {"metadata": {"config": json.dumps({"net": {"width": 10**9}})}},
        "'config.net.width' must lie in",
    ),
    "arch_unknown": (
        lambda k, t: {"metadata": {"config": json.dumps({"net": {"arch": "resnet"}})}},
        "'config.net.arch' must be one of",
    ),
    "not_a_network": (lambda k, t: {"metadata": {"format": "other"}}, "is not a pressurepose network file"),
}


@pytest.mark.parametrize("case", sorted(MODEL_CASES))
def test_malformed_model_file_is_one_line_in_predict_and_evaluate(case, default_run, dataset, tmp_path, capsys):
    from pressurepose.train.checkpoint import read_model

    key = _first_weight(default_run)
    weights, _ = read_model(default_run)
    make, message = MODEL_CASES[case]
    if make is None:  # drop a tensor
        from safetensors.torch import save_file

        (tmp_path / "run").mkdir()
        from safetensors import safe_open

        with safe_open(str(default_run / "model.safetensors"), framework="pt") as f:
            kept = {k: f.get_tensor(k) for k in f.keys() if k != f"model/{key}"}
            meta = dict(f.metadata())
        save_file(kept, str(tmp_path / "run" / "model.safetensors"), metadata=meta)
        run = tmp_path / "run"
    else:
        run = rewrite_model(default_run, tmp_path / "run", **make(key, weights[key]))
    image = good_image(tmp_path / "one.npy")
    for argv in (
        ["predict", "--model", str(run), "--out", str(tmp_path / "p"), str(image)],
        ["evaluate", "--model", str(run), "--data", str(dataset), "--out", str(tmp_path / "e")],
    ):
        capsys.readouterr()
        assert main(argv) == 2, argv
        one_line_error(capsys, "model.safetensors", message)
    assert not (tmp_path / "p").exists()


@pytest.fixture(scope="module")
def finished_run(dataset, tmp_path_factory):
    return make_run(dataset, tmp_path_factory.mktemp("runs") / "run")


def make_run(dataset, run):
    """A one-epoch smoke run folder made without training: config.json, checkpoint, model, metrics."""
    import torch

    from pressurepose.train.checkpoint import save_checkpoint, save_model
    from pressurepose.train.config import TrainConfig
    from pressurepose.train.loop import build_network

    run.mkdir()
    cfg = TrainConfig(data=dataset, out=run, preset="smoke", epochs=1).resolved()
    net = build_network(cfg, torch.device("cpu"))
    opt = torch.optim.Adam([p for p in net.parameters() if p.requires_grad], lr=cfg.lr)
    record = {"train": cfg.to_json(), "net": {**net.config.__dict__}}
    cfg.save(run / "config.json", record["net"])
    save_checkpoint(run, net, opt, 1, record)
    save_model(run, net, record)
    (run / "metrics.jsonl").write_text(json.dumps({"epoch": 1, "loss": 1.0, "train_mpjpe_mm": 100.0}) + "\n")
    return run


def _resume(run, dataset):
    return ["train", "--data", str(dataset), "--out", str(run), "--preset", "smoke", "--epochs", "1"]


RUN_CASES = {
    "config_empty": ("config.json", "{}", "config.json: field 'train' is missing"),
    "config_list": ("config.json", "[1]", "config.json: expected a JSON object"),
    "config_broken": ("config.json", '{"train": ', "config.json is not readable JSON"),
    "config_train_text": ("config.json", '{"train": "x"}', "field 'train' must be a JSON object"),
    "metrics_broken": ("metrics.jsonl", '{"epoch": 1}\n{"epo', "metrics.jsonl: line 2 is not readable JSON"),
    "metrics_no_epoch": ("metrics.jsonl", '{"loss": 1}\n', "metrics.jsonl: field 'line 1: epoch' is missing"),
    "metrics_not_object": ("metrics.jsonl", "[1, 2]\n", "metrics.jsonl: line 1: expected a JSON object"),
}


def test_resuming_a_good_run_works(finished_run, dataset, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    assert main(_resume(run, dataset)) == 0


@pytest.mark.parametrize("case", sorted(RUN_CASES))
def test_resuming_a_damaged_run_is_one_line(case, finished_run, dataset, tmp_path, capsys):
    name, text, message = RUN_CASES[case]
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    (run / name).write_text(text)
    capsys.readouterr()
    assert main(_resume(run, dataset)) == 2
    one_line_error(capsys, message)


def test_resuming_from_a_checkpoint_with_wrong_shapes_is_one_line(finished_run, dataset, tmp_path, capsys):
    from safetensors import safe_open
    from safetensors.torch import save_file

    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    with safe_open(str(run / "checkpoint.safetensors"), framework="pt") as f:
        tensors = {k: f.get_tensor(k) for k in f.keys()}
        meta = dict(f.metadata())
    import torch

    key = "optim/0/exp_avg"  # Adam's first moment of parameter 0, which is no vector of 3
    tensors[key] = torch.zeros(3)
    save_file(tensors, str(run / "checkpoint.safetensors"), metadata=meta)
    capsys.readouterr()
    assert main(_resume(run, dataset)) == 2
    one_line_error(capsys, "checkpoint.safetensors", key, "expected")
    save_file(
        {k: v for k, v in tensors.items() if not k.startswith("optim/")},
        str(run / "checkpoint.safetensors"),
        metadata={**meta, "epoch": "one"},
    )
    assert main(_resume(run, dataset)) == 2
    one_line_error(capsys, "checkpoint.safetensors", "'epoch' must be a whole number")


# --- pickles: a size budget in the restricted unpicklers -----------------------------------

BYTEARRAY_BOMB = b"\x80\x02c__builtin__\nbytearray\n\x8a\x08\x00\x00\x00\x00\x00\x00\x00@\x85R."  # bytearray(2**62)
ARRAY_BOMB = (
    b"\x80\x02cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\n"
    b"\x8a\x06\x00\x00\x00\x00\x00\x01\x85U\x01b\x87R."
)  # _reconstruct(ndarray, (2**40,), 'b')
NDARRAY_BOMB = b"\x80\x02cnumpy\nndarray\n\x8a\x06\x00\x00\x00\x00\x00\x01\x85\x85R."  # ndarray((2**40,))


def _nested_bomb():
    """A 3 kB pickle of {"images": one list shared 1000 x 1000 x 1000 times}: 10^9 numbers."""
    inner = [0.0] * 1000
    middle = [inner] * 1000
    return pickle.dumps(
        {"images": [middle] * 1000, "markers_xyz_m": [], "body_shape": [], "joint_angles": [], "root_xyz_shift": []},
        protocol=2,
    )


@pytest.mark.parametrize("case", ["bytearray", "array", "ndarray", "nested", "global"])
def test_import_original_refuses_memory_bombs_with_one_line(case, tmp_path, capsys):
    path = tmp_path / "train_roll0_f_lay_set1_1.p"
    data = {"bytearray": BYTEARRAY_BOMB, "array": ARRAY_BOMB, "ndarray": NDARRAY_BOMB}.get(case)
    if case == "nested":
        data = _nested_bomb()
    if case == "global":
        data = b"\x80\x02cposix\nsystem\nX\x02\x00\x00\x00id\x85R."
    path.write_bytes(data)
    capsys.readouterr()
    assert main(["import-original", str(path), "--out", str(tmp_path / "out")]) == 2
    line = one_line_error(capsys, str(path))
    assert {"global": "refusing to load the global posix.system", "nested": "more numbers than"}.get(
        case, "asks for"
    ) in line
    assert not (tmp_path / "out" / "manifest.json").exists()


def test_import_original_on_a_folder_names_it(tmp_path, capsys):
    assert main(["import-original", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    one_line_error(capsys, str(tmp_path), "a folder")


@pytest.mark.parametrize("shape", [(10**9, 10**9), (24, -1), ("a", 2), (24, 6890, 1)])
def test_smpl_pickle_with_a_huge_or_bad_sparse_shape_is_refused(shape, tmp_path, monkeypatch):
    import sys
    import types

    from pressurepose.body.smpl_backend import SmplFileError, read_smpl_file

    class csc_matrix:
        def __init__(self):
            self.data, self.indices, self.indptr = np.ones(1), np.zeros(1, np.int64), np.array([0, 1])
            self._shape = shape

    for name in ("scipy", "scipy.sparse"):
        monkeypatch.setitem(sys.modules, name, types.ModuleType(name))
    module = types.ModuleType("scipy.sparse.csc")
    module.csc_matrix = csc_matrix
    csc_matrix.__module__, csc_matrix.__qualname__ = "scipy.sparse.csc", "csc_matrix"
    monkeypatch.setitem(sys.modules, "scipy.sparse.csc", module)
    payload = {k: np.zeros((2, 2)) for k in ("v_template", "shapedirs", "posedirs", "weights", "kintree_table", "f")}
    payload["J_regressor"] = csc_matrix()
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    path.write_bytes(pickle.dumps(payload, protocol=2))
    with pytest.raises(SmplFileError, match="sparse matrix") as info:
        read_smpl_file(path)
    assert str(path) in str(info.value)


def test_smpl_pickle_with_an_allocation_bomb_is_refused(tmp_path):
    from pressurepose.body.smpl_backend import SmplFileError, read_smpl_file

    path = tmp_path / "SMPL_NEUTRAL.pkl"
    path.write_bytes(ARRAY_BOMB)
    with pytest.raises(SmplFileError, match="asks for an array of 1.1e"):
        read_smpl_file(path)


# --- pressure images -------------------------------------------------------------------------


def _predict(tmp_path, *files, extra=()):
    return main(
        ["predict", "--out", str(tmp_path / "p"), "--no-figures", "--no-meshes", *extra, *[str(f) for f in files]]
    )


def test_predict_refuses_a_corrupted_shard_of_a_dataset(dataset, tmp_path, capsys):
    bad = tmp_path / "ds"
    shutil.copytree(dataset, bad)
    shard = sorted((bad / "shards").glob("test-*.parquet"))[0]
    data = bytearray(shard.read_bytes())
    data[len(data) // 2] ^= 0x40  # one flipped bit in the middle of the pressure column
    shard.write_bytes(bytes(data))
    capsys.readouterr()
    assert _predict(tmp_path, shard) == 2
    one_line_error(capsys, str(shard), "sha256")
    # Without the manifest, the shard's own record still catches it.
    (bad / "manifest.json").unlink()
    assert _predict(tmp_path, shard) == 2
    one_line_error(capsys, str(shard), "sha256")
    assert not (tmp_path / "p").exists()


@pytest.mark.parametrize("value,dtype", [(1e30, np.float32), (1e36, np.float32), (1e300, np.float64), (2000, np.int64)])
def test_implausible_pressures_are_refused_unless_forced(value, dtype, tmp_path, capsys):
    import warnings

    image = np.full((64, 27), value, dtype)
    np.save(tmp_path / "high.npy", image)
    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no numpy RuntimeWarning (overflow in a cast) before the error
        assert _predict(tmp_path, tmp_path / "high.npy") == 2
    one_line_error(capsys, "high.npy", "more than 1000 mmHg", "--force")
    assert not (tmp_path / "p").exists()


def test_forced_implausible_pressures_run(tmp_path, capsys):
    np.save(tmp_path / "high.npy", np.full((64, 27), 1e30, np.float32))
    assert _predict(tmp_path, tmp_path / "high.npy", extra=["--force"]) == 0
    assert json.loads((tmp_path / "p" / "high.json").read_text())["height_m"] > 0


def test_pressure_file_messages_name_what_was_given(tmp_path, capsys):
    np.save(tmp_path / "small.npy", np.ones((10, 10)))
    assert _predict(tmp_path, tmp_path / "small.npy") == 2
    one_line_error(capsys, "small.npy", "got shape (10, 10)")
    (tmp_path / "folder").mkdir()
    assert _predict(tmp_path, tmp_path / "folder") == 2
    one_line_error(capsys, "folder", "is a folder")
    good = good_image(tmp_path / "good.npy")
    (tmp_path / "p").write_text("a file")
    assert _predict(tmp_path, good) == 2
    one_line_error(capsys, "--out", "is a file")


# --- command-line arguments ---------------------------------------------------------------


@pytest.mark.parametrize(
    "argv,message",
    [
        (["generate", "--out", "x", "--partition", "sitting"], "unknown partition 'sitting'"),
        (["generate", "--out", "x", "--n", "0"], "n must be >= 1"),
        (["sample", "--out", "x", "--n", "0"], "n must be >= 1"),
    ],
)
def test_config_check_failures_are_one_line_without_tyro_internals(argv, message, capsys):
    assert main(argv) == 2
    line = one_line_error(capsys, message)
    assert "tyro" not in line and "dummy" not in line
