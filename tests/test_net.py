"""PressureNet: shapes, the output head's limits, PMR against the generator's label maps,
gradients (gradcheck of PMR and of the whole forward pass), preprocessing against naive loops,
Mod2's residual start and the analysis-by-synthesis loss."""

import math

import pytest
import torch

from pressurepose.body.limits import ALPHA, JointLimits
from pressurepose.body.rotations import axis_angle_to_matrix
from pressurepose.mat import MatSpec
from pressurepose.net import NetConfig, NetInputs, PressureNet
from pressurepose.net.head import ParamHead, matrix_to_rotation_6d, rotation_6d_to_matrix, union_shape_bounds
from pressurepose.net.pmr import reconstruct_maps
from pressurepose.net.preprocess import SUM_TOTAL, gaussian_blur, pressure_channels, sobel_magnitude
from pressurepose.sim.sensor import label_maps
from pressurepose.train.data import synthetic_arrays


@pytest.fixture(scope="module")
def samples(anny64):
    """Two labelled samples (one per gender) from the generator's pipeline (sim #2 rest)."""
    return synthetic_arrays(2, seed=3, body=anny64)


def _images(B, seed=0):
    g = torch.Generator().manual_seed(seed)
    p = torch.rand(B, 64, 27, generator=g) * 60
    return p * (torch.rand(B, 64, 27, generator=g) > 0.6)


@pytest.mark.parametrize("arch", ["fast", "paper"])
def test_shapes_both_modules(arch, anny32):
    net = PressureNet(NetConfig(arch=arch, modules=2), body=anny32).eval()
    with torch.no_grad():
        est1, est2 = net(NetInputs(_images(2), gender=torch.tensor([0.0, 1.0])))
    for est in (est1, est2):
        assert est.raw.shape == (2, net.head.size) == (2, 6 + 78)
        assert est.joints.shape == (2, 24, 3)
        assert est.vertices.shape == (2, anny32.num_vertices, 3)
        assert est.depth_mm.shape == est.contact.shape == (2, 64, 27)
        assert est.params.pose.shape == (2, 23, 3) and est.params.shape.shape == (2, 6)
    # The gender given replaces Anny's gender phenotype.
    assert est2.params.shape[:, 0].tolist() == [0.0, 1.0]
    # Mod2 starts as "no correction": its residual is zero until trained.
    assert torch.equal(est1.raw, est2.raw)
    if arch == "paper":  # the released size: ~8 M parameters (84 outputs, 4 input planes here)
        assert 7.9e6 < sum(p.numel() for p in net.mod1.parameters()) < 8.4e6


def test_width_scales_the_fast_cnn_and_is_saved(anny32, tmp_path):
    from pressurepose.net.cnn import make_cnn
    from pressurepose.train.checkpoint import load_network, save_model

    count = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
    assert count(make_cnn("fast", 3, 84, width=2)) > 3.5 * count(make_cnn("fast", 3, 84))
    for arch, width in (("paper", 2), ("fast", 0)):
        with pytest.raises(ValueError, match="width"):
            make_cnn(arch, 3, 84, width=width)
    net = PressureNet(NetConfig(width=2, gender_input=False), body=anny32).eval()
    save_model(tmp_path, net, {"train": {}, "net": dict(net.config.__dict__)})
    loaded, _ = load_network(tmp_path, body=anny32)
    assert loaded.config.width == 2
    p = _images(2)
    with torch.no_grad():
        assert torch.equal(net(NetInputs(p))[-1].raw, loaded(NetInputs(p))[-1].raw)


