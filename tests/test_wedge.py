"""The wedge under a tilted body's back (`sim.wedge`): its footprint and slope, its stiffness in
series and the rigid base against hand-computed cases; the rest on it (weight carried, the body
kept turned, the wedge's load read as a flat patch, a mirrored body gives the mirrored image,
no wedge changes nothing); the `tilted` partition's settings and bad input."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from pressurepose.body.capsules import home_pose
from pressurepose.body.params import BodyParams, root_roll
from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.sim.articulated import ArticulatedConfig, rest_articulated
from pressurepose.sim.mattress import GRAVITY_M_S2, MattressParams
from pressurepose.sim.pillow import layer_in_series
from pressurepose.sim.wedge import HIPS, SHOULDERS, Wedge, rigid_base, thickness_map, tilt_of

F64 = torch.float64


def test_tilt_of_by_hand():
    deg = torch.tensor([3.0, 20.0, -30.0, 70.0, 100.0, -180.0, 0.0], dtype=F64)
    got = tilt_of(torch.deg2rad(deg))
    np.testing.assert_allclose(torch.rad2deg(got).numpy(), [0, 20, 30, 60, 0, 0, 0], atol=1e-12)


def _trunk(left_shoulder_higher: bool, B: int = 1) -> torch.Tensor:
    """Joints of a trunk lying along the bed: shoulders at x 0.5, hips at x 0.9, the body's left
    at y 0.4 and right at y 0.6, its middle at (0.7, 0.5)."""
    j = torch.zeros(B, 24, 3, dtype=F64)
    for (ls, rs), x in ((SHOULDERS, 0.5), (HIPS, 0.9)):
        j[:, ls, :2] = torch.tensor([x, 0.4], dtype=F64)
        j[:, rs, :2] = torch.tensor([x, 0.6], dtype=F64)
    j[:, SHOULDERS[0] if left_shoulder_higher else SHOULDERS[1], 2] = 0.1
    return j


def test_thickness_map_by_hand():
    """From inner_m beyond the midline toward the higher shoulder, base_m wide, length_m long
    about the trunk's middle, u tan(tilt) thick; none for tilt 0."""
    wedge = Wedge(length_m=0.4, base_m=0.2, inner_m=0.02)
    xy = torch.tensor(
        [[0.7, 0.42], [0.7, 0.38], [0.55, 0.30], [0.7, 0.25], [0.95, 0.4], [0.7, 0.49], [0.7, 0.6]], dtype=F64
    )
    tilt = torch.tensor([math.radians(30.0)], dtype=F64)
    got = thickness_map(wedge, tilt, _trunk(True), xy)[0]
    t = math.tan(math.radians(30.0))
    # toward y < 0.5 (the left shoulder is higher): u = 0.5 - y - 0.02, on where 0 <= u <= 0.2
    want = [0.06 * t, 0.10 * t, 0.18 * t, 0.0, 0.0, 0.0, 0.0]  # y 0.25: u 0.23 > base; x 0.95: off the length
    np.testing.assert_allclose(got.numpy(), want, atol=1e-12)
    # The right shoulder higher: the mirror image.
    mirrored = xy.clone()
    mirrored[:, 1] = 1.0 - xy[:, 1]
    np.testing.assert_allclose(thickness_map(wedge, tilt, _trunk(False), mirrored)[0].numpy(), want, atol=1e-12)
    assert not bool(thickness_map(wedge, torch.zeros(1, dtype=F64), _trunk(True), xy).any())


def test_stiffness_in_series_by_hand():
    tissue = torch.tensor([[2e5, 5e4, 1e5]], dtype=F64)
    thickness = torch.tensor([[0.1, 0.05, 0.0]], dtype=F64)
    got = layer_in_series(tissue, Wedge(modulus_pa=3e4).modulus_pa, thickness)
    want = [1 / (1 / 2e5 + 0.1 / 3e4), 1 / (1 / 5e4 + 0.05 / 3e4), 1e5]
    np.testing.assert_allclose(got.numpy(), [want], rtol=1e-12)


def _grid(R=10, C=8):
    return torch.arange(R, dtype=F64) * 0.03, torch.arange(C, dtype=F64) * 0.02


