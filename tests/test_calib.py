import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from pressurepose.calib.cmaes import CMASettings, CountedNormal, minimise
from pressurepose.calib.loss import (
    PENALTY,
    CalibrationLoss,
    ParamSpace,
    compression_term,
    contact_term,
    force_term,
    object_region,
)
from pressurepose.calib.measurements import load_measurements, parse_measurements, synthetic_measurements
from pressurepose.calib.objects import CalibObject, SceneSimulator, seed_objects
from pressurepose.cli import main
from pressurepose.mat import MatSpec
from pressurepose.sim.mattress import MattressParams

HIDDEN = MattressParams(
    k1_pa_per_m=3.0e4, k3_pa_per_m3=4.0e7, spread_m=0.012, c0_mmhg=-2.0, c1_mmhg_per_mm=1.3, c2_mmhg_per_mm2=0.004
)


@pytest.fixture(autouse=True)
def one_torch_thread():
    # sim #2 on a few capsules is far slower with 2 threads on a shared machine (~15x).
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _small_scene():
    return [[CalibObject(0.2, 0.05, 4.5, 0.4, 0.37, 90.0, "a"), CalibObject(0.4, 0.05, 14.0, 1.2, 0.37, 90.0, "b")]]


# --- loss terms against hand-computed cases ---------------------------------------------


def test_force_term_hand_computed():
    # sum|d| = 1 + 0 + 1 = 2, sum(u + u') = 8, |sum d| = |3 - 5| = 2: 0.5 * 2/8 + 0.5 * 2/8
    assert force_term(np.array([1.0, 2.0, 0.0]), np.array([2.0, 2.0, 1.0])) == pytest.approx(0.25)
    # a uniform 10% excess: both halves equal 0.1 / 2.1
    u = np.array([1.0, 3.0, 5.0])
    assert force_term(1.1 * u, u) == pytest.approx(0.1 / 2.1)
    assert force_term(np.zeros(4), np.zeros(4)) == 0.0  # nothing loaded in both: they agree
    assert force_term(np.zeros(3), np.array([1.0, 0.0, 2.0])) == pytest.approx(1.0)  # the worst case
    assert force_term(u, u) == 0.0


def test_contact_and_compression_terms_hand_computed():
    # sum|d| = 2, sum = 4, |sum d| = 0 -> 0.5 * 2/4
    assert contact_term(np.array([1, 1, 0, 0]), np.array([1, 0, 1, 0])) == pytest.approx(0.25)
    assert contact_term(np.array([True, True]), np.array([True, False])) == pytest.approx(0.5 * 1 / 3 + 0.5 * 1 / 3)
    assert compression_term(0.02, 0.03) == pytest.approx(0.2)
    assert compression_term(-0.02, 0.02) == pytest.approx(1.0)  # signed, |.| in the denominator
    assert compression_term(0.0, 0.0) == 0.0


def test_object_region_matches_a_naive_loop():
    mat = MatSpec()
    obj = CalibObject(0.3, 0.05, 2.0, 0.8, 0.3, 30.0)
    region = object_region(obj, mat, 0.04)
    (xa, ya), (xb, yb) = obj.axis_ends_m()
    naive = np.zeros(mat.shape, bool)
    for r in range(mat.rows):
        for c in range(mat.cols):
            x, y = (r + 0.5) * mat.pitch_row_m, (c + 0.5) * mat.pitch_col_m
            # closest point of the segment: the clamped projection, written out per taxel
            t = ((x - xa) * (xb - xa) + (y - ya) * (yb - ya)) / ((xb - xa) ** 2 + (yb - ya) ** 2)
            t = min(1.0, max(0.0, t))
            naive[r, c] = ((xa + t * (xb - xa) - x) ** 2 + (ya + t * (yb - ya) - y) ** 2) ** 0.5 <= 0.09
    np.testing.assert_array_equal(region, naive)
    assert 20 < region.sum() < 200


