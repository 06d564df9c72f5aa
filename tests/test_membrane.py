"""The mat as a tensioned membrane on the foam (`sim.membrane`): against the continuum kernel,
force and centre of pressure kept, peaks kept better than a Gaussian of the same reach, the
mattress file and the sensor pipeline."""

import math

import numpy as np
import pytest
import torch
from scipy.special import k0

from pressurepose.blur import gaussian_blur
from pressurepose.mat import MatSpec
from pressurepose.sim.foundation import taxel_pressure
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.membrane import membrane_spread


def test_point_load_follows_the_continuum_kernel():
    """A point load on a fine grid reads K0(r / lambda) / (2 pi lambda^2) x the cell's area
    around it (the Green's function of k u - T laplacian u), and its total is kept."""
    h, lam = 0.005, 0.04
    p = torch.zeros(1, 161, 161, dtype=torch.float64)
    p[0, 80, 80] = 1.0
    q = membrane_spread(p, lam, h, h)[0]
    for cells in (4, 8, 16, 24):  # 2 to 12 cm from the load, along both axes
        expected = k0(cells * h / lam) / (2 * math.pi * lam**2) * h * h
        for got in (q[80, 80 + cells], q[80 - cells, 80]):
            assert float(got) == pytest.approx(expected, rel=0.03)
    # All but the kernel's tail beyond the grid (10 lambda away: ~1e-4 of the load) is kept.
    assert float(q.sum()) == pytest.approx(1.0, abs=5e-4)


def test_force_centre_and_symmetry_are_kept():
    """On a rectangular grid with unequal cells: the total force and the centre of pressure
    are those of the input (the load 10 lambda from the edges: the tail beyond them is lost), a mirrored load reads mirrored, and the
    reading is never negative; length 0 returns the input itself."""
    g = torch.Generator().manual_seed(0)
    p = torch.zeros(2, 60, 40, dtype=torch.float64)
    p[:, 20:40, 12:28] = torch.rand(2, 20, 16, generator=g, dtype=torch.float64) * 3e3
    q = membrane_spread(p, 0.02, 0.0143, 0.0146)
    np.testing.assert_allclose(q.sum((1, 2)).numpy(), p.sum((1, 2)).numpy(), rtol=1e-4)
    rows = torch.arange(60, dtype=torch.float64)[:, None]
    cols = torch.arange(40, dtype=torch.float64)[None]
    for w in (rows, cols):
        np.testing.assert_allclose(
            ((q * w).sum((1, 2)) / q.sum((1, 2))).numpy(), ((p * w).sum((1, 2)) / p.sum((1, 2))).numpy(), atol=1e-3
        )
    assert float(q.min()) >= 0
    np.testing.assert_allclose(membrane_spread(p.flip(-1), 0.02, 0.0143, 0.0146).numpy(), q.flip(-1).numpy(), atol=1e-9)
    assert membrane_spread(p, 0.0, 0.0143, 0.0146) is p


def test_membrane_keeps_peaks_and_loads_a_halo():
    """The membrane's reach (its kernel's second moment is 4 lambda^2 per axis) in a Gaussian
    flattens a small contact's peak far more; the membrane loads cells around the contact."""
    h, lam = 0.0143, 0.02
    p = torch.zeros(1, 60, 60, dtype=torch.float64)
    p[0, 28:32, 28:32] = 5e3  # a heel-sized patch, 5.7 cm square
    q = membrane_spread(p, lam, h, h)
    same_reach = gaussian_blur(p, 2 * lam / h)
    assert float(q.max()) > 1.5 * float(same_reach.max())
    assert float(q[0, 26, 30]) > 0.01 * 5e3  # 2 cells off the edge


def test_membrane_gradients():
    """Differentiable in the pressure and in the length (gradcheck)."""
    p = torch.rand(1, 12, 10, dtype=torch.float64, requires_grad=True)
    lam = torch.tensor(0.02, dtype=torch.float64, requires_grad=True)
    torch.autograd.gradcheck(lambda a, b: membrane_spread(a, b, 0.0143, 0.0146), (p, lam))


def test_mattress_file_and_sensor_pipeline(tmp_path):
    """`membrane_m` is saved only when set (old files and dataset settings unchanged), round
    trips, refuses negatives, and the taxel pressure reads through it: same force, wider."""
    assert "membrane_m" not in MattressParams().to_dict()
    mp = MattressParams(membrane_m=0.03)
    mp.save(tmp_path / "m.json")
    assert MattressParams.load(tmp_path / "m.json") == mp
    from pressurepose.errors import UserError

    with pytest.raises(UserError, match="membrane_m must be >= 0"):
        MattressParams(membrane_m=-0.01)
    mat = MatSpec()
    rows, cols = mat.covered_shape
    f = torch.zeros(1, rows * 2, cols * 2, dtype=torch.float64)
    f[0, 60:70, 30:36] = 4e3
    plain = taxel_pressure(f, MattressParams(spread_m=0.0), mat, 2)
    read = taxel_pressure(f, MattressParams(spread_m=0.0, membrane_m=0.03), mat, 2)
    assert float(read.sum()) == pytest.approx(float(plain.sum()), rel=1e-6)
    assert int((read > 0.01 * 4e3).sum()) > int((plain > 0).sum())
