"""End-to-end dataset generation speed and peak memory (issue 6).

    python benchmarks/generate.py                       # paper preset mix, 128 samples, 2 workers
    python benchmarks/generate.py --n 256 --workers 2 --shard-size 16
    python benchmarks/generate.py --engine ray

Runs `pressurepose generate --preset paper --n N` (the paper's partition, gender and
over-the-bed mix, train and test, spread exactly over N) into a temporary folder and prints
samples/s (excluding the one-off start: process spawn and body-model load), rejections,
and the peak resident memory of the whole process tree (this process + workers), sampled
every 50 ms from /proc (Linux). Record results in docs/benchmarks.md with the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import threading
import time
from pathlib import Path


def _tree_rss_bytes(root: int) -> int:
    """Summed RSS of `root` and all its descendants (Linux /proc)."""
    children: dict[int, list[int]] = {}
    rss: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
            ppid, pages = int(fields[1]), int(fields[21])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(entry))
        rss[int(entry)] = pages * os.sysconf("SC_PAGE_SIZE")
    total, todo = 0, [root]
    while todo:
        pid = todo.pop()
        total += rss.get(pid, 0)
        todo.extend(children.get(pid, []))
    return total


class PeakMemory(threading.Thread):
    def __init__(self, period_s: float = 0.05) -> None:
        super().__init__(daemon=True)
        self.period_s, self.peak, self.running = period_s, 0, True

    def run(self) -> None:
        while self.running:
            self.peak = max(self.peak, _tree_rss_bytes(os.getpid()))
            time.sleep(self.period_s)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=128)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--engine", choices=("local", "ray"), default="local")
    ap.add_argument("--shard-size", type=int, default=16)
    ap.add_argument("--batch", type=int, default=32, help="chunk per batched rest (the generator's default: 32)")
    ap.add_argument("--preset", default="paper")
    args = ap.parse_args()

    import logging

    from pressurepose.generate.plan import GenerateConfig, plan_shards
    from pressurepose.generate.run import run_generate

    logging.basicConfig(level=logging.WARNING)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "ds"
        cfg = GenerateConfig(
            out=out,
            preset=args.preset,
            n=args.n,
            workers=args.workers,
            engine=args.engine,
            shard_size=args.shard_size,
            batch=args.batch,
        )
        shards = plan_shards(cfg)
        mem = PeakMemory()
        mem.start()
        t0 = time.perf_counter()
        summary = run_generate(cfg, progress=False)
        wall = time.perf_counter() - t0
        mem.running = False
        mem.join()
        manifest = json.loads((out / "manifest.json").read_text())
        size = sum(p.stat().st_size for p in (out / "shards").glob("*.parquet"))
    parts = {}
    for s in shards:
        parts[s.group.partition] = parts.get(s.group.partition, 0) + s.count
    print(
        f"generate --preset {args.preset} --n {args.n} --workers {args.workers} --engine {args.engine} "
        f"--shard-size {args.shard_size} --batch {args.batch}"
    )
    print(f"  mix: {parts}; {len(shards)} shards")
    print(f"  wall {wall:.1f} s (incl. start-up), {summary['total'] / wall:.2f} samples/s end to end")
    print(
        f"  simulated {manifest['candidates']} for {manifest['total']} kept "
        f"({100 * manifest['rejected'] / manifest['candidates']:.1f}% rejected): {manifest['rejections']}"
    )
    print(
        f"  peak RSS of the process tree {mem.peak / 2**30:.2f} GiB; shards {size / summary['total'] / 1024:.1f} KiB/sample"
    )


if __name__ == "__main__":
    main()
