"""The heatmap arch's shift test (`--shift-test`, net.shift_test): the moves and the merge against
naive loops, the network's read against reading each moved copy by itself, bad inputs, the CLI."""

import json

import numpy as np
import pytest
import torch

from pressurepose.body.joints import NUM_JOINTS
from pressurepose.commands.netopts import options_label, with_inference_options
from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.net import NetConfig, NetInputs, PressureNet
from pressurepose.net.heatmap import Localisation, cell_centres
from pressurepose.net.shift_test import SHIFT_TEST_ROWS, moved_rows, shift_merged, shift_stack

PITCH = MatSpec().pitch_row_m
f64 = torch.float64


def _moved_naive(image: torch.Tensor, k: int) -> torch.Tensor:
    """Row by row: row r of the moved image is row r - k of the given one, or 0."""
    out = torch.zeros_like(image)
    for r in range(image.shape[-2]):
        if 0 <= r - k < image.shape[-2]:
            out[..., r, :] = image[..., r - k, :]
    return out


@pytest.mark.parametrize("k", [-70, -4, -1, 0, 2, 5, 63, 64])
def test_moved_rows_against_a_naive_loop(k):
    images = torch.rand(3, 64, 27, generator=torch.Generator().manual_seed(k + 100))
    torch.testing.assert_close(moved_rows(images, k), _moved_naive(images, k), rtol=0, atol=0)


def test_shift_stack_holds_the_image_then_each_move():
    images = torch.rand(2, 64, 27, generator=torch.Generator().manual_seed(1))
    stack = shift_stack(images)
    assert stack.shape == ((1 + len(SHIFT_TEST_ROWS)) * 2, 64, 27)
    torch.testing.assert_close(stack[:2], images, rtol=0, atol=0)
    for i, k in enumerate(SHIFT_TEST_ROWS, start=1):
        torch.testing.assert_close(stack[2 * i : 2 * i + 2], _moved_naive(images, k), rtol=0, atol=0)


