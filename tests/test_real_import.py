"""Importers of real datasets: the original PressurePose real set (Python 2 pickles written here
byte by byte as Python 2 + numpy 1 wrote them) and SLP pressure maps (arrays + calibration)."""

import pickle
import struct
import subprocess
import sys

import numpy as np
import pytest

from pressurepose.data.importer import load_restricted
from pressurepose.data.pressurepose_real import BEDSHEET_FACTOR, TAXEL_AREA_M2, CloudFrame, import_pressurepose_real
from pressurepose.data.slp import frame_to_mat, import_slp
from pressurepose.mat import MatSpec
from pressurepose.sim.mattress import GRAVITY_M_S2, MMHG_PA

MAT = MatSpec()


# --- a Python 2 protocol-2 pickler (str = bytes, numpy 1 array layout) -----------------------
def _py2(obj) -> bytes:
    if isinstance(obj, dict):
        return b"}(" + b"".join(_py2(k) + _py2(v) for k, v in obj.items()) + b"u"
    if isinstance(obj, list):
        return b"](" + b"".join(_py2(v) for v in obj) + b"e"
    if isinstance(obj, tuple):
        return b"(" + b"".join(_py2(v) for v in obj) + b"t"
    if isinstance(obj, (str, bytes)):  # Python 2 str: raw bytes
        raw = obj.encode("latin1") if isinstance(obj, str) else obj
        return (b"U" + bytes([len(raw)]) if len(raw) < 256 else b"T" + struct.pack("<i", len(raw))) + raw
    if isinstance(obj, bool):
        return b"\x88" if obj else b"\x89"
    if obj is None:
        return b"N"
    if isinstance(obj, int):
        return b"J" + struct.pack("<i", obj)
    if isinstance(obj, float):
        return b"G" + struct.pack(">d", obj)
    if isinstance(obj, np.ndarray):
        a = np.ascontiguousarray(obj, dtype="<f8")
        dtype = b"cnumpy\ndtype\n" + _py2(("f8", 0, 1)) + b"R" + _py2((3, "<", None, None, None, -1, -1, 0)) + b"b"
        state = b"(" + _py2(1) + _py2(tuple(a.shape)) + dtype + _py2(False) + _py2(a.tobytes()) + b"t"
        return (
            b"cnumpy.core.multiarray\n_reconstruct\n(cnumpy\nndarray\n" + _py2((0,)) + _py2("b") + b"tR" + state + b"b"
        )
    raise TypeError(type(obj))


def py2_pickle(obj) -> bytes:
    return b"\x80\x02" + _py2(obj) + b"."


def test_py2_pickles_load_through_the_restricted_unpickler():
    a = np.arange(6.0).reshape(2, 3) - 2.5
    doc = load_restricted(py2_pickle({"images": [a, a * 2], "gender": "f", "n": 3, "x": 1.5}))
    assert set(doc) == {"images", "gender", "n", "x"} and doc["gender"] == "f" and doc["n"] == 3
    np.testing.assert_array_equal(doc["images"][1], a * 2)
    # Python 3's own protocol-2 pickles of the same content load the same way.
    doc3 = load_restricted(pickle.dumps({"images": [a]}, protocol=2))
    np.testing.assert_array_equal(doc3["images"][0], a)


# --- PressurePose real -----------------------------------------------------------------------
def _frame(rng, head=True):
    """A (64, 27) image with a bright marker in rows 0-2 (the head) and a body below."""
    img = np.zeros((64, 27))
    img[10:50, 8:19] = rng.uniform(1, 5, (40, 11))
    if head:
        img[0:3, 10:17] = 20.0
    return img


def _write_participant(folder, rng, gender="f", height_in=65.0, weight_lbs=150.0, n=3, flat=True, **overrides):
    folder.mkdir(parents=True)
    info = {
        "gender": gender,
        "height_in": height_in,
        "weight_lbs": weight_lbs,
        "prescribed_pose_type": ["supine"] * n,
        "p_select_pose_type": ["x"],
    }
    (folder / "participant_info_red.p").write_bytes(py2_pickle(info))
    images = [_frame(rng).ravel() if flat else _frame(rng) for _ in range(n)]
    clouds = [rng.uniform([0.2, 0.1, -0.3], [1.7, 0.7, 0.07], (50 + 10 * i, 3)) for i in range(n)]
    data = {
        "images": images,
        "pc": clouds,
        "pose_type": [f"pose{i}" for i in range(n)],
        "pmat_corners": [np.zeros((4, 2))] * n,
        "RGB": [np.zeros((2, 2))] * n,
        "depth": [np.zeros((2, 2))] * n,
    }
    data.update(overrides)
    (folder / "prescribed.p").write_bytes(py2_pickle(data))
    return images, clouds


