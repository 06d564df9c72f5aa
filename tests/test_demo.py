"""Embedded defaults: the packaged PmatData copy, the default-model lookup, `pressurepose demo`'s
report, and its bad inputs."""

import hashlib
import subprocess
import sys

import pytest

from pressurepose.data.pmatdata import load_index
from pressurepose.models import DEFAULT, default_model_dir, resolve_model
from pressurepose.samples import pmatdata_dir, resolve_pmatdata


def run(*args):
    return subprocess.run([sys.executable, "-m", "pressurepose.cli", *args], capture_output=True, text=True)


def test_packaged_pmatdata_matches_the_published_sums():
    root = pmatdata_dir()
    sums = [line.split() for line in (root / "SHA256SUMS.txt").read_text().splitlines() if line.strip()]
    listed = {name.lstrip("*") for _, name in sums}
    assert len(sums) >= 465
    for digest, name in sums:
        path = root / name.lstrip("*")
        if path.is_file():  # the sums cover experiment I too; the copy holds experiment II
            assert hashlib.sha256(path.read_bytes()).hexdigest() == digest, name
    frames = sorted(p.relative_to(root).as_posix() for p in (root / "experiment-ii").rglob("*.txt"))
    assert len(frames) == 465 and set(frames) <= listed
    records = load_index(root)
    assert len(records) == 465 and all(r.path.is_file() for r in records)
    assert "Open Data Commons Attribution" in (root / "README.md").read_text()


def test_names_resolve_to_packaged_files_unless_a_path_exists(tmp_path, monkeypatch):
    assert resolve_pmatdata("pmatdata") == pmatdata_dir()
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pmatdata").mkdir()
    assert resolve_pmatdata("pmatdata").resolve() == (tmp_path / "pmatdata").resolve()  # a real folder wins
    (tmp_path / DEFAULT).mkdir()
    assert resolve_model(DEFAULT).resolve() == (tmp_path / DEFAULT).resolve()
    assert resolve_model(tmp_path / "run") == tmp_path / "run"


def test_missing_default_model_is_a_clear_error(tmp_path, monkeypatch):
    import pressurepose.models as models

    monkeypatch.setattr(models, "_HERE", tmp_path)
    with pytest.raises(ValueError, match="no default model in this installation"):
        resolve_model(DEFAULT)


def test_demo_bad_model_exits_2_before_simulating(tmp_path):
    r = run("demo", "--out", str(tmp_path / "d"), "--model", str(tmp_path / "nowhere"))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "model.safetensors" in r.stderr and not (tmp_path / "d" / "data").exists()


def test_packaged_default_model_estimates_bodies(anny64):
    """The shipped weights are a trained network: on fresh simulated samples it beats
    predicting their mean joints, and its bodies are people-sized."""
    import torch

    from pressurepose.net import NetInputs
    from pressurepose.train.checkpoint import load_network
    from pressurepose.train.data import synthetic_arrays

    assert (default_model_dir() / "model.safetensors").is_file()
    net, record = load_network(DEFAULT)
    assert record["net"]["arch"] == "heatmap" and record["net"]["gender_input"] is False
    a = synthetic_arrays(12, seed=321, body=anny64)
    with torch.no_grad():
        est = net(NetInputs(pressure_mmhg=a["pressure_mmhg"]))[-1]
    true = a["joints"]
    mpjpe = (est.joints - true).norm(dim=-1).mean()
    mean_pose = (true.mean(0, keepdim=True) - true).norm(dim=-1).mean()
    assert torch.isfinite(est.joints).all()
    assert mpjpe < 0.8 * mean_pose, (float(mpjpe), float(mean_pose))
    height = net.body.measure(est.params.shape).height_m
    assert ((height > 1.3) & (height < 2.2)).all()


def test_demo_summary_names_the_tilted_and_raised_frames_when_read():
    """The demo's real section: the posture over groups B-D's frames, and group E's turned shares
    and group F's supine shares and heights when evaluate-real read them (a line each only then)."""
    from pressurepose.commands.demo import _markdown, _summary

    frame = {"posture": "left", "estimated_posture": "left", "height_m": 1.8, "estimated_height_m": 1.9}
    rows = [
        dict(frame, mass_kg=80.0, estimated_mass_kg=70.0),
        dict(frame, estimated_posture="prone", mass_kg=80.0, estimated_mass_kg=85.0),
    ]
    overall = {"vpe_m": {"mean": 0.03}, "mpjpe_m": {"mean": 0.08}}
    synthetic = {"count": 5, "overall": overall, "baselines_vpe_m": {"mean_body": {"mean": 0.11}}}
    real = {"per_frame": rows, "by_mattress": {"air": {"posture_accuracy": 0.5, "height_mae_m": 0.1}}}
    tilted = {"by_mattress": {"air": {"share_turned": 0.31}, "sponge": {"share_turned": 0.52}}}
    raised = {"by_mattress": {"air": {"posture_accuracy": 0.9375, "height_median_signed_m": 0.111}}}
    for with_tilts, with_raised in ((False, False), (True, False), (False, True), (True, True)):
        extra = {"tilted": tilted} if with_tilts else {}
        s = _summary(synthetic, {**real, **extra, **({"raised": raised} if with_raised else {})})
        assert s["real"]["posture_accuracy"] == 0.5
        assert s["real"]["tilted_turned"] == ({"air": 0.31, "sponge": 0.52} if with_tilts else {})
        text = _markdown({**s, "model": "m", "seconds": {"total_s": 1.0}, "samples": 6, "seed": 0})
        assert (
            "tilted on wedges or a pillow (group E), read turned 10-135 deg toward their side: air 31%, sponge 52%"
            in text
        ) == with_tilts
        line = "group F, outside the flat-bed scope), read supine: air 94% (height error +11.1 cm)"
        assert (line in text) == with_raised