def test_scene_pressure_is_the_sum_of_its_objects():
    scenes = _small_scene()
    together = SceneSimulator(scenes)(HIDDEN)
    alone = [SceneSimulator([[o]])(HIDDEN) for o in scenes[0]]
    torch.testing.assert_close(together.pressure_pa[0], alone[0].pressure_pa[0] + alone[1].pressure_pa[0])
    torch.testing.assert_close(together.compression_m, torch.cat([a.compression_m for a in alone]))
    # Heavier sinks deeper; the sum of pressures carries both weights.
    assert together.compression_m[1] > together.compression_m[0]
    mat = MatSpec()
    assert float(together.pressure_pa.sum()) * mat.taxel_area_m2 == pytest.approx((4.5 + 14.0) * 9.81, rel=1e-3)


def test_loss_is_zero_at_the_truth_and_terms_match_the_images():
    meas = synthetic_measurements(_small_scene(), HIDDEN)
    space = ParamSpace()
    loss = CalibrationLoss(meas, space)
    assert loss(space.encode(HIDDEN)) == 0.0
    other = HIDDEN.replace(k1_pa_per_m=2.4e4, spread_m=0.02)
    b = loss.breakdown(space.encode(other))
    sim = SceneSimulator(meas.object_scenes())(other)
    for i, obj in enumerate(meas.scenes[0].objects):
        mask = object_region(obj, MatSpec(), 0.06)
        u, ur = sim.reading_mmhg[0].numpy()[mask], meas.scenes[0].pressure_mmhg[mask]
        assert b.force[i] == pytest.approx(force_term(u, ur))
        assert b.contact[i] == pytest.approx(contact_term(u > 0, ur > 0))
        assert b.compression[i] == pytest.approx(
            compression_term(float(sim.compression_m[i]), meas.scenes[0].compression_m[i])
        )
    assert b.total == pytest.approx(b.force.sum() + b.contact.sum() + b.compression.sum())
    assert b.total > 0.1 and b.penalty == 0.0


# --- penalties ------------------------------------------------------------------------------


def test_penalties():
    meas = synthetic_measurements(_small_scene(), HIDDEN)
    space = ParamSpace()
    loss = CalibrationLoss(meas, space)
    x = space.encode(HIDDEN)
    # Negative parameter: a high value, growing with the violation, and not simulated.
    neg = x.copy()
    neg[0] = -0.5
    b = loss.breakdown(neg)
    assert b.total == pytest.approx(PENALTY + 0.5) and np.isnan(b.force).all()
    neg[0] = -1.0
    assert loss(neg) > b.total
    # c0 may be negative (it is the taxel threshold).
    assert space.penalty(x)[0] == 0.0 and x[space.free.index("c0_mmhg")] < 0
    # Out of the plausible range: 10 x the deviation in units of the scale.
    wide = HIDDEN.replace(spread_m=0.07)
    pen, invalid = space.penalty(space.encode(wide))
    assert not invalid and pen == pytest.approx(10 * 0.02 / 0.01)
    assert loss(space.encode(wide)) >= pen
    # An unstable rollout (the objects sink through a 2 cm mattress): high value.
    thin = ParamSpace(space.free, MattressParams(thickness_m=0.02))
    b = CalibrationLoss(meas, thin).breakdown(thin.encode(HIDDEN))
    assert b.total == pytest.approx(PENALTY + 1.0) and all(b.failures)


# --- measurement files ------------------------------------------------------------------------


def test_measurement_file_round_trip(tmp_path):
    meas = synthetic_measurements(seed_objects(), HIDDEN, noise_mmhg=0.5, compression_noise_m=0.001, seed=3)
    path = meas.save(tmp_path / "m.json")
    back = load_measurements(path)
    assert len(back.scenes) == 2 and back.n_objects == 10
    for a, b in zip(meas.scenes, back.scenes):
        np.testing.assert_array_equal(a.pressure_mmhg, b.pressure_mmhg)
        np.testing.assert_array_equal(a.compression_m, b.compression_m)
        assert a.objects == b.objects
    # The objects are the seed's ten capsule-weight pairs.
    assert sorted((o.length_m, o.mass_kg) for s in back.scenes for o in s.objects) == sorted(
        [(0.2, m) for m in (1.3, 2.3, 4.5, 9.1, 14.0)] + [(0.4, m) for m in (1.3, 4.5, 9.1, 14.0, 18.0)]
    )
    # Noise is reproducible from the seed and changes the image.
    again = synthetic_measurements(seed_objects(), HIDDEN, noise_mmhg=0.5, compression_noise_m=0.001, seed=3)
    np.testing.assert_array_equal(again.scenes[0].pressure_mmhg, meas.scenes[0].pressure_mmhg)
    clean = synthetic_measurements(seed_objects(), HIDDEN)
    assert np.abs(clean.scenes[0].pressure_mmhg - meas.scenes[0].pressure_mmhg).max() > 0.1


