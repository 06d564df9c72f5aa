"""The pillow in the articulated rest (`sim.pillow`): its footprint, its stiffness in series and
its spread against hand-computed cases, the rest on it (weight carried, the head lifted, the
head's load spread wider; no pillow changes nothing), the generator's draws and bad input."""

import math

import numpy as np
import pytest
import torch

from pressurepose.body.capsules import home_pose
from pressurepose.body.joints import joint_index
from pressurepose.body.params import BodyParams
from pressurepose.errors import UserError
from pressurepose.generate.plan import GenerateConfig
from pressurepose.generate.worker import pillow_thickness
from pressurepose.mat import MatSpec
from pressurepose.sampling.partitions import SamplingConfig
from pressurepose.sim.articulated import rest_articulated
from pressurepose.sim.mattress import GRAVITY_M_S2, MattressParams
from pressurepose.sim.pillow import HEAD, NECK, PILLOW_THICKNESS_M, Pillow, footprint, in_series, spread_load

F64 = torch.float64


def _joints(head_xy, neck_xy):
    j = torch.zeros(len(head_xy), 24, 3, dtype=F64)
    j[:, HEAD, :2] = torch.tensor(head_xy, dtype=F64)
    j[:, NECK, :2] = torch.tensor(neck_xy, dtype=F64)
    return j


def test_footprint_by_hand():
    """From past_neck beyond the neck toward the head (either way along the bed), length long,
    width wide about the head; none for thickness 0."""
    pillow = Pillow(length_m=0.4, width_m=0.3, past_neck_m=0.02)
    xs, ys = torch.linspace(0.0, 1.0, 101, dtype=F64), torch.linspace(0.0, 0.6, 61, dtype=F64)
    X, Y = torch.meshgrid(xs, ys, indexing="ij")
    xy = torch.stack([X.reshape(-1), Y.reshape(-1)], -1)
    # Head toward smaller x (the usual way), toward larger x (lying the other way), no pillow.
    joints = _joints([[0.45, 0.3], [0.55, 0.2], [0.45, 0.3]], [[0.6, 0.3], [0.4, 0.2], [0.6, 0.3]])
    got = footprint(pillow, joints, xy, torch.tensor([0.1, 0.1, 0.0], dtype=F64))
    x, y = xy[:, 0], xy[:, 1]
    eps = 1e-9
    want0 = (x <= 0.58 + eps) & (x >= 0.18 - eps) & ((y - 0.3).abs() <= 0.15 + eps)
    want1 = (x >= 0.42 - eps) & (x <= 0.82 + eps) & ((y - 0.2).abs() <= 0.15 + eps)
    # Cells exactly on an edge may go either way with round-off: compare away from the edges.
    near = lambda a, b, c: ((x - a).abs() < 1e-6) | ((x - b).abs() < 1e-6) | (((y - c).abs() - 0.15).abs() < 1e-6)  # noqa: E731
    for b, want, (a0, a1, c) in ((0, want0, (0.18, 0.58, 0.3)), (1, want1, (0.42, 0.82, 0.2))):
        keep = ~near(a0, a1, c)
        assert torch.equal(got[b][keep], want[keep])
    assert not bool(got[2].any())


def test_stiffness_in_series_by_hand():
    tissue = torch.tensor([[2e5, 5e4, 1e5]], dtype=F64)
    under = torch.tensor([[True, True, False]])
    got = in_series(tissue, Pillow(modulus_pa=3000.0), torch.tensor([0.1], dtype=F64), under)
    k_p = 3000.0 / 0.1
    np.testing.assert_allclose(got.numpy(), [[1 / (1 / 2e5 + 1 / k_p), 1 / (1 / 5e4 + 1 / k_p), 1e5]], rtol=1e-12)


