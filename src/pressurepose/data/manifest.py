"""`manifest.json`: what a finished dataset folder holds and how it was made.

Written once, after the last shard, atomically - a folder without it is an unfinished run
(re-running the same `pressurepose generate` command completes it). It holds the package
version, the generation config, the mattress parameters, the seeds and how samples derive
from them, counts per split / partition / gender, rejection counts by reason, and one entry
per shard (id, file, counts, sha256). It has no timestamps or timings, so a resumed run
writes the same manifest, byte for byte, as an uninterrupted one (timings go to timing.json).
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

from pressurepose.data.shards import check_shard_record, verify_shard
from pressurepose.errors import UserError
from pressurepose.files import atomic_write
from pressurepose.validate import field, read_json

MANIFEST = "manifest.json"
FORMAT = "pressurepose-dataset"
FORMAT_VERSION = 1


def summarise(records: list[dict]) -> dict:
    """Counts and rejections over shard records (in plan order)."""
    counts: dict = {}
    rejections: Counter = Counter()
    sampling: Counter = Counter()
    candidates = 0
    for r in records:
        leaf = counts.setdefault(r["split"], {}).setdefault(r["partition"], {})
        leaf[r["gender"]] = leaf.get(r["gender"], 0) + r["count"]
        rejections.update(r["rejections"])
        sampling.update(r["sampling_rejections"])
        candidates += r["candidates"]
    total = sum(r["count"] for r in records)
    return {
        "total": total,
        "counts": counts,
        "candidates": candidates,
        "rejected": candidates - total,
        "rejections": dict(sorted(rejections.items())),
        "sampling_rejections": dict(sorted(sampling.items())),
    }


def write_manifest(root: Path, header: dict, records: list[dict]) -> Path:
    manifest = {"format": FORMAT, "format_version": FORMAT_VERSION, **header, **summarise(records), "shards": records}
    text = json.dumps(manifest, indent=1, sort_keys=True)
    return atomic_write(Path(root) / MANIFEST, lambda tmp: Path(tmp).write_text(text))


# Fields every manifest has, with their kinds (pressurepose.validate.KINDS).
TOP_FIELDS = {
    "total": "count",
    "counts": "dict",
    "candidates": "count",
    "rejected": "int",
    "rejections": "dict",
    "sampling_rejections": "dict",
    "config": "dict",
    "shards": "list",
}
SPLITS, GENDERS = ("train", "test"), ("female", "male")


def check_manifest(manifest, path: Path) -> dict:
    """The manifest's fields, checked (UserError naming the file and the field): every shard
    record complete, its file inside the dataset folder, its counts adding up to the total."""
    if not isinstance(manifest, dict):
        raise UserError(f"{path}: expected a JSON object (a {FORMAT} manifest), got {type(manifest).__name__}")
    if manifest.get("format") != FORMAT or manifest.get("format_version") != FORMAT_VERSION:
        raise UserError(f"{path}: not a {FORMAT} v{FORMAT_VERSION} manifest (fields 'format' and 'format_version')")
    for key, kind in TOP_FIELDS.items():
        field(manifest, key, kind, path)
    for k, record in enumerate(manifest["shards"]):
        check_shard_record(record, path, Path(path).parent, where=f"shards[{k}].")
    total = sum(r["count"] for r in manifest["shards"])
    if total != manifest["total"]:
        raise UserError(f"{path}: field 'total' is {manifest['total']} but the shards hold {total} samples")
    counts: dict = {}
    for r in manifest["shards"]:
        leaf = counts.setdefault(r["split"], {}).setdefault(r["partition"], {})
        leaf[r["gender"]] = leaf.get(r["gender"], 0) + r["count"]
    if manifest["counts"] != counts:
        raise UserError(f"{path}: field 'counts' does not match the shards' records (expected {counts})")
    for key in ("rejections", "sampling_rejections"):
        for reason in manifest[key]:
            field(manifest[key], reason, "count", path, f"{key}.")
    return manifest


def load_manifest(root: Path, verify: bool = True) -> dict:
    """The manifest of a finished dataset folder, checked (`check_manifest`); with `verify`,
    every shard's sha256 is checked (CorruptShardError names the bad shard)."""
    root = Path(root)
    path = root / MANIFEST
    if not root.is_dir():
        raise UserError(f"{root}: no such dataset folder")
    if not path.exists():
        if (root / "generate.json").exists():
            raise UserError(
                f"{root} holds an unfinished dataset (no {MANIFEST}); re-run the same "
                "`pressurepose generate` command to finish it"
            )
        raise UserError(f"{root} is not a pressurepose dataset (no {MANIFEST})")
    manifest = check_manifest(read_json(path, "manifest", "; re-run `pressurepose generate` to rewrite it"), path)
    if verify:
        for record in manifest["shards"]:
            verify_shard(root, record)
    return manifest


__all__ = ["MANIFEST", "check_manifest", "load_manifest", "summarise", "write_manifest"]
