"""The articulated rest's batch bookkeeping: a body's Newton steps do not depend on the other
bodies in its batch (done bodies leave it, `Linearised.take`), and the rasterisation of the
surface points against a brute-force reference."""

import pytest
import torch

import pressurepose.sim.articulated as articulated
from pressurepose.mat import MatSpec
from pressurepose.sampling.partitions import PARTITIONS, SamplingConfig
from pressurepose.sampling.sampler import PoseSampler
from pressurepose.sim.linearised import minimise
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.run import articulated_config_for
from pressurepose.sim.soft_contact import SeriesLaw, lowest_points


@pytest.fixture(scope="module")
def solves(anny64):
    """The (linearisation, start, weight, steps) of every solve of a rest of 4 drawn bodies."""
    over_bed = PARTITIONS["general"].over_bed_choices[0]
    cfg = SamplingConfig(partition="general", gender="female", seed=0, over_bed=over_bed)
    params = PoseSampler(anny64, cfg).sample(range(4)).params
    seen = []

    def capture(lin, q, mp, weight, config, max_steps, step_tol=0.0):
        seen.append((lin, q.clone(), weight, max_steps, step_tol))
        return minimise(lin, q, mp, weight, config, max_steps, step_tol)

    mp, config = MattressParams.preset("sponge"), articulated_config_for("general")
    patch = pytest.MonkeyPatch()
    patch.setattr(articulated, "minimise", capture)
    try:
        articulated.rest_articulated(anny64, params, mattress=mp, config=config)
    finally:
        patch.undo()
    return seen, mp, config


def test_take_gives_the_same_rows(solves):
    seen, mp, _ = solves
    lin = seen[3][0]
    B = lin.h.shape[0]
    q = 0.01 * torch.sin(torch.arange(B * lin.dofs.n, dtype=torch.float64)).view(B, -1)
    full = lin.newton_step(q, mp)
    idx = torch.tensor([B - 1, 0])
    part = lin.take(idx).newton_step(q[idx], mp)
    for a, b in zip(full, part):
        # Per-cell results (forces, compressions) come trimmed to the taken bodies' cells: the
        # rest of the batch's padding, zero.
        a = a[idx]
        if a.ndim == 2 and a.shape[1] > b.shape[1]:
            assert not bool(a[:, b.shape[1] :].any())
            a = a[:, : b.shape[1]]
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(lin.energy(q, mp)[idx], lin.take(idx).energy(q[idx], mp), rtol=1e-14, atol=0.0)


def test_a_body_steps_alone_as_in_its_batch(solves):
    """Every solve of the rest, once for the batch and once per body alone: the same motion to
    round-off (batched LAPACK and matrix products are not bitwise the same for every batch
    size) and the same steps - up to one: a stopping test (a step below 1e-6, the imbalance
    below `tol`) that lands within round-off of its threshold ends the solve a step earlier or
    later, a step too small to move the body beyond the motion's tolerance (seen: 2 against 3
    steps, the motions 1.8e-9 apart)."""
    seen, mp, config = solves
    differ = 0
    for lin, q0, weight, steps, step_tol in seen:
        q, iters = minimise(lin, q0, mp, weight, config, steps, step_tol)
        for i in range(q.shape[0]):
            idx = torch.tensor([i])
            qi, it = minimise(lin.take(idx), q0[idx], mp, weight[idx], config, steps, step_tol)
            assert abs(int(it[0]) - int(iters[i])) <= 1
            differ += int(it[0]) != int(iters[i])
            torch.testing.assert_close(qi[0], q[i], rtol=0.0, atol=1e-8)
    assert differ <= 2  # of the ~64 solves: a coincidence, not a batch effect


def _lowest_reference(points, labels, mat, sub, values):
    """Cell by cell: the lowest point (the last listed of equals), its part and value."""
    from pressurepose.maps import EMPTY_HEIGHT_M, grid_origin, grid_shape

    nr, nc = grid_shape(mat, sub, True)
    x0, y0 = grid_origin(mat, True)
    B = points.shape[0]
    h = torch.full((B, nr * nc), EMPTY_HEIGHT_M, dtype=points.dtype)
    part = torch.zeros(B, nr * nc, dtype=torch.long)
    value = torch.ones(B, nr * nc, dtype=points.dtype)
    for b in range(B):
        for i in range(points.shape[1]):
            x, y, z = points[b, i].tolist()
            r, c = (
                int(torch.floor(torch.tensor((x - x0) * (sub / mat.pitch_row_m)))),
                int(torch.floor(torch.tensor((y - y0) * (sub / mat.pitch_col_m)))),
            )
            if not (0 <= r < nr and 0 <= c < nc):
                continue
            z = min(z, EMPTY_HEIGHT_M)
            cell = r * nc + c
            if z <= h[b, cell]:
                h[b, cell], part[b, cell], value[b, cell] = z, labels[i], values[b, i]
    return h, part, value


def test_lowest_points_match_a_cell_by_cell_reference():
    mat, sub = MatSpec(), 2
    g = torch.Generator().manual_seed(0)
    B, P = 2, 3000
    x = torch.rand(B, P, generator=g, dtype=torch.float64) * 2.6 - 0.3  # some beyond the grid
    y = torch.rand(B, P, generator=g, dtype=torch.float64) * 1.3 - 0.2
    z = torch.rand(B, P, generator=g, dtype=torch.float64).mul(0.8).sub(0.1).mul(50).round().div(50)  # ties
    points = torch.stack([x, y, z], -1)
    labels = torch.sort(torch.randint(0, 24, (P,), generator=g)).values
    values = torch.rand(B, P, generator=g, dtype=torch.float64)
    got = lowest_points(points, labels, mat, sub, values)
    want = _lowest_reference(points, labels, mat, sub, values)
    for a, b in zip(got, want):
        assert torch.equal(a, b)


def test_series_law_take_and_energy_agree_with_the_full_law():
    mp = MattressParams.preset("sponge")
    g = torch.Generator().manual_seed(1)
    tissue = 1e5 + 4e5 * torch.rand(3, 50, generator=g, dtype=torch.float64)
    w = 0.05 * torch.rand(3, 50, generator=g, dtype=torch.float64)
    w[:, ::5] = 0.0
    law = SeriesLaw(mp, tissue)
    p, dp, phi = law(w)
    assert torch.equal(law.energy(w), phi)
    idx = torch.tensor([2, 0])
    for a, b in zip(law.take(idx)(w[idx]), (p[idx], dp[idx], phi[idx])):
        # Vectorised transcendental functions round a value by its place in the array.
        torch.testing.assert_close(a, b, rtol=1e-14, atol=0.0)
    # asinh in its log1p form against torch's, the foam's share u through the cubic's root.
    a, b = mp.k3_pa_per_m3 / tissue, 1 + mp.k1_pa_per_m / tissue
    s = (b / (3 * a)).sqrt()
    u = 2 * s * torch.sinh(torch.asinh(w / (2 * a * s**3)) / 3)
    torch.testing.assert_close(p, u * (mp.k1_pa_per_m + mp.k3_pa_per_m3 * u * u), rtol=1e-14, atol=1e-12)
