"""`pressurepose compare`: paired differences against reference formulas, and its bad inputs."""

from __future__ import annotations

import json
from math import comb

import numpy as np
import pytest
from scipy.stats import t as student_t

from pressurepose.cli import main
from pressurepose.eval.compare import compare_real, compare_synthetic, mcnemar_exact, paired_difference


def test_paired_difference_matches_the_paired_t_interval():
    rng = np.random.default_rng(0)
    a = rng.uniform(0.02, 0.05, 200)
    b = a + 0.002 + rng.normal(0, 0.001, 200)
    d = paired_difference(a, b)
    diff = b - a
    half = student_t.ppf(0.975, diff.size - 1) * diff.std(ddof=1) / np.sqrt(diff.size)
    assert d["difference"] == pytest.approx(diff.mean(), rel=1e-12)
    assert d["ci"] == pytest.approx([diff.mean() - half, diff.mean() + half], rel=1e-9)
    assert d["mean_a"] == pytest.approx(a.mean()) and d["mean_b"] == pytest.approx(b.mean())
    assert d["p"] < 1e-6  # a consistent shift of 2 sigma per sample
    same = paired_difference(a, a.copy())
    assert same["difference"] == 0.0 and same["ci"] == [0.0, 0.0] and same["p"] == 1.0
    noise = paired_difference(a, a + rng.normal(0, 0.001, 200))
    assert noise["ci"][0] < 0 < noise["ci"][1]
    with pytest.raises(ValueError, match="one length"):
        paired_difference(a, b[:-1])


@pytest.mark.parametrize("gained,lost", [(0, 0), (0, 6), (6, 11), (1, 9), (7, 7), (12, 0)])
def test_mcnemar_exact_matches_the_binomial_sum(gained, lost):
    n, k = gained + lost, min(gained, lost)
    expected = 1.0 if n == 0 else min(1.0, 2 * sum(comb(n, i) for i in range(k + 1)) / 2**n)
    assert mcnemar_exact(gained, lost) == pytest.approx(expected, rel=1e-9)
    assert mcnemar_exact(gained, lost) == pytest.approx(mcnemar_exact(lost, gained), rel=1e-12)


def _frames(right: list[bool], heights: list[float], seed: int = 0) -> list[dict]:
    """PmatData-like rows: 4 subjects, two mattresses, frames alternately supine / left."""
    rows = []
    for i, (ok, h) in enumerate(zip(right, heights)):
        posture = "supine" if i % 2 else "left"
        rows.append(
            {
                "file": f"S{i % 4}/{'air' if i < len(right) // 2 else 'sponge'}/f{i}.txt",
                "subject": i % 4,
                "mattress": "air" if i < len(right) // 2 else "sponge",
                "posture": posture,
                "estimated_posture": posture if ok else "prone",
                "height_m": 1.75,
                "estimated_height_m": 1.75 + h,
            }
        )
    return rows


