"""`pressurepose compare`: paired differences against reference formulas, and its bad inputs."""

from __future__ import annotations

import json
from math import comb

import numpy as np
import pytest
from scipy.stats import t as student_t
from scipy.stats import ttest_rel

from pressurepose.cli import main
from pressurepose.eval.compare import (
    NotComparable,
    compare_real,
    compare_synthetic,
    compare_tilted,
    mcnemar_exact,
    paired_difference,
)


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
    t = diff.mean() / (diff.std(ddof=1) / np.sqrt(diff.size))
    assert d["p"] == pytest.approx(2 * student_t.sf(abs(t), diff.size - 1), rel=1e-6)
    assert d["p"] < 1e-6 and d["p_wilcoxon"] < 1e-6  # a consistent shift of 2 sigma per sample
    same = paired_difference(a, a.copy())
    assert same["difference"] == 0.0 and same["ci"] == [0.0, 0.0] and same["p"] == same["p_wilcoxon"] == 1.0
    nb = a + rng.normal(0, 0.001, 200)
    noise = paired_difference(a, nb)
    assert noise["p"] == pytest.approx(ttest_rel(nb, a).pvalue, rel=1e-9)
    assert (noise["ci"][0] < 0 < noise["ci"][1]) == (noise["p"] > 0.05)  # the interval and its p agree
    shift = paired_difference([1.0, 2.0, 3.0], [1.5, 2.5, 3.5])  # no spread: the interval is the shift itself
    assert shift["ci"] == pytest.approx([0.5, 0.5]) and shift["p"] == 0.0
    with pytest.raises(NotComparable, match="one length"):
        paired_difference(a, b[:-1])
    with pytest.raises(NotComparable, match="not finite"):
        paired_difference(a, np.where(np.arange(200) == 7, np.nan, b))


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
    assert "trunk_spread_change_median_m" not in air  # reports without heatmap spreads
    # two heatmap networks' reports: the median per-frame change of the trunk's spread, B - A
    spread_a = [dict(r, trunk_spread_m=0.12) for r in a]
    spread_b = [dict(r, trunk_spread_m=0.12 - 0.01 * (i < n // 2)) for i, r in enumerate(b)]
    both = compare_real(spread_a, spread_b)
    assert both["air"]["trunk_spread_change_median_m"] == pytest.approx(-0.01)
    assert both["sponge"]["trunk_spread_change_median_m"] == pytest.approx(0.0)
    assert "trunk_spread_change_median_m" not in compare_real(spread_a, b)["air"]  # one side has none
    same = compare_real(a, a)["air"]
    assert (same["posture_gained"], same["posture_lost"], same["posture_mcnemar_p"]) == (0, 0, 1.0)
    assert same["height_abs_change_p"] == 1.0
    with pytest.raises(NotComparable, match="different frames"):
        compare_real(a, b[:-1])
    with pytest.raises(NotComparable, match="twice"):
        compare_real(a, [*b, b[0]])


def test_compare_synthetic_refuses_other_samples():
    a = {"partition": ["supine", "general"] * 5, "gender": ["male"] * 10, "vpe_m": list(np.linspace(0.02, 0.04, 10))}
    shift = 0.001 + np.random.default_rng(1).normal(0, 1e-4, 10)
    b = dict(a, vpe_m=list(np.asarray(a["vpe_m"]) + shift))
    res = compare_synthetic(a, b)
    assert res["samples"] == 10 and set(res["by_partition"]) == {"general", "supine"}
    assert res["overall"]["vpe_m"]["difference"] == pytest.approx(shift.mean(), rel=1e-9)
    assert res["by_partition"]["supine"]["samples"] == 5
    assert "mpjpe_m" not in res["overall"]  # a metric is compared only where both reports hold it
    assert "mpjpe_m" not in compare_synthetic(dict(a, mpjpe_m=a["vpe_m"]), b)["overall"]
    with pytest.raises(NotComparable, match="different samples"):
        compare_synthetic(a, dict(b, partition=["supine"] * 10))
    with pytest.raises(NotComparable, match="different images"):
        compare_synthetic(dict(a, load_ends=["neither"] * 10), dict(b, load_ends=["both"] + ["neither"] * 9))
    with pytest.raises(NotComparable, match=">= 2"):
        compare_synthetic({k: v[:1] for k, v in a.items()}, {k: v[:1] for k, v in b.items()})
    # reports with sample ids: the same shards, rows, seeds and indices, wherever the dataset lies
    ids = [{"dataset": "/x", "shard": "test-s-00000", "row": i, "seed": 3, "index": 100 + i} for i in range(10)]
    moved = [dict(s, dataset="/elsewhere") for s in ids]
    assert compare_synthetic(dict(a, sample_id=ids), dict(b, sample_id=moved))["samples"] == 10
    other = ids[:9] + [dict(ids[9], index=7)]
    with pytest.raises(NotComparable, match="shards, rows or seeds"):
        compare_synthetic(dict(a, sample_id=ids), dict(b, sample_id=other))
    assert compare_synthetic(dict(a, sample_id=[None] * 10), dict(b, sample_id=[None] * 10))["samples"] == 10
    lone = compare_synthetic(
        dict(a, partition=["supine"] * 9 + ["general"]), dict(b, partition=["supine"] * 9 + ["general"])
    )
    assert lone["partitions_left_out"] == {"general": 1} and set(lone["by_partition"]) == {"supine"}


def _write(folder, name, record):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_text(json.dumps(record))
    return folder


def _real_report(rows, **config):
    return {
        "command": "evaluate-real",
        "config": {"model": "a", "groups": "BCD", "threshold": 20.0, **config},
        "per_frame": rows,
    }


def _syn_report(per_sample, **config):
    return {
        "command": "evaluate",
        "config": {"model": "a", "data": "d", "split": "test", "limit": None, **config},
        "per_sample": per_sample,
    }


def test_compare_cli_writes_both_reports(tmp_path, capsys):
    n = 20
    real_a = _write(tmp_path / "ra", "real.json", _real_report(_frames([True] * n, [0.07] * n)))
    right = [True] * n
    right[2] = False
    real_b = _write(tmp_path / "rb", "real.json", _real_report(_frames(right, [0.05] * n), model="b", flip_test=True))
    assert main(["compare", str(real_a), str(real_b / "real.json"), "--out", str(tmp_path / "o")]) == 0
    assert "air: posture +0 / -1 frames" in capsys.readouterr().out
    record = json.loads((tmp_path / "o" / "compare.json").read_text())
    assert record["kind"] == "evaluate-real" and record["result"]["air"]["posture_lost"] == 1
    assert "B = b (flip test) against A = a" in (tmp_path / "o" / "compare.md").read_text()

    rng = np.random.default_rng(2)
    ps = {
        "partition": ["supine"] * 6 + ["general"] * 6,
        "gender": ["female"] * 12,
        "vpe_m": list(rng.uniform(0.02, 0.04, 12)),
    }
    ps["mpjpe_m"] = [3 * v for v in ps["vpe_m"]]
    better = {
        **ps,
        "vpe_m": [v - 0.002 for v in ps["vpe_m"]],
        "mpjpe_m": list(np.asarray(ps["mpjpe_m"]) - rng.uniform(0, 0.01, 12)),
    }
    syn_a = _write(tmp_path / "sa", "report.json", _syn_report(ps))
    syn_b = _write(tmp_path / "sb", "report.json", _syn_report(better, model="b", ik_steps=6))
    assert main(["compare", str(syn_a), str(syn_b), "--out", str(tmp_path / "os")]) == 0
    assert "12 samples: 3DVPE B - A -0.20 cm" in capsys.readouterr().out
    md = (tmp_path / "os" / "compare.md").read_text()
    assert "B = b (6 IK steps) against A = a" in md and "| MPJPE (mm) |" in md and "| supine | 6 |" in md


def test_compare_finds_a_relative_data_path_from_its_report(tmp_path, monkeypatch, capsys):
    """A report records --data as typed (relative to where evaluate ran); B's may be absolute.
    Compare finds both again from another folder, and still refuses two different datasets."""
    (tmp_path / "work" / "data" / "set").mkdir(parents=True)
    (tmp_path / "work" / "data" / "other").mkdir()
    ps = {"partition": ["supine"] * 4, "gender": ["male"] * 4, "vpe_m": [0.03] * 4, "mpjpe_m": [0.09] * 4}
    a = _write(tmp_path / "work" / "eval" / "a", "report.json", _syn_report(ps, data="data/set"))
    b = _write(tmp_path / "b", "report.json", _syn_report(ps, data=str(tmp_path / "work" / "data" / "set")))
    c = _write(tmp_path / "c", "report.json", _syn_report(ps, data=str(tmp_path / "work" / "data" / "other")))
    monkeypatch.chdir(tmp_path)  # not where evaluate ran: data/set is not found from here
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "o")]) == 0
    assert "4 samples" in capsys.readouterr().out
    assert main(["compare", str(a), str(c), "--out", str(tmp_path / "o2")]) == 2
    assert "the same dataset" in capsys.readouterr().err and not (tmp_path / "o2").exists()


