"""`pressurepose evaluate`: a report end to end for a tiny model and dataset, the per-sample
metric pipeline (zero for the truth), and bad inputs."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from pressurepose.commands.evaluate import EvaluateConfig, run_evaluate
from pressurepose.eval.evaluation import METRICS, _as_params, _sample_metrics
from pressurepose.train.config import TrainConfig
from pressurepose.train.data import open_dataset, synthetic_arrays, write_npz
from pressurepose.train.loop import train


@pytest.fixture(scope="module")
def tiny(anny64, tmp_path_factory):
    """A smoke-trained network, a training set and a separate test set (sampler + sim #2)."""
    root = tmp_path_factory.mktemp("eval")
    for sub in ("train", "test"):
        (root / sub).mkdir()
    write_npz(root / "train" / "train.npz", synthetic_arrays(10, seed=1, body=anny64))
    write_npz(root / "test" / "test.npz", synthetic_arrays(6, seed=2, body=anny64))
    run = train(TrainConfig.smoke(data=root / "train", out=root / "run", epochs=1, progress=False, val_fraction=0.2))
    return root, run


def test_report_end_to_end(tiny):
    from scipy.stats import t as student_t

    root, run = tiny
    out = root / "report"
    paths = run_evaluate(
        EvaluateConfig(model=run, data=root / "test", out=out, train_data=root / "train", batch=4, failures=3)
    )
    record = json.loads(paths["json"].read_text())
    n = len(open_dataset(root / "test"))
    assert record["count"] == n and len(record["per_sample"]["vpe_m"]) == n
    for m in METRICS:
        vals = np.asarray(record["per_sample"][m])
        assert np.isfinite(vals).all() and (vals >= 0).all()
    # PA-MPJPE never exceeds MPJPE; a barely trained network is centimetres off, not metres.
    assert (np.asarray(record["per_sample"]["pa_mpjpe_m"]) <= np.asarray(record["per_sample"]["mpjpe_m"]) + 1e-6).all()
    assert 0.005 < record["overall"]["vpe_m"]["mean"] < 1.0
    assert set(record["baselines_vpe_m"]) == {"mean_body", "nearest_image"}
    assert {e["gender"] for e in record["by_gender"]} == {"female", "male"}
    assert sum(e["count"] for e in record["by_gender"]) == n
    # each group's 95% interval for its mean 3DVPE, from the per-sample rows by hand
    vpe, genders = np.asarray(record["per_sample"]["vpe_m"]), np.asarray(record["per_sample"]["gender"])
    for e in record["by_gender"]:
        v = vpe[genders == e["gender"]]
        if len(v) < 2:
            assert e["vpe_m_ci95"] is None
            continue
        half = student_t.ppf(0.975, len(v) - 1) * np.sqrt(((v - v.mean()) ** 2).sum() / (len(v) - 1)) / np.sqrt(len(v))
        np.testing.assert_allclose(e["vpe_m_ci95"], [max(v.mean() - half, 0.0), v.mean() + half], rtol=1e-12, atol=0)
    text = paths["markdown"].read_text()
    assert "| gender partition |" in text and "nearest image" in text and "| arms |" in text
    # the table's row for each gender: count, mean, then the interval, in that order
    for e in record["by_gender"]:
        row = next(line for line in text.splitlines() if line.startswith(f"| {e['gender']} |"))
        cells = [c.strip() for c in row.strip("|").split("|")]
        ci = "-" if e["vpe_m_ci95"] is None else f"{e['vpe_m_ci95'][0] * 100:.2f} - {e['vpe_m_ci95'][1] * 100:.2f}"
        assert cells[1:4] == [str(e["count"]), f"{e['vpe_m'] * 100:.2f}", ci], cells
    for name in ("cases", "failures"):
        assert paths[name].read_bytes()[:4] == b"\x89PNG"
    # The signed height error by where each image's load lies, as evaluate-real reports it: the
    # classes recomputed from the test images, the groups' counts and medians from the rows.
    from pressurepose.eval.real import LOAD_ENDS, load_ends

    per = record["per_sample"]
    signed = np.asarray(per["height_signed_m"])
    np.testing.assert_allclose(np.abs(signed), per["height_err_m"], rtol=0, atol=1e-7)
    test = open_dataset(root / "test")
    images = np.stack([np.asarray(test[i]["pressure_mmhg"], dtype=np.float32) for i in range(n)])
    assert per["load_ends"] == load_ends(images)
    groups = record["height_by_load_ends"]
    assert sum(g["frames"] for g in groups.values()) == n and set(groups) <= set(LOAD_ENDS)
    for where, g in groups.items():
        mine = signed[np.asarray(per["load_ends"]) == where]
        assert g["frames"] == len(mine) and g["height_median_signed_m"] == pytest.approx(
            float(np.median(mine)), abs=1e-12
        )
    cells = [
        "-" if w not in groups else f"{groups[w]['height_median_signed_m'] * 100:+.1f} ({groups[w]['frames']})"
        for w in LOAD_ENDS
    ]
    assert "| " + " | ".join(cells) + " |" in text and "## Height error by where the load lies" in text
    # .npz samples have no shards or generator's coordinates: no ids, no table of where they live
    assert per["sample_id"] == [None] * n and all(f["sample_id"] is None for f in record["failures"])
    assert "initial pose again" not in text
    # a network without heatmaps has no spreads to read, and its real-frame report says nothing of them
    from pressurepose.eval.real import read_bodies
    from pressurepose.train.checkpoint import load_network

    assert read_bodies(load_network(run)[0], torch.from_numpy(images[:2])).spread_m is None


def test_failure_table_names_the_shard_and_the_command_that_redraws_the_pose():
    from pressurepose.commands.evaluate import _failure_table

    sid = {"shard": "test-general-male-over-00002", "row": 7, "seed": 52, "partition": "general"}
    rows = _failure_table(
        [
            {"index": 3, "vpe_m": 0.0912, "sample_id": dict(sid, gender="male", over_bed=True, index=4294967301)},
            {"index": 9, "vpe_m": 0.05, "sample_id": None},
        ]
    )
    assert rows[2] == (
        "| 3 | 9.12 | test-general-male-over-00002, 7 | `pressurepose sample --seed 52 --partition general "
        "--gender male --over-bed --start 4294967301 --n 1` |"
    )
    assert rows[3] == "| 9 | 5.00 | - | - |"
    assert _failure_table([{"index": 0, "vpe_m": 0.1, "sample_id": None}]) == []
    imported = dict(sid, gender="male", over_bed=False, seed=None, index=None)  # a dataset generate did not make
    assert _failure_table([{"index": 1, "vpe_m": 0.1, "sample_id": imported}])[2].endswith("7 | - |")
    smpl = dict(sid, gender="female", over_bed=False, backend="smpl", index=12)
    assert (
        "--gender female --backend smpl --smpl-dir DIR --start 12 --n 1`"
        in _failure_table([{"index": 1, "vpe_m": 0.1, "sample_id": smpl}])[2]
    )


def test_height_by_load_ends_by_hand():
    from pressurepose.eval.real import height_by_load_ends, load_ends_cells

    groups = height_by_load_ends([0.01, -0.03, 0.05, 0.02], ["neither", "foot only", "neither", "foot only"])
    assert list(groups) == ["neither", "foot only"]  # LOAD_ENDS's order, absent classes left out
    assert groups["neither"] == {"frames": 2, "height_median_signed_m": pytest.approx(0.03)}
    assert groups["foot only"] == {"frames": 2, "height_median_signed_m": pytest.approx(-0.005)}
    assert load_ends_cells(groups) == ["+3.0 (2)", "-", "-0.5 (2)", "-", "-"]
    with pytest.raises(ValueError, match="one class per height error"):
        height_by_load_ends([0.01, 0.02], ["neither"])


def test_mean_interval_by_hand():
    from pressurepose.commands.evaluate import mean_interval

    lo, hi = mean_interval(np.array([1.0, 2.0, 3.0]))  # mean 2, sample sd 1, t(0.975, 2) = 4.302653
    assert abs(lo - (2 - 4.302653 / np.sqrt(3))) < 1e-6 and abs(hi - (2 + 4.302653 / np.sqrt(3))) < 1e-6
    lo, hi = mean_interval(np.arange(1000.0))  # large n: the normal 1.96 to 0.5% (t = 1.9623)
    half = 1.96 * np.arange(1000.0).std(ddof=1) / np.sqrt(1000)
    assert abs((hi - lo) / 2 - half) < 5e-3 * half
    assert mean_interval(np.array([4.0, 4.0])) == [4.0, 4.0]
    assert mean_interval(np.array([0.5])) is None
    # an error's mean cannot be below 0: the floor clips the lower end only
    lo, hi = mean_interval(np.array([0.1, 3.0]), floor=0.0)
    assert lo == 0.0 and hi == mean_interval(np.array([0.1, 3.0]))[1] and mean_interval(np.array([0.1, 3.0]))[0] < 0


def reference_vpe(est, true, faces):
    """3DVPE as evaluate computed it before the exact pruned search: per sample, brute-force
    nearest neighbours between the camera-facing vertices."""
    from pressurepose.eval.metrics import camera_facing
    from pressurepose.eval.nearest import nearest_brute

    (mask_e, area_e), (mask_t, area_t) = camera_facing(est, faces), camera_facing(true, faces)
    out = []
    for i in range(est.shape[0]):
        e, t, we, wt = est[i][mask_e[i]], true[i][mask_t[i]], area_e[i][mask_e[i]], area_t[i][mask_t[i]]
        out.append(float((nearest_brute(e, t) * we).sum() / we.sum() + (nearest_brute(t, e) * wt).sum() / wt.sum()) / 2)
    return out


def test_report_numbers_equal_the_per_sample_reference(tiny, tmp_path):
    """The batched evaluate (meshes packed once per batch, the mean body's once per run, exact
    pruned nearest neighbours) against the old path: every mesh re-posed per comparison, the
    mean body once per sample, brute-force 3DVPE."""
    from pressurepose.eval import evaluation as R
    from pressurepose.net.model import NetInputs
    from pressurepose.train.checkpoint import load_network

    root, run = tiny
    paths = run_evaluate(
        EvaluateConfig(
            model=run, data=root / "test", out=tmp_path / "r", train_data=root / "train", batch=4, failures=2
        )
    )
    record = json.loads(paths["json"].read_text())
    net, _ = load_network(run)
    body, f32 = net.body, torch.float32
    mean, images, bodies = R._baseline_data(R.open_split(root / "train", "train"), 4096, f32)
    want = {"vpe_m": [], "v2v_m": [], "mpjpe_m": [], "mean_body": [], "nearest_image": []}
    with torch.no_grad():
        for _, b in R._batches(R.open_split(root / "test", "test"), 4, None):  # batches of 4 and 2
            true = body(R._as_params(b, f32))
            est = body(
                net(
                    NetInputs(
                        pressure_mmhg=b["pressure_mmhg"],
                        gender=b["gender"],
                        height_m=b["height_m"],
                        mass_kg=b["mass_kg"],
                    ),
                    mesh=False,
                )[-1].params
            )
            want["vpe_m"] += reference_vpe(est.vertices, true.vertices, body.faces)
            want["v2v_m"] += (est.vertices - true.vertices).norm(dim=-1).mean(-1).tolist()
            want["mpjpe_m"] += (est.joints - b["joints"]).norm(dim=-1).mean(-1).tolist()
            n = len(b["shape"])
            want["mean_body"] += reference_vpe(
                body(mean.index(torch.zeros(n, dtype=torch.long))).vertices, true.vertices, body.faces
            )
            nearest = torch.cdist(R._normalised(b["pressure_mmhg"]), images).argmin(1)
            want["nearest_image"] += reference_vpe(body(bodies.index(nearest)).vertices, true.vertices, body.faces)
    got = record["per_sample"]
    assert len(got["vpe_m"]) == len(want["vpe_m"]) == 6
    # The brute force picks neighbours by |p|^2 - 2 q.p in float32: equal to its round-off.
    np.testing.assert_allclose(got["vpe_m"], want["vpe_m"], rtol=1e-5, atol=0)
    assert got["v2v_m"] == want["v2v_m"] and got["mpjpe_m"] == want["mpjpe_m"]  # untouched paths: exact
    for name in ("mean_body", "nearest_image"):
        s = record["baselines_vpe_m"][name]
        assert s["mean"] == pytest.approx(np.mean(want[name]), rel=1e-5)
        assert s["median"] == pytest.approx(np.median(want[name]), rel=1e-5)


def test_metrics_of_the_truth_are_zero(anny32, tiny):
    root, _ = tiny
    ds = open_dataset(root / "test")
    batch = {k: torch.stack([ds[i][k] for i in range(3)]) for k in ds[0]}
    body = anny32
    true = _as_params(batch, torch.float32)
    out = body(true)
    res = _sample_metrics(body, true, true, out.joints, out, body.measure(true.shape))
    for k, v in res.items():
        assert float(v.abs().max()) < 1e-5, k


def test_bad_inputs(tiny, tmp_path):
    root, run = tiny
    arrays = synthetic_arrays(2, seed=3)
    arrays["shape"] = torch.zeros(len(arrays["shape"]), 10)  # SMPL-sized shapes
    for sub in ("smpl", "empty"):
        (tmp_path / sub).mkdir()
    write_npz(tmp_path / "smpl" / "d.npz", arrays)
    with pytest.raises(ValueError, match="another body model"):
        run_evaluate(EvaluateConfig(model=run, data=tmp_path / "smpl", out=tmp_path / "o"))
    empty = {k: v[:0] for k, v in arrays.items()}
    write_npz(tmp_path / "empty" / "d.npz", empty)
    with pytest.raises(ValueError, match="no test samples"):
        run_evaluate(EvaluateConfig(model=run, data=tmp_path / "empty", out=tmp_path / "o"))
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "pressurepose.cli",
            "evaluate",
            "--model",
            str(tmp_path / "nothing"),
            "--data",
            str(root / "test"),
            "--out",
            str(tmp_path / "o"),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr


PMAT = Path(__file__).resolve().parent / "data" / "pmatdata"  # 20 frames of PmatData (its README)


def test_posture_from_the_root_orientation():
    from pressurepose.eval.real import posture_of, roll_deg
    from pressurepose.sampling.sampler import root_axis_angle

    rolls = [0.0, -math.pi / 2, math.pi / 2, math.pi, 0.3, -2.0]
    aa = torch.tensor(np.stack([root_axis_angle(r, yaw) for r, yaw in zip(rolls, [0.2, -0.4, 0.5, 0.1, -0.3, 0.0])]))
    got = roll_deg(aa)
    want = torch.rad2deg(torch.tensor(rolls, dtype=torch.float64))
    diff = (got - want + 180) % 360 - 180  # +-180 are the same roll
    assert float(diff.abs().max()) < 1e-9
    assert posture_of(got) == ["supine", "left", "right", "prone", "supine", "left"]


def test_subject_interval_hand_computed_cases():
    from pressurepose.eval.real import subject_interval

    # Every subject alike: each resample gives the same accuracy, the interval collapses.
    v, s = [1, 0, 1, 0, 1, 0], [1, 1, 2, 2, 3, 3]
    assert subject_interval(v, s, np.mean) == pytest.approx((0.5, 0.5), abs=1e-12)
    # Two subjects of equal size, all right and all wrong: a resample holds (1, 1), (1, 2), (2, 1)
    # or (2, 2) - mean 1, 0.5, 0.5, 0 with probabilities 1/4, 1/2, 1/4; the 2.5% and 97.5%
    # quantiles are 0 and 1, and the 25%..75% interval is 0.5.
    v, s = [1, 1, 0, 0], [7, 7, 9, 9]
    assert subject_interval(v, s, np.mean) == pytest.approx((0.0, 1.0), abs=1e-12)
    assert subject_interval(v, s, np.mean, level=0.4) == pytest.approx((0.5, 0.5), abs=1e-12)
    # Whole subjects are resampled, not frames: a subject's 3 frames move together, so with two
    # subjects the means are 0, 1 or the pooled mean 3/4 (subject 1: 3 frames, subject 2: 1).
    v, s = [1, 1, 1, 0], [1, 1, 1, 2]
    lo, hi = subject_interval(v, s, np.mean, level=0.9)
    assert (lo, hi) == pytest.approx((0.0, 1.0), abs=1e-12)
    assert subject_interval(v, s, np.mean, seed=3) == subject_interval(v, s, np.mean, seed=3)
    with pytest.raises(ValueError, match="one length"):
        subject_interval([1.0, 2.0], [1], np.mean)
    with pytest.raises(ValueError, match="level"):
        subject_interval([1.0], [1], np.mean, level=1.0)


def test_load_ends_by_hand():
    """Whether a frame's load reaches the mat's head row (row 0) and its foot row: rows holding
    < 0.2% of the force do not count."""
    from pressurepose.eval.real import load_ends

    images = np.zeros((7, 8, 3))
    images[0, 2:6, 1] = 1.0  # rows 2-5: neither end
    images[1, 0:5, 1] = 1.0  # from the head row
    images[2, 3:8, 1] = 1.0  # to the foot row
    images[3, :, 1] = 1.0  # every row: both
    images[4, :, 1] = 1.0
    images[4, 7, 1] = 1e-4  # its last row too faint to count: the head row only
    images[5, 2:6, 1] = 1.0
    images[5, 7, 0] = 0.01  # 0.25% of the force: counts, the foot row only
    # images[6]: empty
    assert load_ends(images) == ["neither", "head only", "foot only", "both", "head only", "foot only", "empty"]
    with pytest.raises(ValueError, match=r"\(N, rows, cols\)"):
        load_ends(np.zeros((8, 3)))


def test_a_frame_repeating_another_subjects_is_left_out(tiny, tmp_path):
    """PmatData repeats subject 4's files as subject 8's: a frame whose file is byte for byte an
    earlier record's is left out of evaluate-real and named in its report; the others stay."""
    import shutil

    from pressurepose.cli import main
    from pressurepose.data.pmatdata import distinct_frames, load_index, repeated_frames

    root = tmp_path / "pmat"
    shutil.copytree(PMAT, root)
    src = root / "experiment-ii" / "S1" / "Air_Mat" / "Matrix_Air_C1.txt"
    copy = root / "experiment-ii" / "S9" / "Air_Mat" / "Matrix_Air_C1.txt"
    copy.parent.mkdir(parents=True)
    shutil.copyfile(src, copy)
    near = root / "experiment-ii" / "S9" / "Air_Mat" / "Matrix_Air_C2.txt"  # one byte off: a frame of its own
    text = (root / "experiment-ii" / "S1" / "Air_Mat" / "Matrix_Air_C2.txt").read_text()
    near.write_text(text.replace(" ", "  ", 1))
    with (root / "index.csv").open("a") as fh:
        fh.write("experiment-ii/S9/Air_Mat/Matrix_Air_C1.txt,9,air,C,1,right,0,0,right lateral,30,180,80\n")
        fh.write("experiment-ii/S9/Air_Mat/Matrix_Air_C2.txt,9,air,C,2,right,0,0,right lateral,30,180,80\n")
    records = load_index(root)
    pairs = repeated_frames(records)
    assert [(r.subject, r.path.name, o.subject, o.path.name) for r, o in pairs] == [
        (9, "Matrix_Air_C1.txt", 1, "Matrix_Air_C1.txt")
    ]
    kept = distinct_frames(records)
    assert len(kept) == len(records) - 1 and pairs[0][0] not in kept and pairs[0][1] in kept
    _, run = tiny
    out = tmp_path / "real"
    args = ["evaluate-real", "--model", str(run), "--pmatdata", str(root), "--groups", "CD", "--out", str(out)]
    assert main(args) == 0
    record = json.loads((out / "real.json").read_text())
    assert record["frames"] == 13 and record["by_mattress"]["air"]["frames"] == 7
    assert record["repeats_left_out"] == [
        {"file": "experiment-ii/S9/Air_Mat/Matrix_Air_C1.txt", "same_as": "experiment-ii/S1/Air_Mat/Matrix_Air_C1.txt"}
    ]
    assert "Matrix_Air_C1.txt" not in {f["file"] for f in record["per_frame"] if f["subject"] == 9}
    assert "1 frame(s) left out (all groups): each repeats another record's file" in (out / "real.md").read_text()
    # Of a group of copies the lowest-numbered subject's is the original, wherever it is listed.
    swapped = repeated_frames(records[::-1])
    assert [(r.subject, o.subject) for r, o in swapped] == [(9, 1)]


def test_tilt_summary_by_hand():
    """Group E's measures on seven frames worked out by hand, the roll error wrapped to [0, 180]."""
    from pressurepose.eval.real import documented_roll, tilt_summary

    doc = [documented_roll("right", 20), documented_roll("left", 40), 20, 40, -20, 20, 20]
    read = [25, 100, -15, -170, -25, 5, 170]
    s = tilt_summary(doc, read)
    # toward the documented side: 25, -100, -15, -170, 25, 5, 170 -> median 5
    assert s["read_toward_median_deg"] == pytest.approx(5.0)
    # errors 5, 140, 35, 150 (not 210: wrapped), 5, 15, 150 -> median 35
    assert s["abs_error_median_deg"] == pytest.approx(35.0)
    # turned: 25 and 25 (5 is too little; 170 toward the side is face down); the other way: 3
    assert s["share_turned"] == pytest.approx(2 / 7) and s["share_other_way"] == pytest.approx(3 / 7)
    assert s["frames"] == 7 and "share_turned_ci" not in s
    one = tilt_summary(doc, read, subjects=[1] * 7)  # one subject: every resample is the set itself
    assert one["share_turned_ci"] == pytest.approx((2 / 7, 2 / 7))
    with pytest.raises(ValueError, match="right or the left"):
        documented_roll("supine", 20)
    with pytest.raises(ValueError, match=r"\(0, 90\)"):
        documented_roll("left", 0)
    with pytest.raises(ValueError, match="no roll may be 0"):
        tilt_summary([20, 0], [1, 2])
    with pytest.raises(ValueError, match="one read roll per documented roll"):
        tilt_summary([20, -20], [1])


def test_evaluate_real_reads_tilted_frames_against_their_rolls(tiny, tmp_path):
    """Group E (lateral on wedges at 20 / 40 deg) is reported by its roll, apart from the posture
    table; with E alone there is no posture table, and an earlier run's figure of it is removed."""
    from pressurepose.cli import main
    from pressurepose.eval.real import tilt_summary

    _, run = tiny
    out = tmp_path / "real"
    assert main(["evaluate-real", "--model", str(run), "--pmatdata", str(PMAT), "--out", str(out)]) == 0
    record = json.loads((out / "real.json").read_text())
    assert record["frames"] == 12 and {f["variant"][0] for f in record["per_frame"]} == {"C", "D"}
    tilted = record["tilted"]
    rows = tilted["per_frame"]
    assert tilted["frames"] == len(rows) == 4
    assert sorted((f["variant"], f["mattress"], f["documented_roll_deg"]) for f in rows) == [
        ("E1", "air", 20.0),
        ("E2", "sponge", 40.0),
        ("E3", "sponge", -20.0),
        ("E4", "air", -40.0),
    ]
    for mattress, s in tilted["by_mattress"].items():
        sel = [f for f in rows if f["mattress"] == mattress]
        expect = tilt_summary([f["documented_roll_deg"] for f in sel], [f["roll_deg"] for f in sel], [1] * len(sel))
        assert s.pop("share_turned_ci") == pytest.approx(list(expect.pop("share_turned_ci")))
        assert s == pytest.approx(expect)
    assert set(tilted["by_variant"]) == {"E1 air", "E2 sponge", "E3 sponge", "E4 air"}
    text = (out / "real.md").read_text()
    assert "(12 frames flat, 4 tilted, 4 raised, groups BCDEF)" in text and "posture accuracy" in text
    assert record["raised"]["frames"] == 4 and {v[0] for v in record["by_variant"]} == {"C", "D"}
    assert "| E4 air (1) | -40 |" in text and "![tilt](tilt.png)" in text
    for name in ("real.png", "tilt.png"):
        assert (out / name).read_bytes()[:4] == b"\x89PNG"
    assert (
        main(["evaluate-real", "--model", str(run), "--pmatdata", str(PMAT), "--groups", "E", "--out", str(out)]) == 0
    )
    record = json.loads((out / "real.json").read_text())
    assert record["frames"] == 0 and record["by_mattress"] == {} and record["tilted"]["frames"] == 4
    text = (out / "real.md").read_text()
    assert "posture accuracy" not in text and "![real]" not in text and "| E1 air (1) | +20 |" in text
    assert not (out / "real.png").exists() and (out / "tilt.png").exists()
    # A group E row without its roll: one line naming the index and the file, nothing written.
    import shutil

    root = tmp_path / "pmat"
    shutil.copytree(PMAT, root)
    index = root / "index.csv"
    index.write_text(index.read_text().replace(",E,1,right,20,", ",E,1,right,0,"))
    r = subprocess.run(
        [sys.executable, "-m", "pressurepose.cli", "evaluate-real", "--model", str(run), "--pmatdata", str(root)]
        + ["--groups", "E", "--out", str(tmp_path / "bad")],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "Matrix_Air_E1.txt" in r.stderr and "index.csv" in r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "bad").exists()


def test_evaluate_real_reads_raised_beds_by_angle(tiny, tmp_path):
    """Group F (supine, the head of the bed raised) is reported apart: the share read supine and the
    height error per mattress and per angle, each recomputed from the per-frame rows; with F alone
    there is no posture table and no figure."""
    from pressurepose.cli import main

    _, run = tiny
    out = tmp_path / "real"
    args = ["evaluate-real", "--model", str(run), "--pmatdata", str(PMAT), "--groups", "F", "--out", str(out)]
    assert main(args) == 0
    record = json.loads((out / "real.json").read_text())
    assert record["frames"] == 0 and record["by_mattress"] == {} and "tilted" not in record
    raised = record["raised"]
    rows = raised["per_frame"]
    assert raised["frames"] == len(rows) == 4
    assert sorted((f["variant"], f["mattress"], f["bed_incline_deg"], f["posture"]) for f in rows) == [
        ("F1", "air", 0.0, "supine"),
        ("F3", "sponge", 20.0, "supine"),
        ("F5", "air", 40.0, "supine"),
        ("F7", "sponge", 60.0, "supine"),
    ]
    for mattress, s in raised["by_mattress"].items():
        sel = [f for f in rows if f["mattress"] == mattress]
        assert s["frames"] == 2 and s["posture_accuracy"] == np.mean([f["estimated_posture"] == "supine" for f in sel])
        errors = [f["estimated_height_m"] - f["height_m"] for f in sel]
        assert s["height_median_signed_m"] == pytest.approx(np.median(errors))
    assert [a["bed_incline_deg"] for a in raised["by_angle"]] == [0.0, 20.0, 40.0, 60.0]
    for a in raised["by_angle"]:
        (f,) = [f for f in rows if f["variant"] == a["variant"] and f["mattress"] == a["mattress"]]
        assert a["estimated"] == {f["estimated_posture"]: 1} and a["frames"] == 1
        assert a["height_median_signed_m"] == pytest.approx(f["estimated_height_m"] - f["height_m"])
    text = (out / "real.md").read_text()
    assert "(4 raised, groups F)" in text and "posture accuracy" not in text
    assert "| F5 | 40 | air | 1 |" in text and "![" not in text
    assert not (out / "real.png").exists() and not (out / "tilt.png").exists()
    # Two group-F-only reports compare (their raised beds alone).
    assert main([*args[:-1], str(tmp_path / "real2")]) == 0
    assert main(["compare", str(out), str(tmp_path / "real2"), "--out", str(tmp_path / "cmp")]) == 0
    compared = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert compared["result"] == {} and set(compared["raised"]) == {"air", "sponge"}
    assert compared["raised"]["air"]["posture_gained"] == compared["raised"]["air"]["posture_lost"] == 0
    # A group F row without its bed angle, or not supine: one line naming the file, nothing written.
    import shutil

    for old, new in ((",F,5,supine,0,40,", ",F,5,supine,0,,"), (",F,5,supine,0,40,", ",F,5,left,0,40,")):
        root = tmp_path / "pmat"
        shutil.rmtree(root, ignore_errors=True)
        shutil.copytree(PMAT, root)
        index = root / "index.csv"
        assert old in index.read_text()
        index.write_text(index.read_text().replace(old, new))
        r = subprocess.run(
            [sys.executable, "-m", "pressurepose.cli", "evaluate-real", "--model", str(run), "--pmatdata", str(root)]
            + ["--groups", "F", "--out", str(tmp_path / "bad")],
            capture_output=True,
            text=True,
        )
        assert r.returncode == 2 and "index.csv" in r.stderr and "Traceback" not in r.stderr, r.stderr
        assert ("line 19" in r.stderr) if ",," in new else ("Matrix_Air_F5.txt" in r.stderr)
        assert not (tmp_path / "bad").exists()


def test_evaluate_real_on_pmatdata(tiny, tmp_path):
    from pressurepose.cli import main

    _, run = tiny
    out = tmp_path / "real"
    assert (
        main(["evaluate-real", "--model", str(run), "--pmatdata", str(PMAT), "--groups", "CD", "--out", str(out)]) == 0
    )
    record = json.loads((out / "real.json").read_text())
    assert record["frames"] == 12 and set(record["by_mattress"]) == {"air", "sponge"}
    assert record["repeats_left_out"] == []  # the fixture's frames are all distinct
    assert "left out" not in (out / "real.md").read_text()
    for s in record["by_mattress"].values():
        assert 0.0 <= s["posture_accuracy"] <= 1.0 and s["frames"] == 6
        assert sum(sum(row.values()) for row in s["confusion"].values()) == 6
        assert set(s["confusion"]) == {"supine", "left", "right"} and sum(s["confusion"]["supine"].values()) == 0
        assert s["height_mae_m"] < 1.0 and s["mass_mae_kg"] < 200
    # The medians and the per-variant counts, recomputed from the per-frame rows.
    for mattress, s in record["by_mattress"].items():
        err = [f["estimated_height_m"] - f["height_m"] for f in record["per_frame"] if f["mattress"] == mattress]
        assert s["height_median_signed_m"] == pytest.approx(float(np.median(err)), abs=1e-12)
        assert s["height_median_abs_m"] == pytest.approx(float(np.median(np.abs(err))), abs=1e-12)
        lo, hi = s["posture_accuracy_ci"]
        assert 0.0 <= lo <= s["posture_accuracy"] <= hi <= 1.0
        lo, hi = s["height_median_signed_ci_m"]
        assert lo <= hi and min(err) <= lo and hi <= max(err)
        assert s["subjects"] == len({f["subject"] for f in record["per_frame"] if f["mattress"] == mattress})
    variants = record["by_variant"]
    assert set(variants) == {f["variant"] for f in record["per_frame"]} and all(v[0] in "CD" for v in variants)
    for name, v in variants.items():
        frames = [f for f in record["per_frame"] if f["variant"] == name]
        assert v["frames"] == len(frames) == sum(v["estimated"].values())
        assert v["estimated"].get(v["posture"], 0) == sum(f["estimated_posture"] == f["posture"] for f in frames)
    # The height error by where the load lies: each frame's class recomputed from its image, the
    # groups' counts and medians from the per-frame rows.
    from pressurepose.data.pmatdata import load_images, load_index
    from pressurepose.eval.real import LOAD_ENDS, load_ends

    index = {str(r.path.relative_to(PMAT)): r for r in load_index(PMAT)}
    images = load_images([index[f["file"]] for f in record["per_frame"]])
    assert [f["load_reaches"] for f in record["per_frame"]] == load_ends(images)
    for f, image in zip(record["per_frame"], images):  # by hand: the rows holding >= 0.2% of the force
        rows = np.nonzero(image.sum(1) >= 0.002 * image.sum())[0]
        head, foot = rows[0] == 0, rows[-1] == image.shape[0] - 1
        assert (
            f["load_reaches"]
            == {(0, 0): "neither", (1, 0): "head only", (0, 1): "foot only", (1, 1): "both"}[(int(head), int(foot))]
        )
    for mattress, s in record["by_mattress"].items():
        frames = [f for f in record["per_frame"] if f["mattress"] == mattress]
        assert sum(g["frames"] for g in s["height_by_load_ends"].values()) == len(frames)
        for where, g in s["height_by_load_ends"].items():
            err = [f["estimated_height_m"] - f["height_m"] for f in frames if f["load_reaches"] == where]
            assert where in LOAD_ENDS and g["frames"] == len(err)
            assert g["height_median_signed_m"] == pytest.approx(float(np.median(err)), abs=1e-12)
    text = (out / "real.md").read_text()
    assert (out / "real.png").read_bytes()[:4] == b"\x89PNG" and "posture accuracy" in text and "| C1 | right |" in text
    assert "| mattress | neither | head only | foot only | both | empty |" in text
    # A class a mattress lacks reads "-"; the others their median and count, as in the JSON.
    for mattress, s in record["by_mattress"].items():
        cells = [
            "-"
            if w not in s["height_by_load_ends"]
            else f"{s['height_by_load_ends'][w]['height_median_signed_m'] * 100:+.1f} ({s['height_by_load_ends'][w]['frames']})"
            for w in LOAD_ENDS
        ]
        assert f"| {mattress} | " + " | ".join(cells) + " |" in text
        assert len(s["height_by_load_ends"]) < len(LOAD_ENDS)  # the fixture's frames leave classes out
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "pressurepose.cli",
            "evaluate-real",
            "--model",
            str(run),
            "--pmatdata",
            str(PMAT),
            "--groups",
            "BG",
            "--out",
            str(tmp_path / "o"),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "groups must be letters of BCDEF" in r.stderr


@pytest.mark.slow
def test_report_on_a_generated_dataset_has_partitions_and_baselines(tiny, tmp_path):
    from pressurepose.cli import main

    _, run = tiny
    data = tmp_path / "data"
    assert main(["generate", "--out", str(data), "--preset", "tiny", "--partition", "supine"]) == 0
    out = tmp_path / "report"
    assert main(["evaluate", "--model", str(run), "--data", str(data), "--out", str(out)]) == 0
    record = json.loads((out / "report.json").read_text())
    assert [e["partition"] for e in record["by_partition"]] == ["supine"]
    assert record["by_partition"][0]["seed_synth_vpe_cm"] == 3.40
    assert set(record["baselines_vpe_m"]) == {"mean_body", "nearest_image"}  # from the train split


def test_evaluate_real_3dvpe_against_point_clouds_per_participant(tiny, tmp_path):
    """Clouds made from the network's own estimate (its camera-facing vertices): participant A's
    are exact, B's lifted 5 cm - A's 3DVPE is millimetres, B's about the lift."""
    from pressurepose.cli import main
    from pressurepose.eval.metrics import camera_facing
    from pressurepose.net.inputs import read_pressure_file
    from pressurepose.net.model import NetInputs
    from pressurepose.train.checkpoint import load_network

    root, run = tiny
    images = read_pressure_file(root / "test" / "test.npz")[:4]
    gender = np.array(["female", "male", "female", "male"])
    height, mass = np.array([1.6, 1.8, 1.7, 1.75]), np.array([60.0, 85.0, 70.0, 80.0])
    net, _ = load_network(run)
    with torch.no_grad():
        est = net(
            NetInputs(
                torch.from_numpy(images),
                gender=torch.tensor([1.0, 0.0, 1.0, 0.0]),
                height_m=torch.tensor(height, dtype=torch.float32),
                mass_kg=torch.tensor(mass, dtype=torch.float32),
            ),
            mesh=True,
            maps=False,
        )[-1]
        mask, _ = camera_facing(est.vertices, net.faces)
    lift = 0.05
    clouds = [est.vertices[i][mask[i]].numpy() + (np.array([0, 0, lift]) if i >= 2 else 0) for i in range(4)]
    data = tmp_path / "real.npz"
    np.savez(
        data,
        pressure_mmhg=images,
        subject=np.array(["A", "A", "B", "B"]),
        gender=gender,
        height_m=height,
        mass_kg=mass,
        cloud_points=np.concatenate(clouds).astype(np.float32),
        cloud_offsets=np.concatenate([[0], np.cumsum([len(c) for c in clouds])]),
    )
    out = tmp_path / "report"
    assert main(["evaluate-real", "--model", str(run), "--data", str(data), "--out", str(out), "--batch", "3"]) == 0
    record = json.loads((out / "real.json").read_text())
    a, b = record["by_participant"]["A"], record["by_participant"]["B"]
    assert a["frames"] == b["frames"] == 2 and record["frames"] == 4
    assert a["vpe_m"] < 0.006  # only the 1 cm voxel averaging separates them
    # Never more than the lift (each point's lifted twin is `lift` away; + the voxel averaging),
    # less on the body's sloping sides, where the nearest lifted point is closer.
    assert 0.4 * lift < b["vpe_m"] < lift + 0.006 and b["vpe_m"] > 5 * a["vpe_m"]
    o = record["overall"]
    assert o["vpe_m"] == pytest.approx((a["vpe_m"] + b["vpe_m"]) / 2)
    assert o["vpe_m_over_frames"] == pytest.approx(np.mean([r["vpe_m"] for r in record["per_frame"]]))
    # Height and mass from the estimated shape against the participants' values.
    rows = record["per_frame"]
    assert o["height_mae_m"] == pytest.approx(np.mean([abs(r["estimated_height_m"] - r["height_m"]) for r in rows]))
    assert [r["height_m"] for r in rows] == pytest.approx(height.tolist())
    assert "| A | 2 |" in (out / "real.md").read_text() and (out / "real.png").read_bytes()[:4] == b"\x89PNG"
    # A file without clouds, or with offsets that do not fit, is refused in one line.
    np.savez(data, pressure_mmhg=images, subject=np.array(["A"] * 4))
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "pressurepose.cli",
            "evaluate-real",
            "--model",
            str(run),
            "--data",
            str(data),
            "--out",
            str(tmp_path / "o"),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "missing arrays ['cloud_points', 'cloud_offsets']" in r.stderr
    np.savez(
        data,
        pressure_mmhg=images,
        subject=np.array(["A"] * 4),
        cloud_points=np.zeros((3, 3)),
        cloud_offsets=np.array([0, 1, 1, 2, 3]),
    )
    with pytest.raises(ValueError, match="every frame with at least one point"):
        from pressurepose.commands.evaluate_real import RealEvalConfig, run_evaluate_real

        run_evaluate_real(RealEvalConfig(model=run, data=data, out=tmp_path / "o"))