def test_import_pressurepose_real_converts_units_orientation_and_clouds(tmp_path):
    rng = np.random.default_rng(0)
    root = tmp_path / "real"
    img_a, pc_a = _write_participant(root / "S103", rng, "f", 65.0, 150.0, n=3)
    img_b, pc_b = _write_participant(root / "S104", rng, "m", 72.0, 200.0, n=2, flat=False)
    out = tmp_path / "r.npz"
    res = import_pressurepose_real(root, out, pose_sets=("prescribed",))
    assert res == {"frames": 5, "participants": 2, "points": sum(len(c) for c in pc_a + pc_b), "out": str(out)}
    with np.load(out, allow_pickle=False) as f:
        d = {k: f[k] for k in f.files}
    assert d["pressure_mmhg"].shape == (5, 64, 27) and d["pressure_mmhg"].dtype == np.float32
    assert (
        d["subject"].tolist() == ["S103"] * 3 + ["S104"] * 2 and d["gender"].tolist() == ["female"] * 3 + ["male"] * 2
    )
    assert d["pose_type"].tolist() == ["pose0", "pose1", "pose2", "pose0", "pose1"] and (d["bed_angle_deg"] == 0).all()
    np.testing.assert_allclose(d["height_m"], [65 * 0.0254] * 3 + [72 * 0.0254] * 2)
    np.testing.assert_allclose(d["mass_kg"], [150 * 0.45359237] * 3 + [200 * 0.45359237] * 2)
    # Stored orientation kept (row 0 at the head): the marker is in rows 0-2; x4, clipped at 100.
    for k, img in enumerate([im.reshape(64, 27) for im in img_a + img_b]):
        np.testing.assert_allclose(d["pressure_mmhg"][k], np.minimum(img * BEDSHEET_FACTOR, 100), rtol=1e-6)
        assert d["pressure_mmhg"][k][:3].max() == 80.0
    # Clouds: the release's frame (axis 0 from the foot, axis 2 down) -> ours, exactly.
    off = d["cloud_offsets"]
    assert off[0] == 0 and off[-1] == len(d["cloud_points"]) and np.diff(off).tolist() == [50, 60, 70, 50, 60]
    for k, pc in enumerate(pc_a + pc_b):
        got = d["cloud_points"][off[k] : off[k + 1]]
        want = np.stack([64 * 0.0286 * 1.04 - pc[:, 0], pc[:, 1], 0.075 - pc[:, 2]], 1)
        np.testing.assert_allclose(got, want, atol=1e-6)
        assert (got[:, 2] > -0.001).all()  # points above the bed stay above z = 0
    # A single participant folder works too, and "weight" makes sum p A = m g.
    import_pressurepose_real(
        root / "S103", out, pose_sets=("prescribed",), pressure="weight", cloud_frame=CloudFrame(2.0, 0.1, 0.0)
    )
    with np.load(out, allow_pickle=False) as f:
        p, m = f["pressure_mmhg"].astype(float), f["mass_kg"]
        np.testing.assert_allclose(
            f["cloud_points"][:50], np.stack([2.0 - pc_a[0][:, 0], pc_a[0][:, 1] - 0.1, -pc_a[0][:, 2]], 1), atol=1e-6
        )
    assert p.max() < 100  # unclipped here: exact force balance
    np.testing.assert_allclose(p.sum((1, 2)) * TAXEL_AREA_M2 * MMHG_PA, m * GRAVITY_M_S2, rtol=1e-5)


