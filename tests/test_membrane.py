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
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.membrane import membrane_spread
from pressurepose.sim.reading import taxel_pressure


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


def _corrugated(depth: float, pitch: float = 0.1024, h: float = 0.0143 / 2):
    """The air tubes' seam depth below their crests at row index r (crest at row 0)."""
    return lambda r: 0.5 * depth * (1 - torch.cos(2 * math.pi * r * h / pitch))


def test_membrane_over_seams_reduces_to_flat_and_reads_nothing_unloaded():
    """Seams of zero depth give the flat model; an unloaded mat on the crests reads nothing; a
    foundation stiffness of 0 with seams is refused."""
    h = 0.0143 / 2
    p = torch.zeros(2, 80, 40, dtype=torch.float64)
    p[:, 20:60, 10:30] = 3e3
    flat = membrane_spread(p, 0.02, h, h)
    np.testing.assert_allclose(membrane_spread(p, 0.02, h, h, _corrugated(0.0), 5e5).numpy(), flat.numpy(), atol=1e-6)
    assert float(membrane_spread(torch.zeros_like(p), 0.02, h, h, _corrugated(0.004), 5e5).abs().max()) == 0
    with pytest.raises(ValueError, match="support_pa_per_m"):
        membrane_spread(p, 0.02, h, h, _corrugated(0.004), 0.0)


def test_membrane_over_seams_makes_bands_that_deeper_loads_fill():
    """A uniform load over the tubes reads more on the crests than in the seams (the mat bridges
    them); the total force is kept to 0.5% on a grid twice the load's width (the mat carries load
    along the crests beyond a grid's sides, where it is lost as at the real mat's edges), the
    reading is mirror-symmetric across the bed, and a heavier load presses the mat
    further into the seams, so its bands are weaker relative to its mean."""
    h, pitch = 0.0143 / 2, 0.1024
    crest, seam = 3 * round(pitch / h), 3 * round(pitch / h) + round(pitch / h / 2)  # rows 42 and 49
    contrast = []
    for load in (1.5e3, 3e3, 6e3):
        p = torch.zeros(1, 128, 108, dtype=torch.float64)
        p[0, 20:108, 39:69] = load
        q = membrane_spread(p, 0.02, h, h, _corrugated(0.004, pitch), 5e5)
        assert float(q.sum()) == pytest.approx(float(p.sum()), rel=0.005)
        np.testing.assert_allclose(q.flip(-1).numpy(), q.numpy(), atol=1e-6 * load)
        middle = q[0, :, 54]
        assert float(middle[crest]) > 1.1 * float(middle[seam])
        contrast.append(float(middle[crest] - middle[seam]) / load)
    assert contrast[0] > contrast[1] > contrast[2]


def test_membrane_over_seams_gradients(monkeypatch):
    """Differentiable in the pressure and the length through the fixed point (a fixed number of
    passes, so the finite differences see the same function)."""
    import pressurepose.sim.membrane as membrane

    monkeypatch.setattr(membrane, "SEAM_TOL_PA", 0.0)
    monkeypatch.setattr(membrane, "SEAM_ITERATIONS", 6)
    h = 0.0143 / 2
    g = torch.Generator().manual_seed(1)
    p = (1e3 + 2e3 * torch.rand(1, 16, 8, generator=g, dtype=torch.float64)).requires_grad_()
    lam = torch.tensor(0.02, dtype=torch.float64, requires_grad=True)
    seams = _corrugated(0.003, pitch=0.05)
    torch.autograd.gradcheck(lambda a, b: membrane.membrane_spread(a, b, h, h, seams, 5e5), (p, lam), atol=1e-5)


def test_air_cells_read_bands_through_the_sensor_pipeline(tmp_path):
    """On a bed with air cells and `membrane_support_pa_per_m`, the taxels over the crests read
    more than those over the seams; the field round trips and is left out of files when 0."""
    assert "membrane_support_pa_per_m" not in MattressParams(membrane_m=0.03).to_dict()
    mat = MatSpec()
    rows, cols = mat.covered_shape
    bed = MattressParams(spread_m=0.0, membrane_m=0.02, cell_pitch_m=0.1024, cell_depth_m=0.004, cell_crest_m=0.0)
    mp = bed.replace(membrane_support_pa_per_m=5e5)
    mp.save(tmp_path / "m.json")
    assert MattressParams.load(tmp_path / "m.json") == mp
    f = torch.zeros(1, rows * 2, cols * 2, dtype=torch.float64)
    f[0, 20:110, 20:40] = 3e3
    flat = taxel_pressure(f, bed, mat, 2)[0].mean(1)
    bands = taxel_pressure(f, mp, mat, 2)[0].mean(1)
    assert float(bands.sum()) == pytest.approx(float(flat.sum()), rel=0.01)
    from pressurepose.maps import cell_centres

    x = cell_centres(mat, 1, covered=True, dtype=torch.float64)[0][:, 0]
    inside = (x > x[15]) & (x < x[50])
    on_crest = inside & (mp.top_height(x) > -0.0005)
    in_seam = inside & (mp.top_height(x) < -0.0035)
    assert on_crest.any() and in_seam.any()
    assert float(bands[on_crest].mean()) > 1.2 * float(bands[in_seam].mean())
    assert float(flat[on_crest].mean()) < 1.05 * float(flat[in_seam].mean())


