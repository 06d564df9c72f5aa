"""Realism metrics against hand-computed cases; `pressurepose realism` on a tiny folder."""

import numpy as np
import pytest

from pressurepose.cli import main
from pressurepose.eval import realism as R


def test_coverage_by_hand():
    img = np.zeros((10, 3))
    img[2] = [50, 40, 10]  # 100
    img[3] = [0, 0.5, 0]  # 0.5 < 1% of 200.5
    img[5] = [0, 100, 0]  # 100
    # rows 2..5 span 4 rows, 2 carry >= 1%: coverage 0.5
    assert R.coverage(img) == pytest.approx(0.5)
    assert R.coverage(np.zeros((4, 4))) == 0.0


def test_extent_and_high_pressure_by_hand():
    img = np.zeros((10, 3))
    img[2] = [50, 40, 10]  # 100
    img[3] = [0, 0.1, 0]  # 0.1 < 0.2% of 200.1: not counted
    img[6] = [0, 100, 0]  # 100
    img[8] = [0.1, 0, 0]  # 0.1: not counted
    # rows 2..6 hold >= 0.2%: 5 rows x 0.1 m over a 2 m subject
    assert R.extent_of_height(img, 2.0, 0.1) == pytest.approx(0.25)
    assert R.extent_of_height(np.zeros((4, 4)), 1.0, 0.1) == 0.0
    # the loaded taxels 0.1, 0.1, 10, 40, 50, 100: the 99th percentile by linear interpolation
    # lies 0.95 of the way from 50 to 100
    assert R.high_pressure(img) == pytest.approx(97.5)
    assert R.high_pressure(img, 0.5) == pytest.approx(25.0)
    assert R.high_pressure(np.zeros((2, 2))) == 0.0


def test_reading_floor_and_read_with_floor_by_hand():
    a = np.zeros((2, 2, 3))
    a[0] = [[1.0, 4.0, 0.0], [5.0, 0.0, 0.0]]  # lowest loaded 1
    a[1] = [[0.0, 3.0, 6.0], [0.0, 0.0, 1.0]]  # lowest loaded 1
    b = np.concatenate([a, np.full((1, 2, 3), 2.0)])  # a third frame, lowest 2
    assert R.reading_floor(a) == 1.0 and R.reading_floor(b) == 1.0
    assert R.reading_floor(b[1:]) == pytest.approx(1.5)  # the median of 1 and 2
    assert R.reading_floor(np.zeros((1, 2, 2))) == 0.0
    got = R.read_with_floor(a, 3.5)
    # frame 0: 1 zeroed, 4 and 5 kept and scaled to the force 10: x 10/9
    assert got[0] == pytest.approx(np.array([[0.0, 40 / 9, 0.0], [50 / 9, 0.0, 0.0]]))
    # frame 1: 3 and 1 zeroed, 6 carries the force 10
    assert got[1] == pytest.approx(np.array([[0.0, 0.0, 10.0], [0.0, 0.0, 0.0]]))
    assert got.sum((1, 2)) == pytest.approx(a.sum((1, 2)))
    # a frame with nothing at or above the floor is left as it was (no division by zero)
    low = np.full((1, 2, 2), 0.5)
    assert R.read_with_floor(low, 3.0) == pytest.approx(low)
    assert R.read_with_floor(a, 0.0) == pytest.approx(a)


def test_profile_similarity_by_hand():
    a = np.array([0.0, 0.5, 0.5, 0.0, 0.0])
    b = np.array([0.0, 0.0, 0.5, 0.5, 0.0])
    # unshifted overlap: 1 - (0.5 + 0 + 0.5) / 2 = 0.5; shifted by -1: identical
    sim, shift = R.profile_similarity(a, b, 0)
    assert sim == pytest.approx(0.5) and shift == 0
    sim, shift = R.profile_similarity(a, b, 2)
    assert sim == pytest.approx(1.0) and shift == -1
    # disjoint profiles score 0; scale does not matter
    assert R.profile_similarity(np.array([1.0, 0, 0]), np.array([0, 0, 7.0]), 0)[0] == pytest.approx(0.0)
    # shifted along either axis of an image, zero-filled
    img = np.arange(6.0).reshape(2, 3)
    np.testing.assert_array_equal(R.shifted(img, 1, axis=1), [[0, 0, 1], [0, 3, 4]])
    np.testing.assert_array_equal(R.shifted(img, -1, axis=0), [[3, 4, 5], [0, 0, 0]])
    np.testing.assert_array_equal(R.shifted(img, 5, axis=0), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="same length"):
        R.profile_similarity(a, b[:3], 1)