def _doc():
    return synthetic_measurements(_small_scene(), HIDDEN).to_json()


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d.pop("format"), "not a pressurepose measurement file"),
        (lambda d: d["scenes"][0].pop("pressure_mmhg"), 'missing "pressure_mmhg"'),
        (lambda d: d["scenes"][0]["objects"][1].pop("mass_kg"), 'object 1 is missing "mass_kg"'),
        (lambda d: d["scenes"][0]["objects"][0].pop("compression_m"), 'missing "compression_m"'),
        (lambda d: d["scenes"][0].__setitem__("pressure_mmhg", [[0.0] * 27] * 60), "must have shape (64, 27)"),
        (lambda d: d["scenes"][0].__setitem__("pressure_mmhg", [[0.0] * 26] * 64), "must have shape (64, 27)"),
        (lambda d: d["scenes"][0]["objects"][0].__setitem__("mass_kg", -1.3), "mass_kg must be > 0"),
        (lambda d: d["scenes"][0]["objects"][0].__setitem__("mass_kg", "heavy"), "mass_kg must be a finite number"),
        (lambda d: d["scenes"][0]["objects"][0].__setitem__("compression_m", -0.01), "compression_m"),
        (lambda d: d["scenes"][0]["objects"][0].__setitem__("radius_m", 0.0), "radius_m > 0"),
        (lambda d: d["scenes"][0]["objects"][0].__setitem__("x_m", 3.0), "does not lie wholly on the mattress"),
        (lambda d: d["scenes"][0]["objects"][0].__setitem__("shape", "box"), 'only "capsule"'),
        (lambda d: d["scenes"][0]["pressure_mmhg"][3].__setitem__(4, -5.0), "within [0, 100]"),
        (lambda d: d.__setitem__("scenes", []), "non-empty list"),
    ],
)
def test_bad_measurement_files_are_clear(tmp_path, edit, message):
    doc = _doc()
    edit(doc)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError) as err:
        load_measurements(path)
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_unreadable_and_overlapping_measurements(tmp_path):
    path = tmp_path / "x.json"
    path.write_text("{not json")
    with pytest.raises(ValueError, match="not readable JSON"):
        load_measurements(path)
    with pytest.raises(ValueError, match="does not exist"):
        load_measurements(tmp_path / "missing.json")
    doc = _doc()
    doc["scenes"][0]["objects"][1]["x_m"] = 0.45  # 5 cm from the other capsule
    with pytest.raises(ValueError, match="regions overlap"):
        CalibrationLoss(parse_measurements(doc), ParamSpace())


# --- CMA-ES: recovery, determinism, resume -----------------------------------------------------


def test_counted_normal_is_a_function_of_seed_and_count():
    a, b = CountedNormal(5), CountedNormal(5, count=1)
    first, second = a(4, 3), a(4, 3)
    np.testing.assert_array_equal(second, b(4, 3))
    assert not np.array_equal(first, second) and a.count == 2


def _sphere(X):
    return [float(((np.asarray(x) - np.array([1.0, -2.0, 0.5])) ** 2).sum()) for x in X]


def test_resumed_cmaes_equals_uninterrupted(tmp_path):
    settings = CMASettings(popsize=6, max_iter=12, sigma0=0.5, seed=3)
    x0 = np.zeros(3)
    full = minimise(_sphere, x0, settings, tmp_path / "full.npz")
    part = minimise(_sphere, x0, settings, tmp_path / "part.npz", stop_after=5)
    assert part.iterations == 5 and not part.stop
    rest = minimise(_sphere, x0, settings, tmp_path / "part.npz")
    assert rest.resumed_from == 5 and rest.iterations == 12
    np.testing.assert_array_equal(rest.history_f, full.history_f)
    np.testing.assert_array_equal(rest.mean, full.mean)
    assert rest.best_f == full.best_f and rest.sigma == full.sigma
    with np.load(tmp_path / "part.npz", allow_pickle=False) as z:  # the summary is in the file
        assert int(z["iteration"]) == 12 and z["covariance"].shape == (3, 3) and int(z["rng_count"]) >= 12
    # Other settings cannot resume that state; an unreadable state is a clear error.
    with pytest.raises(ValueError, match="other settings"):
        minimise(_sphere, x0, CMASettings(popsize=8, max_iter=12, sigma0=0.5, seed=3), tmp_path / "part.npz")
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(ValueError, match="unreadable"):
        minimise(_sphere, x0, settings, tmp_path / "junk.npz")


