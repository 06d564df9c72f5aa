"""The `pressurepose realism` report's records and markdown (`commands.realism` runs it): per
posture and mattress the frame sets' measures, the comparison, load per region, transverse
bands and the real-vs-real ceiling."""

from __future__ import annotations

import dataclasses

from pressurepose.commands.realism_raised import raised_markdown
from pressurepose.commands.realism_tilted import tilted_markdown
from pressurepose.eval import realism as R


def set_dict(s: R.FrameSet) -> dict:
    return {
        "frames": s.n,
        "area_m2": round(s.area_m2, 4),
        "mean_mmhg": round(s.mean_mmhg, 2),
        "peak_mmhg": round(s.peak_mmhg, 1),
        "p99_mmhg": round(s.p99_mmhg, 1),
        "extent": round(s.extent, 3),
        "coverage": round(s.coverage, 3),
        "regions": {k: round(v, 3) for k, v in s.regions.items()},
        "area_tenths": [round(float(v), 1) for v in s.area_tenths],
        "head_end": [round(float(v), 4) for v in s.head_end],
    }


def bands_dict(b: R.Bands) -> dict:
    return {k: round(v, 4) for k, v in dataclasses.asdict(b).items()}


def _paired_table(record: dict, key: str, caption: str, columns: list[str], fmt: str) -> list[str]:
    """Markdown lines of one table: per posture and mattress, `key`'s values simulated / real."""
    lines = ["", caption, "", "| posture | mattress | " + " | ".join(columns) + " |"]
    lines.append("| --- | --- |" + " --- |" * len(columns))
    for r in record["rows"]:
        s, re_ = r["simulated"], r["real"]
        if s and key in s:
            pairs = (f"{fmt.format(a)} / {fmt.format(b)}" for a, b in zip(s[key], re_[key]))
            lines.append(f"| {r['posture']} | {r['mattress']} | " + " | ".join(pairs) + " |")
    return lines