def test_region_shares_by_hand():
    """A 1 m tall subject on a 0.1 m grid: the head top at row 1, so row r's centre lies at
    (r - 1 + 0.5) x 0.1 of the height."""
    img = np.zeros((12, 9))
    img[1, 4] = 10.0  # frac 0.05: head
    img[4, 4] = 20.0  # frac 0.35: back
    img[4, 0] = 5.0  # frac 0.35, 0.4 m from the centre column (> 0.09 m): arms
    img[10, 4] = 15.0  # frac 0.95: heels
    s = R.region_shares(img, 1.0, 0.1, 0.1)
    assert s["head"] == pytest.approx(0.2)
    assert s["back"] == pytest.approx(0.4)
    assert s["arms"] == pytest.approx(0.1)
    assert s["heels"] == pytest.approx(0.3)
    assert sum(s.values()) == pytest.approx(1.0)


def test_summarise_and_compare_by_hand():
    a = np.zeros((2, 4, 3))
    a[0, 1, 1] = 10.0
    a[0, 2, 1] = 30.0
    a[1, 1, 1] = 20.0
    s = R.summarise(a, np.array([1.0, 1.0]), 0.5, 0.5)
    assert s.area_m2 == pytest.approx(np.median([2 * 0.25, 1 * 0.25]))
    assert s.mean_mmhg == pytest.approx(np.median([20.0, 20.0]))
    assert s.peak_mmhg == pytest.approx(25.0)  # median of 30 and 20
    # 99th percentiles: frame 0 of (10, 30) 29.8, frame 1 of (20) 20
    assert s.p99_mmhg == pytest.approx(np.median([29.8, 20.0]))
    # lengths: frame 0 two rows, frame 1 one row, x 0.5 m over 1 m
    assert s.extent == pytest.approx(np.median([1.0, 0.5]))
    # mean of unit-sum row profiles: frame 0 (0, .25, .75, 0), frame 1 (0, 1, 0, 0)
    np.testing.assert_allclose(s.along, [0, 0.625, 0.375, 0])
    c = R.compare(s, s)
    assert (
        c.along == pytest.approx(1.0) and c.area_ratio == pytest.approx(1.0) and c.coverage_ratio == pytest.approx(1.0)
    )
    with pytest.raises(ValueError, match="finite"):
        R.summarise(np.full((1, 4, 3), np.nan), np.ones(1), 0.5, 0.5)
    with pytest.raises(ValueError, match="carry no load"):
        R.summarise(np.zeros((1, 4, 3)), np.ones(1), 0.5, 0.5)


def test_band_ratios_against_a_loop():
    rng = np.random.default_rng(0)
    images = rng.uniform(0, 10, (3, 64, 27)) * (rng.uniform(size=(3, 64, 1)) > 0.2)
    got = R.band_ratios(images)
    for n in range(3):
        rows = images[n].sum(1) / images[n].sum()
        for i in range(64):
            if i < 2 or i > 61:
                assert np.isnan(got[n, i])
                continue
            avg = sum(rows[j] for j in range(i - 2, i + 3)) / 5
            want = rows[i] / avg - 1 if avg >= R.BAND_MIN_SHARE else np.nan
            np.testing.assert_allclose(got[n, i], want, rtol=1e-12, equal_nan=True)


def test_fit_bands_by_hand():
    """Rows modulated by 1 + a cos(2 pi (x - c) / T): the fit finds T and c, and the amplitude a
    times (1 - g), g the 5-row average's gain at that period (to first order in a)."""
    pitch, period, crest, a = 0.0286, 0.1024, 0.013, 0.02
    x = (np.arange(64) + 0.5) * pitch
    rows = 1 + a * np.cos(2 * np.pi * (x - crest) / period)
    images = np.repeat(rows[None, :, None], 27, axis=2).repeat(2, axis=0)
    b = R.fit_bands(images, pitch)
    assert b.period_m == pytest.approx(period, abs=4e-4)
    assert b.crest_m == pytest.approx(crest, abs=1e-3)
    gain = np.mean([np.cos(2 * np.pi * k * pitch / period) for k in range(-2, 3)])
    assert b.amplitude == pytest.approx(a * (1 - gain), rel=0.05)
    assert b.r2 > 0.99
    # A given period is used as it is; unbanded frames have no amplitude.
    assert R.fit_bands(images, pitch, 0.11).period_m == 0.11
    assert R.fit_bands(np.ones((2, 64, 27)), pitch).amplitude < 1e-12
    with pytest.raises(ValueError, match="too few loaded rows"):
        R.fit_bands(np.pad(np.ones((1, 2, 27)), ((0, 0), (0, 62), (0, 0))), pitch)  # load in rows 0-1 only


