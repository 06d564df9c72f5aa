"""Real images from other mats: area resampling onto the BT3510 grid, orientation."""

import numpy as np
import pytest

from pressurepose.data.real import orient, resample_to_mat
from pressurepose.mat import MatSpec

MAT = MatSpec()


def naive_resample(img, pr, pc, offset):
    """Per destination taxel, integrate the source image on a fine grid (1/100 taxel)."""
    out = np.zeros((MAT.rows, MAT.cols))
    n = 100
    for i in range(MAT.rows):
        xs = (i + (np.arange(n) + 0.5) / n) * MAT.pitch_row_m
        si = np.floor((xs - offset[0]) / pr).astype(int)
        for j in range(MAT.cols):
            ys = (j + (np.arange(n) + 0.5) / n) * MAT.pitch_col_m
            sj = np.floor((ys - offset[1]) / pc).astype(int)
            ri, cj = np.meshgrid(si, sj, indexing="ij")
            ok = (ri >= 0) & (ri < img.shape[0]) & (cj >= 0) & (cj < img.shape[1])
            out[i, j] = np.where(ok, img[np.clip(ri, 0, img.shape[0] - 1), np.clip(cj, 0, img.shape[1] - 1)], 0).mean()
    return out


def test_resampling_matches_fine_integration_and_keeps_force():
    rng = np.random.default_rng(0)
    img = rng.uniform(0, 50, (150, 60))  # a 1.2 cm mat, smaller than ours
    out = resample_to_mat(img, 0.012, 0.012)
    offset = ((MAT.sensing_length_m - 150 * 0.012) / 2, (MAT.sensing_width_m - 60 * 0.012) / 2)
    # (the fine grid misplaces <= 1% of a taxel per edge)
    np.testing.assert_allclose(out, naive_resample(img, 0.012, 0.012, offset), atol=1.0)
    force_in = img.sum() * 0.012**2
    force_out = out.sum() * MAT.pitch_row_m * MAT.pitch_col_m
    assert force_out == pytest.approx(force_in, rel=1e-12)  # entirely inside our area


def test_same_grid_is_identity_and_uniform_stays_uniform():
    img = np.random.default_rng(1).uniform(0, 100, (64, 27))
    np.testing.assert_allclose(resample_to_mat(img, MAT.pitch_row_m, MAT.pitch_col_m), img, atol=1e-12)
    big = np.full((300, 120), 7.0)  # a larger mat covering ours: every taxel reads 7
    np.testing.assert_allclose(resample_to_mat(big, 0.01, 0.01), 7.0, atol=1e-12)


def test_orientation_and_bad_images():
    img = np.arange(12.0).reshape(4, 3)
    np.testing.assert_array_equal(orient(img, "last"), img[::-1])
    np.testing.assert_array_equal(orient(img, "first", flip_columns=True), img[:, ::-1])
    for bad, msg in ((np.zeros(5), "2-D"), (np.full((3, 3), np.nan), "NaN"), (-np.ones((3, 3)), "negative")):
        with pytest.raises(ValueError, match=msg):
            resample_to_mat(bad, 0.01, 0.01)
    with pytest.raises(ValueError, match="pitches"):
        resample_to_mat(np.ones((3, 3)), 0.0, 0.01)
    with pytest.raises(ValueError, match="head_row"):
        orient(img, "top")


def test_import_pmatdata_writes_predict_ready_images(tmp_path):
    from pathlib import Path

    from pressurepose.cli import main
    from pressurepose.data.pmatdata import read_frame
    from pressurepose.net.inputs import read_pressure_file

    root = Path(__file__).resolve().parent / "data" / "pmatdata"
    out = tmp_path / "p.npz"
    assert main(["import-pmatdata", "--pmatdata", str(root), "--out", str(out), "--mattress", "air"]) == 0
    with np.load(out, allow_pickle=False) as f:
        assert f["pressure_mmhg"].shape == (10, 64, 27) and set(f["posture"].tolist()) == {"left", "right", "supine"}
        # group E's documented rolls (20 / 40 deg on wedges); the other groups have none
        assert sorted(f["body_roll_deg"][f["group"] == "E"].tolist()) == [20.0, 40.0]
        assert (f["body_roll_deg"][f["group"] != "E"] == 0).all()
        # group F's beds, their head raised 0 and 40 deg; the other groups' flat
        assert sorted(f["bed_incline_deg"][f["group"] == "F"].tolist()) == [0.0, 40.0]
        assert (f["bed_incline_deg"][f["group"] != "F"] == 0).all()
        assert (f["mattress"] == "air").all() and (f["height_m"] == 1.75).all() and (f["mass_kg"] == 87).all()
        p, first = f["pressure_mmhg"], f["path"][0]
    assert (p >= 0).all() and (p <= 100).all()
    # Same orientation as the reader (row 0 at the head): the loaded rows follow the raw frame's.
    raw = read_frame(root / first)
    assert np.corrcoef((raw > raw.min() + 30).sum(1), (p[0] > 0).sum(1))[0, 1] > 0.9
    assert read_pressure_file(out).shape == (10, 64, 27)  # predict reads it
    assert main(["import-pmatdata", "--pmatdata", str(root), "--out", str(out), "--groups", "B"]) == 2
