import numpy as np
import pytest
import torch

from pressurepose.mat import MatSpec


def test_defaults_match_reference():
    mat = MatSpec()
    assert mat.shape == (64, 27) and mat.covered_shape == (68, 33)
    assert mat.pitch_row_m == pytest.approx(0.0286)
    assert mat.pitch_col_m == pytest.approx(0.0275, abs=1e-4)
    assert mat.sensing_length_m == pytest.approx(1.8304)
    assert mat.sensing_width_m == pytest.approx(0.7425, abs=1e-4)
    assert mat.mattress_length_m == pytest.approx(1.945, abs=1e-3)
    assert mat.mattress_width_m == pytest.approx(0.9075, abs=1e-4)
    # Sensing area centred: 2 rows at head and foot, 3 columns per side.
    assert (mat.border_rows, mat.border_cols) == (2, 3)
    assert mat.border_head_foot_m == pytest.approx(0.0572)
    assert mat.border_side_m == pytest.approx(0.0825, abs=1e-4)
    (x0, x1), (y0, y1) = mat.mattress_bounds_m
    assert x1 - x0 == pytest.approx(mat.mattress_length_m)
    assert y1 - y0 == pytest.approx(mat.mattress_width_m)


def test_taxel_round_trip_numpy_and_torch():
    mat = MatSpec()
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.1, 2.0, (50, 2))
    assert np.allclose(mat.to_metres(mat.to_taxel(xy)), xy)
    t = torch.tensor(xy, requires_grad=True)
    rc = mat.to_taxel(t)
    rc.sum().backward()
    assert torch.allclose(t.grad[:, 0], torch.full((50,), 1 / mat.pitch_row_m, dtype=torch.float64))


def test_taxel_centres_and_indexing():
    mat = MatSpec()
    centres = mat.taxel_centres_m()
    assert centres.shape == (64, 27, 2)
    # Row 0 is at the head end (small x), column index grows with y.
    assert centres[0, 0, 0] == pytest.approx(mat.pitch_row_m / 2)
    assert centres[63, 0, 0] > centres[0, 0, 0] and centres[0, 26, 1] > centres[0, 0, 1]
    assert np.allclose(
        np.floor(mat.to_taxel(centres)), np.stack(np.meshgrid(np.arange(64), np.arange(27), indexing="ij"), -1)
    )
    covered = mat.taxel_centres_m(covered=True)
    assert covered.shape == (68, 33, 2)
    assert np.allclose(covered[mat.sensing_slice()], centres)


@pytest.mark.parametrize(
    "kwargs",
    [dict(rows=0), dict(pitch_row_m=-1.0), dict(covered_rows=65), dict(cols=2.5), dict(pitch_col_m=float("nan"))],
)
def test_bad_mat_spec(kwargs):
    with pytest.raises(ValueError, match="MatSpec"):
        MatSpec(**kwargs)


def test_bad_coordinate_shape():
    with pytest.raises(ValueError, match=r"xy_m must have shape \(\.\.\., 2\)"):
        MatSpec().to_taxel(np.zeros((4, 3)))
