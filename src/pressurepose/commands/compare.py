"""`pressurepose compare A B`: two evaluations of the same samples, compared sample by sample.

A and B are output folders (or their JSON files) of `evaluate` on one split, or of
`evaluate-real` on the same PmatData frames (`eval.compare` says what is measured). Differences
read B - A: a negative error difference or a positive posture difference means B is better.
Writes compare.md and compare.json.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import tyro

from pressurepose.commands.outputs import Written
from pressurepose.errors import UserError
from pressurepose.eval.compare import compare_real, compare_synthetic
from pressurepose.files import write_text

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
    """The reference: an `evaluate` or `evaluate-real` output folder, or its report.json / real.json."""
    b: tyro.conf.Positional[Path]
    """The candidate, of the same command on the same samples."""
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
        record = json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise UserError(f"{name}: {path} is not JSON ({exc.msg}, line {exc.lineno})") from None
    command = record.get("command") if isinstance(record, dict) else None
    if command not in _KINDS or record.get("kind") == "point-cloud":
        raise UserError(f"{name}: {path} is not a PmatData `evaluate-real` or an `evaluate` report")
    key = "per_frame" if command == "evaluate-real" else "per_sample"
    if key not in record:
        raise UserError(f"{name}: {path} has no {key} (written by an older version: evaluate again)")
    return record


def run_compare(cfg: CompareConfig) -> Written:
    a, b = _load(cfg.a, "A"), _load(cfg.b, "B")
    if a["command"] != b["command"]:
        raise UserError(f"A is an `{a['command']}` report and B an `{b['command']}` one: compare like with like")
    try:
        if a["command"] == "evaluate":
            if a["config"].get("split") != b["config"].get("split"):
                raise ValueError(f"A read the {a['config'].get('split')} split, B the {b['config'].get('split')} one")
            result = compare_synthetic(a["per_sample"], b["per_sample"])
        else:
            result = compare_real(a["per_frame"], b["per_frame"])
    except ValueError as exc:
        raise UserError(f"{exc}: evaluate both on the same data") from None
    record = {
        "command": "compare",
        "kind": a["command"],
        "a": {"path": str(cfg.a), "model": a["config"].get("model"), "flip_test": a["config"].get("flip_test")},
        "b": {"path": str(cfg.b), "model": b["config"].get("model"), "flip_test": b["config"].get("flip_test")},
        "result": result,
    }
    cfg.out.mkdir(parents=True, exist_ok=True)
    paths = {"json": write_text(cfg.out / "compare.json", json.dumps(record, indent=1))}
    paths["markdown"] = write_text(cfg.out / "compare.md", _markdown(record))
    return Written(paths, record)


def _name(side: dict) -> str:
    return f"{side['model']}{' (flip test)' if side['flip_test'] else ''}"


def _markdown(r: dict) -> str:
    lines = [f"# B = {_name(r['b'])} against A = {_name(r['a'])} (`{r['kind']}`, sample by sample)", ""]
    res = r["result"]
    if r["kind"] == "evaluate":
        lines += [
            f"{res['samples']} samples. Difference B - A, 95% interval (paired t), Wilcoxon signed-rank p; "
            "below 0 = B's error smaller.",
            "",
            "| metric | A | B | B - A [95% CI] | p |",
            "| --- | --- | --- | --- | --- |",
        ]
        for m, d in res["overall"].items():
            label, unit, k = _LABELS[m]
            lines.append(
                f"| {label} ({unit}) | {d['mean_a'] * k:.2f} | {d['mean_b'] * k:.2f} | {d['difference'] * k:+.2f} "
                f"[{d['ci'][0] * k:+.2f}, {d['ci'][1] * k:+.2f}] | {d['p']:.3g} |"
            )
        lines += [
            "",
            "| partition | samples | 3DVPE A / B (cm) | B - A [95% CI] | p |",
            "| --- | --- | --- | --- | --- |",
        ]
        for p, s in res["by_partition"].items():
            d = s["vpe_m"]
            lines.append(
                f"| {p} | {s['samples']} | {d['mean_a'] * 100:.2f} / {d['mean_b'] * 100:.2f} | {d['difference'] * 100:+.2f} "
                f"[{d['ci'][0] * 100:+.2f}, {d['ci'][1] * 100:+.2f}] | {d['p']:.3g} |"
            )
    else:
        lines += [
            "Posture: frames B reads right where A read them wrong (gained) and the reverse (lost), exact "
            "McNemar p, and the accuracy difference's 95% interval resampling whole subjects. Height: "
            "median change of each frame's absolute error (below 0 = B nearer), its interval, Wilcoxon p.",
            "",
            "| mattress | frames | posture A / B | gained / lost | McNemar p | B - A [95% CI] "
            "| height median signed A / B (cm) | abs. error change [95% CI] (cm) | p |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
        for m, s in res.items():
            ci, hci = s["posture_difference_ci"], s["height_abs_change_ci_m"]
            lines.append(
                f"| {m} | {s['frames']} | {s['posture_accuracy_a'] * 100:.1f} / {s['posture_accuracy_b'] * 100:.1f}% | "
                f"{s['posture_gained']} / {s['posture_lost']} | {s['posture_mcnemar_p']:.3g} | "
                f"{(s['posture_accuracy_b'] - s['posture_accuracy_a']) * 100:+.1f} [{ci[0] * 100:+.1f}, {ci[1] * 100:+.1f}] | "
                f"{s['height_median_signed_a_m'] * 100:+.1f} / {s['height_median_signed_b_m'] * 100:+.1f} | "
                f"{s['height_abs_change_median_m'] * 100:+.1f} [{hci[0] * 100:+.1f}, {hci[1] * 100:+.1f}] | "
                f"{s['height_abs_change_p']:.3g} |"
            )
    return "\n".join([*lines, ""])


def compare(cfg: CompareConfig) -> None:
    """Compare two `evaluate` (or two `evaluate-real`) reports of the same samples, sample by
    sample: paired differences with intervals and tests (compare.md, compare.json)."""
    written = run_compare(cfg)
    res = written.record["result"]
    if written.record["kind"] == "evaluate":
        d = res["overall"]["vpe_m"]
        head = f"{res['samples']} samples: 3DVPE B - A {d['difference'] * 100:+.2f} cm [{d['ci'][0] * 100:+.2f}, {d['ci'][1] * 100:+.2f}]"
    else:
        head = "; ".join(
            f"{m}: posture +{s['posture_gained']} / -{s['posture_lost']} frames (McNemar p {s['posture_mcnemar_p']:.2g})"
            for m, s in res.items()
        )
    print(f"{head} -> {written['markdown']}")


__all__ = ["CompareConfig", "compare", "run_compare"]