def test_shift_merged_against_a_naive_loop():
    g = torch.Generator().manual_seed(0)
    B, H, W = 2, 32, 14
    n = 1 + len(SHIFT_TEST_ROWS)
    loc = Localisation(
        joints=torch.rand(n * B, NUM_JOINTS, 3, generator=g, dtype=f64),
        grid_joints=torch.rand(n * B, NUM_JOINTS, 2, generator=g, dtype=f64),
        spread_m2=torch.rand(n * B, NUM_JOINTS, generator=g, dtype=f64),
        logits=torch.randn(n * B, NUM_JOINTS, H, W, generator=g, dtype=f64),
        centres=cell_centres(MatSpec(), H, W),
        posture_logits=torch.randn(n * B, 4, generator=g, dtype=f64),
        features=torch.randn(n * B, 5, generator=g, dtype=f64),
    )
    out = shift_merged(loc, PITCH)
    moves = [0, *SHIFT_TEST_ROWS]
    floor = float(loc.logits.min())
    for b in range(B):
        rows = [i * B + b for i in range(n)]
        for j in range(NUM_JOINTS):
            want = sum(loc.joints[r, j] - torch.tensor([k * PITCH, 0, 0], dtype=f64) for r, k in zip(rows, moves)) / n
            torch.testing.assert_close(out.joints[b, j], want)
            grid = sum(loc.grid_joints[r, j] - torch.tensor([k * PITCH, 0], dtype=f64) for r, k in zip(rows, moves)) / n
            torch.testing.assert_close(out.grid_joints[b, j], grid)
            assert float(out.spread_m2[b, j]) == pytest.approx(float(sum(loc.spread_m2[r, j] for r in rows)) / n)
            for cell in range(H):  # cell c of a copy moved k rows holds the given image's cell c - k / 2
                vals = [
                    loc.logits[r, j, cell + k // 2] if 0 <= cell + k // 2 < H else torch.full((W,), floor, dtype=f64)
                    for r, k in zip(rows, moves)
                ]
                torch.testing.assert_close(out.logits[b, j, cell], sum(vals) / n)
        torch.testing.assert_close(out.posture_logits[b], sum(loc.posture_logits[r] for r in rows) / n)
    torch.testing.assert_close(out.features, loc.features[:B], rtol=0, atol=0)
    assert out.centres is loc.centres
    # moves that do not cancel: each copy is moved back by its own move (not only on average)
    two = Localisation(
        loc.joints[: 3 * B], loc.grid_joints[: 3 * B], loc.spread_m2[: 3 * B], loc.logits[: 3 * B], loc.centres
    )
    got = shift_merged(two, PITCH, moves=(2, 4))
    step = torch.tensor([PITCH, 0, 0], dtype=f64)
    want = (two.joints[:B] + two.joints[B : 2 * B] - 2 * step + two.joints[2 * B :] - 4 * step) / 3
    torch.testing.assert_close(got.joints, want)
    assert got.posture_logits is None and got.features is None
    with pytest.raises(ValueError, match="must be even"):
        shift_merged(loc, PITCH, moves=(1, 2, 3, 4))
    with pytest.raises(ValueError, match="holds 5 x B reads"):
        shift_merged(
            Localisation(loc.joints[:7], loc.grid_joints[:7], loc.spread_m2[:7], loc.logits[:7], loc.centres), PITCH
        )


def test_the_shift_test_reads_each_moved_copy_and_averages(anny32):
    """The network's shift-test localisation is the mean of the plain network's reads of each
    moved image, their joints moved back; the parameter head then reads those mean joints."""
    torch.manual_seed(0)
    plain = PressureNet(NetConfig(arch="heatmap", gender_input=False, ik_steps=1), body=anny32).eval()
    with torch.no_grad():  # sharper heatmaps than an untrained network's near-uniform ones
        for w in plain.mod1.maps.parameters():
            w.mul_(30.0)
    shifted = PressureNet(NetConfig(arch="heatmap", gender_input=False, ik_steps=1, shift_test=True), body=anny32)
    shifted.load_state_dict(plain.state_dict())
    shifted.eval()
    p = torch.rand(2, 64, 27) * 40 * (torch.rand(2, 64, 27) > 0.5)
    with torch.inference_mode():
        got = shifted(NetInputs(p), mesh=False)[-1]
        reads = [plain(NetInputs(moved_rows(p, k)), mesh=False)[-1].localisation for k in (0, *SHIFT_TEST_ROWS)]
        want = sum(r.joints - torch.tensor([k * PITCH, 0.0, 0.0]) for r, k in zip(reads, (0, *SHIFT_TEST_ROWS))) / 5
        raw = plain.mod1.read_params(want, reads[0].features)
    torch.testing.assert_close(got.localisation.joints, want, rtol=0, atol=1e-5)
    torch.testing.assert_close(got.raw, raw, rtol=1e-4, atol=1e-5)
    gap = float((reads[1].joints + torch.tensor([4 * PITCH, 0.0, 0.0]) - reads[0].joints).abs().max())
    assert gap > 1e-3  # the copies do read differently: the mean is not one read


def test_the_shift_test_with_per_image_inputs_and_a_posture_readout(anny32):
    """Per-image inputs (gender, height, mass planes) follow their images into every moved copy,
    and a posture readout with the consistency swap reads the merged localisation: one estimate
    per image, each the read of its own inputs."""
    cfg = dict(arch="heatmap", gender_input=True, height_weight=True, ik_steps=1, posture_head=True)
    torch.manual_seed(1)
    plain = PressureNet(NetConfig(**cfg), body=anny32).eval()
    with torch.no_grad():  # the constant planes (x INPUT_SCALE) made to matter: a wrong person's values would show
        plain.mod1.enc1[0][0].weight[:, 3:].mul_(1000.0)
    shifted = PressureNet(NetConfig(**cfg, shift_test=True, posture_consistent=True), body=anny32)
    shifted.load_state_dict(plain.state_dict())
    shifted.eval()
    p = torch.rand(3, 64, 27) * 40 * (torch.rand(3, 64, 27) > 0.5)
    inputs = NetInputs(
        p,
        gender=torch.tensor([0.0, 1.0, 0.5]),
        height_m=torch.tensor([1.6, 1.7, 1.9]),
        mass_kg=torch.tensor([55.0, 70.0, 95.0]),
    )
    with torch.inference_mode():
        est = shifted(inputs, mesh=False)[-1]
        one = shifted(
            NetInputs(p[1:2], gender=inputs.gender[1:2], height_m=inputs.height_m[1:2], mass_kg=inputs.mass_kg[1:2]),
            mesh=False,
        )[-1]
    assert est.joints.shape == (3, NUM_JOINTS, 3) and est.localisation.posture_logits.shape == (3, 4)
    torch.testing.assert_close(est.localisation.joints[1:2], one.localisation.joints, rtol=0, atol=1e-5)
    torch.testing.assert_close(est.localisation.features[1:2], one.localisation.features, rtol=0, atol=1e-6)
    torch.testing.assert_close(est.joints[1:2], one.joints, rtol=0, atol=1e-4)


@pytest.mark.parametrize("chunk", [None, 4])
def test_the_shift_test_with_the_flip_test(anny32, monkeypatch, chunk):
    """Both tests: the mean over the moved copies of the flip test's reads, each moved back; the
    same when the encoder-decoder runs the stacked batch in chunks (HeatmapNet.EVAL_CHUNK)."""
    from pressurepose.net.heatmap import HeatmapNet

    if chunk is not None:
        monkeypatch.setattr(HeatmapNet, "EVAL_CHUNK", chunk)
    cfg = dict(arch="heatmap", gender_input=True, ik_steps=1, flip_test=True)
    torch.manual_seed(2)
    flip = PressureNet(NetConfig(**cfg), body=anny32).eval()
    with torch.no_grad():
        for w in flip.mod1.maps.parameters():
            w.mul_(30.0)
    both = PressureNet(NetConfig(**cfg, shift_test=True), body=anny32)
    both.load_state_dict(flip.state_dict())
    both.eval()
    p = torch.rand(2, 64, 27) * 40 * (torch.rand(2, 64, 27) > 0.5)
    gender = torch.tensor([0.0, 1.0])
    moves = (0, *SHIFT_TEST_ROWS)
    with torch.inference_mode():
        got = both(NetInputs(p, gender=gender), mesh=False)[-1].localisation
        reads = [flip(NetInputs(moved_rows(p, k), gender=gender), mesh=False)[-1].localisation for k in moves]
    want = sum(r.joints - torch.tensor([k * PITCH, 0.0, 0.0]) for r, k in zip(reads, moves)) / len(moves)
    torch.testing.assert_close(got.joints, want, rtol=0, atol=1e-5)
    torch.testing.assert_close(got.spread_m2, sum(r.spread_m2 for r in reads) / len(moves), rtol=1e-4, atol=1e-8)


def test_shift_test_bad_inputs_and_label(anny32):
    with pytest.raises(ValueError, match="shift test is for arch 'heatmap'"):
        NetConfig(arch="fast", shift_test=True)
    net = PressureNet(NetConfig(arch="fast", gender_input=False), body=anny32)
    with pytest.raises(UserError, match="--shift-test applies to arch heatmap"):
        with_inference_options(net, shift_test=True)
    heat = PressureNet(NetConfig(arch="heatmap", gender_input=False), body=anny32)
    assert with_inference_options(heat, shift_test=True).config.shift_test
    assert options_label(None, True, True) == " (flip test, shift test)"
    assert options_label(6, False, True) == " (shift test, 6 IK steps)"


def test_predict_and_evaluate_real_with_the_shift_test(untrained_run, tmp_path):
    """`predict --shift-test` writes its outputs; `evaluate-real --shift-test` names the option
    in its report's title (a tiny untrained heatmap model)."""
    from pressurepose.cli import main

    run, _ = untrained_run(arch="heatmap", gender_input=False, ik_steps=1)
    image = tmp_path / "three.npy"
    np.save(image, (np.random.default_rng(0).random((3, 64, 27)) * 30).astype(np.float32))
    out = tmp_path / "pred"
    args = ["predict", "--model", str(run), "--out", str(out), "--shift-test", "--no-figures", "--no-meshes"]
    assert main([*args, "--batch-size", "2", str(image)]) == 0
    record = json.loads((out / "three_0002.json").read_text())
    assert len(record["joints_m"]) == 24
    assert record["inference"] == {"ik_steps": 1, "flip_test": False, "shift_test": True}
    both = ["--shift-test", "--flip-test", "--head-end", "auto", "--no-figures", "--no-meshes"]
    assert main(["predict", "--model", str(run), "--out", str(tmp_path / "both"), *both, str(image)]) == 0
    record = json.loads((tmp_path / "both" / "three_0000.json").read_text())
    assert record["head_end"] in ("first row", "last row")
    assert record["inference"] == {"ik_steps": 1, "flip_test": True, "shift_test": True}
    real = tmp_path / "real"
    assert main(["evaluate-real", "--model", str(run), "--groups", "B", "--shift-test", "--out", str(real)]) == 0
    assert (
        (real / "real.md")
        .read_text()
        .splitlines()[0]
        .endswith("(shift test) on PmatData experiment II (145 frames, groups B)")
    )