def test_compare_reads_the_posture_groups_only(tmp_path, capsys):
    """A report read with group E's tilts (the default since session 59) pairs with one without:
    compare reads the posture table's groups B-D."""
    rows = _frames([True] * 20, [0.07] * 20)
    a = _write(tmp_path / "a", "real.json", _real_report(rows))
    b = _write(tmp_path / "b", "real.json", _real_report(rows, groups="BCDE"))
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "o")]) == 0
    assert "air: posture +0 / -0 frames" in capsys.readouterr().out


def test_compare_cli_refuses_bad_inputs(tmp_path, capsys):
    rows = _frames([True] * 20, [0.07] * 20)
    real_a = _write(tmp_path / "ra", "real.json", _real_report(rows))
    ps = {"partition": ["supine"] * 6, "gender": ["female"] * 6, "vpe_m": [0.03, 0.02, 0.04, 0.03, 0.05, 0.02]}
    syn = _write(tmp_path / "sa", "report.json", _syn_report(ps))
    bad = {
        "other_split": _syn_report(ps, split="train"),
        "other_limit": _syn_report(ps, limit=6),
        "other_data": _syn_report(ps, data="elsewhere"),
        "nan": _syn_report(dict(ps, vpe_m=[0.03, float("nan"), 0.04, 0.03, 0.05, 0.02])),
        "no_partition": _syn_report({"vpe_m": [0.03] * 6}),
        "no_config": {"command": "evaluate-real", "per_frame": rows},
        "no_subject": _real_report([{k: v for k, v in r.items() if k != "subject"} for r in rows]),
        "rows_not_list": _real_report({"file": "x"}),
        "other_threshold": _real_report(rows, threshold=30.0),
        "other_groups": _real_report(rows, groups="BC"),
        "tilts_only": _real_report(rows, groups="E"),
        "short": _real_report(_frames([True] * 10, [0.0] * 10)),
        "cloud": {"command": "evaluate-real", "kind": "point-cloud", "config": {}},
        "other_command": {"command": "train", "config": {}},
    }
    folders = {
        k: _write(tmp_path / k, "report.json" if v.get("command") == "evaluate" else "real.json", v)
        for k, v in bad.items()
    }
    (tmp_path / "nojson").mkdir()
    (tmp_path / "nojson" / "real.json").write_text("{not json")
    (tmp_path / "latin").mkdir()
    (tmp_path / "latin" / "real.json").write_bytes(b'{"command": "\xe9"}' + bytes([0xE9]))
    (tmp_path / "empty").mkdir()
    both = _write(_write(tmp_path / "both", "real.json", {}), "report.json", {})
    cases = [
        ([tmp_path / "empty", real_a], "no report.json or real.json"),
        ([real_a, tmp_path / "absent.json"], "absent.json"),
        ([both, real_a], "holds both"),
        ([real_a, syn], "compare like with like"),
        ([syn, folders["other_split"]], "split"),
        ([syn, folders["other_limit"]], "limit"),
        ([syn, folders["other_data"]], "the same dataset"),
        ([syn, folders["nan"]], "not finite"),
        ([syn, folders["no_partition"]], "damaged"),
        ([folders["no_config"], real_a], "damaged"),
        ([real_a, folders["no_subject"]], "damaged"),
        ([real_a, folders["rows_not_list"]], "damaged"),
        ([real_a, folders["other_threshold"]], "threshold"),
        ([real_a, folders["other_groups"]], "groups BCD, B with BC"),
        ([folders["tilts_only"], folders["tilts_only"]], "neither report read PmatData's groups B-D"),
        ([real_a, folders["short"]], "different frames"),
        ([real_a, folders["cloud"]], "point-cloud"),
        ([real_a, folders["other_command"]], "not an `evaluate`"),
        ([tmp_path / "nojson", real_a], "is not a JSON report"),
        ([tmp_path / "latin", real_a], "is not a JSON report"),
    ]
    for args, message in cases:
        assert main(["compare", *map(str, args), "--out", str(tmp_path / "bad")]) == 2, message
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "bad").exists()  # nothing written for refused inputs


