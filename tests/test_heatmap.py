"""arch=heatmap: integral regression against naive loops, the analytic IK Jacobian against
autograd, gradcheck of an IK step, IK convergence, an overfit run, save/load, bad inputs."""

import dataclasses
import json

import pytest
import torch

from pressurepose.body.joints import NUM_JOINTS
from pressurepose.body.kinematics import pose_in_mat
from pressurepose.body.limits import ALPHA, JointLimits
from pressurepose.body.params import BodyParams
from pressurepose.body.rotations import axis_angle_to_matrix
from pressurepose.mat import MatSpec
from pressurepose.net import NetConfig, NetInputs, PressureNet
from pressurepose.net.heatmap import (
    HEIGHT_BIAS_M,
    HEIGHT_SCALE_M,
    OFFSET_SCALE_M,
    HeatmapNet,
    cell_centres,
    integral_joints,
    localisation_loss,
    lowpass,
    soft_argmax,
)
from pressurepose.net.ik import (
    IKConfig,
    IKState,
    fit_to_joints,
    free_pose,
    ik_step,
    joint_jacobian,
    left_jacobian,
)

f64 = torch.float64


def _naive_soft_argmax(logits, centres):
    B, J, H, W = logits.shape
    mean = torch.zeros(B, J, 2, dtype=logits.dtype)
    var = torch.zeros(B, J, dtype=logits.dtype)
    for b in range(B):
        for j in range(J):
            z = sum(torch.exp(logits[b, j, r, c]) for r in range(H) for c in range(W))
            m = sum(torch.exp(logits[b, j, r, c]) / z * centres[r, c] for r in range(H) for c in range(W))
            v = sum(
                torch.exp(logits[b, j, r, c]) / z * ((centres[r, c] - m) ** 2).sum() for r in range(H) for c in range(W)
            )
            mean[b, j], var[b, j] = m, v
    return mean, var


