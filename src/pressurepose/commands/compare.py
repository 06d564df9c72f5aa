"""`pressurepose compare A B`: two evaluations of the same samples, compared sample by sample.

A and B are output folders (or their JSON files) of `evaluate` on one dataset and split, or of
`evaluate-real` on the same PmatData frames (`eval.compare` says what is measured). Differences
read B - A: a negative error difference or a positive posture difference means B is better.
Writes compare.md and compare.json.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import tyro

from pressurepose.commands.netopts import recorded_options_label
from pressurepose.commands.outputs import Written
from pressurepose.errors import UserError
from pressurepose.eval.compare import (
    REAL_FIELDS,
    TILTED_FIELDS,
    NotComparable,
    compare_real,
    compare_synthetic,
    compare_tilted,
)
from pressurepose.eval.real import GROUP_POSTURE
from pressurepose.files import write_text
from pressurepose.validate import resolve_recorded

_KINDS = {"evaluate": "report.json", "evaluate-real": "real.json"}
_LABELS = {
    "vpe_m": ("3DVPE", "cm", 100),
    "mpjpe_m": ("MPJPE", "mm", 1000),
    "pa_mpjpe_m": ("PA-MPJPE", "mm", 1000),
    "joints_arms_m": ("arm joints", "cm", 100),
    "joints_legs_m": ("leg joints", "cm", 100),
    "height_err_m": ("height error", "cm", 100),
}


@dataclasses.dataclass(frozen=True)
class CompareConfig:
    """Compare two evaluations of the same samples (B - A, sample by sample)."""

    a: tyro.conf.Positional[Path]
    """A, the reference: an `evaluate` or `evaluate-real` output folder, or its report.json / real.json."""
    b: tyro.conf.Positional[Path]
    """B, the candidate: the same command's output on the same samples."""
    out: Path = Path("out/compare")
    """Report folder: compare.md, compare.json."""


