"""Bad inputs at every file boundary: one line naming the file and the field, exit 2, no
traceback (issue #24). Each case here failed before the fix it names; the property-based
versions (mutated files) are in test_fuzz.py."""

import json
import pickle
import shutil

import numpy as np
import pytest
import tyro

from pressurepose.cli import main
from pressurepose.errors import UserError
from test_data import GROUPS, make_fake_dataset


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
    for argv in (["info", str(bad), "--sheet", "0"],
                 ["train", "--data", str(bad), "--out", str(tmp_path / "run"), "--preset", "smoke"],
                 ["evaluate", "--data", str(bad), "--out", str(tmp_path / "ev")]):
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
    m["shards"][0]["count"] += 1
    m["total"] += 1
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
