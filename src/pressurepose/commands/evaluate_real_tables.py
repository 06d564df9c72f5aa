"""`evaluate-real`'s markdown tables: the flat groups' (B-D), group E's tilts and group F's raised beds."""

from __future__ import annotations

from pressurepose.eval.real import POSTURES, TURN_DEG, load_ends_table, spread_lines


def flat_lines(r: dict) -> list[str]:
    """The flat groups' tables: per mattress, confusions, heights by load ends, per variant."""
    lines = [
        "| mattress | frames (subjects) | posture accuracy [95% CI] | height MAE (cm) "
        "| height error median: absolute / signed [95% CI] (cm) | mass MAE (kg) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for name, s in r["by_mattress"].items():
        lines.append(
            f"| {name} | {s['frames']} ({s['subjects']}) | {s['posture_accuracy'] * 100:.1f}% "
            f"[{s['posture_accuracy_ci'][0] * 100:.1f}, {s['posture_accuracy_ci'][1] * 100:.1f}] | "
            f"{s['height_mae_m'] * 100:.1f} | {s['height_median_abs_m'] * 100:.1f} / "
            f"{s['height_median_signed_m'] * 100:+.1f} [{s['height_median_signed_ci_m'][0] * 100:+.1f}, "
            f"{s['height_median_signed_ci_m'][1] * 100:+.1f}] | {s['mass_mae_kg']:.1f} |"
        )
    lines += spread_lines({k: s["trunk_spread"] for k, s in r["by_mattress"].items() if "trunk_spread" in s})
    for name, s in r["by_mattress"].items():
        lines += [
            "",
            f"Confusion ({name}; rows: true, columns: estimated)",
            "",
            "| | " + " | ".join(POSTURES) + " |",
            "| --- |" + " --- |" * len(POSTURES),
        ]
        for t, row in s["confusion"].items():
            lines.append(f"| {t} | " + " | ".join(str(row[e]) for e in POSTURES) + " |")
    lines += [
        "",
        "Height error (median signed, cm; frames) by where the load lies: a frame whose load (the rows "
        "holding >= 0.2% of its force) reaches the mat's head or foot row may run on beyond the mat",
        "",
        *load_ends_table({name: s["height_by_load_ends"] for name, s in r["by_mattress"].items()}, "mattress"),
    ]
    lines += [
        "",
        "Per posture variant (both mattresses; PmatData's groups: B supine variants, C right, D left)",
        "",
        "| variant | posture | frames | correct | " + " | ".join(f"read {e}" for e in POSTURES) + " |",
        "| --- | --- | --- | --- |" + " --- |" * len(POSTURES),
    ]
    for name, v in r["by_variant"].items():
        counts = [v["estimated"].get(e, 0) for e in POSTURES]
        lines.append(
            f"| {name} | {v['posture']} | {v['frames']} | {v['estimated'].get(v['posture'], 0)} | "
            + " | ".join(map(str, counts))
            + " |"
        )
    readout = {k: s["readout_accuracy"] for k, s in r["by_mattress"].items() if "readout_accuracy" in s}
    if readout:
        lines += [
            "",
            "The network's posture readout (net.posture; the posture above is its body's): "
            + ", ".join(f"{k} {v * 100:.1f}%" for k, v in readout.items()),
        ]
    return lines


def tilt_lines(t: dict) -> list[str]:
    """Group E's table: the roll read against the documented one, per mattress and variant."""
    lines = [
        "",
        f"Tilted bodies (group E: lateral on one or two wedges, E1-E4, or a pillow, E5-E6; {t['frames']} frames): "
        f"the roll read (+ right, - left) against the documented one; turned = read {TURN_DEG:.0f}-135 deg "
        f"toward the documented side (beyond 135: face down); other way = at least {TURN_DEG:.0f} deg toward the other",
        "",
        "| mattress / variant (frames) | documented roll (deg) | read toward that side, median (deg) | abs. roll error, median (deg) "
        "| turned [95% CI] | other way |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for name, s in {**t["by_mattress"], **t["by_variant"]}.items():
        doc = f"{s['documented_roll_deg']:+.0f}" if "documented_roll_deg" in s else "+-20, +-40"
        lo, hi = s["share_turned_ci"]
        lines.append(
            f"| {name} ({s['frames']}) | {doc} | {s['read_toward_median_deg']:+.1f} | {s['abs_error_median_deg']:.1f} | "
            f"{s['share_turned'] * 100:.0f}% [{lo * 100:.0f}, {hi * 100:.0f}] | {s['share_other_way'] * 100:.0f}% |"
        )
    return lines


def raised_lines(t: dict) -> list[str]:
    """Group F's tables: per mattress, then per bed angle and mattress."""
    lines = [
        "",
        f"Raised beds (group F: supine with the head of the bed raised 0-60 deg, F1-F7; {t['frames']} frames; "
        "the network's scope is a flat bed): the share read supine and the height error",
        "",
        "| mattress | frames (subjects) | read supine [95% CI] | height error median signed [95% CI] (cm) | height MAE (cm) |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name, s in t["by_mattress"].items():
        lo, hi = s["posture_accuracy_ci"]
        hlo, hhi = s["height_median_signed_ci_m"]
        lines.append(
            f"| {name} | {s['frames']} ({s['subjects']}) | {s['posture_accuracy'] * 100:.1f}% [{lo * 100:.1f}, "
            f"{hi * 100:.1f}] | {s['height_median_signed_m'] * 100:+.1f} [{hlo * 100:+.1f}, {hhi * 100:+.1f}] | "
            f"{s['height_mae_m'] * 100:.1f} |"
        )
    lines += [
        "",
        "| variant | head of bed (deg) | mattress | frames | "
        + " | ".join(f"read {e}" for e in POSTURES)
        + " | height error median signed (cm) |",
        "| --- | --- | --- | --- |" + " --- |" * len(POSTURES) + " --- |",
    ]
    for v in t["by_angle"]:
        counts = " | ".join(str(v["estimated"].get(e, 0)) for e in POSTURES)
        lines.append(
            f"| {v['variant']} | {v['bed_incline_deg']:.0f} | {v['mattress']} | {v['frames']} | {counts} | "
            f"{v['height_median_signed_m'] * 100:+.1f} |"
        )
    return lines


__all__ = ["flat_lines", "raised_lines", "tilt_lines"]
