"""The heatmap arch's flip test (`predict --flip-test`): the merge against a naive loop, the
mirror symmetry it gives the localisation, bad inputs."""

import pytest
import torch

from pressurepose.body.joints import J24_MIRROR, NUM_JOINTS
from pressurepose.commands.netopts import options_label, with_inference_options
from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.net import NetConfig, NetInputs, PressureNet
from pressurepose.net.heatmap import Localisation, cell_centres, flip_merged

W = MatSpec().sensing_width_m
f64 = torch.float64


def _mirror_back(joints):
    """Naive: the joints of a mirrored body, joint by joint, reflected and renamed."""
    out = torch.empty_like(joints)
    for j in range(NUM_JOINTS):
        m = J24_MIRROR[j]
        out[:, j, 0], out[:, j, 1], out[:, j, 2] = joints[:, m, 0], W - joints[:, m, 1], joints[:, m, 2]
    return out


def test_flip_merged_against_a_naive_loop():
    g = torch.Generator().manual_seed(0)
    B, H, Wc = 3, 32, 14
    loc = Localisation(
        joints=torch.rand(2 * B, NUM_JOINTS, 3, generator=g, dtype=torch.float64),
        grid_joints=torch.rand(2 * B, NUM_JOINTS, 2, generator=g, dtype=torch.float64),
        spread_m2=torch.rand(2 * B, NUM_JOINTS, generator=g, dtype=torch.float64),
        logits=torch.randn(2 * B, NUM_JOINTS, H, Wc, generator=g, dtype=torch.float64),
        centres=cell_centres(MatSpec(), H, Wc),
    )
    out = flip_merged(loc, W)
    back = _mirror_back(loc.joints[B:])
    torch.testing.assert_close(out.joints, (loc.joints[:B] + back) / 2)
    for b in range(B):
        for j in range(NUM_JOINTS):
            m = J24_MIRROR[j]
            grid = torch.stack([loc.grid_joints[B + b, m, 0], W - loc.grid_joints[B + b, m, 1]])
            torch.testing.assert_close(out.grid_joints[b, j], (loc.grid_joints[b, j] + grid) / 2)
            assert abs(float(out.spread_m2[b, j]) - float(loc.spread_m2[b, j] + loc.spread_m2[B + b, m]) / 2) < 1e-12
            for c in range(Wc):  # the heatmap's column c holds the mirror image's column Wc - 1 - c
                want = (loc.logits[b, j, :, c] + loc.logits[B + b, m, :, Wc - 1 - c]) / 2
                torch.testing.assert_close(out.logits[b, j, :, c], want)
    assert out.joints.shape == (B, NUM_JOINTS, 3) and out.centres is loc.centres
    # the geometry behind flipping the maps: column c's centre mirrors column Wc - 1 - c's
    torch.testing.assert_close(loc.centres[:, :, 1] + loc.centres[:, :, 1].flip(-1), torch.full((H, Wc), W, dtype=f64))


@pytest.mark.parametrize("flip", [True, False])
def test_flip_test_makes_the_localisation_mirror_symmetric(anny32, flip):
    """With the flip test the joints localised on a mirrored image are the mirrored joints of the
    image (exactly, up to float round-off); an untrained network without it is far from that."""
    torch.manual_seed(0)
    net = PressureNet(NetConfig(arch="heatmap", gender_input=False, ik_steps=1, flip_test=flip), body=anny32).eval()
    with torch.no_grad():  # sharper heatmaps than an untrained network's near-uniform ones
        for w in net.mod1.maps.parameters():
            w.mul_(30.0)
    p = torch.rand(2, 64, 27) * 40 * (torch.rand(2, 64, 27) > 0.5)
    with torch.inference_mode():
        a = net(NetInputs(p), mesh=False)[-1].localisation.joints
        b = net(NetInputs(p.flip(-1)), mesh=False)[-1].localisation.joints
    gap = float((_mirror_back(b) - a).abs().max())
    if flip:
        assert gap < 1e-5
    else:
        assert gap > 1e-3  # millimetres, against the flip test's float round-off


