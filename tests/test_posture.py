"""The posture readout (net.posture): its labels from the joints against the root-rotation
reference of eval.real, the thresholds, mirror symmetry, the head in the heatmap network
(flip test, chunked evaluation) and its reports (evaluate-real, predict)."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from pressurepose.body.joints import J24_NAMES, mirror_joints
from pressurepose.body.params import BodyParams
from pressurepose.cli import main
from pressurepose.eval.real import posture_of, read_bodies, roll_deg
from pressurepose.net import NetConfig, NetInputs, PressureNet
from pressurepose.net.posture import MIRRORED, POSTURES, posture_index, roll_from_joints, swapped_sides, to_swap
from pressurepose.sampling.poses import root_axis_angles
from pressurepose.train.checkpoint import load_network, save_model

PMAT = str(Path(__file__).resolve().parent / "data" / "pmatdata")  # 20 frames of PmatData (its README)


def test_roll_from_joints_against_the_root_reference(anny32):
    """Bodies of the model rolled about the bed's long axis and turned on the mat: the roll read
    from their joints follows the root's (eval.real.roll_deg) and gives the same posture."""
    rolls = [-170, -120, -95, -60, -20, 0, 25, 70, 100, 150, 178]
    pairs = np.radians([(r, y) for r in rolls for y in (0, 30, -50)])
    roots = torch.from_numpy(root_axis_angles(pairs[:, 0], pairs[:, 1]))
    B = roots.shape[0]
    p = BodyParams.zeros(B, anny32.default_shape(1).reshape(-1))
    p = BodyParams(shape=p.shape, root_rotation=roots.to(p.shape), root_translation=p.root_translation, pose=p.pose)
    joints = anny32.joints(p).double()
    reference = roll_deg(roots)
    assert reference.tolist() == pytest.approx([r for r in rolls for _ in range(3)], abs=1e-6)
    got = roll_from_joints(joints)
    diff = (got - reference + 180) % 360 - 180
    assert diff.abs().max() < 4.0, diff
    assert [POSTURES[i] for i in posture_index(got).tolist()] == posture_of(reference)


def test_posture_index_thresholds_and_mirror():
    roll = torch.tensor([0.0, 45.0, -45.0, 46.0, -46.0, 134.9, -134.9, 135.0, -135.0, 180.0, -90.0, 90.0])
    names = [POSTURES[i] for i in posture_index(roll).tolist()]
    assert names == ["supine", "supine", "supine", "right", "left", "right", "left", "prone", "prone", "prone", "left", "right"]  # fmt: skip
    assert names == posture_of(roll)
    # The mirrored body rolls the other way: left and right swap (MIRRORED), the rest stay.
    g = torch.Generator().manual_seed(0)
    joints = torch.rand(64, 24, 3, generator=g, dtype=torch.float64)
    a = posture_index(roll_from_joints(joints))
    b = posture_index(roll_from_joints(mirror_joints(joints, 0.9)))
    assert torch.equal(b, torch.tensor(MIRRORED)[a])
    assert torch.allclose(roll_from_joints(mirror_joints(joints, 0.9)), -roll_from_joints(joints), atol=1e-9)


def _net(anny32, **kw):
    torch.manual_seed(0)
    net = PressureNet(NetConfig(arch="heatmap", gender_input=False, posture_head=True, **kw), body=anny32).eval()
    with torch.no_grad():
        net.mod1.posture.layers[-1].weight.normal_(0, 1.0)
    return net