def test_compare_real_counts_gains_and_losses_frame_by_frame():
    n = 40
    right_a = [True] * n
    right_b = [True] * n
    right_a[0] = right_a[1] = False  # air: B gains 2 ...
    right_b[3] = False  # ... and loses 1; sponge: B loses 3
    right_b[25] = right_b[26] = right_b[27] = False
    a = _frames(right_a, [0.08] * n)
    b = _frames(right_b, [0.05] * (n // 2) + [0.10] * (n // 2))
    res = compare_real(a, list(reversed(b)))  # rows are matched by file, not by order
    air, sponge = res["air"], res["sponge"]
    assert (air["posture_gained"], air["posture_lost"]) == (2, 1)
    assert (sponge["posture_gained"], sponge["posture_lost"]) == (0, 3)
    assert air["posture_accuracy_a"] == pytest.approx(18 / 20) and air["posture_accuracy_b"] == pytest.approx(19 / 20)
    assert air["posture_mcnemar_p"] == pytest.approx(mcnemar_exact(2, 1))
    lo, hi = sponge["posture_difference_ci"]
    assert lo <= -3 / 20 <= hi <= 0.0
    assert air["height_abs_change_median_m"] == pytest.approx(-0.03)
    assert sponge["height_abs_change_median_m"] == pytest.approx(0.02)
    assert air["height_median_signed_a_m"] == pytest.approx(0.08) and sponge[
        "height_median_signed_b_m"
    ] == pytest.approx(0.10)
    same = compare_real(a, a)["air"]
    assert (same["posture_gained"], same["posture_lost"], same["posture_mcnemar_p"]) == (0, 0, 1.0)
    assert same["height_abs_change_p"] == 1.0
    with pytest.raises(ValueError, match="different frames"):
        compare_real(a, b[:-1])


def test_compare_synthetic_refuses_other_samples():
    a = {"partition": ["supine", "general"] * 5, "gender": ["male"] * 10, "vpe_m": list(np.linspace(0.02, 0.04, 10))}
    shift = 0.001 + np.random.default_rng(1).normal(0, 1e-4, 10)
    b = dict(a, vpe_m=list(np.asarray(a["vpe_m"]) + shift))
    res = compare_synthetic(a, b)
    assert res["samples"] == 10 and set(res["by_partition"]) == {"general", "supine"}
    assert res["overall"]["vpe_m"]["difference"] == pytest.approx(shift.mean(), rel=1e-9)
    assert res["by_partition"]["supine"]["samples"] == 5
    assert "mpjpe_m" not in res["overall"]  # metrics neither report holds are left out
    with pytest.raises(ValueError, match="different samples"):
        compare_synthetic(a, dict(b, partition=["supine"] * 10))


def _write(folder, name, record):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_text(json.dumps(record))
    return folder


def test_compare_cli_writes_the_report_and_refuses_bad_inputs(tmp_path, capsys):
    n = 20
    real_a = _write(
        tmp_path / "ra",
        "real.json",
        {
            "command": "evaluate-real",
            "config": {"model": "a", "flip_test": False},
            "per_frame": _frames([True] * n, [0.07] * n),
        },
    )
    right = [True] * n
    right[2] = False
    real_b = _write(
        tmp_path / "rb",
        "real.json",
        {
            "command": "evaluate-real",
            "config": {"model": "b", "flip_test": True},
            "per_frame": _frames(right, [0.05] * n),
        },
    )
    assert main(["compare", str(real_a), str(real_b / "real.json"), "--out", str(tmp_path / "o")]) == 0
    assert "air: posture +0 / -1 frames" in capsys.readouterr().out
    record = json.loads((tmp_path / "o" / "compare.json").read_text())
    assert record["kind"] == "evaluate-real" and record["result"]["air"]["posture_lost"] == 1
    assert "b (flip test) against A = a" in (tmp_path / "o" / "compare.md").read_text()

    per_sample = {"partition": ["supine"] * 6, "gender": ["female"] * 6, "vpe_m": [0.03] * 6, "mpjpe_m": [0.08] * 6}
    syn = _write(
        tmp_path / "sa",
        "report.json",
        {"command": "evaluate", "config": {"model": "a", "split": "test"}, "per_sample": per_sample},
    )
    other_split = _write(
        tmp_path / "sb",
        "report.json",
        {"command": "evaluate", "config": {"model": "b", "split": "train"}, "per_sample": per_sample},
    )
    (tmp_path / "nojson").mkdir()
    (tmp_path / "nojson" / "real.json").write_text("{not json")
    short = _write(
        tmp_path / "rc",
        "real.json",
        {"command": "evaluate-real", "config": {"model": "c"}, "per_frame": _frames([True] * 10, [0.0] * 10)},
    )
    (tmp_path / "empty_dir_missing").mkdir()
    both = _write(_write(tmp_path / "both", "real.json", {}), "report.json", {})
    cases = [
        ([str(tmp_path / "empty_dir_missing"), str(real_a)], "no report.json or real.json"),
        ([str(real_a), str(tmp_path / "absent.json")], "absent.json"),
        ([str(both), str(real_a)], "holds both"),
        ([str(real_a), str(syn)], "compare like with like"),
        ([str(syn), str(other_split)], "split"),
        ([str(tmp_path / "nojson"), str(real_a)], "is not JSON"),
        ([str(real_a), str(short)], "different frames"),
    ]
    for args, message in cases:
        assert main(["compare", *args, "--out", str(tmp_path / "bad")]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "bad" / "compare.json").exists()  # nothing written for refused inputs