@pytest.mark.parametrize(
    "case, message",
    [
        ("truncated", "not a readable pickle"),
        ("missing_pc", "missing keys \\['pc'\\]"),
        ("wrong_shape", "image 1 is not 64 x 27"),
        ("bad_cloud", "point cloud 0 must be a non-empty \\(P, 3\\)"),
        ("count", "'pc' has 1 entries but 'images' has 2"),
        ("info_units", "not plausible"),
        ("forbidden", "refusing to load the global os.system"),
    ],
)
def test_malformed_pressurepose_real_files_fail_with_one_line(tmp_path, case, message, capsys):
    rng = np.random.default_rng(1)
    folder = tmp_path / "S103"
    img = _frame(rng).ravel()
    pc = rng.uniform(0, 1, (10, 3))
    if case == "info_units":
        _write_participant(folder, rng, height_in=170.0, n=2)  # centimetres in an inches field
    else:
        _write_participant(folder, rng, n=2)
    data_file = folder / "prescribed.p"
    marker = tmp_path / "pwned"
    if case == "truncated":
        data_file.write_bytes(data_file.read_bytes()[:200])
    elif case == "missing_pc":
        data_file.write_bytes(py2_pickle({"images": [img, img]}))
    elif case == "wrong_shape":
        data_file.write_bytes(py2_pickle({"images": [img, img[:100]], "pc": [pc, pc]}))
    elif case == "bad_cloud":
        data_file.write_bytes(py2_pickle({"images": [img, img], "pc": [pc[:, :2], pc]}))
    elif case == "count":
        data_file.write_bytes(py2_pickle({"images": [img, img], "pc": [pc]}))
    elif case == "forbidden":  # would create a file if it ran
        data_file.write_bytes(b"\x80\x02cos\nsystem\n" + _py2((f"touch {marker}",)) + b"R.")
    out = tmp_path / "o.npz"
    with pytest.raises(ValueError, match=message) as err:
        import_pressurepose_real(folder, out)
    assert "\n" not in str(err.value) and not out.exists() and not marker.exists()
    from pressurepose.cli import main

    assert main(["import-pressurepose-real", str(folder), "--out", str(out)]) == 2
    captured = capsys.readouterr().err.strip()
    assert captured.count("\n") == 0 and "Traceback" not in captured and not out.exists()


def test_import_pressurepose_real_cli_and_predict_reads_it(tmp_path):
    rng = np.random.default_rng(2)
    _write_participant(tmp_path / "real" / "S107", rng, n=2)
    out = tmp_path / "r.npz"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "pressurepose.cli",
            "import-pressurepose-real",
            str(tmp_path / "real"),
            "--out",
            str(out),
            "--pose-sets",
            "prescribed",
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0 and "2 frames of 1 participants" in r.stdout
    from pressurepose.net.inputs import read_pressure_file

    assert read_pressure_file(out).shape == (2, 64, 27)
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "pressurepose.cli",
            "import-pressurepose-real",
            str(tmp_path / "none"),
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "no folder" in r.stderr and "Traceback" not in r.stderr


# --- SLP ---------------------------------------------------------------------------------------
def _write_slp(root, rng, subjects=(1, 2), frames=3, physique=None):
    root.mkdir(parents=True)
    phys = physique if physique is not None else np.array([[0, 165.0, 60.0, 90, 70], [1, 182.0, 85.0, 100, 90]])
    np.save(root / "physiqueData.npy", phys)
    maps = {}
    for s in subjects:
        folder = root / f"{s:05d}"
        folder.mkdir()
        np.save(folder / "PMcali.npy", rng.uniform(0.5, 2.0, (3, 45)))
        for cover in ("uncover", "cover1"):
            (folder / "PMarray" / cover).mkdir(parents=True)
            for k in range(1, frames + 1):
                pm = np.zeros((192, 84))
                pm[40:150, 25:60] = rng.uniform(1, 30, (110, 35))  # the body, well inside our area
                pm[6:12, 35:50] = 200.0  # a marker at the head end (row 0 = head as stored)
                np.save(folder / "PMarray" / cover / f"{k:06d}.npy", pm)
                maps[(s, cover, k)] = pm
    return maps


