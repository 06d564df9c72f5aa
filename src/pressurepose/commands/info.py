"""`pressurepose info DIR`: what a dataset holds, checked, with a contact sheet.

Counts come from the manifest; every shard's sha256 is verified; pressure statistics are
accumulated shard by shard, reading only the pressure column (memory: one shard's images).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import tyro

from pressurepose.data.dataset import PressurePoseDataset
from pressurepose.data.manifest import load_manifest
from pressurepose.data.schema import from_table
from pressurepose.data.shards import CorruptShardError
from pressurepose.files import atomic_write
from pressurepose.viz.dataset import plot_contact_sheet

SHEET = "contact_sheet.png"


def _read_columns(path: Path, columns: list[str]) -> dict:
    try:
        return from_table(pq.read_table(path, columns=columns), tuple(columns))
    except (OSError, pa.ArrowException) as exc:
        raise CorruptShardError(f"shard {path} cannot be read ({exc})") from None


def dataset_info(root: str | Path, sheet: int = 24, seed: int = 0) -> dict:
    """Counts, rejections, pressure statistics per partition; writes root/contact_sheet.png
    with `sheet` random samples (0: no figure). Raises CorruptShardError on a bad shard."""
    root = Path(root)
    manifest = load_manifest(root, verify=True)
    stats: dict[str, dict] = {}
    for r in manifest["shards"]:
        p = _read_columns(root / r["file"], ["pressure_mmhg"])["pressure_mmhg"].astype(np.float64)  # (B, 64, 27)
        if len(p) != r["count"]:
            raise CorruptShardError(
                f"shard {root / r['file']} holds {len(p)} samples but the manifest records "
                f"{r['count']}; re-run `pressurepose generate` to regenerate the dataset"
            )
        s = stats.setdefault(
            r["partition"], {"n": 0, "sum": 0.0, "contact_taxels": 0, "contact_sum": 0.0, "peaks": [], "nan": 0}
        )
        touching = p > 0
        s["n"] += len(p)
        s["sum"] += float(p.sum())
        s["contact_taxels"] += int(touching.sum())
        s["peaks"].extend(p.reshape(len(p), -1).max(1).tolist())
        s["nan"] += int(np.isnan(p).sum())
    pressure = {}
    for part, s in stats.items():
        peaks = np.array(s["peaks"])
        pressure[part] = {
            "samples": s["n"],
            "mean_contact_pressure_mmhg": round(s["sum"] / max(s["contact_taxels"], 1), 2),
            "mean_contact_taxels": round(s["contact_taxels"] / max(s["n"], 1), 1),
            "peak_mmhg_median": round(float(np.median(peaks)), 2) if len(peaks) else None,
            "peak_mmhg_p95": round(float(np.percentile(peaks, 95)), 2) if len(peaks) else None,
            "nan_values": s["nan"],
        }
    info = {
        "root": str(root),
        "total": manifest["total"],
        "shards": len(manifest["shards"]),
        "counts": manifest["counts"],
        "candidates": manifest["candidates"],
        "rejected": manifest["rejected"],
        "rejections": manifest["rejections"],
        "sampling_rejections": manifest["sampling_rejections"],
        "pressure": pressure,
        "config": manifest["config"],
    }
    if sheet > 0 and manifest["total"] > 0:
        info["contact_sheet"] = str(_contact_sheet(root, manifest, sheet, seed))
    return info


def _contact_sheet(root: Path, manifest: dict, k: int, seed: int) -> Path:
    ds = PressurePoseDataset(
        root, columns=("pressure_mmhg", "partition", "gender", "index", "mass_kg", "head_angle_deg"), verify=False
    )
    rows = np.sort(np.random.default_rng(seed).choice(len(ds), size=min(k, len(ds)), replace=False))
    items = [ds[int(i)] for i in rows]
    images = np.stack([it["pressure_mmhg"].numpy() for it in items])
    labels = [
        f"{it['partition']} {it['gender'][0]} #{int(it['index'])}\n{float(it['mass_kg']):.0f} kg"
        + (f", bed {float(it['head_angle_deg']):.0f} deg" if float(it["head_angle_deg"]) else "")
        for it in items
    ]
    return atomic_write(root / SHEET, lambda tmp: plot_contact_sheet(tmp, images, labels))


def format_info(info: dict) -> str:
    lines = [f"{info['root']}: {info['total']} samples in {info['shards']} shards (all sha256 verified)"]
    for split, parts in info["counts"].items():
        for part, genders in parts.items():
            lines.append(f"  {split:5s} {part:18s} " + "  ".join(f"{g} {n}" for g, n in genders.items()))
    rate = info["rejected"] / max(info["candidates"], 1)
    lines.append(f"rejected {info['rejected']} of {info['candidates']} simulated ({100 * rate:.1f}%), replaced:")
    lines += [f"  {n:6d}  {reason}" for reason, n in info["rejections"].items()]
    lines.append("sampling: " + json.dumps(info["sampling_rejections"]))
    lines.append("pressure per partition (mmHg; contact = taxels > 0):")
    for part, p in info["pressure"].items():
        lines.append(
            f"  {part:18s} n={p['samples']} mean on contact {p['mean_contact_pressure_mmhg']}, "
            f"contact taxels {p['mean_contact_taxels']}, peak median {p['peak_mmhg_median']} "
            f"p95 {p['peak_mmhg_p95']}, NaN {p['nan_values']}"
        )
    if "contact_sheet" in info:
        lines.append(f"contact sheet: {info['contact_sheet']}")
    return "\n".join(lines)


def info(dataset: tyro.conf.Positional[Path], sheet: int = 24, seed: int = 0) -> None:
    """Describe a dataset: counts per partition and gender, rejections, pressure statistics;
    verifies every shard's sha256 and writes DATASET/contact_sheet.png.

    Args:
        dataset: Dataset folder (with manifest.json).
        sheet: Random samples drawn in the contact sheet (0: none).
        seed: Which random samples.
    """
    print(format_info(dataset_info(dataset, sheet=sheet, seed=seed)))


__all__ = ["dataset_info", "format_info", "info"]