def test_channels_and_options(anny32):
    net = PressureNet(NetConfig(height_weight=True, gender_input=True), body=anny32)
    p = _images(3)
    x = net.channels(NetInputs(p, gender=torch.ones(3), height_m=torch.full((3,), 1.7), mass_kg=torch.full((3,), 70.0)))
    assert x.shape == (3, 6, 64, 27)
    assert torch.allclose(x[:, 1].sum((1, 2)), torch.full((3,), SUM_TOTAL))
    assert torch.equal(x[:, 0], (p > 0).float() * 100)
    assert torch.allclose(x[:, 3], torch.full_like(x[:, 3], 1.7)) and torch.allclose(
        x[:, 4], torch.full_like(x[:, 4], 0.7)
    )
    with pytest.raises(ValueError, match="height and mass"):
        net.channels(NetInputs(p))
    with pytest.raises(ValueError, match="shape"):
        net.channels(NetInputs(torch.zeros(3, 27, 64)))
    with pytest.raises(ValueError, match="NaN"):
        net.channels(NetInputs(torch.full((1, 64, 27), float("nan"))))


def test_squash_keeps_every_output_inside_its_bounds():
    head = ParamHead("anny", ("gender", "age", "muscle", "weight", "height", "proportions")).double()
    raw = torch.randn(256, head.size, dtype=torch.float64) * 50  # far outside any sensible range
    params = head(raw)
    limits = JointLimits.default(torch.float64)
    mid, width = (limits.lower + limits.upper) / 2, ALPHA * (limits.upper - limits.lower)
    assert ((params.pose - mid).abs() <= width / 2 + 1e-6).all()  # buffers held in float32
    assert ((params.pose - mid).abs() > width / 2 * 0.999).any()  # and the squash does reach them
    low, high = union_shape_bounds("anny", head_names := ("gender", "age", "muscle", "weight", "height", "proportions"))
    assert len(head_names) == 6
    assert ((params.shape >= low - 1e-6) & (params.shape <= high + 1e-6)).all()
    assert ((params.shape >= 0) & (params.shape <= 1)).all()  # Anny's valid range
    # raw = 0 is the reference: supine, pelvis over the mat centre, mid-range joint angles.
    zero = head(torch.zeros(1, head.size, dtype=torch.float64))
    assert torch.allclose(zero.root_rotation, torch.zeros(1, 3, dtype=torch.float64), atol=1e-12)
    cx, cy = MatSpec().centre_m
    assert torch.allclose(zero.root_translation[0, :2], torch.tensor([cx, cy], dtype=torch.float64))
    assert torch.allclose(zero.pose[0], mid)


def test_rotation_6d_round_trip():
    rv = torch.randn(100, 3, dtype=torch.float64) * 1.5
    R = axis_angle_to_matrix(rv)
    back = rotation_6d_to_matrix(matrix_to_rotation_6d(R))
    assert torch.allclose(back, R, atol=1e-12)
    R2 = rotation_6d_to_matrix(torch.randn(100, 6, dtype=torch.float64))
    eye = torch.eye(3, dtype=torch.float64).expand(100, 3, 3)
    assert torch.allclose(R2.transpose(1, 2) @ R2, eye, atol=1e-12)
    assert torch.allclose(torch.linalg.det(R2), torch.ones(100, dtype=torch.float64))


def test_pmr_equals_the_generator_label_maps(anny64, samples):
    from pressurepose.body import BodyParams

    params = BodyParams(**{k: samples[k].double() for k in ("shape", "root_rotation", "root_translation", "pose")})
    out = anny64(params)
    q, c = label_maps(out.vertices, out.faces)
    maps = reconstruct_maps(out.vertices, out.faces)
    assert torch.equal(maps.depth_mm, q) and torch.equal(maps.contact, c)
    assert c.sum() > 100  # the bodies do touch the mattress
    # The stored labels were made from the mesh at rest: the parameters reproduce them
    # (float32 storage of the parameters moves the mesh by ~1e-7 m).
    assert (maps.contact != samples["contact"].double()).float().mean() < 0.01


def _toy_mesh(seed=0, V=120):
    g = torch.Generator().manual_seed(seed)
    v = torch.rand(1, V, 3, generator=g, dtype=torch.float64)
    v = v * torch.tensor([0.5, 0.3, 0.08], dtype=torch.float64) + torch.tensor([0.6, 0.2, -0.04], dtype=torch.float64)
    faces = torch.randint(0, V, (80, 3), generator=g)
    return v, faces


