"""Air cells: the air mattress's top is a row of tubes across the bed (MattressParams.top_height);
both sim #2 rests measure the compression from it, so the load concentrates on the crests."""

import math

import numpy as np
import pytest
import torch

from pressurepose.body.capsules import home_pose
from pressurepose.body.params import BodyParams
from pressurepose.errors import UserError
from pressurepose.maps import cell_centres
from pressurepose.mat import MatSpec
from pressurepose.sim.articulated import rest_articulated
from pressurepose.sim.foundation import simulate_pressure
from pressurepose.sim.mattress import GRAVITY_M_S2, MattressParams

PITCH, CREST = 0.1024, 0.0013
CELLS = {"cell_pitch_m": PITCH, "cell_depth_m": 0.01, "cell_crest_m": CREST}


def test_top_height_by_hand():
    mp = MattressParams(**CELLS)
    x = torch.tensor(
        [CREST, CREST + PITCH, CREST - 3 * PITCH, CREST + PITCH / 2, CREST + PITCH / 4], dtype=torch.float64
    )
    # crests at 0, seams 1 cm down half a pitch away, a quarter pitch: half way down
    np.testing.assert_allclose(mp.top_height(x).numpy(), [0, 0, 0, -0.01, -0.005], atol=1e-15)
    xs = torch.linspace(-1, 3, 2001, dtype=torch.float64)
    z = mp.top_height(xs)
    assert float(z.max()) <= 0 and float(z.min()) >= -0.01 - 1e-15
    assert mp.has_cells
    flat = MattressParams()
    assert not flat.has_cells and bool((flat.top_height(xs) == 0).all())
    assert not MattressParams(cell_pitch_m=PITCH).has_cells  # no depth: flat


def test_cells_need_a_pitch_and_a_positive_depth(tmp_path):
    with pytest.raises(UserError, match="cell_pitch_m is 0"):
        MattressParams(cell_depth_m=0.01)
    with pytest.raises(UserError, match="cell_depth_m must be >= 0"):
        MattressParams(cell_pitch_m=PITCH, cell_depth_m=-0.01)
    mp = MattressParams(**CELLS)
    mp.save(tmp_path / "air.json")
    assert MattressParams.load(tmp_path / "air.json") == mp


def _crest_share(foundation_pa: torch.Tensor, sub: int, crest: float = CREST) -> float:
    """Share of the force on the cells within a quarter pitch of a crest (0.5 on a flat top,
    for a load that spans many pitches)."""
    X, _ = cell_centres(MatSpec(), sub, covered=True, dtype=torch.float64)
    near = torch.cos(2 * math.pi * (X - crest) / PITCH) > 0
    f = foundation_pa.to(torch.float64)
    return float((f * near).sum() / f.sum())


def _supine(model, B=1):
    mat = MatSpec()
    return BodyParams.zeros(B, model.default_shape(B)).replace(
        pose=home_pose(B),
        root_translation=torch.tensor([[0.85, mat.sensing_width_m / 2, 0.25]] * B, dtype=torch.float64),
    )


@pytest.fixture(scope="module")
def supine_on_cells(anny64):
    p = _supine(anny64)
    air = MattressParams.preset("air")
    flat = rest_articulated(anny64, p, mattress=air.replace(cell_depth_m=0.0))
    cells = rest_articulated(anny64, p, mattress=air.replace(**CELLS))
    shifted = rest_articulated(anny64, p, mattress=air.replace(**dict(CELLS, cell_crest_m=CREST + PITCH / 2)))
    return p, flat, cells, shifted


def test_articulated_rest_on_cells_balances_and_loads_the_crests(anny64, supine_on_cells):
    p, flat, cells, shifted = supine_on_cells
    weight = float(anny64.measure(p.shape).mass_kg[0]) * GRAVITY_M_S2
    for r in (flat, cells, shifted):
        assert r.failure == [""] and torch.isfinite(r.foundation_pa).all()
        assert abs(float(r.force_n[0]) - weight) < 0.01 * weight
    share_flat = _crest_share(flat.foundation_pa[0], flat.sub)
    assert 0.4 < share_flat < 0.6
    # The crests carry most of the load, wherever they are.
    assert _crest_share(cells.foundation_pa[0], cells.sub) > share_flat + 0.04
    assert _crest_share(shifted.foundation_pa[0], shifted.sub, CREST + PITCH / 2) > share_flat + 0.04
    # Bridging the seams, the body touches fewer cells near them (~7% fewer; in all, about as
    # many: the tubes' one pressure sets the contact area, and the crests take the rest).
    X, _ = cell_centres(MatSpec(), cells.sub, covered=True, dtype=torch.float64)
    seam = torch.cos(2 * math.pi * (X - CREST) / PITCH) < 0
    assert int(((cells.foundation_pa[0] > 0) & seam).sum()) < 0.97 * int(((flat.foundation_pa[0] > 0) & seam).sum())


def test_deeper_seams_concentrate_more(anny64, supine_on_cells):
    p, _, cells, _ = supine_on_cells
    air = MattressParams.preset("air")
    deeper = rest_articulated(anny64, p, mattress=air.replace(**dict(CELLS, cell_depth_m=0.02)))
    assert deeper.failure == [""]
    assert _crest_share(deeper.foundation_pa[0], deeper.sub) > _crest_share(cells.foundation_pa[0], cells.sub)


def test_rigid_rest_on_cells_balances_and_loads_the_crests(anny64):
    out = anny64(_supine(anny64))
    mass = anny64.measure(_supine(anny64).shape).mass_kg
    flat = simulate_pressure(out.vertices, anny64.faces, mass)
    cells = simulate_pressure(out.vertices, anny64.faces, mass, params=MattressParams(**CELLS))
    for r in (flat, cells):
        assert r.failure == [""]
        np.testing.assert_allclose(r.force_n.numpy(), (mass * GRAVITY_M_S2).numpy(), rtol=1e-3)
    assert _crest_share(cells.foundation_pa[0], cells.sub) > _crest_share(flat.foundation_pa[0], flat.sub) + 0.04