def test_rigid_base_keeps_force_and_moments_and_reproduces_a_plane():
    g = torch.Generator().manual_seed(1)
    x, y = _grid()
    on = torch.zeros(3, 10, 8, dtype=torch.bool)
    on[:, 2:8, 3:8] = True
    on[2] = False  # a body without a wedge
    p = torch.rand(3, 10, 8, generator=g, dtype=F64) * 1000 + 2000
    got = rigid_base(p, on, x, y)
    X, Y = torch.meshgrid(x, y, indexing="ij")
    for b in range(2):
        m = on[b]
        for weight in (torch.ones_like(X), X, Y):  # force and first moments kept
            np.testing.assert_allclose(float((got[b] * weight)[m].sum()), float((p[b] * weight)[m].sum()), rtol=1e-10)
        # affine on the footprint: the residual of a plane fit is round-off
        A = torch.stack([torch.ones_like(X[m]), X[m], Y[m]], -1)
        coef = torch.linalg.lstsq(A, got[b][m][:, None]).solution
        np.testing.assert_allclose((A @ coef)[:, 0].numpy(), got[b][m].numpy(), rtol=1e-9)
    assert torch.equal(got[~on], p[~on]) and torch.equal(got[2], p[2])
    # A load that is already a plane is read as it is.
    plane = (1000 + 300 * X - 200 * Y).expand(3, -1, -1) * on
    np.testing.assert_allclose(rigid_base(plane, on, x, y).numpy(), plane.numpy(), rtol=1e-9, atol=1e-9)


def test_rigid_base_clips_at_zero_and_keeps_the_force():
    x, y = _grid()
    on = torch.zeros(1, 10, 8, dtype=torch.bool)
    on[0, :, 2:8] = True
    p = torch.zeros(1, 10, 8, dtype=F64)
    p[0, 0, 7] = 5000.0  # all the load at one corner: the plane would pull at the far one
    got = rigid_base(p, on, x, y)
    assert float(got.min()) >= 0 and float(got[0, 0, 7]) == float(got.max())
    np.testing.assert_allclose(float(got.sum()), 5000.0, rtol=1e-12)
    # One column wide: no moment about its long axis, still solved.
    thin = torch.zeros(1, 10, 8, dtype=torch.bool)
    thin[0, 2:8, 4] = True
    q = torch.rand(1, 10, 8, dtype=F64, generator=torch.Generator().manual_seed(2)) + 1
    got = rigid_base(q, thin, x, y)
    assert bool(torch.isfinite(got).all())
    np.testing.assert_allclose(float(got[thin].sum()), float(q[thin].sum()), rtol=1e-10)


def _tilted(model, roll_deg, B=1):
    mat = MatSpec()
    return BodyParams.zeros(B, model.default_shape(B)).replace(
        pose=home_pose(B),
        root_rotation=torch.tensor([[math.radians(roll_deg), 0.0, 0.0]] * B, dtype=F64),
        root_translation=torch.tensor([[0.85, mat.sensing_width_m / 2, 0.25]] * B, dtype=F64),
    )


@pytest.fixture(scope="module")
def wedge_rests(anny64):
    bed = MattressParams.preset("sponge")
    cfg = ArticulatedConfig(wedge=Wedge(), friction=False)  # friction's path dependence aside (test_articulated)
    right = rest_articulated(anny64, _tilted(anny64, 30.0), mattress=bed, config=cfg)
    left = rest_articulated(anny64, _tilted(anny64, -30.0), mattress=bed, config=cfg)
    bare = rest_articulated(anny64, _tilted(anny64, 30.0), mattress=bed, config=ArticulatedConfig(friction=False))
    return right, left, bare


def test_rest_on_a_wedge(anny64, wedge_rests):
    """The weight is carried (1%) and the image's force is the contact's; the body stays turned
    toward its side, where without the wedge it rolls back further; beside the back the mat
    reads a broad patch of the wedge's base."""
    right, left, bare = wedge_rests
    assert right.failure == left.failure == bare.failure == [""]
    weight = anny64.measure(_tilted(anny64, 30.0).shape).mass_kg * GRAVITY_M_S2
    area = MatSpec().pitch_row_m * MatSpec().pitch_col_m / right.sub**2
    for rest in (right, left):
        np.testing.assert_allclose(rest.force_n.numpy(), weight.numpy(), rtol=1e-2)
        np.testing.assert_allclose((rest.foundation_pa.sum((1, 2)) * area).numpy(), rest.force_n.numpy(), rtol=1e-9)
    turned = math.degrees(float(root_roll(right.params.root_rotation)[0]))
    free = math.degrees(float(root_roll(bare.params.root_rotation)[0]))
    assert 15.0 < turned < 35.0 and free < turned - 5.0, (turned, free)
    # The base's broad patch: more of the mat loaded than under the same body without a wedge.
    assert int((right.foundation_pa[0] > 0).sum()) > int((bare.foundation_pa[0] > 0).sum()) + 50


def test_mirrored_tilt_gives_mirrored_image(wedge_rests):
    right, left, _ = wedge_rests
    a, b = right.foundation_pa[0], left.foundation_pa[0].flip(-1)
    rows_a, rows_b = a.sum(1) / a.sum(), b.sum(1) / b.sum()
    assert float(0.5 * (rows_a - rows_b).abs().sum()) < 0.1
    cols_a, cols_b = a.sum(0) / a.sum(), b.sum(0) / b.sum()
    assert float(0.5 * (cols_a - cols_b).abs().sum()) < 0.15
    np.testing.assert_allclose(
        float(root_roll(right.params.root_rotation)[0]), -float(root_roll(left.params.root_rotation)[0]), atol=0.05
    )