def _tilts(reads: list[float], docs=(20.0, -40.0, 20.0, -20.0)) -> list[dict]:
    """Group E-like rows: four air frames of two subjects."""
    return [
        {"file": f"E/f{i}.txt", "subject": i // 2, "mattress": "air", "documented_roll_deg": d, "roll_deg": r}
        for i, (d, r) in enumerate(zip(docs, reads))
    ]


def test_compare_cli_pairs_the_raised_beds_when_both_read_them(tmp_path, capsys):
    """Group F's rows pair as the flat ones do (read supine = right), in a table of their own; a
    report without them pairs on B-D alone, with a note."""
    rows = _frames([True] * 20, [0.07] * 20)
    raised_a = _frames([True, False, False, True] + [True] * 4, [0.10] * 8)  # air: the first four
    raised_b = _frames([True, True, True, False] + [True] * 4, [0.05] * 8)

    def report(raised):
        return {**_real_report(rows, groups="BCDF"), "raised": {"per_frame": raised}}

    a = _write(tmp_path / "a", "real.json", report(raised_a))
    b = _write(tmp_path / "b", "real.json", report(raised_b))
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "o")]) == 0
    assert "raised air: supine +2 / -1, height error -5.0 cm" in capsys.readouterr().out
    record = json.loads((tmp_path / "o" / "compare.json").read_text())
    assert record["raised"] == compare_real(raised_a, raised_b)
    text = (tmp_path / "o" / "compare.md").read_text()
    assert "Raised beds (group F" in text and "| air | 4 | 50.0 / 75.0% | 2 / 1 |" in text
    flat = _write(tmp_path / "flat", "real.json", _real_report(rows))
    assert main(["compare", str(flat), str(b), "--out", str(tmp_path / "o2")]) == 0
    record = json.loads((tmp_path / "o2" / "compare.json").read_text())
    assert "raised" not in record and record["raised_note"].startswith("only B read group F")
    assert main(["compare", str(a), str(flat), "--out", str(tmp_path / "o4")]) == 0
    assert json.loads((tmp_path / "o4" / "compare.json").read_text())["raised_note"].startswith("only A read group F")
    other = _write(tmp_path / "other", "real.json", report(raised_b[:6]))  # two raised frames fewer
    capsys.readouterr()
    assert main(["compare", str(a), str(other), "--out", str(tmp_path / "o5")]) == 2
    assert "group F: the two reports read different frames" in capsys.readouterr().err
    damaged = _write(tmp_path / "d", "real.json", {**_real_report(rows), "raised": {"per_frame": [{"file": "x"}]}})
    capsys.readouterr()
    assert main(["compare", str(a), str(damaged), "--out", str(tmp_path / "o3")]) == 2
    assert "damaged" in capsys.readouterr().err


