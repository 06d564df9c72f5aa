"""The air support (`sim.air_law`): the pressure solve against bisection, the law's energy as the
maximum over the pressure, derivatives against autograd, and the articulated rest on air."""

import math

import numpy as np
import pytest
import torch

from pressurepose.body.capsules import home_pose
from pressurepose.body.params import BodyParams
from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.sim.air_law import AirLaw
from pressurepose.sim.articulated import rest_articulated
from pressurepose.sim.mattress import GRAVITY_M_S2, MattressParams

AIR = {"air_pressure_pa": 3000.0, "air_stiffness_pa_per_m3": 5e5}
AREA = 0.0286**2 / 4


def _cells(seed=0, B=3, K=400):
    g = torch.Generator().manual_seed(seed)
    w = (torch.rand(B, K, generator=g, dtype=torch.float64) * 0.06 - 0.02).clamp(min=0)
    kt = torch.rand(B, K, generator=g, dtype=torch.float64) * 4e5 + 5e4
    return w, kt


# The tubes' travel: the default thickness (no cell bottoms out here) and 5 mm (many do).
TRAVELS = pytest.mark.parametrize("travel", [0.15, 0.005], ids=["free", "bottoming"])


@TRAVELS
def test_pressure_solves_the_air_balance_like_bisection(travel):
    w, kt = _cells()
    law = AirLaw(MattressParams(**AIR, thickness_m=travel), kt, AREA)
    P = law.solve(w)
    for b in range(w.shape[0]):

        def excess(p):  # displaced volume minus what the pressure rise says
            u = (w[b] - p / kt[b]).clamp(0.0, travel)
            return AREA * float(u.sum()) - (p - AIR["air_pressure_pa"]) / AIR["air_stiffness_pa_per_m3"]

        lo, hi = AIR["air_pressure_pa"], 1e7
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if excess(mid) > 0 else (lo, mid)
        assert float(P[b]) == pytest.approx(0.5 * (lo + hi), rel=1e-9)
    # No contact: the inflation pressure.
    scalar = AirLaw(MattressParams(**AIR), 3e5, AREA)
    assert float(scalar.solve(torch.zeros(1, 5, dtype=torch.float64))[0]) == AIR["air_pressure_pa"]


@TRAVELS
def test_law_is_the_maximum_over_the_pressure(travel):
    w, kt = _cells(1)
    law = AirLaw(MattressParams(**AIR, thickness_m=travel), kt, AREA)
    p, dp, psi = law(w)
    P = law.pressure[:, None]
    E = AREA * psi.sum(1) + law.air_energy()
    u = (w - P / kt).clamp(0.0, travel)
    np.testing.assert_allclose(p.numpy(), (kt * (w - u)).numpy(), rtol=1e-12)
    # Cells pressing the air carry P exactly and have no stiffness of their own; below P and
    # bottomed ones their tissue's; only bottomed cells press harder than P.
    D = law.displaced
    assert bool(D.any()) and bool((~D & (w > 0)).any())
    np.testing.assert_allclose(p[D].numpy(), P.expand_as(p)[D].numpy(), rtol=1e-12)
    assert bool((dp[D] == 0).all()) and bool((dp[~D] == kt[~D]).all())
    bottomed = u >= travel
    assert bool((p[~bottomed] <= P.expand_as(p)[~bottomed] * (1 + 1e-12)).all())
    assert bool(bottomed.any()) == (travel < 0.01)
    for b in range(w.shape[0]):
        for other in np.linspace(0.5, 1.5, 11) * float(P[b]):
            uo = (w[b] - other / kt[b]).clamp(0.0, travel)
            psi_o = 0.5 * kt[b] * (w[b] - uo) ** 2 + other * uo
            e_o = AREA * psi_o.sum() - (other - AIR["air_pressure_pa"]) ** 2 / (2 * AIR["air_stiffness_pa_per_m3"])
            assert float(e_o) <= float(E[b]) + 1e-9 * abs(float(E[b]))


@TRAVELS
def test_law_derivatives_against_autograd(travel):
    """The gradient of the energy is A p; its Hessian A k_t on the tissue's cells (below P or
    bottomed) plus the rank-one coupling beta of the ones pressing the air."""
    w, kt = _cells(2, B=1, K=60)
    law = AirLaw(MattressParams(**AIR, thickness_m=travel), kt, AREA)

    def energy(x):
        psi = law(x[None])[2]
        return AREA * psi.sum() + law.air_energy()[0]

    x = w[0].clone().requires_grad_(True)
    g = torch.autograd.grad(energy(x), x)[0]
    p, dp, _ = law(w)
    np.testing.assert_allclose(g.numpy(), (AREA * p[0]).numpy(), rtol=1e-9, atol=1e-12)
    H = torch.autograd.functional.hessian(energy, w[0])
    law(w)
    D = law.displaced[0].to(torch.float64)
    want = torch.diag(AREA * dp[0]) + law.beta[0] * D[:, None] * D[None, :]
    np.testing.assert_allclose(H.numpy(), want.numpy(), rtol=1e-8, atol=1e-10)


def test_air_fields_validate_and_stay_out_of_foam_beds(tmp_path):
    assert MattressParams(**AIR).has_air_support and not MattressParams().has_air_support
    assert "air_pressure_pa" not in MattressParams().to_dict()
    mp = MattressParams(**AIR)
    mp.save(tmp_path / "air.json")
    assert MattressParams.load(tmp_path / "air.json") == mp
    with pytest.raises(UserError, match="air_stiffness_pa_per_m3 must be >= 0"):
        MattressParams(air_pressure_pa=3000.0, air_stiffness_pa_per_m3=-1.0)
    with pytest.raises(ValueError, match="needs a tissue"):
        AirLaw(mp, None, AREA)


def _supine(model, B=1, weight=None):
    mat = MatSpec()
    shape = model.default_shape(B)
    if weight is not None:
        shape[:, model.shape_names.index("weight")] = torch.tensor(weight, dtype=shape.dtype)
    return BodyParams.zeros(B, shape).replace(
        pose=home_pose(B),
        root_translation=torch.tensor([[0.85, mat.sensing_width_m / 2, 0.25]] * B, dtype=torch.float64),
    )


def test_rest_on_air_balances_and_caps_the_pressure(anny64):
    """On air the weight is carried (1%), the most loaded cells form a plateau at the air's
    pressure (the unsmoothed field), and a heavier body sinks deeper and raises the pressure."""
    p = _supine(anny64, 2, weight=[0.3, 0.8])
    bed = MattressParams.preset("sponge").replace(**AIR)
    r = rest_articulated(anny64, p, mattress=bed)
    assert r.failure == ["", ""]
    weight = anny64.measure(p.shape).mass_kg * GRAVITY_M_S2
    np.testing.assert_allclose(r.force_n.numpy(), weight.numpy(), rtol=1e-2)
    peak = r.foundation_pa.amax((1, 2))
    # The field's plateau: the most loaded cells all carry about the same pressure P.
    for b in range(2):
        f = r.foundation_pa[b]
        top = f[f > 0.98 * float(peak[b])]
        assert top.numel() >= 20, top.numel()
    assert float(peak[1]) > float(peak[0])  # heavier: the air compressed more
    assert float(r.max_compression_m[1]) > float(r.max_compression_m[0])
    assert math.isfinite(float(r.foundation_pa.sum()))