def test_import_slp_resamples_with_force_kept_and_head_at_row_0(tmp_path):
    rng = np.random.default_rng(3)
    root = tmp_path / "danaLab"
    maps = _write_slp(root, rng)
    out = tmp_path / "slp.npz"
    res = import_slp(root, out, covers=("uncover", "cover1"), calibration="pmcali")
    assert res == {"frames": 12, "subjects": 2, "out": str(out)}
    with np.load(out, allow_pickle=False) as f:
        d = {k: f[k] for k in f.files}
    assert d["pressure_mmhg"].shape == (12, 64, 27)
    assert d["gender"].tolist() == ["female"] * 6 + ["male"] * 6
    np.testing.assert_allclose(d["height_m"], [1.65] * 6 + [1.82] * 6)
    np.testing.assert_allclose(d["mass_kg"], [60.0] * 6 + [85.0] * 6)
    assert d["cover"].tolist()[:6] == ["uncover"] * 3 + ["cover1"] * 3 and d["frame"].tolist()[:3] == [1, 2, 3]
    for i in range(12):
        s, cover, k = int(d["subject"][i]), str(d["cover"][i]), int(d["frame"][i])
        p = d["pressure_mmhg"][i].astype(float)
        # Head marker (rows 6-12 cm of 192; after centring, our rows 0-2) lands at the head end.
        assert np.argmax(p.max(1)) <= 2
        # pmcali: PMarray x the frame's factor (kPa) -> mmHg, resampled with the force kept (the whole
        # load lies inside our area), then clipped at 100 mmHg.
        cali = np.load(root / f"{s:05d}" / "PMcali.npy")[["uncover", "cover1", "cover2"].index(cover), k - 1]
        src = maps[(s, cover, k)] * cali * 1000 / MMHG_PA
        free = frame_to_mat(maps[(s, cover, k)], 0.0, "pmcali", cali, mat=MatSpec(max_pressure_mmhg=1e12))
        assert free.sum() * MAT.pitch_row_m * MAT.pitch_col_m == pytest.approx(src.sum() * 0.01**2, rel=1e-9)
        np.testing.assert_allclose(p, np.minimum(free, 100.0), rtol=1e-6)
        assert p.max() == 100.0  # the marker (>= 750 mmHg) is clipped
    # Weight calibration: the summed force on our grid is the subject's weight (before the 100 mmHg clip).
    import_slp(root, out, covers=("uncover",), subjects=[2], calibration="weight")
    with np.load(out, allow_pickle=False) as f:
        p = f["pressure_mmhg"].astype(float)
        assert f["subject"].tolist() == [2, 2, 2]
    force = p.sum((1, 2)) * MAT.pitch_row_m * MAT.pitch_col_m * MMHG_PA
    assert (force <= 85.0 * GRAVITY_M_S2 * (1 + 1e-6)).all() and (force > 0.5 * 85.0 * GRAVITY_M_S2).all()
    free = frame_to_mat(maps[(2, "uncover", 1)], 85.0, "weight", mat=MatSpec(max_pressure_mmhg=1e12))
    assert free.sum() * MAT.pitch_row_m * MAT.pitch_col_m * MMHG_PA == pytest.approx(85.0 * GRAVITY_M_S2, rel=1e-12)
    # head_row="last" turns the image over: the marker goes to the foot end.
    import_slp(root, out, covers=("uncover",), subjects=[1], head_row="last")
    with np.load(out, allow_pickle=False) as f:
        assert np.argmax(f["pressure_mmhg"][0].max(1)) >= 61


@pytest.mark.parametrize(
    "case, message",
    [
        ("shape", "expected an SLP pressure map of shape \\(192, 84\\)"),
        ("physique", "are not gender \\(0/1\\), height \\(cm\\), weight \\(kg\\)"),
        ("nocali", "no PMcali.npy"),
        ("pickle", "not a numpy array file without pickles"),
        ("cover", "covers must be among"),
    ],
)
def test_bad_slp_inputs_fail_with_one_line(tmp_path, case, message, capsys):
    rng = np.random.default_rng(4)
    root = tmp_path / "danaLab"
    if case == "physique":  # weight and gender swapped
        _write_slp(root, rng, subjects=(1,), frames=1, physique=np.array([[60.0, 165.0, 0.0]]))
    else:
        _write_slp(root, rng, subjects=(1,), frames=1)
    if case == "nocali":
        (root / "00001" / "PMcali.npy").unlink()
    if case == "shape":
        np.save(root / "00001" / "PMarray" / "uncover" / "000001.npy", np.ones((120, 84)))
    if case == "pickle":
        np.save(
            root / "00001" / "PMarray" / "uncover" / "000001.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True
        )
    covers = ["uncover", "blanket"] if case == "cover" else ["uncover"]
    out = tmp_path / "o.npz"
    from pressurepose.cli import main

    rc = main(
        ["import-slp", str(root), "--out", str(out), "--calibration", "pmcali"]
        + (["--covers", *covers] if case != "cover" else [])
    )
    if case == "cover":
        with pytest.raises(ValueError, match=message):
            import_slp(root, out, covers=tuple(covers))
        return
    assert rc == 2 and not out.exists()
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err
    with pytest.raises(ValueError, match=message):
        import_slp(root, out, calibration="pmcali")