def markdown(record: dict) -> str:
    lines = [
        "# Realism: simulated vs real pressure images",
        "",
        f"sim #2 `{record['config']['sim2']}`, sim #1 `{record['config']['settle']}`, "
        f"placement `{record['config']['placement']}`, "
        f"real frames `{record['config']['real']}`",
        "",
        "| posture | mattress | along | across | area sim/real | coverage sim (real) | mean mmHg sim (real) "
        "| peak mmHg sim (real) | bodies |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in record["rows"]:
        s, re_, c = r["simulated"], r["real"], r.get("comparison")
        if not s:
            lines.append(
                f"| {r['posture']} | {r['mattress']} | - | - | - | - | - | - | 0 ({len(r['rejected'])} rejected) |"
            )
            continue
        moving = f" ({r['still_moving']} still moving)" if r.get("still_moving") else ""
        lines.append(
            f"| {r['posture']} | {r['mattress']} | {c['along']:.3f} | {c['across']:.3f} | {c['area_ratio']:.2f} "
            f"| {s['coverage']:.2f} ({re_['coverage']:.2f}) | {s['mean_mmhg']:.1f} ({re_['mean_mmhg']:.1f}) "
            f"| {s['peak_mmhg']:.0f} ({re_['peak_mmhg']:.0f}) | {r['simulated_bodies']}{moving} |"
        )
    lines += [
        "",
        "High pressure (99th percentile of the loaded taxels, median over frames) and the load's length "
        "along the bed over the subject's height (rows holding >= 0.2% of the force), simulated (real):",
        "",
        "| posture | mattress | p99 mmHg | length / height | simulated images read from (mmHg) |",
        "| --- | --- | --- | --- | --- |",
    ]
    for r in record["rows"]:
        s, re_ = r["simulated"], r["real"]
        if s:
            floor = r.get("floor_mmhg", 0.0)
            lines.append(
                f"| {r['posture']} | {r['mattress']} | {s['p99_mmhg']:.0f} ({re_['p99_mmhg']:.0f}) "
                f"| {s['extent']:.3f} ({re_['extent']:.3f}) | "
                + (f"{floor:.2f} (the real set's lowest reading)" if floor > 0 else "the sensor's own floor")
                + " |"
            )
    lines += [
        "",
        "Load share per body region, simulated (real):",
        "",
        "| posture | mattress | " + " | ".join(R.REGION_NAMES) + " |",
        "| --- | --- |" + " --- |" * len(R.REGION_NAMES),
    ]
    for r in record["rows"]:
        if r["simulated"]:
            lines.append(
                f"| {r['posture']} | {r['mattress']} | "
                + " | ".join(
                    f"{r['simulated']['regions'][k]:.2f} ({r['real']['regions'][k]:.2f})" for k in R.REGION_NAMES
                )
                + " |"
            )
    lines += _paired_table(
        record,
        "area_tenths",
        "Where the contact lies: loaded taxels (mean over frames) in each tenth of the load's length, "
        "head end first, simulated / real:",
        [str(i + 1) for i in range(10)],
        "{:.0f}",
    )
    lines += _paired_table(
        record,
        "head_end",
        f"Where the load lies along the body: share of the force in each {R.HEAD_END_WIDTH:g} of the subject's "
        "height, measured from the load's first row (head end), simulated / real:",
        [f"{i * R.HEAD_END_WIDTH:.2f}-" for i in range(R.HEAD_END_BINS)],
        "{:.3f}",
    )
    lines += [
        "",
        "Transverse bands (air cells; row force over its 5-row average, one cosine fitted along the bed "
        "at the real frames' best period):",
        "",
        "| posture | mattress | period (m) | amplitude sim (real) | crest x sim (real) (m) | R^2 of the real fit |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for r in record["rows"]:
        if r.get("bands"):
            b, rb = r["bands"]["simulated"], r["bands"]["real"]
            lines.append(
                f"| {r['posture']} | {r['mattress']} | {rb['period_m']:.4f} | {b['amplitude']:.3f} "
                f"({rb['amplitude']:.3f}) | {b['crest_m']:.4f} ({rb['crest_m']:.4f}) | {rb['r2']:.3f} |"
            )
    lines += spread_markdown(record["rows"], record["config"].get("model"))
    lines += [
        "",
        "Ceiling (real against real, the same measures):",
        "",
        "| posture | between | along | across | area ratio |",
        "| --- | --- | --- | --- | --- |",
    ]
    for c in record["ceilings"]:
        lines.append(
            f"| {c['posture']} | {c['between']} | {c['along']:.3f} | {c['across']:.3f} | {c['area_ratio']:.2f} |"
        )
    lines += raised_markdown(record.get("raised", []))
    lines += tilted_markdown(record.get("tilted", []))
    return "\n".join(lines) + "\n"


def spread_markdown(rows: list[dict], model: str | None) -> list[str]:
    """The network's heatmap spread of the head and torso on the real frames and on their simulated
    twins (`trunk_spread` in the rows); none without it."""
    rows = [r for r in rows if r.get("trunk_spread")]
    if not rows:
        return []
    cell = lambda s: "-" if not s else f"{s['median_m'] * 100:.1f} cm, {s['share_sure'] * 100:.0f}%"  # noqa: E731
    lines = [
        "",
        f"Through the estimator's eyes (`{model}`): its heatmaps' spread over the head and torso joints, median "
        "per image, and the share of those joints under 10 cm - how sure it is where each body lies:",
        "",
        "| posture | mattress | real | simulated twins |",
        "| --- | --- | --- | --- |",
    ]
    for r in rows:
        s = r["trunk_spread"]
        lines.append(f"| {r['posture']} | {r['mattress']} | {cell(s['real'])} | {cell(s['simulated'])} |")
    return lines


__all__ = ["bands_dict", "markdown", "set_dict", "spread_markdown"]