def _spread_reference(p, under, sigma, x, y):
    """Per cell: every footprint cell's load sent to the footprint cells by Gaussian weights
    normalised over the whole grid, then scaled to the footprint's force."""
    R, C = p.shape
    out = torch.zeros_like(p)
    for i in range(R):
        for j in range(C):
            if not under[i, j] or p[i, j] == 0:
                continue
            wx = torch.exp(-0.5 * ((x - x[i]) / sigma) ** 2)
            wy = torch.exp(-0.5 * ((y - y[j]) / sigma) ** 2)
            out += p[i, j] * (wx / wx.sum())[:, None] * (wy / wy.sum())[None, :]
    out = out * under
    inside = (p * under).sum()
    return p * ~under + out * inside / out.sum()


def test_spread_against_a_per_cell_reference_and_conserves_force():
    g = torch.Generator().manual_seed(0)
    R, C = 12, 9
    x, y = torch.arange(R, dtype=F64) * 0.02, torch.arange(C, dtype=F64) * 0.025
    p = torch.rand(2, R, C, generator=g, dtype=F64) * (torch.rand(2, R, C, generator=g, dtype=F64) > 0.4)
    under = torch.zeros(2, R, C, dtype=torch.bool)
    under[:, 2:8, 1:6] = True
    t = torch.tensor([0.06, 0.1], dtype=F64)
    pillow = Pillow(spread=0.5)
    got = spread_load(p, under, pillow, t, x, y)
    for b in range(2):
        want = _spread_reference(p[b], under[b], 0.5 * float(t[b]), x, y)
        np.testing.assert_allclose(got[b].numpy(), want.numpy(), rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(got.sum((1, 2)).numpy(), p.sum((1, 2)).numpy(), rtol=1e-12)
    assert torch.equal(got[~under], p[~under])  # outside the footprint: untouched
    # The load spreads: fewer extremes inside the footprint.
    assert float(got[under].std()) < float(p[under].std())
    # No pillow (thickness 0): the image as it was, bit for bit.
    assert torch.equal(spread_load(p, under, pillow, torch.zeros(2, dtype=F64), x, y), p)


def _supine(model, B=1):
    mat = MatSpec()
    return BodyParams.zeros(B, model.default_shape(B)).replace(
        pose=home_pose(B),
        root_translation=torch.tensor([[0.85, mat.sensing_width_m / 2, 0.25]] * B, dtype=F64),
    )


@pytest.fixture(scope="module")
def rests(anny64):
    bed = MattressParams.preset("sponge")
    p = _supine(anny64, 2)
    bare = rest_articulated(anny64, p, mattress=bed)
    zero = rest_articulated(anny64, p, mattress=bed, pillow_m=torch.zeros(2, dtype=F64))
    on = rest_articulated(anny64, p, mattress=bed, pillow_m=torch.tensor([0.06, 0.12], dtype=F64))
    return p, bare, zero, on


def test_no_pillow_changes_nothing(rests):
    _, bare, zero, _ = rests
    assert torch.equal(bare.foundation_pa, zero.foundation_pa)
    assert torch.equal(bare.joints, zero.joints)


def test_rest_on_a_pillow_carries_the_weight_and_lifts_the_head(anny64, rests):
    """The weight is carried (1%), the head rides higher on a thicker pillow, the head's load
    spreads over more cells at a lower peak, and the image's force is the contact's."""
    p, bare, _, on = rests
    assert on.failure == ["", ""]
    weight = anny64.measure(p.shape).mass_kg * GRAVITY_M_S2
    np.testing.assert_allclose(on.force_n.numpy(), weight.numpy(), rtol=1e-2)
    area = MatSpec().pitch_row_m * MatSpec().pitch_col_m / on.sub**2
    np.testing.assert_allclose((on.foundation_pa.sum((1, 2)) * area).numpy(), on.force_n.numpy(), rtol=1e-9)
    head = joint_index("head")
    z0, z1, z2 = float(bare.joints[0, head, 2]), float(on.joints[0, head, 2]), float(on.joints[1, head, 2])
    assert z0 + 0.01 < z1 < z2, (z0, z1, z2)
    # The head's region: the rows above the shoulders (the head end of the loaded rows).
    for b in range(2):
        rows = (bare.foundation_pa[b].sum(1) > 0).nonzero()[:, 0]
        band = slice(int(rows.min()), int(rows.min()) + 12)
        before, after = bare.foundation_pa[b, band], on.foundation_pa[b, band]
        assert int((after > 100).sum()) > int((before > 100).sum())
        assert float(after.max()) < float(before.max())
    assert math.isfinite(float(on.foundation_pa.sum()))


def test_pillow_draws_are_per_sample_and_in_range():
    cfg = SamplingConfig(partition="supine", gender="female", seed=3)
    a = pillow_thickness(cfg, [5, 6, 7, 8], 0.5)
    b = pillow_thickness(cfg, [8, 7], 0.5)
    np.testing.assert_array_equal(a[[3, 2]], b)  # a sample's pillow does not depend on its batch
    many = pillow_thickness(cfg, range(400), 0.5)
    on = many > 0
    assert 0.4 < on.mean() < 0.6
    lo, hi = PILLOW_THICKNESS_M
    assert bool(((many[on] >= lo) & (many[on] <= hi)).all())
    assert not pillow_thickness(cfg, range(50), 0.0).any()
    assert (pillow_thickness(cfg, range(50), 1.0) > 0).all()
    other = SamplingConfig(partition="supine", gender="female", seed=4)
    assert not np.array_equal(pillow_thickness(other, range(50), 0.5), pillow_thickness(cfg, range(50), 0.5))


def test_bad_pillows_are_refused_by_the_commands(tmp_path, capsys):
    from pressurepose.cli import main
    from pressurepose.commands.realism import RealismConfig

    for argv, message in (
        (["simulate", "--out", str(tmp_path / "s"), "--pillow-m", "0.5"], "pillow_m is a pillow's thickness"),
        (
            ["simulate", "--out", str(tmp_path / "s"), "--pillow-m", "0.1", "--settle", "mujoco"],
            "needs the articulated",
        ),
        (
            ["simulate", "--out", str(tmp_path / "s"), "--pillow-m", "0.1", "--head-angle-deg", "30"],
            "pillows lie on flat beds only",
        ),
        (["realism", "--out", str(tmp_path / "r"), "--pillow-m", "-0.1"], "pillow_m is a pillow's thickness"),
        (["generate", "--out", str(tmp_path / "g"), "--pillow", "1.5"], "share of the samples"),
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err
        assert not any(tmp_path.iterdir())  # nothing written
    with pytest.raises(UserError, match="needs the articulated sim #2"):
        RealismConfig(pillow_m=0.1, sim2="rigid")


def test_bad_pillows_are_refused(anny64):
    with pytest.raises(UserError, match="Pillow.modulus_pa must be > 0"):
        Pillow(modulus_pa=0.0)
    p = _supine(anny64, 2)
    for bad in ([0.1], [0.1, -0.01], [0.1, float("nan")]):
        with pytest.raises(UserError, match="pillow_m must hold 2 finite thicknesses"):
            rest_articulated(anny64, p, mattress=MattressParams.preset("sponge"), pillow_m=torch.tensor(bad))
    with pytest.raises(UserError, match="needs the soft tissue"):
        rest_articulated(anny64, p, mattress=MattressParams(tissue_pa_per_m=0.0), pillow_m=torch.tensor([0.1, 0.1]))
    with pytest.raises(UserError, match="share of the samples"):
        GenerateConfig(pillow=1.5)
    with pytest.raises(UserError, match="needs the articulated engine"):
        GenerateConfig(pillow=0.5, settle="mujoco")
    assert "pillow" not in GenerateConfig().identity() and GenerateConfig(pillow=0.5).identity()["pillow"] == 0.5