def test_calibration_recovers_hidden_parameters_small_case():
    scenes = [[CalibObject(0.2, 0.05, 2.3, 0.4, 0.37), CalibObject(0.4, 0.05, 14.0, 1.2, 0.37)]]
    meas = synthetic_measurements(scenes, HIDDEN, sub=1)
    space = ParamSpace(("k1_pa_per_m", "spread_m"), HIDDEN.replace(k1_pa_per_m=2.0e4, spread_m=0.008))
    loss = CalibrationLoss(meas, space, sub=1)
    res = minimise(
        lambda X: [loss(x) for x in X],
        space.encode(space.base),
        CMASettings(popsize=8, max_iter=40, tolx=1e-3, tolfun=1e-4, sigma0=0.2, seed=0),
    )
    got = space.decode(res.best_x)
    assert got["k1_pa_per_m"] == pytest.approx(HIDDEN.k1_pa_per_m, rel=0.05)
    assert got["spread_m"] == pytest.approx(HIDDEN.spread_m, rel=0.05)
    assert res.best_f < 0.05 * loss(space.encode(space.base))


def test_sim1_sinks_the_calibration_capsules_like_sim2():
    from pressurepose.calib.coupling import coupling_check
    from pressurepose.calib.loss import CalibrationLoss as _L  # noqa: F401 (same module the CLI uses)

    scenes = [
        [CalibObject(0.2, 0.05, 1.3, 0.4, 0.37, 90.0, "light"), CalibObject(0.4, 0.05, 18.0, 1.2, 0.37, 90.0, "heavy")]
    ]
    loss = CalibrationLoss(synthetic_measurements(scenes, HIDDEN), ParamSpace())
    rows = coupling_check(loss, HIDDEN)
    assert [r["name"] for r in rows] == ["light", "heavy"]
    for r in rows:
        assert r["sim1_settled"] and abs(r["relative_difference"]) < 0.10, r
    assert rows[1]["sim2_sink_m"] > rows[0]["sim2_sink_m"]


# --- CLI --------------------------------------------------------------------------------------


@pytest.mark.slow
def test_cli_calibrate_smoke_and_resume(tmp_path):
    meas = synthetic_measurements(_small_scene(), HIDDEN).save(tmp_path / "m.json")
    out = tmp_path / "cal"
    common = [
        "calibrate",
        "--measurements",
        str(meas),
        "--out",
        str(out),
        "--popsize",
        "4",
        "--max-iter",
        "3",
        "--free",
        "k1_pa_per_m",
        "spread_m",
        "--sub",
        "1",
        "--no-coupling-check",
    ]
    assert main(common + ["--stop-after", "2", "--workers", "2"]) == 0  # the process pool, then in-process
    first = json.loads((out / "calibrate.json").read_text())
    assert not first["finished"] and first["iterations"] == 2
    assert main(common + ["--workers", "1"]) == 0
    record = json.loads((out / "calibrate.json").read_text())
    assert record["finished"] and record["iterations"] == 3 and record["resumed_from_generation"] == 2
    params = MattressParams.load(out / "params.json")
    assert params.to_dict() == pytest.approx(record["params"])
    assert (out / "convergence.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert record["best_loss"] <= record["start_loss"]


def test_cli_calibrate_bad_input_exits_2(tmp_path):
    bad = tmp_path / "bad.json"
    doc = _doc()
    doc["scenes"][0]["objects"][0]["mass_kg"] = -2
    bad.write_text(json.dumps(doc))
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "pressurepose.cli",
            "calibrate",
            "--measurements",
            str(bad),
            "--out",
            str(tmp_path / "o"),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr and "mass_kg must be > 0" in r.stderr
    assert main(["calibrate", "--measurements", str(tmp_path / "none.json")]) == 2
    assert main(["calibrate", "--measurements", str(bad), "--free", "k9"]) == 2
