"""Paired comparison of two evaluations of the same samples (`pressurepose compare`).

Two networks read the same test split or the same real frames; their difference is measured
sample by sample, which resolves far smaller differences than comparing two means with their
own intervals (a hard sample is hard for both). Synthetic reports (`evaluate`): per metric, the
mean paired difference B - A with its 95% interval and p (paired t), and the Wilcoxon
signed-rank p beside it (no assumption of normal differences; it tests their median).
Real reports (`evaluate-real`, PmatData): per mattress, the postures B reads right where A read
them wrong and the reverse, the exact McNemar p (a binomial test on those discordant frames),
and the accuracy difference's 95% interval resampling whole subjects (a subject's frames are
not independent: McNemar alone overstates the evidence); the heights likewise, by each frame's
change of absolute error.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import stats

from pressurepose.eval.real import roll_error, subject_interval, turned_toward

REAL_FIELDS = ("file", "subject", "mattress", "posture", "estimated_posture", "height_m", "estimated_height_m")


class NotComparable(ValueError):
    """The two reports cannot be paired (other samples or frames, too few, damaged values)."""


SYNTHETIC_METRICS = (
    "vpe_m",
    "mpjpe_m",
    "pa_mpjpe_m",
    "joints_arms_m",
    "joints_legs_m",
    "height_err_m",
)


def paired_difference(a: Sequence[float], b: Sequence[float]) -> dict:
    """Mean of b - a with its 95% interval and two-sided p (paired t), and the two-sided
    Wilcoxon signed-rank p; identical inputs give a zero interval and p 1."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if a.shape != b.shape or a.ndim != 1 or a.size < 2:
        raise NotComparable(f"paired values must be two 1-D arrays of one length >= 2, got {a.shape} / {b.shape}")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise NotComparable(f"{int((~np.isfinite(a)).sum() + (~np.isfinite(b)).sum())} values are not finite")
    d = b - a
    out = {"mean_a": float(a.mean()), "mean_b": float(b.mean()), "difference": float(d.mean())}
    if not np.any(d):
        return {**out, "ci": [0.0, 0.0], "p": 1.0, "p_wilcoxon": 1.0}
    if np.ptp(d) <= 1e-12 * np.abs(d).max():  # one constant shift: no spread to test against
        return {**out, "ci": [float(d.mean())] * 2, "p": 0.0, "p_wilcoxon": float(stats.wilcoxon(d).pvalue)}
    t = stats.ttest_rel(b, a)
    ci = t.confidence_interval(0.95)
    return {
        **out,
        "ci": [float(ci.low), float(ci.high)],
        "p": float(t.pvalue),
        "p_wilcoxon": float(stats.wilcoxon(d).pvalue),
    }


def mcnemar_exact(gained: int, lost: int) -> float:
    """Two-sided exact McNemar p: under "A and B are as good", each discordant frame is B's
    gain or loss with probability 1/2."""
    if gained < 0 or lost < 0:
        raise ValueError(f"counts must be >= 0, got {gained} / {lost}")
    n = gained + lost
    return 1.0 if n == 0 else float(stats.binomtest(gained, n, 0.5).pvalue)


def _made_as(per_sample: dict) -> list:
    """Each sample's shard, row, dataset seed and sampler index (`evaluate`'s `sample_id`; the
    dataset's folder left out: the same data may lie elsewhere)."""
    return [None if s is None else (s["shard"], s["row"], s["seed"], s["index"]) for s in per_sample["sample_id"]]


def compare_synthetic(a: dict, b: dict) -> dict:
    """`per_sample` columns of two `evaluate` reports of the same samples -> overall and per
    partition paired differences (a metric is compared when both reports hold it; partitions of
    fewer than 2 samples are counted in `partitions_left_out`)."""
    n = len(a["partition"])
    if n < 2:
        raise NotComparable(f"the reports hold {n} sample(s); a paired comparison needs >= 2")
    if len(b["partition"]) != n or a["partition"] != b["partition"] or a.get("gender") != b.get("gender"):
        raise NotComparable("the two reports hold different samples (counts, partitions or genders differ)")
    if "load_ends" in a and "load_ends" in b and a["load_ends"] != b["load_ends"]:
        raise NotComparable("the two reports hold different images (where their loads lie differs)")
    if "sample_id" in a and "sample_id" in b and _made_as(a) != _made_as(b):
        raise NotComparable("the two reports hold different samples (their shards, rows or seeds differ)")
    metrics = [m for m in SYNTHETIC_METRICS if m in a and m in b]
    out = {"samples": n, "overall": {}, "by_partition": {}, "partitions_left_out": {}}
    for m in metrics:
        try:
            out["overall"][m] = paired_difference(a[m], b[m])
        except NotComparable as exc:
            raise NotComparable(f"{m}: {exc}") from None
    parts = np.asarray(a["partition"])
    for p in sorted(set(a["partition"])):
        idx = np.flatnonzero(parts == p)
        if idx.size < 2:
            out["partitions_left_out"][p] = int(idx.size)
            continue
        out["by_partition"][p] = {
            "samples": int(idx.size),
            "vpe_m": paired_difference(np.asarray(a["vpe_m"])[idx], np.asarray(b["vpe_m"])[idx]),
        }
    return out