def test_pmr_gradcheck_and_gradient_reaches_the_lowest_points():
    v, faces = _toy_mesh()
    v.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: reconstruct_maps(x, faces).depth_mm, (v,), eps=1e-7, atol=1e-6)
    maps = reconstruct_maps(v, faces)
    maps.depth_mm.sum().backward()
    assert (v.grad[..., 2] > 0).sum() > 30  # lowering a lowest point lowers Q (1000 mm/m each)
    # Contact: exact 0/1 values with a non-zero (straight-through sigmoid) gradient.
    v2 = v.detach().clone().requires_grad_(True)
    c = reconstruct_maps(v2, faces).contact
    assert set(c.detach().unique().tolist()) <= {0.0, 1.0}
    c.sum().backward()
    assert (v2.grad[..., 2] < 0).any()


@pytest.mark.slow
def test_gradcheck_of_the_whole_forward_pass(anny64):
    """Pressure -> channels -> CNN -> head -> body model -> joints and PMR depth, float64."""
    torch.manual_seed(0)
    net = PressureNet(NetConfig(arch="fast"), body=anny64).double().eval()
    with torch.no_grad():  # a non-trivial output, not the reference pose
        net.mod1.fc[-1].weight.normal_(0, 0.05)
    p0 = _images(1).double() * 0.8 + 0.0  # < 100 mmHg: away from the clip
    regions = torch.zeros(3, 64, 27, dtype=torch.float64)
    regions[0, :20], regions[1, 20:40], regions[2, 40:] = 1, 1, 1

    def forward(u):
        p = p0 * (1 + (u[:, None, None] * regions).sum(0))
        est = net(NetInputs(p, gender=torch.zeros(1, dtype=torch.float64)), mesh=True)[-1]
        return est.joints, est.depth_mm

    u = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    # fast_mode: checks a random projection of the Jacobian (1,800 outputs, each a backward pass).
    assert torch.autograd.gradcheck(forward, (u,), eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=True)
    joints, depth = forward(u)
    grad = torch.autograd.grad(joints.sum(), u)[0]
    assert grad.abs().sum() > 0


def test_blur_and_sobel_against_naive_loops():
    img = _images(2, seed=4).double()
    sigma = torch.tensor([0.5, 1.1], dtype=torch.float64)
    out = gaussian_blur(img, sigma)
    pixels = [(0, 0), (63, 26), (1, 25), (30, 13), (62, 1)] + [(i, (7 * i) % 27) for i in range(2, 60, 5)]
    for b in range(2):
        r = math.ceil(3 * 1.1)  # the batch's kernel radius follows its largest sigma
        k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=torch.float64) / sigma[b]) ** 2)
        k = k / k.sum()
        for i, j in pixels:
            ref = 0.0
            for di in range(-r, r + 1):
                for dj in range(-r, r + 1):
                    if 0 <= i + di < 64 and 0 <= j + dj < 27:
                        ref += float(k[di + r] * k[dj + r] * img[b, i + di, j + dj])
            assert float(out[b, i, j]) == pytest.approx(ref, abs=1e-10)
    assert torch.equal(gaussian_blur(img, 0.0), img)
    s = sobel_magnitude(img[:1])[0]
    pad = torch.nn.functional.pad(img[0], (1, 1, 1, 1))
    gx = (pad[:-2, 2:] + 2 * pad[1:-1, 2:] + pad[2:, 2:]) - (pad[:-2, :-2] + 2 * pad[1:-1, :-2] + pad[2:, :-2])
    gy = (pad[2:, :-2] + 2 * pad[2:, 1:-1] + pad[2:, 2:]) - (pad[:-2, :-2] + 2 * pad[:-2, 1:-1] + pad[:-2, 2:])
    assert torch.allclose(s, (gx**2 + gy**2).sqrt(), atol=1e-5)