def test_posture_head_in_the_network(anny32):
    net = _net(anny32)
    p = torch.rand(70, 64, 27) * 40  # more than EVAL_CHUNK: evaluated in pieces
    with torch.no_grad():
        whole = net(NetInputs(p), mesh=False)[0].localisation.posture_logits
        pieces = torch.cat(
            [net(NetInputs(p[i : i + 7]), mesh=False)[0].localisation.posture_logits for i in range(0, 70, 7)]
        )
        mirror = net(NetInputs(p.flip(-1)), mesh=False)[0].localisation.posture_logits
    assert whole.shape == (70, 4) and torch.allclose(whole, pieces, atol=1e-4)
    flip = PressureNet(dataclasses.replace(net.config, flip_test=True), body=anny32).eval()
    flip.load_trainable_state(net.trainable_state())
    with torch.no_grad():
        merged = flip(NetInputs(p[:8]), mesh=False)[0].localisation.posture_logits
    assert torch.allclose(merged, (whole[:8] + mirror[:8, list(MIRRORED)]) / 2, atol=1e-4)
    with pytest.raises(ValueError, match="posture head is for arch 'heatmap'"):
        NetConfig(arch="fast", posture_head=True)


def test_readout_in_evaluate_real_and_predict(anny32, tmp_path):
    net = _net(anny32)
    with torch.no_grad():  # peaked heatmaps: each joint's spread its own (flat ones all read ~0.57 m)
        net.mod1.maps.weight.mul_(300.0)
    save_model(tmp_path / "run", net, {"train": {}, "net": dict(net.config.__dict__)})
    loaded, _ = load_network(tmp_path / "run", body=anny32)
    assert loaded.config.posture_head
    out = tmp_path / "real"
    assert main(["evaluate-real", "--model", str(tmp_path / "run"), "--pmatdata", PMAT, "--groups", "CD", "--out", str(out)]) == 0  # fmt: skip
    record = json.loads((out / "real.json").read_text())
    for mattress, s in record["by_mattress"].items():
        frames = [f for f in record["per_frame"] if f["mattress"] == mattress]
        assert s["readout_accuracy"] == pytest.approx(
            sum(f["readout_posture"] == f["posture"] for f in frames) / len(frames)
        )
    assert "posture readout" in (out / "real.md").read_text()
    # the head and torso joints' heatmap spreads: per frame, and summarised per mattress from them
    for mattress, s in record["by_mattress"].items():
        frames = [f["trunk_spread_m"] for f in record["per_frame"] if f["mattress"] == mattress]
        assert s["trunk_spread"]["median_m"] == pytest.approx(float(torch.tensor(frames).median()), rel=1e-6)
        assert 0 <= s["trunk_spread"]["share_sure"] <= 1
    assert "Heatmap spread of the head and torso joints" in (out / "real.md").read_text()
    images = torch.rand(12, 64, 27) * 40
    readings = read_bodies(loaded, images, batch=5)  # in batches smaller than N
    with torch.no_grad():
        loc = loaded(NetInputs(images), mesh=False)[0].localisation
    assert readings.readout == [POSTURES[i] for i in loc.posture_logits.argmax(-1).tolist()]
    torch.testing.assert_close(readings.spread_m, loc.spread_m2.sqrt(), rtol=1e-5, atol=1e-7)
    assert float(readings.spread_m.std()) > 0.005  # the spreads differ from joint to joint and image to image
    image = torch.rand(64, 27, generator=torch.Generator().manual_seed(3)).numpy() * 40
    np.save(tmp_path / "a.npy", image)
    assert main(["predict", "--model", str(tmp_path / "run"), "--out", str(tmp_path / "pred"), str(tmp_path / "a.npy"), "--no-figures"]) == 0  # fmt: skip
    record = json.loads((tmp_path / "pred" / "a.json").read_text())
    header, row = (tmp_path / "pred" / "predictions.csv").read_text().splitlines()
    assert header == "image,posture,roll_deg,height_m,mass_kg,load_ends,trunk_spread_m,readout_posture"
    readout = record["posture_readout"]
    assert row.split(",")[-1] == max(readout, key=readout.get)
    trunk = [record["joint_spread_m"][n] for n in ("neck", "head", "pelvis", "spine1", "spine2", "spine3")]
    trunk += [record["joint_spread_m"][n] for n in ("left_collar", "right_collar")]
    assert float(row.split(",")[-2]) == pytest.approx(sorted(trunk)[3], abs=1e-4)  # torch's median: the lower middle
    assert list(readout) == list(POSTURES) and sum(readout.values()) == pytest.approx(1.0)
    # each joint's heatmap spread: the localisation's, as a standard deviation in metres
    with torch.no_grad():
        spread = loaded(NetInputs(torch.from_numpy(image)[None]), mesh=False)[0].localisation.spread_m2[0]
    assert list(record["joint_spread_m"]) == list(J24_NAMES)
    assert list(record["joint_spread_m"].values()) == pytest.approx(spread.double().sqrt().tolist(), rel=1e-5)