def test_flip_test_bad_inputs(anny32):
    with pytest.raises(ValueError, match="flip test is for arch 'heatmap'"):
        NetConfig(arch="fast", flip_test=True)
    net = PressureNet(NetConfig(arch="fast", gender_input=False), body=anny32)
    with pytest.raises(UserError, match="--flip-test applies to arch heatmap"):
        with_inference_options(net, flip_test=True)
    with pytest.raises(UserError, match="--ik-steps and --flip-test apply to arch heatmap"):
        with_inference_options(net, 4, True)
    assert with_inference_options(net) is net  # nothing asked: any arch
    heat = PressureNet(NetConfig(arch="heatmap", gender_input=False), body=anny32)
    with pytest.raises(UserError, match="ik_steps"):
        with_inference_options(heat, ik_steps=99)
    assert with_inference_options(heat, 5, True).config.flip_test and heat.config.ik_steps == 5
    assert options_label(None, False) == "" and options_label(6, True) == " (flip test, 6 IK steps)"


def test_predict_and_evaluate_real_with_the_flip_test(untrained_run, tmp_path):
    """`predict --flip-test` writes its outputs; `evaluate-real --flip-test` names the option in
    its report's title (a tiny untrained heatmap model, two frames)."""
    import json

    import numpy as np

    from pressurepose.cli import main

    run, _ = untrained_run(arch="heatmap", gender_input=False, ik_steps=1)
    image = tmp_path / "one.npy"
    np.save(image, (np.random.default_rng(0).random((64, 27)) * 30).astype(np.float32))
    out = tmp_path / "pred"
    args = ["predict", "--model", str(run), "--out", str(out), "--flip-test", "--no-figures", "--no-meshes"]
    assert main([*args, str(image)]) == 0
    assert len(json.loads((out / "one.json").read_text())["joints_m"]) == 24
    real = tmp_path / "real"
    assert main(["evaluate-real", "--model", str(run), "--groups", "B", "--flip-test", "--out", str(real)]) == 0
    lines = (real / "real.md").read_text().splitlines()
    # Group B's 159 frames less subject 8's 14 repeats of subject 4's (B4-B10 on both mattresses).
    assert lines[0].endswith("(flip test) on PmatData experiment II (145 frames, groups B)")
    assert lines[2].startswith("14 frame(s) left out")


def test_predict_head_end_auto_gives_the_network_its_inputs(untrained_run, tmp_path, monkeypatch):
    """`--head-end auto` reads the head end with the subject's height, mass and gender for a
    network that takes them, as the estimate itself does."""
    import json

    import numpy as np

    from pressurepose.cli import main

    run, _ = untrained_run(arch="heatmap", gender_input=True, height_weight=True, ik_steps=1)
    image = tmp_path / "two.npy"
    np.save(image, (np.random.default_rng(0).random((2, 64, 27)) * 30).astype(np.float32))
    out = tmp_path / "pred"
    import pressurepose.eval.real as real_mod

    seen, read = [], real_mod.read_bodies

    def spy(net, images, height_m=None, mass_kg=None, batch=32, gender=None):
        seen.append((height_m, mass_kg, gender))
        return read(net, images, height_m, mass_kg, batch, gender)

    monkeypatch.setattr(real_mod, "read_bodies", spy)
    args = ["predict", "--model", str(run), "--out", str(out), "--no-figures", "--no-meshes", "--head-end", "auto"]
    assert main([*args, "--height-m", "1.7", "--mass-kg", "70", "--gender", "female", str(image)]) == 0
    assert len(seen) == 2  # the file read as given and turned, with the subject's inputs
    for h, m, g in seen:
        np.testing.assert_allclose([h.tolist(), m.tolist(), g.tolist()], [[1.7] * 2, [70.0] * 2, [1.0] * 2], rtol=1e-6)
    record = json.loads((out / "two_0000.json").read_text())
    assert record["head_end"] in ("first row", "last row") and set(record["head_end_trunk_spread_m"]) == {
        "first row",
        "last row",
    }
