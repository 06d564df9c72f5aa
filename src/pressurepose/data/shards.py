"""Shard files: Parquet bytes, atomic writes, sha256 records and checks.

A dataset folder holds `shards/<id>.parquet`, each with a record `shards/<id>.json` (sha256,
size, counts, rejections) written after it, and, once every shard is there, `manifest.json`.
A shard counts as done only when its record exists and its bytes hash to the recorded sha256:
a crash between the two writes, a truncated copy or flipped bits are all caught by the hash.
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import os
from pathlib import Path

from pressurepose.errors import UserError
from pressurepose.files import atomic_write
from pressurepose.validate import field, inside

SHARD_DIR = "shards"
ROW_GROUP_ROWS = 32  # rows per Parquet row group: the unit the Dataset reads lazily


class CorruptShardError(UserError):
    """A shard whose bytes do not match its recorded sha256 (or that cannot be parsed)."""


def table_bytes(table) -> bytes:
    """pyarrow.Table -> Parquet bytes (zstd; no timestamps, so equal tables give equal bytes)."""
    import pyarrow.parquet as pq

    buf = io.BytesIO()
    pq.write_table(table, buf, compression="zstd", row_group_size=ROW_GROUP_ROWS)
    return buf.getvalue()


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def shard_paths(root: Path, shard_id: str) -> tuple[Path, Path]:
    """(parquet file, json record) of a shard."""
    folder = Path(root) / SHARD_DIR
    return folder / f"{shard_id}.parquet", folder / f"{shard_id}.json"


def explain_os_error(exc: OSError, path: Path) -> OSError:
    if exc.errno == errno.ENOSPC:
        return OSError(
            f"no space left on the device writing {path}; shards already written are intact - "
            "free some space and re-run the same command to resume"
        )
    if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return OSError(
            f"cannot write {path} (permission denied or read-only file system); choose a writable --out folder"
        )
    return OSError(f"cannot write {path}: {exc.strerror or exc}")


def write_shard(root: Path, shard_id: str, data: bytes, record: dict) -> dict:
    """Write a shard's bytes, then its record (with sha256 and size added), both atomically.
    Returns the record. OSErrors come back with a message that says what to do."""
    parquet, meta = shard_paths(root, shard_id)
    record = {
        **record,
        "id": shard_id,
        "file": f"{SHARD_DIR}/{parquet.name}",
        "sha256": sha256_bytes(data),
        "bytes": len(data),
    }
    text = json.dumps(record, indent=1, sort_keys=True)
    for path, write in (
        (parquet, lambda tmp: Path(tmp).write_bytes(data)),
        (meta, lambda tmp: Path(tmp).write_text(text)),
    ):
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(path, lambda tmp: _write_synced(tmp, write))
        except OSError as exc:
            raise explain_os_error(exc, path) from None
    return record


def _write_synced(tmp, write) -> None:
    # fsync before the rename: after a power cut a shard is either complete or absent.
    write(tmp)
    fd = os.open(tmp, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


# The fields of a shard record (its .json, and its entry in the manifest) and their kinds.
RECORD_FIELDS = {
    "file": "str",
    "sha256": "sha256",
    "bytes": "count",
    "count": "count",
    "split": "name",
    "partition": "name",
    "gender": "name",
    "over_bed": "bool",
}


def check_shard_record(record, path: Path, root: Path, where: str = "") -> dict:
    """UserError naming `path` and the field unless `record` is a complete shard record whose
    file lies inside the dataset folder `root` (never read a path like ../../etc/passwd)."""
    for key, kind in RECORD_FIELDS.items():
        field(record, key, kind, path, where)
    inside(root, record["file"], path, f"{where}file")
    for key, allowed in (("split", ("train", "test")), ("gender", ("female", "male"))):
        if record[key] not in allowed:
            raise UserError(f"{path}: field '{where}{key}' must be one of {', '.join(allowed)}, got {record[key]!r}")
    return record


def read_record(root: Path, shard_id: str) -> dict | None:
    """The shard's record, or None when the shard is not finished (no record, or unreadable)."""
    _, meta = shard_paths(root, shard_id)
    try:
        return check_shard_record(json.loads(meta.read_text()), meta, root)
    except FileNotFoundError:
        return None
    except (OSError, ValueError):  # unreadable or incomplete: the shard is made again
        return None


def verify_shard(root: Path, record: dict, contents: bool = True) -> None:
    """CorruptShardError unless the shard file exists and hashes to its recorded sha256;
    `contents=False` checks only its recorded size (a stat, for a quick look: the viewer)."""
    path = inside(root, record["file"], f"the record of shard {record.get('id', '?')}", "file")
    if not path.is_file():
        raise CorruptShardError(
            f"shard {path} is missing; re-run `pressurepose generate` with the same arguments to regenerate it"
        )
    size = path.stat().st_size
    if size != record["bytes"] or (contents and sha256_file(path) != record["sha256"]):
        what = f"truncated ({size} of {record['bytes']} bytes)" if size < record["bytes"] else "corrupted"
        raise CorruptShardError(
            f"shard {path} is {what}: its sha256 does not match the recorded {record['sha256'][:16]}...; "
            "re-run `pressurepose generate` with the same arguments to regenerate it"
        )


__all__ = [
    "CorruptShardError",
    "RECORD_FIELDS",
    "check_shard_record",
    "explain_os_error",
    "ROW_GROUP_ROWS",
    "SHARD_DIR",
    "read_record",
    "sha256_bytes",
    "sha256_file",
    "shard_paths",
    "table_bytes",
    "verify_shard",
    "write_shard",
]