def compare_real(a: list[dict], b: list[dict]) -> dict:
    """`per_frame` rows of two `evaluate-real` reports of the same frames -> per mattress."""
    by_file = {r["file"]: r for r in b}
    files = [r["file"] for r in a]
    if len(by_file) != len(b) or len(set(files)) != len(files):
        raise NotComparable("a report lists one frame twice")
    if set(files) != set(by_file):
        only_a, only_b = len(set(files) - set(by_file)), len(set(by_file) - set(files))
        raise NotComparable(f"the two reports read different frames ({only_a} only in A, {only_b} only in B)")
    heights = np.array([[r["estimated_height_m"], by_file[r["file"]]["estimated_height_m"]] for r in a], dtype=float)
    if not np.isfinite(heights).all():
        raise NotComparable(f"{int((~np.isfinite(heights)).sum())} estimated heights are not finite")
    out = {}
    for mattress in sorted({r["mattress"] for r in a}):
        ra = [r for r in a if r["mattress"] == mattress]
        rb = [by_file[r["file"]] for r in ra]
        right_a = np.array([r["estimated_posture"] == r["posture"] for r in ra], dtype=float)
        right_b = np.array([r["estimated_posture"] == r["posture"] for r in rb], dtype=float)
        subjects = [r["subject"] for r in ra]
        gained, lost = int(((right_b == 1) & (right_a == 0)).sum()), int(((right_b == 0) & (right_a == 1)).sum())
        err_a = np.array([r["estimated_height_m"] - r["height_m"] for r in ra])
        err_b = np.array([r["estimated_height_m"] - r["height_m"] for r in rb])
        change = np.abs(err_b) - np.abs(err_a)
        out[mattress] = {
            "frames": len(ra),
            "subjects": len(set(subjects)),
            "posture_accuracy_a": float(right_a.mean()),
            "posture_accuracy_b": float(right_b.mean()),
            "posture_gained": gained,
            "posture_lost": lost,
            "posture_mcnemar_p": mcnemar_exact(gained, lost),
            "posture_difference_ci": list(subject_interval(right_b - right_a, subjects, np.mean)),
            "height_median_signed_a_m": float(np.median(err_a)),
            "height_median_signed_b_m": float(np.median(err_b)),
            "height_abs_change_median_m": float(np.median(change)),
            "height_abs_change_ci_m": list(subject_interval(change, subjects, np.median)),
            "height_abs_change_p": 1.0 if not np.any(change) else float(stats.wilcoxon(change).pvalue),
        }
        if all("trunk_spread_m" in r for r in (*ra, *rb)):  # two heatmap networks: which is surer
            spread = np.array([r["trunk_spread_m"] for r in rb]) - np.array([r["trunk_spread_m"] for r in ra])
            out[mattress]["trunk_spread_change_median_m"] = float(np.median(spread))
            out[mattress]["trunk_spread_change_ci_m"] = list(subject_interval(spread, subjects, np.median))
    return out


TILTED_FIELDS = ("file", "subject", "mattress", "documented_roll_deg", "roll_deg")


def compare_tilted(a: list[dict], b: list[dict]) -> dict:
    """`tilted.per_frame` rows of two `evaluate-real` reports of the same frames (PmatData group
    E) -> per mattress: frames read turned toward their side by B and not A (gained) and the
    reverse (lost, exact McNemar p), and the median per-frame change of the absolute roll error
    (B - A, deg) with its interval resampling whole subjects and the Wilcoxon p."""
    by_file = {r["file"]: r for r in b}
    files = [r["file"] for r in a]
    if len(by_file) != len(b) or len(set(files)) != len(files) or set(files) != set(by_file):
        raise NotComparable("the two reports read different tilted frames")
    out = {}
    for mattress in sorted({r["mattress"] for r in a}):
        ra = [r for r in a if r["mattress"] == mattress]
        rb = [by_file[r["file"]] for r in ra]
        doc = np.array([r["documented_roll_deg"] for r in ra], dtype=float)
        if any(r["documented_roll_deg"] != by_file[r["file"]]["documented_roll_deg"] for r in ra):
            raise NotComparable("the two reports document the tilted frames' rolls differently")
        read_a, read_b = (np.array([r["roll_deg"] for r in rows], dtype=float) for rows in (ra, rb))
        if not (np.isfinite(read_a).all() and np.isfinite(read_b).all()):
            raise NotComparable("a read roll is not finite")
        ta, tb = turned_toward(doc, read_a), turned_toward(doc, read_b)
        gained, lost = int((tb & ~ta).sum()), int((ta & ~tb).sum())
        change = roll_error(doc, read_b) - roll_error(doc, read_a)
        subjects = [r["subject"] for r in ra]
        out[mattress] = {
            "frames": len(ra),
            "turned_a": float(ta.mean()),
            "turned_b": float(tb.mean()),
            "turned_gained": gained,
            "turned_lost": lost,
            "turned_mcnemar_p": mcnemar_exact(gained, lost),
            "roll_error_change_median_deg": float(np.median(change)),
            "roll_error_change_ci_deg": list(subject_interval(change, subjects, np.median)),
            "roll_error_change_p": 1.0 if not np.any(change) else float(stats.wilcoxon(change).pvalue),
        }
    return out


__all__ = [
    "REAL_FIELDS",
    "TILTED_FIELDS",
    "SYNTHETIC_METRICS",
    "NotComparable",
    "compare_real",
    "compare_tilted",
    "compare_synthetic",
    "mcnemar_exact",
    "paired_difference",
]