def test_no_wedge_for_untilted_bodies_changes_nothing(anny64):
    """A supine body (tilt 0) rests the same bit for bit with or without the wedge setting."""
    bed = MattressParams.preset("sponge")
    p = _tilted(anny64, 0.0)
    a = rest_articulated(anny64, p, mattress=bed, config=ArticulatedConfig(wedge=Wedge()))
    b = rest_articulated(anny64, p, mattress=bed)
    assert torch.equal(a.foundation_pa, b.foundation_pa) and torch.equal(a.joints, b.joints)


def test_wedges_in_a_mixed_batch_and_on_both_grids(anny64, monkeypatch):
    """A batch of a tilted and a supine body: the supine one rests as it does in the same batch
    without the wedge setting (friction makes a rest depend on its batch at round-off, wedge or
    not: compared within one batch), the tilted one on its wedge - whose map reaches the coarse
    grid's re-posings as well as the image's grid."""
    from pressurepose.sim.contact_grid import ContactGrid

    seen = []
    heights = ContactGrid.heights

    def spy(self, *args, **kwargs):
        wedge = kwargs.get("wedge")
        seen.append((self.sub, None if wedge is None or wedge[0] is None else tuple(wedge[0].shape)))
        return heights(self, *args, **kwargs)

    monkeypatch.setattr(ContactGrid, "heights", spy)
    bed = MattressParams.preset("sponge")
    cfg = ArticulatedConfig(wedge=Wedge())
    both = _tilted(anny64, 30.0, B=2)
    both = both.replace(root_rotation=torch.tensor([[math.radians(30.0), 0, 0], [0.0, 0, 0]], dtype=F64))
    mixed = rest_articulated(anny64, both, mattress=bed, config=cfg)
    assert {sub for sub, shape in seen if shape is not None} == {cfg.sub, cfg.coarse_sub}
    seen.clear()
    plain = rest_articulated(anny64, both, mattress=bed, config=ArticulatedConfig())
    assert all(shape is None for _, shape in seen)  # no wedge setting: no maps at all
    assert mixed.failure == plain.failure == ["", ""]
    np.testing.assert_allclose(mixed.foundation_pa[1].numpy(), plain.foundation_pa[1].numpy(), rtol=1e-6, atol=1e-3)
    turned = math.degrees(float(root_roll(mixed.params.root_rotation)[0]))
    free = math.degrees(float(root_roll(plain.params.root_rotation)[0]))
    assert turned > free + 3.0, (turned, free)


def test_tilted_partition_rests_on_wedges_and_bad_input(anny64):
    from pressurepose.generate.plan import GenerateConfig
    from pressurepose.sim.run import articulated_config_for

    assert articulated_config_for("tilted").wedge == Wedge() and articulated_config_for("supine").wedge is None
    with pytest.raises(UserError, match="Wedge.base_m must be > 0"):
        Wedge(base_m=0.0)
    for sim2 in (None, "articulated", "rigid"):  # MuJoCo's settling has no wedges, whatever sim #2
        with pytest.raises(UserError, match="needs the articulated engine"):
            GenerateConfig(partition="tilted", settle="mujoco", sim2=sim2)
    # Its datasets record the wedge; other partitions' do not.
    from pressurepose.generate.run import _settings

    assert _settings(GenerateConfig(partition="tilted"), {})["wedge"] == dataclasses.asdict(Wedge())
    assert "wedge" not in _settings(GenerateConfig(partition="supine"), {})
    with pytest.raises(UserError, match="a wedge needs the soft tissue"):
        rest_articulated(
            anny64,
            _tilted(anny64, 30.0),
            mattress=MattressParams(tissue_pa_per_m=0.0),
            config=ArticulatedConfig(wedge=Wedge()),
        )


def test_simulate_tilted_records_the_wedge_and_refuses_raised_beds(tmp_path, capsys):
    import json

    from pressurepose.cli import main

    assert main(["simulate", "--partition", "tilted", "--out", str(tmp_path / "s")]) == 0
    record = json.loads((tmp_path / "s" / "simulate.json").read_text())
    assert record["wedge"] == dataclasses.asdict(Wedge())
    capsys.readouterr()
    for flags, said in (
        (["--head-angle-deg", "20"], "wedges, which lie on flat beds only"),
        (["--settle", "mujoco"], "needs --settle articulated"),
    ):
        assert main(["simulate", "--partition", "tilted", *flags, "--out", str(tmp_path / "r")]) == 2
        err = capsys.readouterr().err
        assert said in err and "Traceback" not in err
    assert not (tmp_path / "r").exists()