def _forced(net, posture):
    """The readout made to say `posture` whatever the image."""
    layer = net.mod1.posture.layers[-1]
    with torch.no_grad():
        layer.weight.zero_()
        layer.bias.copy_(torch.tensor([10.0 if p == posture else 0.0 for p in POSTURES]))
    return net


def test_posture_consistent_reads_the_body_again_with_sides_exchanged(anny32):
    """An untrained network's bodies lie supine. Readout 'prone' (the pair's other posture):
    the joints come back with left and right exchanged and the parameters read again from them;
    readout 'supine' or 'left' (another pair): nothing changes."""
    p = torch.rand(6, 64, 27) * 40
    base = _net(anny32, ik_steps=0)
    with torch.no_grad():
        plain = base(NetInputs(p), mesh=False)[0]
    assert posture_of(roll_deg(plain.params.root_rotation.double())) == ["supine"] * 6
    for posture, swapped in (("prone", True), ("supine", False), ("left", False)):
        net = _forced(_net(anny32, ik_steps=0), posture)
        net.config = dataclasses.replace(net.config, posture_consistent=True)
        with torch.no_grad():
            est = net(NetInputs(p), mesh=False)[0]
            again = net.mod1.read_params(swapped_sides(plain.localisation.joints), plain.localisation.features)
        loc = est.localisation
        if swapped:
            assert torch.allclose(loc.joints, swapped_sides(plain.localisation.joints))
            assert torch.allclose(loc.spread_m2, swapped_sides(plain.localisation.spread_m2))
            assert torch.allclose(est.raw, again, atol=1e-6)
            assert (est.raw - plain.raw).norm() > 1e-3 * plain.raw.norm()  # read again: another body
        else:
            assert torch.equal(loc.joints, plain.localisation.joints) and torch.equal(est.raw, plain.raw)
    with pytest.raises(ValueError, match="posture_consistent needs a network with a posture head"):
        NetConfig(arch="heatmap", posture_consistent=True)


def test_to_swap_pairs():
    roll = torch.tensor([0.0, 0.0, 0.0, 0.0, 180.0, -90.0, -90.0, 90.0])
    read = torch.tensor([0, 3, 1, 2, 0, 2, 3, 1])
    swap = to_swap(roll, torch.nn.functional.one_hot(read, 4).float())
    assert swap.tolist() == [False, True, False, False, True, True, False, True]


def test_prediction_figure_marks_each_joint_by_its_spread_band(tmp_path):
    """`viz.prediction`: every joint lands in exactly one trust band (edges to the band above),
    and the figure is written with and without spreads."""
    import matplotlib.pyplot as plt

    from pressurepose.mat import MatSpec
    from pressurepose.viz.prediction import TRUST_BANDS, _trust, plot_prediction

    spread = np.array([0.02] * 5 + [0.10] * 7 + [0.2499] * 3 + [0.25] * 4 + [0.6] * 5)
    fig, ax = plt.subplots()
    _trust(ax, np.arange(24.0), np.arange(24.0), spread)
    counts = [len(line.get_xdata()) for line in ax.lines]
    plt.close(fig)
    assert len(counts) == len(TRUST_BANDS) and counts == [5, 10, 9]
    joints = np.zeros((24, 3)) + [0.9, 0.4, 0.1]
    vertices = np.random.default_rng(0).normal([0.9, 0.4, 0.1], 0.1, (500, 3))
    for name, s in (("with", spread), ("without", None)):
        path = plot_prediction(tmp_path / f"{name}.png", np.zeros((64, 27)), vertices, joints, MatSpec(), name, s)
        assert path.stat().st_size > 10_000