def test_compare_tilted_by_hand():
    """Turned = 10-135 deg toward the documented side. A: 25 (turned), 0, 5, -170 against -20 (170
    toward it: face down, not turned); B: all four turned. Errors A 5 / 40 / 15 / 150, B 5 / 10 / 5 / 5."""
    res = compare_tilted(_tilts([25, 0, 5, -170]), _tilts([25, -30, 15, -25]))["air"]
    assert res["frames"] == 4 and res["turned_a"] == 0.25 and res["turned_b"] == 1.0
    assert (res["turned_gained"], res["turned_lost"]) == (3, 0) and res["turned_mcnemar_p"] == mcnemar_exact(3, 0)
    assert res["roll_error_change_median_deg"] == pytest.approx(-20.0)  # changes 0, -30, -10, -145
    lo, hi = res["roll_error_change_ci_deg"]
    assert -145.0 <= lo <= hi <= 0.0 and 0 < res["roll_error_change_p"] <= 1
    with pytest.raises(NotComparable, match="different tilted frames"):
        compare_tilted(_tilts([1, 2, 3, 4]), _tilts([1, 2, 3, 4])[:3])
    with pytest.raises(NotComparable, match="document"):
        compare_tilted(_tilts([1, 2, 3, 4]), _tilts([1, 2, 3, 4], docs=(20.0, -40.0, 20.0, 20.0)))


def test_compare_cli_pairs_the_tilts_when_both_read_them(tmp_path, capsys):
    rows = _frames([True] * 20, [0.07] * 20)

    def report(reads, **extra):
        return {**_real_report(rows, groups="BCDE"), "tilted": {"per_frame": _tilts(reads)}, **extra}

    a = _write(tmp_path / "a", "real.json", report([25, 0, 5, -170]))
    b = _write(tmp_path / "b", "real.json", report([25, -30, 15, -25]))
    flat = _write(tmp_path / "flat", "real.json", _real_report(rows))
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "o")]) == 0
    assert "tilted air: turned +3 / -0, roll error -20.0 deg" in capsys.readouterr().out
    record = json.loads((tmp_path / "o" / "compare.json").read_text())
    assert record["tilted"]["air"]["turned_gained"] == 3
    assert "| air | 4 | 25 / 100% | 3 / 0 |" in (tmp_path / "o" / "compare.md").read_text()
    assert main(["compare", str(flat), str(b), "--out", str(tmp_path / "o2")]) == 0  # one without: B-D only
    record = json.loads((tmp_path / "o2" / "compare.json").read_text())
    assert "tilted" not in record and record["tilted_note"].startswith("only B read group E")
    assert "only B read group E's tilted frames: not compared" in (tmp_path / "o2" / "compare.md").read_text()
    damaged = _write(tmp_path / "d", "real.json", {**_real_report(rows, groups="BCDE"), "tilted": {"per_frame": [{}]}})
    capsys.readouterr()
    assert main(["compare", str(a), str(damaged), "--out", str(tmp_path / "o3")]) == 2
    assert "damaged" in capsys.readouterr().err