def test_stiffness_wave_reads_bands_of_the_same_share_in_any_load():
    """Over tubes stiffer on their crests (k (1 + w), w = a cos): no wave gives the flat model; the
    crests read more than the seams by the same share of the load whatever its size (the smooth
    mat presses every row alike, the stiff rows push back harder); the total force is kept; a
    wave reaching 1 is refused."""
    h, pitch = 0.0143 / 2, 0.1024
    crest, seam = 3 * round(pitch / h), 3 * round(pitch / h) + round(pitch / h / 2)
    p = torch.zeros(2, 128, 108, dtype=torch.float64)
    p[0, 20:108, 39:69] = 1e3
    p[1, 20:108, 39:69] = 4e3
    flat = membrane_spread(p, 0.02, h, h)
    np.testing.assert_allclose(
        membrane_spread(p, 0.02, h, h, wave=lambda r: 0 * r).numpy(), flat.numpy(), atol=1e-9 * 4e3
    )
    q = membrane_spread(p, 0.02, h, h, wave=lambda r: 0.4 * torch.cos(2 * math.pi * r * h / pitch))
    np.testing.assert_allclose(q.sum((1, 2)).numpy(), p.sum((1, 2)).numpy(), rtol=1e-3)
    np.testing.assert_allclose(q.flip(-1).numpy(), q.numpy(), atol=1e-6 * 4e3)
    middle = q[:, :, 54]
    share = (middle[:, crest] - middle[:, seam]) / (middle[:, crest] + middle[:, seam])
    assert float(share[0]) > 0.1
    assert float(share[0]) == pytest.approx(float(share[1]), rel=0.01)
    with pytest.raises(ValueError, match="within"):
        membrane_spread(p, 0.02, h, h, wave=lambda r: 1.0 + 0 * r)


def test_stiffness_wave_gradients(monkeypatch):
    """Differentiable in the pressure, the length and the wave's amplitude (gradcheck; a fixed
    number of passes)."""
    import pressurepose.sim.membrane as membrane

    monkeypatch.setattr(membrane, "SEAM_TOL_PA", 0.0)
    monkeypatch.setattr(membrane, "SEAM_ITERATIONS", 6)
    h = 0.0143 / 2
    g = torch.Generator().manual_seed(2)
    p = (1e3 * torch.rand(1, 16, 8, generator=g, dtype=torch.float64)).requires_grad_()
    lam = torch.tensor(0.02, dtype=torch.float64, requires_grad=True)
    amp = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)

    def run(a, b, c):
        return membrane.membrane_spread(a, b, h, h, wave=lambda r: c * torch.cos(2 * math.pi * r * h / 0.05))

    torch.autograd.gradcheck(run, (p, lam, amp), atol=1e-6)


def test_mattress_wave_field_and_pipeline(tmp_path):
    """`membrane_wave` round trips, is left out of files when 0, refuses 1 or more; on air cells
    the taxels over the crests read more than those over the seams, by about the same share for
    a light and a heavy load."""
    from pressurepose.errors import UserError
    from pressurepose.maps import cell_centres

    with pytest.raises(UserError, match="membrane_wave"):
        MattressParams(membrane_wave=1.0)
    with pytest.raises(UserError, match="set one of them"):
        MattressParams(membrane_wave=0.3, membrane_support_pa_per_m=1e5)
    assert "membrane_wave" not in MattressParams(membrane_m=0.02).to_dict()
    mp = MattressParams(
        spread_m=0.0, membrane_m=0.02, membrane_wave=0.4, cell_pitch_m=0.1024, cell_depth_m=0.004, cell_crest_m=0.0
    )
    mp.save(tmp_path / "m.json")
    assert MattressParams.load(tmp_path / "m.json") == mp
    mat = MatSpec()
    rows, cols = mat.covered_shape
    x = cell_centres(mat, 1, covered=True, dtype=torch.float64)[0][:, 0]
    inside = (x > x[15]) & (x < x[50])
    on_crest = inside & (mp.top_height(x) > -0.0005)
    in_seam = inside & (mp.top_height(x) < -0.0035)
    shares = []
    for load in (1e3, 4e3):
        f = torch.zeros(1, rows * 2, cols * 2, dtype=torch.float64)
        f[0, 20:110, 20:40] = load
        image = taxel_pressure(f, mp, mat, 2)[0]
        plain = taxel_pressure(f, mp.replace(membrane_wave=0.0), mat, 2)[0]
        assert float(image.sum()) == pytest.approx(float(plain.sum()), rel=0.01)
        read = image.mean(1)
        shares.append(float(read[on_crest].mean() / read[in_seam].mean()))
    assert shares[0] > 1.2
    assert shares[0] == pytest.approx(shares[1], rel=0.02)