def test_spread_summary_by_hand():
    from pressurepose.eval.real import spread_lines, spread_summary

    spread = torch.tensor([[0.05, 0.08, 0.30, 0.40], [0.12, 0.20, 0.02, 0.01], [0.09, 0.11, 0.15, 0.50]])
    # frame medians, the lower middle of four: 0.08, 0.02, 0.11 -> 0.08; 5 of 12 joints under 0.10
    s = spread_summary(spread)
    assert s == {"median_m": pytest.approx(0.08), "share_sure": pytest.approx(5 / 12)}
    assert spread_lines({}) == [] and spread_lines({"air": s})[1].endswith("air 8.0 cm, 42% under 10 cm")


def test_evaluate_reports_the_trunk_spread_of_a_heatmap_network(anny32, anny64, tmp_path):
    """`evaluate` with a heatmap network: each sample's median head-and-torso spread, their summary
    (the same `spread_summary` as evaluate-real) and its line in report.md."""
    from pressurepose.commands.evaluate import EvaluateConfig, run_evaluate
    from pressurepose.train.data import synthetic_arrays, write_npz

    net = _net(anny32)
    with torch.no_grad():
        net.mod1.maps.weight.mul_(300.0)  # peaked heatmaps
    save_model(tmp_path / "run", net, {"train": {}, "net": dict(net.config.__dict__)})
    write_npz(tmp_path / "test.npz", synthetic_arrays(4, seed=5, body=anny64))
    paths = run_evaluate(EvaluateConfig(model=tmp_path / "run", data=tmp_path / "test.npz", out=tmp_path / "r"))
    record = json.loads(paths["json"].read_text())
    per = record["per_sample"]["trunk_spread_m"]
    assert len(per) == record["count"] and all(0.0 < v < 1.0 for v in per)
    assert record["trunk_spread"]["median_m"] == pytest.approx(float(torch.tensor(per).median()), rel=1e-6)
    assert "Heatmap spread of the head and torso joints" in paths["markdown"].read_text()


def test_realism_reads_the_real_frames_and_their_twins_through_a_heatmap_network(anny32, tmp_path):
    """`realism --model`: the trunk's spread summary of each image set by the network, as
    `spread_summary` of `read_bodies` gives it; nothing for no images or no model; the report's table."""
    from pressurepose.body.joints import TRUNK_JOINTS
    from pressurepose.commands.realism import _readers
    from pressurepose.commands.realism_report import spread_markdown
    from pressurepose.eval.real import spread_summary

    net = _net(anny32)
    with torch.no_grad():
        net.mod1.maps.weight.mul_(300.0)
    save_model(tmp_path / "run", net, {"train": {}, "net": dict(net.config.__dict__)})
    reader, rolls = _readers(tmp_path / "run")
    images = torch.rand(5, 64, 27, generator=torch.Generator().manual_seed(4)) * 40
    s = reader(images.numpy())
    loaded, _ = load_network(tmp_path / "run", body=anny32)
    assert s == spread_summary(read_bodies(loaded, images).spread_m[:, list(TRUNK_JOINTS)])
    assert reader(np.zeros((0, 64, 27))) is None and _readers(None) == (None, None)
    # The roll read, as read_bodies reads it (the tilted rows' `turned`).
    np.testing.assert_allclose(rolls(images.numpy()), read_bodies(loaded, images).roll_deg.numpy(), atol=1e-9)
    rows = [
        {"posture": "supine", "mattress": "air", "trunk_spread": {"real": s, "simulated": None}},
        {"posture": "left", "mattress": "air"},
    ]
    md = spread_markdown(rows, "run")
    assert (
        len(md) == 6 and md[-1] == f"| supine | air | {s['median_m'] * 100:.1f} cm, {s['share_sure'] * 100:.0f}% | - |"
    )
    assert spread_markdown(rows[1:], "run") == []
