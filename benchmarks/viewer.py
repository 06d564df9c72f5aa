"""Viewer latency: opening a dataset, listing it, and one sample's data and meshes (the first
request, which reads a row group and poses the body, and a repeated one, from the cache).

    PYTHONPATH=src python benchmarks/viewer.py [--n 8]

Makes a small dataset with `train.data.synthetic_arrays` (sampler + sim #2) in a temporary
folder, a smoke-trained run on it (so the run view predicts on demand), and times the JSON API
over HTTP on 127.0.0.1. Prints milliseconds.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))


def timed(url: str) -> tuple[float, int]:
    t = time.perf_counter()
    with urllib.request.urlopen(url, timeout=120) as r:
        size = len(r.read())
    return (time.perf_counter() - t) * 1e3, size


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=8)
    args = ap.parse_args()

    import torch
    from test_viewer import write_dataset

    from pressurepose.body import load_body_model
    from pressurepose.commands.train import run_train as train
    from pressurepose.train.config import TrainConfig
    from pressurepose.train.data import synthetic_arrays, write_npz
    from pressurepose.viz.viewer import ViewConfig, make_server

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        arrays = synthetic_arrays(args.n, seed=2, body=load_body_model("anny", dtype=torch.float64))
        write_dataset(root / "data", arrays)
        (root / "train").mkdir()
        write_npz(root / "train" / "t.npz", arrays)
        run = train(TrainConfig.smoke(data=root / "train", out=root / "run", epochs=1, progress=False))
        for kind, path in (("dataset", root / "data"), ("run", run)):
            t = time.perf_counter()
            server = make_server(ViewConfig(path=path, port=0, open=False))
            open_ms = (time.perf_counter() - t) * 1e3
            threading.Thread(target=server.serve_forever, daemon=True).start()
            u = server.url
            rows = [
                ("open the folder", open_ms, 0),
                ("list", *timed(u + "api/list?limit=500")),
                ("faces (body model already in memory)", *timed(u + "api/faces")),
                ("sample 1 (first: read + pose)", *timed(u + "api/sample/1")),
                ("mesh 1 (cached)", *timed(u + "api/mesh/1")),
                (
                    "sample 2 + mesh 2 (first)",
                    *[a + b for a, b in zip(timed(u + "api/sample/2"), timed(u + "api/mesh/2"))],
                ),
                ("sample 1 again (cached)", *timed(u + "api/sample/1")),
            ]
            print(f"{kind} ({path.name}, {len(server.browser)} samples)")
            for name, ms, size in rows:
                print(f"  {name:40s} {ms:8.1f} ms  {size / 1e3:8.1f} kB")
            server.shutdown()
            server.server_close()


if __name__ == "__main__":
    main()