def test_calibration_noise_is_seeded_and_keeps_empty_taxels_empty():
    p = _images(4, seed=5)
    a = pressure_channels(p, augment=True, generator=torch.Generator().manual_seed(1))
    b = pressure_channels(p, augment=True, generator=torch.Generator().manual_seed(1))
    c = pressure_channels(p, augment=True, generator=torch.Generator().manual_seed(2))
    assert torch.equal(a, b) and not torch.equal(a, c)
    clean = pressure_channels(p)
    assert torch.equal(a[:, 0], clean[:, 0])  # contact channel: the original loaded taxels
    assert not torch.allclose(a[:, 1], clean[:, 1])


def test_synthesis_loss_prefers_the_true_body(anny64, samples):
    from pressurepose.body import BodyParams
    from pressurepose.net.model import Estimate
    from pressurepose.net.synthesis import synthesis_loss

    net = PressureNet(NetConfig(), body=anny64).double()
    true = BodyParams(**{k: samples[k][:1].double() for k in ("shape", "root_rotation", "root_translation", "pose")})
    pressure = samples["pressure_mmhg"][:1].double()
    losses = []
    for shift in (0.0, 0.12):
        params = true.replace(
            root_translation=(
                true.root_translation + torch.tensor([[shift, 0.0, 0.0]], dtype=torch.float64)
            ).requires_grad_(True)
        )
        out = anny64(params)
        est = Estimate(raw=torch.zeros(1, 1), params=params, joints=out.joints, vertices=out.vertices)
        loss = synthesis_loss(net, est, pressure)
        losses.append(float(loss.detach()))
        if shift:
            (g,) = torch.autograd.grad(loss, params.root_translation)
            assert torch.isfinite(g).all() and g[0, 0] > 0  # moving back towards the truth lowers it
    assert losses[0] < 0.2 < losses[1]


def test_smpl_backend_gives_the_released_output_size(smpl_dir):
    net = PressureNet(NetConfig(backend="smpl", smpl_dir=str(smpl_dir))).eval()
    assert net.head.size == 88  # 10 betas + 3 + 6 + 69, as released
    with torch.no_grad():
        est = net(NetInputs(_images(2), gender=torch.tensor([0.0, 1.0])))[-1]
    assert est.joints.shape == (2, 24, 3) and est.vertices.shape[0] == 2
    assert (est.params.shape.abs() <= 3.0 + 1e-6).all()  # betas inside the sampling bounds


def test_the_one_blur_is_anisotropic_per_image_and_differentiable_in_sigma():
    """pressurepose.blur.gaussian_blur (sim #2's cover spread and the network's channels):
    against a dense 2D convolution with the outer product of the two 1D kernels, per image;
    gradcheck in sigma."""
    import math

    from pressurepose.blur import gaussian_blur as blur

    g = torch.Generator().manual_seed(0)
    img = torch.rand(3, 9, 7, generator=g, dtype=torch.float64)
    sr = torch.tensor([0.7, 1.3, 0.0], dtype=torch.float64)
    sc = torch.tensor([1.1, 0.4, 0.9], dtype=torch.float64)
    out = blur(img, sr, sc)
    for b in range(3):
        radius = max(1, math.ceil(3 * float(max(sr.max(), sc.max()))))
        x = torch.arange(-radius, radius + 1, dtype=torch.float64)

        def kernel(s):
            if s <= 1e-6:
                return (x == 0).to(torch.float64)
            k = torch.exp(-0.5 * (x / s) ** 2)
            return k / k.sum()

        k2 = torch.outer(kernel(float(sr[b])), kernel(float(sc[b])))
        want = torch.nn.functional.conv2d(img[b][None, None], k2[None, None], padding=radius)[0, 0]
        torch.testing.assert_close(out[b], want, rtol=1e-12, atol=1e-12)
    s = torch.tensor(0.8, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: blur(img[:1], t, 0.5 * t), (s,))
