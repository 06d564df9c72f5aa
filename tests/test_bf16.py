"""Training's --bf16: the heatmap encoder-decoder under bfloat16 autocast, everything else float32."""

import json
import logging

import pytest
import torch

from pressurepose.cli import main
from pressurepose.commands.train import run_train as train
from pressurepose.errors import UserError
from pressurepose.net.heatmap import HeatmapNet
from pressurepose.train import loop, precision
from pressurepose.train.checkpoint import load_network
from pressurepose.train.config import TrainConfig
from pressurepose.train.data import TensorDictDataset, synthetic_arrays


def _images(B=16, channels=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(B, channels, 64, 27, generator=g) * 400 * (torch.rand(B, 1, 64, 27, generator=g) > 0.5)


def _trunk(net, x, dtype):
    net.trunk_dtype = dtype
    return net._trunk(x)


def test_bf16_trunk_follows_float32_within_bfloat16_precision():
    """Training mode: float32 outputs within bfloat16's precision of the float32 trunk's, and
    gradients (float32, on every weight) pointing the same way; the weights stay float32."""
    torch.manual_seed(0)
    net = HeatmapNet(4, 84, width=1).train()
    x = _images()
    outs, grads = {}, {}
    for name, dtype in (("fp32", None), ("bf16", torch.bfloat16)):
        net.zero_grad()
        e3, maps = _trunk(net, x, dtype)
        assert e3.dtype == maps.dtype == torch.float32
        (maps.square().mean() + e3.square().mean()).backward()
        outs[name] = (e3.detach(), maps.detach())
        grads[name] = {k: p.grad.clone() for k, p in net.named_parameters() if p.grad is not None}
    for a, b in zip(outs["fp32"], outs["bf16"]):
        rel = (a - b).norm() / a.norm()
        assert 1e-5 < rel < 0.03, rel  # bfloat16 did run (not bit-equal), and stayed close
    assert set(grads["fp32"]) == set(grads["bf16"]) and len(grads["fp32"]) > 10
    for k, g32 in grads["fp32"].items():
        g16 = grads["bf16"][k]
        assert g16.dtype == torch.float32 and torch.isfinite(g16).all(), k
        cos = torch.nn.functional.cosine_similarity(g32.flatten(), g16.flatten(), dim=0)
        assert cos > 0.98, (k, float(cos))
    assert all(p.dtype == torch.float32 for p in net.parameters())


def test_bf16_leaves_eval_mode_in_float32():
    """Validation and use read the float32 network: trunk_dtype changes nothing in eval mode."""
    torch.manual_seed(1)
    net = HeatmapNet(4, 84).eval()
    x = _images(4)
    with torch.enable_grad():  # the modules' path (no fused trunk)
        ref = _trunk(net, x, None)
        got = _trunk(net, x, torch.bfloat16)
    assert all(torch.equal(a, b) for a, b in zip(ref, got))


@pytest.fixture(scope="module")
def small(anny64):
    arrays = synthetic_arrays(20, seed=3, body=anny64)
    return TensorDictDataset({k: torch.as_tensor(v[:16]) for k, v in arrays.items()})


def test_bf16_training_learns_as_float32_and_saves_a_float32_network(small, tmp_path):
    """Same seed, same data: the bfloat16 run's loss falls as the float32 run's does; the run
    records bf16, its model is read in float32, and a resume may switch bf16 off."""
    common = dict(arch="heatmap", gender_input=False, batch_size=8, lr=3e-3, augment=False, dropout=0.0)
    common |= dict(val_fraction=0.0, progress=False, seed=2, save_every=100)
    for name, bf16 in (("fp32", False), ("bf16", True)):
        train(TrainConfig.smoke(out=tmp_path / name, epochs=25, bf16=bf16, **common), small)
    rows = {name: loop.read_metrics(tmp_path / name) for name in ("fp32", "bf16")}
    first32, last32 = rows["fp32"][0]["loss"], rows["fp32"][-1]["loss"]
    first16, last16 = rows["bf16"][0]["loss"], rows["bf16"][-1]["loss"]
    assert first16 == pytest.approx(first32, rel=0.05)
    assert last32 < 0.6 * first32 and last16 < 0.6 * first16, (first32, last32, first16, last16)
    assert last16 == pytest.approx(last32, rel=0.1)
    record = json.loads((tmp_path / "bf16" / "config.json").read_text())
    assert record["train"]["bf16"] is True and "bf16" not in record["net"]
    net, _ = load_network(tmp_path / "bf16")
    assert net.mod1.trunk_dtype is None
    train(TrainConfig.smoke(out=tmp_path / "bf16", epochs=26, bf16=False, **common), small)
    assert [r["epoch"] for r in loop.read_metrics(tmp_path / "bf16")][-1] == 26


def test_bf16_warns_on_a_cpu_without_bfloat16_units(small, tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(precision, "cpu_has_bf16", lambda: False)
    cfg = TrainConfig.smoke(
        out=tmp_path / "run", arch="heatmap", epochs=1, batch_size=8, bf16=True, val_fraction=0.0, progress=False
    )
    with caplog.at_level(logging.WARNING, logger="pressurepose.train.precision"):
        train(cfg, small)
    assert "no bfloat16 units" in caplog.text


def test_bf16_is_for_the_heatmap_arch(tmp_path, capsys):
    with pytest.raises(UserError, match="--bf16 is for --arch heatmap"):
        TrainConfig.smoke(arch="fast", bf16=True)
    args = ["train", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--preset", "smoke", "--bf16"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "--bf16 is for --arch heatmap" in err and "Traceback" not in err