def test_soft_argmax_against_a_naive_loop_values_and_gradients():
    g = torch.Generator().manual_seed(0)
    logits = (3 * torch.randn(2, 3, 5, 4, generator=g, dtype=f64)).requires_grad_()
    centres = cell_centres(MatSpec(), 5, 4)
    mean, var = soft_argmax(logits, centres)
    ref_mean, ref_var = _naive_soft_argmax(logits, centres)
    torch.testing.assert_close(mean, ref_mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(var, ref_var, rtol=1e-10, atol=1e-12)
    w = torch.randn(2, 3, 2, generator=g, dtype=f64)
    (grad,) = torch.autograd.grad((mean * w).sum() + var.sum(), logits)
    (ref,) = torch.autograd.grad((ref_mean * w).sum() + ref_var.sum(), logits)
    torch.testing.assert_close(grad, ref, rtol=1e-10, atol=1e-12)
    # A one-hot heatmap lands on its cell, with no spread.
    sharp = torch.full((1, 1, 5, 4), -1e3, dtype=f64)
    sharp[0, 0, 3, 1] = 0.0
    m, v = soft_argmax(sharp, centres)
    torch.testing.assert_close(m[0, 0], centres[3, 1])
    assert float(v) < 1e-12


def test_integral_joints_against_a_naive_loop():
    g = torch.Generator().manual_seed(1)
    maps = torch.randn(2, 3, 4, 6, 5, generator=g, dtype=f64)
    centres = cell_centres(MatSpec(), 6, 5)
    loc = integral_joints(maps, centres)
    for b in range(2):
        for j in range(3):
            p = torch.softmax(maps[b, j, 0].flatten(), 0).reshape(6, 5)
            xy = sum(
                p[r, c] * (centres[r, c] + OFFSET_SCALE_M * maps[b, j, 1:3, r, c]) for r in range(6) for c in range(5)
            )
            z = sum(p[r, c] * HEIGHT_SCALE_M * maps[b, j, 3, r, c] for r in range(6) for c in range(5)) + HEIGHT_BIAS_M
            torch.testing.assert_close(loc.joints[b, j], torch.cat([xy, z.reshape(1)]), rtol=1e-12, atol=1e-12)


def test_cell_centres_cover_the_sensing_area():
    mat = MatSpec()
    c = cell_centres(mat, 32, 14)
    torch.testing.assert_close(c[0, 0], torch.tensor([mat.sensing_length_m / 64, mat.sensing_width_m / 28], dtype=f64))
    torch.testing.assert_close(c[:, :, 0].mean(), torch.tensor(mat.centre_m[0], dtype=f64))
    torch.testing.assert_close(c[:, :, 1].mean(), torch.tensor(mat.centre_m[1], dtype=f64))


def _random_body(B, seed, scale=0.4):
    g = torch.Generator().manual_seed(seed)
    rest = 0.3 * torch.randn(B, NUM_JOINTS, 3, generator=g, dtype=f64)
    rest[:, 0] = 0
    params = BodyParams(
        shape=torch.zeros(B, 6, dtype=f64),
        root_rotation=torch.randn(B, 3, generator=g, dtype=f64),
        root_translation=torch.randn(B, 3, generator=g, dtype=f64),
        pose=scale * torch.randn(B, 23, 3, generator=g, dtype=f64),
    )
    return rest, params


def test_left_jacobian_matches_the_exponential_map():
    g = torch.Generator().manual_seed(2)
    for phi in (torch.randn(3, generator=g, dtype=f64), torch.full((3,), 1e-6, dtype=f64), torch.zeros(3, dtype=f64)):
        d = 1e-6 * torch.randn(3, generator=g, dtype=f64)
        lhs = axis_angle_to_matrix(phi + d)
        rhs = axis_angle_to_matrix(left_jacobian(phi) @ d) @ axis_angle_to_matrix(phi)
        torch.testing.assert_close(lhs, rhs, rtol=0, atol=1e-11)


def test_joint_jacobian_equals_autograd():
    rest, p = _random_body(2, seed=3)
    rot, pos = pose_in_mat(rest, p)
    J = joint_jacobian(rot, pos, p)

    def positions(x):
        q = p.replace(root_translation=x[:, :3], root_rotation=x[:, 3:6], pose=x[:, 6:].reshape(2, 23, 3))
        return pose_in_mat(rest, q)[1].reshape(2, -1)

    x = torch.cat([p.root_translation, p.root_rotation, p.pose.reshape(2, -1)], 1)
    ref = torch.autograd.functional.jacobian(lambda x: positions(x).sum(0), x).permute(1, 0, 2)
    torch.testing.assert_close(J, ref, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("limited", [False, True])
def test_ik_step_gradcheck_float64(limited):
    """An IK step is differentiable in the pose, root, targets, weights, prior and rest joints,
    free and under the joint limits' squash."""
    limits = JointLimits.default(f64) if limited else None
    rest, p = _random_body(2, seed=4, scale=0.3)
    _, target_params = _random_body(2, seed=5, scale=0.3)
    target = pose_in_mat(rest, target_params)[1].detach()
    weights = torch.rand(2, NUM_JOINTS, dtype=f64, generator=torch.Generator().manual_seed(6)) + 0.5
    cfg = IKConfig(joint_sigma_m=0.1, prior_sigma_rad=1.0, damping=0.5)

    def step(u, r, t, q, w, prior, rest):
        out = ik_step(rest, p.shape, IKState(t, r, u), q, w, prior, cfg, limits)
        return out.free_pose, out.root_rotation, out.root_translation

    inputs = tuple(
        v.clone().requires_grad_()
        for v in (p.pose, p.root_rotation, p.root_translation, target, weights, 0.5 * p.pose.detach(), rest)
    )
    assert torch.autograd.gradcheck(step, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_ik_converges_to_reachable_targets_within_limits(anny64):
    """Targets made by the body model itself from a pose inside the limits: a few steps from a
    perturbed start bring the joints within millimetres (weak prior) and stay inside the limits."""
    g = torch.Generator().manual_seed(7)
    limits = JointLimits.default(f64)
    B = 3
    u = torch.rand(B, 23, 3, generator=g, dtype=f64)
    true_pose = limits.lower + (0.2 + 0.6 * u) * (limits.upper - limits.lower)
    shape = torch.full((B, 6), 0.5, dtype=f64)
    truth = BodyParams(
        shape=shape,
        root_rotation=0.2 * torch.randn(B, 3, generator=g, dtype=f64),
        root_translation=torch.tensor([[0.9, 0.4, 0.1]], dtype=f64).expand(B, 3),
        pose=true_pose,
    )
    target = anny64.joints(truth)
    start = truth.replace(
        pose=limits.lower + (0.2 + 0.6 * torch.rand(B, 23, 3, generator=g, dtype=f64)) * (limits.upper - limits.lower),
        root_translation=truth.root_translation + 0.05,
        root_rotation=truth.root_rotation + 0.1,
    )
    err = lambda p: float((anny64.joints(p) - target).norm(dim=-1).mean())  # noqa: E731
    cfg = IKConfig(steps=10, prior_sigma_rad=10.0, damping=1.0)
    fitted = fit_to_joints(anny64, start, target, config=cfg)
    three = fit_to_joints(anny64, start, target, config=dataclasses.replace(cfg, steps=3))
    assert err(fitted) < 0.003 < err(three) < 0.5 * err(start), (err(start), err(three), err(fitted))
    inflated = JointLimits(
        lower=limits.lower - 0.1 * (limits.upper - limits.lower),
        upper=limits.upper + 0.1 * (limits.upper - limits.lower),
    )
    assert bool(inflated.contains(fitted.pose).all())
    # Zero steps change nothing; a free round trip through the squash is exact.
    same = fit_to_joints(anny64, start, target, config=IKConfig(steps=0))
    assert torch.equal(same.pose, start.pose)
    torch.testing.assert_close(limits.squash(free_pose(start.pose, limits)), start.pose)


def _blob_images(joints, mat):
    """Pressure images with a bump under every joint: something a network can localise."""
    rc = mat.to_taxel(joints[..., :2])  # (B, 24, 2)
    r = torch.arange(64.0)[:, None] + 0.5
    c = torch.arange(27.0)[None] + 0.5
    d2 = (r - rc[..., 0, None, None]) ** 2 + (c - rc[..., 1, None, None]) ** 2  # (B, 24, 64, 27)
    return 60 * torch.exp(-d2 / 2).amax(1)


def test_heatmap_net_overfits_a_handful_of_samples():
    """The localisation part learns 4 images by heart: mean joint error < 2 cm from ~20 cm."""
    mat = MatSpec()
    g = torch.Generator().manual_seed(8)
    joints = torch.stack(
        [
            0.2 + 1.4 * torch.rand(4, 24, generator=g),
            0.1 + 0.55 * torch.rand(4, 24, generator=g),
            0.05 + 0.1 * torch.rand(4, 24, generator=g),
        ],
        -1,
    )
    from pressurepose.net.preprocess import pressure_channels

    x = pressure_channels(_blob_images(joints, mat))
    torch.manual_seed(0)
    model = HeatmapNet(3, 84, mat, dropout=0.0)
    opt = torch.optim.Adam(model.parameters(), 3e-3)
    err = lambda loc: float((loc.joints.detach() - joints).norm(dim=-1).mean())  # noqa: E731
    model.train()
    first = err(model(x)[1])
    for _ in range(250):
        loss, _ = localisation_loss(model(x)[1], joints, mat)
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    with torch.no_grad():
        last = err(model(x)[1])
    assert first > 0.15 and last < 0.02, (first, last)


def test_heatmap_arch_end_to_end_save_and_load(anny32, tmp_path):
    from pressurepose.train.checkpoint import load_network, save_model

    torch.manual_seed(0)
    net = PressureNet(NetConfig(arch="heatmap", gender_input=False, ik_steps=2), body=anny32).eval()
    p = torch.rand(2, 64, 27) * 40
    with torch.no_grad():
        est = net(NetInputs(p), mesh=True, maps=False)[-1]
    assert est.joints.shape == (2, 24, 3) and est.localisation.joints.shape == (2, 24, 3)
    assert est.vertices.shape == (2, anny32.num_vertices, 3)
    limits = JointLimits.default()
    margin = 0.1 * (limits.upper - limits.lower) + 1e-6  # the head's squash inflates the limits by 20%
    assert bool(JointLimits(limits.lower - margin, limits.upper + margin).contains(est.params.pose).all())
    record = {"train": {}, "net": dict(net.config.__dict__)}
    save_model(tmp_path, net, record)
    loaded, rec = load_network(tmp_path, body=anny32)
    assert rec == json.loads(json.dumps(record)) and loaded.config.arch == "heatmap"
    with torch.inference_mode():  # the IK needs no autograd
        again = loaded(NetInputs(p), mesh=False)[-1]
    torch.testing.assert_close(again.joints, est.joints)
    # In training mode the IK is skipped: the head's body, with the localisation for the loss.
    net.train()
    est = net(NetInputs(p), mesh=False)[-1]
    assert est.localisation is not None and est.joints.requires_grad


def test_heatmap_bad_inputs(anny32, tmp_path):
    from pressurepose.errors import UserError
    from pressurepose.train.checkpoint import net_config_from_record

    with pytest.raises(ValueError, match=r"logits \(B, J, H, W\) and centres"):
        soft_argmax(torch.zeros(1, 2, 3, 4), torch.zeros(4, 3, 2))
    with pytest.raises(ValueError, match="maps must have shape"):
        integral_joints(torch.zeros(1, 2, 3, 4, 5), torch.zeros(4, 5, 2))
    rest, p = _random_body(2, seed=9)
    state = IKState(p.root_translation, p.root_rotation, p.pose)
    with pytest.raises(ValueError, match=r"target must have shape \(2, 24, 3\)"):
        ik_step(rest, p.shape, state, torch.zeros(2, 23, 3, dtype=f64), torch.ones(2, 24, dtype=f64), p.pose)
    with pytest.raises(ValueError, match="weights must have shape"):
        ik_step(rest, p.shape, state, torch.zeros(2, 24, 3, dtype=f64), torch.ones(2, 23, dtype=f64), p.pose)
    with pytest.raises(ValueError, match="target must have shape"):
        fit_to_joints(anny32, p.to(torch.float32), torch.zeros(3, 24, 3))
    with pytest.raises(ValueError, match="one module"):
        NetConfig(arch="heatmap", modules=2)
    with pytest.raises(ValueError, match="ik_steps"):
        NetConfig(arch="heatmap", ik_steps=-1)
    with pytest.raises(ValueError, match="IKConfig.damping must be > 0"):
        IKConfig(damping=0.0)
    with pytest.raises(UserError, match="config.net.arch"):
        net_config_from_record({"net": {"arch": "heatmaps"}}, tmp_path / "model.safetensors")
    with pytest.raises(UserError, match="config.net.ik_steps"):
        net_config_from_record({"net": {"arch": "heatmap", "ik_steps": "3"}}, tmp_path / "model.safetensors")
    with pytest.raises(UserError, match="ik_steps"):
        net_config_from_record({"net": {"arch": "heatmap", "ik_steps": 500}}, tmp_path / "model.safetensors")


def test_train_heatmap_arch_smoke(anny64, tmp_path):
    """`train --arch heatmap` runs, logs the localisation losses, validates (with the IK) and
    writes a network that `load_network` rebuilds from the run folder alone."""
    from pressurepose.train.checkpoint import load_network
    from pressurepose.train.config import TrainConfig
    from pressurepose.train.data import TensorDictDataset, synthetic_arrays
    from pressurepose.train.loop import train

    arrays = synthetic_arrays(24, seed=5, body=anny64)
    dataset = TensorDictDataset({k: torch.as_tensor(v) for k, v in arrays.items()})
    cfg = TrainConfig.smoke(
        arch="heatmap",
        out=tmp_path / "run",
        batch_size=8,
        val_fraction=0.25,
        progress=False,
        gender_input=False,
        shift_rows=4,
        mirror=0.5,
        pillow=0.5,
    )
    run = train(cfg, dataset)
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == 2 and all({"localised", "heatmap", "joints", "val_mpjpe_mm"} <= set(r) for r in rows)
    net, _ = load_network(run)
    assert net.config.arch == "heatmap" and net.config.ik_steps == 3


def test_train_cli_refuses_heatmap_mod2(tmp_path, capsys):
    from pressurepose.cli import main

    args = [
        "train",
        "--data",
        str(tmp_path),
        "--out",
        str(tmp_path / "run"),
        "--arch",
        "heatmap",
        "--module",
        "2",
        "--mod1",
        str(tmp_path),
    ]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "arch heatmap is one module" in err and len(err.strip().splitlines()) == 1


def test_more_ik_steps_bring_the_body_closer_to_the_localised_joints(anny32):
    """The IK is the heatmap arch's test-time refinement (`predict --ik-steps N`): more steps
    fit the body's joints closer to where the heatmaps put them."""
    torch.manual_seed(0)
    net = PressureNet(NetConfig(arch="heatmap", gender_input=False, ik_steps=0), body=anny32).eval()
    p = torch.rand(3, 64, 27) * 40
    gaps = []
    for steps in (0, 2, 8):
        net.config = dataclasses.replace(net.config, ik_steps=steps)
        with torch.inference_mode():
            est = net(NetInputs(p), mesh=False)[-1]
        w = IKConfig().weights(est.localisation.spread_m2)
        gaps.append(float((w * (est.joints - est.localisation.joints).square().sum(-1)).sum()))
    assert gaps[0] > gaps[1] > gaps[2]


def test_heatmap_net_eval_in_chunks_equals_one_pass():
    """Eval batches larger than EVAL_CHUNK run in pieces (speed): the same numbers as one pass."""
    torch.manual_seed(0)
    net = HeatmapNet(3, 84).eval()
    x = torch.rand(5, 3, 64, 27) * 50
    with torch.no_grad():
        raw, loc = net(x)
        net.EVAL_CHUNK = 2
        raw2, loc2 = net(x)
    torch.testing.assert_close(raw2, raw)
    for name in ("joints", "grid_joints", "spread_m2", "log_prob"):
        torch.testing.assert_close(getattr(loc2, name), getattr(loc, name))


@pytest.mark.parametrize("antialias", [False, True])
def test_heatmap_net_fused_inference_matches_the_modules(antialias):
    """Without autograd on a CPU the encoder-decoder runs with batch norm folded into fused
    convolutions: the same outputs as the modules to float32 round-off (the anti-aliased
    network's low-pass included), and a change of the weights (training between evaluations)
    is picked up."""
    from pressurepose.net.heatmap_fused import fusable, fused_trunk

    torch.manual_seed(0)
    net = HeatmapNet(3, 84, antialias=antialias).eval()
    for bn in [m for m in net.modules() if isinstance(m, torch.nn.BatchNorm2d)]:
        bn.running_mean.uniform_(-0.5, 0.5)
        bn.running_var.uniform_(0.5, 2.0)
        bn.weight.data.uniform_(0.5, 1.5)
        bn.bias.data.uniform_(-0.5, 0.5)
    x = torch.rand(3, 3, 64, 27) * 50
    for _ in range(2):
        with torch.no_grad():
            assert fusable(net, x)
            raw, loc = net(x)
        with torch.enable_grad():  # autograd: the modules
            assert not fusable(net, x)
            raw_ref, loc_ref = net(x)
        torch.testing.assert_close(raw, raw_ref.detach(), atol=1e-5, rtol=1e-5)
        for name in ("joints", "grid_joints", "spread_m2", "logits"):
            torch.testing.assert_close(getattr(loc, name), getattr(loc_ref, name).detach(), atol=1e-5, rtol=1e-5)
        with torch.no_grad():  # the trunk itself, to round-off relative to its (small, untrained) scale
            for got, ref in zip(fused_trunk(net, x), net._trunk(x)):
                torch.testing.assert_close(got, ref, atol=1e-5 * float(ref.abs().max()), rtol=1e-4)
            net.dec1[0].weight.mul_(1.5)  # the next round must see it


def test_heatmap_net_falls_back_to_the_modules_when_the_fused_operator_fails(monkeypatch):
    """The fused path calls a private oneDNN operator: if this torch's differs (or lacks it),
    the modules run instead - the same outputs - and keep running."""
    import pressurepose.net.heatmap_fused as hf

    def broken(*args, **kwargs):
        raise RuntimeError("unknown signature")

    torch.manual_seed(0)
    net = HeatmapNet(3, 84).eval()
    x = torch.rand(2, 3, 64, 27) * 50
    with torch.no_grad():
        raw_ref, loc_ref = net(x)
        monkeypatch.setattr(hf, "_FAILED", [])
        monkeypatch.setattr(hf, "_run", broken)
        raw, loc = net(x)
        assert hf._FAILED and not hf.fusable(net, x)
        raw2, _ = net(x)
    torch.testing.assert_close(raw, raw_ref, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(raw2, raw, atol=0, rtol=0)
    torch.testing.assert_close(loc.joints, loc_ref.joints, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("batch", [1, 5])
def test_fused_fit_matches_the_reference_steps(batch):
    """Without autograd the IK runs fused (`ik_inference.fit`): the same steps as iterating the
    differentiable `ik_step`, to float64 round-off, from a start at the limits' edge too."""
    from pressurepose.net import ik_inference

    limits = JointLimits.default(f64)
    rest, p = _random_body(batch, seed=8, scale=0.3)
    p = p.replace(pose=limits.squash(p.pose))
    inflated_upper = (limits.lower + limits.upper) / 2 + ALPHA * (limits.upper - limits.lower) / 2
    p.pose[0, 4] = inflated_upper[4]  # on the inflated limit: free_pose takes it from just inside
    _, target_params = _random_body(batch, seed=9, scale=0.3)
    target = pose_in_mat(rest, target_params)[1]
    weights = torch.rand(batch, NUM_JOINTS, dtype=f64, generator=torch.Generator().manual_seed(10)) + 0.1
    cfg = IKConfig(steps=4, joint_sigma_m=0.05, prior_sigma_rad=1.5, damping=0.7)
    state = IKState(p.root_translation, p.root_rotation, free_pose(p.pose, limits))
    prior = state.free_pose
    for _ in range(cfg.steps):
        state = ik_step(rest, p.shape, state, target, weights, prior, cfg, limits)
    ref = state.params(p.shape, limits)
    steps = (cfg.steps, cfg.joint_sigma_m, cfg.prior_sigma_rad, cfg.damping)
    fused = ik_inference.fit(rest, p, free_pose(p.pose, limits), target, weights, *steps, limits)
    assert float((ref.pose - p.pose).abs().max()) > 0.05  # the steps moved the body
    for name in ("root_translation", "root_rotation", "pose"):
        torch.testing.assert_close(getattr(fused, name), getattr(ref, name), rtol=0, atol=1e-10)
    assert torch.equal(fused.shape, p.shape)


@pytest.mark.parametrize("dtype, atol", [(f64, 1e-13), (torch.float32, 2e-6)])
def test_rotations_and_left_jacobians_match_the_separate_formulas(dtype, atol):
    """R and J_l from shared terms equal `axis_angle_to_matrix` and `left_jacobian`, on both
    sides of the series' threshold (a = 0.05), at 0 and near pi."""
    from pressurepose.net.ik_inference import rotations_and_left_jacobians

    g = torch.Generator().manual_seed(11)
    axes = torch.nn.functional.normalize(torch.randn(8, 3, generator=g, dtype=f64), dim=-1)
    angles = torch.tensor([0.0, 1e-7, 1e-3, 0.0499, 0.0501, 0.7, 2.0, 3.1], dtype=f64)
    phi = (axes * angles[:, None]).to(dtype)[None]  # (1, 8, 3)
    R, J_l = rotations_and_left_jacobians(phi)
    torch.testing.assert_close(R, axis_angle_to_matrix(phi.double()).to(dtype), rtol=0, atol=atol)
    torch.testing.assert_close(J_l, left_jacobian(phi.double()).to(dtype), rtol=0, atol=atol)


def test_fit_to_joints_with_autograd_runs_the_differentiable_steps(anny64, monkeypatch):
    """With a tensor that wants gradients `fit_to_joints` runs `ik_step` (gradients reach the
    targets), and its answer equals the fused one's."""
    from pressurepose.net import ik_inference

    fused_fit = ik_inference.fit
    rest, p = _random_body(2, seed=12, scale=0.2)
    p = p.replace(shape=torch.full((2, 6), 0.5, dtype=f64), pose=JointLimits.default(f64).squash(p.pose))
    target = anny64.joints(p.replace(root_translation=p.root_translation + 0.03)).detach()
    calls = []
    monkeypatch.setattr(ik_inference, "fit", lambda *a, **k: calls.append(1) or fused_fit(*a, **k))
    fused = fit_to_joints(anny64, p, target)
    assert len(calls) == 1  # nothing wanted gradients: the fused steps ran
    wanting = target.clone().requires_grad_()
    ref = fit_to_joints(anny64, p, wanting)
    assert len(calls) == 1  # a target wanting gradients: the differentiable steps, not the fused ones
    ref.pose.sum().backward()
    assert wanting.grad is not None and float(wanting.grad.abs().sum()) > 0
    for name in ("root_translation", "root_rotation", "pose"):
        torch.testing.assert_close(getattr(fused, name), getattr(ref, name).detach(), rtol=0, atol=1e-10)


def test_fit_to_joints_refuses_badly_shaped_weights_and_poses(anny32):
    """Both paths get the same one-line ValueError for inputs of the wrong shape."""
    p = BodyParams.zeros(2, torch.full((2, 6), 0.5))
    target = torch.zeros(2, NUM_JOINTS, 3)
    for weights in (torch.ones(2, NUM_JOINTS, 1), torch.ones(1, NUM_JOINTS), torch.ones(NUM_JOINTS), torch.ones(2, 23)):
        for w in (weights, weights.clone().requires_grad_()):
            with pytest.raises(ValueError, match=r"weights must have shape \(2, 24\)"):
                fit_to_joints(anny32, p, target, w)
    with pytest.raises(ValueError, match=r"params.pose must have shape \(2, 23, 3\)"):
        fit_to_joints(anny32, p.replace(pose=torch.zeros(2, 24, 3)), target)


def test_lowpass_against_a_naive_sum_and_it_removes_the_grids_highest_frequency():
    """`lowpass` is the binomial 3 x 3 blur with zero padding (a naive sum over the nine
    neighbours), keeps the sum of an image whose load stays off the border, and wipes a pattern
    alternating from row to row (or column to column) away from the border: the frequency a
    stride-2 layer would fold onto the slowest one."""
    g = torch.Generator().manual_seed(3)
    x = torch.rand(2, 4, 9, 7, dtype=f64, generator=g)
    k = torch.tensor([1.0, 2.0, 1.0], dtype=f64) / 4
    padded = torch.nn.functional.pad(x, (1, 1, 1, 1))
    naive = sum(k[i] * k[j] * padded[..., i : i + 9, j : j + 7] for i in range(3) for j in range(3))
    torch.testing.assert_close(lowpass(x), naive, rtol=0, atol=1e-12)
    inner = torch.zeros(1, 1, 9, 7, dtype=f64)
    inner[..., 2:-2, 2:-2] = torch.rand(5, 3, dtype=f64, generator=g)
    torch.testing.assert_close(lowpass(inner).sum(), inner.sum(), rtol=1e-12, atol=0)
    rows = (-1.0) ** torch.arange(9, dtype=f64)[:, None] * torch.ones(9, 7, dtype=f64)
    cols = (-1.0) ** torch.arange(7, dtype=f64) * torch.ones(9, 7, dtype=f64)
    for pattern in (rows, cols):
        out = lowpass(x + pattern) - lowpass(x)
        assert float(out[..., 1:-1, 1:-1].abs().max()) < 1e-12


def test_antialias_low_passes_what_each_stride_2_block_reads():
    """With `antialias` each of the three stride-2 blocks (enc1, enc2, enc3) reads, in the
    network's own forward, the binomial low-pass of what the block before it wrote (of the
    scaled input for enc1), and without it the plain input; the network keeps that kernel; and a
    row-to-row alternating pattern added to a block's input leaves its output unchanged away
    from the border with the low-pass, where the plain block answers it."""
    torch.manual_seed(0)
    plain = HeatmapNet(3, 84).eval()
    smooth = HeatmapNet(3, 84, antialias=True).eval()
    smooth.load_state_dict(plain.state_dict())
    torch.testing.assert_close(smooth.lowpass_kernel, torch.tensor([[1.0, 2, 1], [2, 4, 2], [1, 2, 1]]) / 16)
    x = torch.rand(2, 3, 64, 27) * 50
    for net in (smooth, plain):
        seen = {}
        blocks = ("enc1", "enc2", "enc3")
        hooks = [
            getattr(net, b).register_forward_pre_hook(lambda m, a, b=b: seen.__setitem__(b + " in", a[0]))
            for b in blocks
        ]
        hooks += [
            getattr(net, b).register_forward_hook(lambda m, a, o, b=b: seen.__setitem__(b + " out", o)) for b in blocks
        ]
        with torch.no_grad():  # the modules' forward (the fused path is held to it elsewhere)
            net._trunk(x)
        for h in hooks:
            h.remove()
        wrote = {"enc1": x * net.INPUT_SCALE, "enc2": seen["enc1 out"], "enc3": seen["enc2 out"]}
        for b in blocks:
            expected = lowpass(wrote[b]) if net.antialias else wrote[b]
            torch.testing.assert_close(seen[b + " in"], expected, rtol=1e-5, atol=1e-6 * float(expected.abs().max()))
    e1 = torch.rand(2, 48, 32, 14)
    alternating = 0.5 * (-1.0) ** torch.arange(32)[:, None].float()
    with torch.no_grad():
        for net, changed in ((smooth, False), (plain, True)):
            a, b = (net.enc2(net.subsampled(v)) for v in (e1, e1 + alternating))
            interior = (a - b)[..., 2:-2, 2:-2].abs().max()
            assert (float(interior) > 1e-2) == changed, float(interior)


def test_antialias_is_a_heatmap_option_recorded_with_the_network(tmp_path):
    """`antialias` belongs to arch heatmap (one-line errors otherwise), is saved with the
    network and rebuilt by `load_network` (the same answers); a fine-tune (`--init`) keeps the
    other network's low-pass or switches it on when asked, and its weights carry over either way."""
    from pressurepose.errors import UserError
    from pressurepose.train.checkpoint import load_network, net_config_from_record, save_model
    from pressurepose.train.config import TrainConfig
    from pressurepose.train.loop import build_network

    with pytest.raises(UserError, match="anti-aliased subsampling is for arch 'heatmap'"):
        NetConfig(arch="fast", antialias=True)
    with pytest.raises(UserError, match="--antialias is for --arch heatmap"):
        TrainConfig.fast(antialias=True)
    with pytest.raises(UserError, match="config.net.antialias"):
        net_config_from_record({"net": {"arch": "heatmap", "antialias": "yes"}}, tmp_path / "model.safetensors")
    built = build_network(TrainConfig.fast(arch="heatmap", gender_input=False, antialias=True), torch.device("cpu"))
    assert built.config.antialias and built.mod1.antialias
    torch.manual_seed(0)
    net = PressureNet(NetConfig(arch="heatmap", gender_input=False, antialias=True, ik_steps=0)).eval()
    save_model(tmp_path / "aa", net, {"train": {}, "net": dict(net.config.__dict__)})
    loaded, record = load_network(tmp_path / "aa", body=net.body)
    assert record["net"]["antialias"] is True and loaded.config.antialias and loaded.mod1.antialias
    p = torch.rand(2, 64, 27) * 40
    with torch.no_grad():
        torch.testing.assert_close(loaded(NetInputs(p))[-1].joints, net(NetInputs(p))[-1].joints)
    save_model(tmp_path / "plain", net, {"train": {}, "net": dict(net.config.__dict__, antialias=False)})
    for init, given, expected in (("aa", False, True), ("plain", False, False), ("plain", True, True)):
        cfg = TrainConfig.fast(arch="heatmap", gender_input=False, antialias=given, init=tmp_path / init)
        other = build_network(cfg, torch.device("cpu")).eval()  # kept; switched on when given
        assert other.config.antialias == other.mod1.antialias == expected
        with torch.no_grad():
            logits = other(NetInputs(p))[-1].localisation.logits
        assert torch.allclose(logits, net(NetInputs(p))[-1].localisation.logits) == expected  # same weights