def _copy_frames(tmp_path, select):
    """A folder in PmatData's layout holding the packaged frames whose index rows `select` picks."""
    import csv
    import shutil

    from pressurepose.samples import pmatdata_dir

    src = pmatdata_dir()
    with (src / "index.csv").open() as fh:
        records = list(csv.DictReader(fh))
    keep = [r for r in records if select(r)]
    for r in keep:
        (tmp_path / r["file"]).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(src / r["file"], tmp_path / r["file"])
    with (tmp_path / "index.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(records[0]))
        w.writeheader()
        w.writerows(keep)
    return keep


def _tiny_folder(tmp_path, frame_text=None):
    """Two subjects' supine, left and right frames copied from the packaged PmatData."""
    keep = _copy_frames(
        tmp_path,
        lambda r: (
            r["subject"] in ("1", "5")
            and r["mattress"] == "sponge"
            and (r["group"] in ("C", "D") or (r["group"] == "B" and r["index"] == "1"))
        ),
    )
    if frame_text is not None:
        (tmp_path / keep[0]["file"]).write_text(frame_text)
    return tmp_path, keep


def test_realism_command_on_a_tiny_folder(tmp_path, capsys):
    folder, _ = _tiny_folder(tmp_path / "real")
    assert main(["realism", "--real", str(folder), "--out", str(tmp_path / "out")]) == 0
    import json

    record = json.loads((tmp_path / "out" / "report.json").read_text())
    rows = {(r["posture"], r["mattress"]): r for r in record["rows"]}
    assert set(rows) == {("supine", "sponge"), ("left", "sponge"), ("right", "sponge")}
    for r in rows.values():
        # one simulated body per real frame (placement "real"): 2 supine, 3 per side and subject
        assert r["simulated_bodies"] == r["real"]["frames"] == (2 if r["posture"] == "supine" else 6)
        assert 0 <= r["still_moving"] <= r["simulated_bodies"]  # ended by the re-posings' cap
        assert 0 < r["comparison"]["along"] <= 1 and 0 < r["comparison"]["across"] <= 1
        assert abs(sum(r["simulated"]["regions"].values()) - 1) < 1e-2
        # by default the images as the generator writes them (the sensor's own floor), not re-read
        assert r["floor_mmhg"] == 0.0
        for side in ("simulated", "real"):  # the force along the body from the head end: shares
            head_end = np.array(r[side]["head_end"])
            assert head_end.shape == (R.HEAD_END_BINS,) and (head_end >= 0).all() and head_end.sum() <= 1 + 1e-3
    assert (tmp_path / "out" / "realism_left_sponge.png").stat().st_size > 0
    report = (tmp_path / "out" / "report.md").read_text()
    assert "Ceiling" in report and "the sensor's own floor" in report
    assert "Where the load lies along the body" in report


@pytest.mark.parametrize("case", ["no index", "short frame", "non-finite"])
def test_realism_bad_input_is_one_line(tmp_path, capsys, case):
    if case == "no index":
        folder = tmp_path / "empty"
        folder.mkdir()
        needle = "index.csv"
    else:
        text = "1 " * 27 + "\n"
        text = text * 10 if case == "short frame" else ("nan " + "1 " * 26 + "\n") * 64
        folder, keep = _tiny_folder(tmp_path / "real", frame_text=text)
        needle = keep[0]["file"].split("/")[-1]
    assert main(["realism", "--real", str(folder), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err
    assert not (tmp_path / "out" / "report.md").exists()


def test_frame_placement_by_hand():
    from pressurepose.commands.realism import frame_placement

    img = np.zeros((1, 10, 5))
    img[0, 2, 1] = 1.0
    img[0, 6, 3] = 1.0  # centre at row 4.5, col 2.5; the axis from (2, 1) to (6, 3)
    centre, angle = frame_placement(img, 0.1, 0.2)
    np.testing.assert_allclose(centre[0], [0.45, 0.5])
    assert angle[0] == pytest.approx(np.arctan2(0.4, 0.4))  # dx = 0.4 m, dy = 0.4 m: 45 deg


def test_area_by_part_of_length_by_hand():
    """Rows 5-14 of a 20 x 6 image carry the load, row r with (r - 4) loaded taxels capped at 6
    (rows 5-10: 1-6 taxels, rows 11-14: 6); a faint row 16 below the share is outside the
    length. Five parts of 2 rows each: (1+2, 3+4, 5+6, 6+6, 6+6). Empty image: zeros."""
    img = np.zeros((20, 6))
    for r in range(5, 15):
        img[r, : min(r - 4, 6)] = 10.0
    img[16, 0] = 1e-4  # < 0.2% of the force
    np.testing.assert_array_equal(R.area_by_part_of_length(img, parts=5), [3, 7, 11, 12, 12])
    # ten parts of one row each: the taxel counts themselves
    np.testing.assert_array_equal(R.area_by_part_of_length(img), [1, 2, 3, 4, 5, 6, 6, 6, 6, 6])
    np.testing.assert_array_equal(R.area_by_part_of_length(np.zeros((20, 6))), np.zeros(10))
    s = R.summarise(np.stack([img, img]), np.array([1.7, 1.7]), 0.0286, 0.0286)
    np.testing.assert_allclose(s.area_tenths, [1, 2, 3, 4, 5, 6, 6, 6, 6, 6])


def test_force_from_head_end_by_hand():
    """Rows 3-6 of a 20 x 4 image carry forces 1, 1, 2, 4 (a faint row 1 below the share does not
    start the load). With a 0.025 m pitch and a 1 m subject each 0.05 slice holds two rows: (1 + 1,
    2 + 4) / 8; with a 2 m subject each row is 0.0125 of the height, four rows per slice: all in the
    first. Rows past the last slice do not count (the shares then add to less than 1); an empty
    image gives zeros; the report's set carries the mean over frames."""
    img = np.zeros((20, 4))
    for r, f in zip(range(3, 7), (1.0, 1.0, 2.0, 4.0)):
        img[r, 0] = f
    img[1, 0] = 1e-4  # < 0.2% of the force
    total = img.sum()
    out = R.force_from_head_end(img, 1.0, 0.025, bins=4)
    np.testing.assert_allclose(out, np.array([2.0, 6.0, 0.0, 0.0]) / total)
    np.testing.assert_allclose(R.force_from_head_end(img, 2.0, 0.025, bins=2), np.array([8.0, 0.0]) / total)
    cut = R.force_from_head_end(img, 1.0, 0.025, bins=1)  # only the first slice, rows 3-4
    np.testing.assert_allclose(cut, [2.0 / total])
    np.testing.assert_array_equal(R.force_from_head_end(np.zeros((20, 4)), 1.0, 0.025), np.zeros(R.HEAD_END_BINS))
    s = R.summarise(np.stack([img, img]), np.array([1.0, 1.0]), 0.025, 0.025)
    np.testing.assert_allclose(s.head_end[:2], np.array([2.0, 6.0]) / total)


def test_real_frames_are_read_once(tmp_path):
    """PmatData files subject 4's frames again as subject 8's: the report's flat and raised sets
    read each frame once (the lower-numbered subject's copy)."""
    from pressurepose.commands.realism import load_real
    from pressurepose.commands.realism_raised import load_raised

    def s4_s8(r):
        return r["subject"] in ("4", "8") and r["mattress"] == "sponge" and r["index"] == "1" and r["group"] in "CF"

    keep = _copy_frames(tmp_path, s4_s8)
    assert [(r["group"], r["subject"]) for r in keep] == [("C", "4"), ("F", "4"), ("C", "8"), ("F", "8")]
    for a, b in ((0, 2), (1, 3)):  # each of subject 8's frames is subject 4's file again
        assert (tmp_path / keep[a]["file"]).read_bytes() == (tmp_path / keep[b]["file"]).read_bytes()
    real, _ = load_real(tmp_path, 20.0)
    images, _, ids = real[("right", "sponge")]
    assert images.shape == (1, 64, 27) and ids.tolist() == [4]
    (raised,) = load_raised(tmp_path, 20.0).values()
    assert raised[0].shape == (1, 64, 27)


def _first(n: int, **match):
    """An index-row selector for `_copy_frames`: the first n rows whose fields equal `match`'s."""
    picked = []

    def select(r):
        if len(picked) < n and all(r[k] == v for k, v in match.items()):
            picked.append(r)
            return True
        return False

    return select


def test_raised_rows_on_two_frames(tmp_path):
    """The report's raised beds (`commands.realism_raised`) on two PmatData group F frames (30
    deg, sponge): one body per frame, its hips moved to the frame's centre of pressure, the
    measures in range, and the markdown's table."""
    from pressurepose.commands.realism import RealismConfig
    from pressurepose.commands.realism_raised import load_raised, raised_markdown, raised_rows

    assert len(_copy_frames(tmp_path, _first(2, group="F", bed_incline_deg="30", mattress="sponge"))) == 2
    real = load_raised(tmp_path, 20.0)
    assert list(real) == [(30.0, "sponge")] and real[(30.0, "sponge")][0].shape == (2, 64, 27)
    (row,) = raised_rows(real, RealismConfig(out=tmp_path / "out", real=tmp_path))
    assert row["frames"] == row["simulated_bodies"] == 2 and not row["rejected"]
    assert 0 < row["comparison"]["along"] <= 1 and 0 < row["comparison"]["across"] <= 1
    assert 0 < row["raised_share"]["simulated"] < 1 and 0 < row["raised_share"]["real"] < 1
    assert 0.0 <= row["hips_past_hinge_m"] <= 0.6
    table = "\n".join(raised_markdown([row]))
    assert "Raised head of the bed" in table and "| 30 | sponge |" in table and "2 of 2" in table


def test_tilted_rows_on_two_frames(tmp_path):
    """The report's tilted bodies (`commands.realism_tilted`) on two PmatData group E frames (40
    deg to the right on two wedges, sponge): one twin per frame, turned by the documented roll on
    the wedge, resting turned; the measures in range; a reader's rolls give the turned shares; the
    markdown's table."""
    from pressurepose.commands.realism import RealismConfig
    from pressurepose.commands.realism_tilted import load_tilted, tilted_markdown, tilted_rows

    assert len(_copy_frames(tmp_path, _first(2, group="E", index="2", mattress="sponge"))) == 2
    real = load_tilted(tmp_path, 20.0)
    assert list(real) == [(40.0, "sponge")] and real[(40.0, "sponge")][0].shape == (2, 64, 27)

    def reader(images):  # the first image read turned toward the right, the second not
        return np.array([30.0, -5.0])[: len(images)]

    (row,) = tilted_rows(real, RealismConfig(out=tmp_path / "out", real=tmp_path), reader)
    assert row["frames"] == row["simulated_bodies"] == 2 and not row["rejected"]
    assert abs(row["rest_roll_deg"] - 40.0) < 5.0  # held at its roll by the wedge (without: ~36 deg)
    assert 0 < row["comparison"]["along"] <= 1 and 0 < row["comparison"]["across"] <= 1
    assert row["comparison"]["area_ratio"] > 0
    assert row["turned"] == {"real": 0.5, "simulated": 0.5}
    table = "\n".join(tilted_markdown([row]))
    assert "Tilted bodies" in table and "| +40 | sponge |" in table and "2 of 2 | 50% / 50% |" in table
    assert tilted_markdown([]) == []


def test_realism_refuses_a_group_e_row_without_its_roll_before_simulating(tmp_path, capsys):
    """An index whose group E rows carry no roll (e.g. written before session 59): one line naming
    the file and the way out, nothing written."""
    import csv

    keep = _copy_frames(
        tmp_path / "real", lambda r: r["subject"] == "1" and r["mattress"] == "sponge" and r["group"] in ("B", "E")
    )
    rows = [{**r, "body_roll_deg": "0" if r["group"] == "E" else r["body_roll_deg"]} for r in keep]
    with (tmp_path / "real" / "index.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    assert main(["realism", "--real", str(tmp_path / "real"), "--out", str(tmp_path / "out"), "--no-raised"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "body_roll_deg" in err[0] and "--no-tilted" in err[0] and "Matrix_Sponge_E" in err[0]
    assert not (tmp_path / "out").exists()