def _load(path: Path, name: str) -> dict:
    if path.is_dir():
        found = [path / f for f in _KINDS.values() if (path / f).is_file()]
        if not found:
            raise UserError(f"{name}: {path} holds no report.json or real.json (an evaluate / evaluate-real output)")
        if len(found) > 1:
            raise UserError(f"{name}: {path} holds both report.json and real.json: name the file to compare")
        path = found[0]
    try:
        record = json.loads(Path(path).read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(
            f"{name}: {path} is not a JSON report ({exc}); give an evaluate / evaluate-real output"
        ) from None
    command = record.get("command") if isinstance(record, dict) else None
    if command not in _KINDS:
        raise UserError(f"{name}: {path} is not an `evaluate` or `evaluate-real` report; give one of their outputs")
    if record.get("kind") == "point-cloud":
        raise UserError(f"{name}: {path} is a point-cloud report (evaluate-real --data); compare PmatData reports")
    if not _well_formed(record):
        raise UserError(f"{name}: {path} is damaged or from an older version (its per-sample rows): evaluate again")
    return record


def _compare_raised(a: list[dict], b: list[dict]) -> dict:
    try:
        return compare_real(a, b)
    except NotComparable as exc:
        raise NotComparable(f"group F: {exc}") from None


# The groups `evaluate-real` reports apart from the flat table: their rows' fields, how a pair of
# reports compares them, and what they are called when only one report read them.
_APART = {
    "tilted": (TILTED_FIELDS, compare_tilted, "group E's tilted frames"),
    "raised": (REAL_FIELDS, _compare_raised, "group F's raised beds"),
}


def _well_formed(record: dict) -> bool:
    if not isinstance(record.get("config"), dict):
        return False
    if record["command"] == "evaluate":
        rows = record.get("per_sample")
        if not isinstance(rows, dict) or not isinstance(rows.get("partition"), list) or "vpe_m" not in rows:
            return False
        return all(isinstance(v, list) and len(v) == len(rows["partition"]) for v in rows.values())
    # the flat groups' rows; group E's (since session 59) and F's (since session 60) when present
    parts = [(record, REAL_FIELDS)] + [(record[k], part[0]) for k, part in _APART.items() if k in record]
    return all(isinstance(part, dict) and _rows_ok(part.get("per_frame"), fields) for part, fields in parts)


def _rows_ok(rows, fields: tuple[str, ...]) -> bool:
    return isinstance(rows, list) and all(isinstance(r, dict) and all(k in r for k in fields) for r in rows)


def _same_path(x, y, near_x: Path, near_y: Path) -> bool:
    """Two recorded paths name one dataset: equal as written, or the same folder once each is
    found again (as given, or relative to its report's folder or their parents)."""
    if x == y:
        return True
    px, py = resolve_recorded(x, near_x), resolve_recorded(y, near_y)
    try:
        return px is not None and py is not None and px.samefile(py)
    except OSError:
        return False


def _check_pairing(a: dict, b: dict, near_a: Path, near_b: Path) -> None:
    """The two reports' settings that decide which samples (and images) they read agree."""
    ca, cb = a["config"], b["config"]
    if a["command"] == "evaluate":
        if not _same_path(ca.get("data"), cb.get("data"), near_a, near_b):
            raise UserError(f"A read {ca.get('data')} and B {cb.get('data')}: evaluate both on the same dataset")
        keys, what = ("split", "limit"), "was evaluated with"
    else:
        keys, what = ("groups", "threshold"), "read PmatData with"
    for key in keys:
        va, vb = ca.get(key), cb.get(key)
        if key == "groups":  # the posture table's groups (B-D): group E's tilts are not compared
            va, vb = (None if v is None else "".join(sorted(g for g in set(v) if g in GROUP_POSTURE)) for v in (va, vb))
            apart = any(k in a and k in b for k in _APART)  # groups E or F read by both
            if va == vb == "" and not apart:
                raise UserError("neither report read PmatData's groups B-D: compare reads their posture tables")
        if va != vb:
            raise UserError(
                f"A {what} {key} {va or '(none of B-D)'}, B with {vb or '(none of B-D)'}: evaluate both alike"
            )


def _side(record: dict, path: Path) -> dict:
    c = record["config"]
    return {
        "path": str(path),
        "model": c.get("model"),
        "options": recorded_options_label(c),
    }


def run_compare(cfg: CompareConfig) -> Written:
    a, b = _load(cfg.a, "A"), _load(cfg.b, "B")
    if a["command"] != b["command"]:
        raise UserError(f"A is an `{a['command']}` report and B an `{b['command']}` one: compare like with like")
    _check_pairing(a, b, *(p if p.is_dir() else p.parent for p in (cfg.a, cfg.b)))
    try:
        if a["command"] == "evaluate":
            result = compare_synthetic(a["per_sample"], b["per_sample"])
        else:
            result = compare_real(a["per_frame"], b["per_frame"])
            apart = _compare_apart(a, b)
    except NotComparable as exc:
        raise UserError(f"{exc}: compare two evaluations of the same samples") from None
    record = {"command": "compare", "kind": a["command"], "a": _side(a, cfg.a), "b": _side(b, cfg.b), "result": result}
    if a["command"] == "evaluate-real":
        record.update(apart)
    text, markdown = json.dumps(record, indent=1, allow_nan=False), _markdown(record)  # both before any file
    cfg.out.mkdir(parents=True, exist_ok=True)
    paths = {"json": write_text(cfg.out / "compare.json", text)}
    paths["markdown"] = write_text(cfg.out / "compare.md", markdown)
    return Written(paths, record)


def _compare_apart(a: dict, b: dict) -> dict:
    """{key: the paired comparison} for each group both reports read apart (a report without one
    pairs on the rest), {key_note: ...} for each only one of them read."""
    out = {}
    for key, (_, compare, name) in _APART.items():
        if key in a and key in b:
            out[key] = compare(a[key]["per_frame"], b[key]["per_frame"])
        elif key in a or key in b:
            out[f"{key}_note"] = f"only {'A' if key in a else 'B'} read {name}: not compared"
    return out


def _synthetic_lines(res: dict) -> list[str]:
    lines = [
        f"{res['samples']} samples. Difference B - A with its 95% interval and p (paired t); the Wilcoxon "
        "signed-rank p (the differences' median, no normality assumed) beside it. Below 0 = B's error smaller.",
        "",
        "| metric | A | B | B - A [95% CI] | p (t) | p (Wilcoxon) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for m, d in res["overall"].items():
        label, unit, k = _LABELS[m]
        lines.append(
            f"| {label} ({unit}) | {d['mean_a'] * k:.2f} | {d['mean_b'] * k:.2f} | {d['difference'] * k:+.2f} "
            f"[{d['ci'][0] * k:+.2f}, {d['ci'][1] * k:+.2f}] | {d['p']:.3g} | {d['p_wilcoxon']:.3g} |"
        )
    lines += [
        "",
        "| partition | samples | 3DVPE A / B (cm) | B - A [95% CI] | p (t) |",
        "| --- | --- | --- | --- | --- |",
    ]
    for p, s in res["by_partition"].items():
        d = s["vpe_m"]
        lines.append(
            f"| {p} | {s['samples']} | {d['mean_a'] * 100:.2f} / {d['mean_b'] * 100:.2f} | "
            f"{d['difference'] * 100:+.2f} [{d['ci'][0] * 100:+.2f}, {d['ci'][1] * 100:+.2f}] | {d['p']:.3g} |"
        )
    if res["partitions_left_out"]:
        left = ", ".join(f"{p} ({n})" for p, n in res["partitions_left_out"].items())
        lines += ["", f"Left out (fewer than 2 samples): {left}"]
    return lines


def _real_lines(res: dict) -> list[str]:
    lines = [
        "Posture: frames B reads right where A read them wrong (gained) and the reverse (lost), exact "
        "McNemar p, and the accuracy difference's 95% interval resampling whole subjects. Height: median "
        "change of each frame's absolute error (below 0 = B nearer), its interval, Wilcoxon p. McNemar "
        "takes frames as independent, the interval does not, and with few discordant frames the interval "
        "is too narrow: read a difference as shown only when both say so.",
        "",
        "| mattress | frames | posture A / B | gained / lost | McNemar p | B - A [95% CI] "
        "| height median signed A / B (cm) | abs. error change [95% CI] (cm) | p |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for m, s in res.items():
        ci, hci = s["posture_difference_ci"], s["height_abs_change_ci_m"]
        acc_a, acc_b = s["posture_accuracy_a"] * 100, s["posture_accuracy_b"] * 100
        lines.append(
            f"| {m} | {s['frames']} | {acc_a:.1f} / {acc_b:.1f}% | {s['posture_gained']} / {s['posture_lost']} | "
            f"{s['posture_mcnemar_p']:.3g} | {acc_b - acc_a:+.1f} [{ci[0] * 100:+.1f}, {ci[1] * 100:+.1f}] | "
            f"{s['height_median_signed_a_m'] * 100:+.1f} / {s['height_median_signed_b_m'] * 100:+.1f} | "
            f"{s['height_abs_change_median_m'] * 100:+.1f} [{hci[0] * 100:+.1f}, {hci[1] * 100:+.1f}] | "
            f"{s['height_abs_change_p']:.3g} |"
        )
    spread = {m: s for m, s in res.items() if "trunk_spread_change_median_m" in s}
    if spread:
        cells = [
            f"{m} {s['trunk_spread_change_median_m'] * 100:+.1f} cm [{s['trunk_spread_change_ci_m'][0] * 100:+.1f}, "
            f"{s['trunk_spread_change_ci_m'][1] * 100:+.1f}]"
            for m, s in spread.items()
        ]
        lines += ["", "Heatmap spread of the head and torso, median change per frame (B - A; below 0 = B surer): "]
        lines[-1] += "; ".join(cells)
    return lines


def _tilted_lines(res: dict | None) -> list[str]:
    """Group E's paired table (`compare_tilted`); none when a report did not read it."""
    if not res:
        return []
    lines = [
        "",
        "Tilted bodies (group E): frames B reads turned toward their side (10-135 deg) where A did not "
        "(gained) and the reverse (lost), exact McNemar p; the median change of each frame's absolute "
        "roll error (B - A, below 0 = B nearer), its 95% interval resampling whole subjects, Wilcoxon p.",
        "",
        "| mattress | frames | turned A / B | gained / lost | McNemar p | roll error change [95% CI] (deg) | p |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for m, s in res.items():
        ci = s["roll_error_change_ci_deg"]
        lines.append(
            f"| {m} | {s['frames']} | {s['turned_a'] * 100:.0f} / {s['turned_b'] * 100:.0f}% | "
            f"{s['turned_gained']} / {s['turned_lost']} | {s['turned_mcnemar_p']:.3g} | "
            f"{s['roll_error_change_median_deg']:+.1f} [{ci[0]:+.1f}, {ci[1]:+.1f}] | {s['roll_error_change_p']:.3g} |"
        )
    return lines


def _markdown(r: dict) -> str:
    name = lambda side: f"{side['model']}{side['options']}"  # noqa: E731
    lines = [
        f"# B = {name(r['b'])} against A = {name(r['a'])} (`{r['kind']}`, sample by sample)",
        "",
        f"A: `{r['a']['path']}`; B: `{r['b']['path']}`",
        "",
    ]
    if r["kind"] == "evaluate":
        body = _synthetic_lines(r["result"])
    else:  # the flat groups' table unless neither report read them (groups E or F alone)
        body = _real_lines(r["result"]) if r["result"] else ["Groups B-D: read by neither report."]
    body += _tilted_lines(r.get("tilted")) + (["", r["tilted_note"]] if "tilted_note" in r else [])
    if r.get("raised"):
        body += [
            "",
            "Raised beds (group F: supine, the head of the bed raised 0-60 deg; posture = read supine), as above:",
            "",
        ]
        body += _real_lines(r["raised"])[2:]
    body += ["", r["raised_note"]] if "raised_note" in r else []
    return "\n".join([*lines, *body, ""])


def compare(cfg: CompareConfig) -> None:
    """Compare two `evaluate` (or two `evaluate-real`) reports of the same samples, sample by
    sample: paired differences with intervals and tests (compare.md, compare.json)."""
    written = run_compare(cfg)
    res = written.record["result"]
    if written.record["kind"] == "evaluate":
        d = res["overall"]["vpe_m"]
        head = (
            f"{res['samples']} samples: 3DVPE B - A {d['difference'] * 100:+.2f} cm "
            f"[{d['ci'][0] * 100:+.2f}, {d['ci'][1] * 100:+.2f}]"
        )
    else:
        head = "; ".join(
            f"{m}: posture +{s['posture_gained']} / -{s['posture_lost']} frames (McNemar p {s['posture_mcnemar_p']:.2g})"
            for m, s in res.items()
        )
        head += "".join(
            f"; tilted {m}: turned +{s['turned_gained']} / -{s['turned_lost']}, roll error "
            f"{s['roll_error_change_median_deg']:+.1f} deg"
            for m, s in (written.record.get("tilted") or {}).items()
        )
        head += "".join(
            f"; raised {m}: supine +{s['posture_gained']} / -{s['posture_lost']}, height error "
            f"{s['height_abs_change_median_m'] * 100:+.1f} cm"
            for m, s in (written.record.get("raised") or {}).items()
        )
        head = head.removeprefix("; ")
    print(f"{head} -> {written['markdown']}")


__all__ = ["CompareConfig", "compare", "run_compare"]
