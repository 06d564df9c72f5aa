"""Speed of the real-data importers and of 3DVPE against a point cloud (issue 9).

    PYTHONPATH=src .venv/bin/python benchmarks/real_data.py

Synthetic stand-ins of the real files' sizes (no real data is shipped): an SLP frame (192 x
84), a PressurePose real participant (48 frames, 20,000-point clouds, written as a Python 2
pickle by the test suite's writer), and one Anny mesh against a 20,000-point cloud of noisy
samples of its upper surface.
Prints the median of 5 runs.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def timed(fn, repeats: int = 5) -> float:
    fn()
    samples = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t)
    return statistics.median(samples)


def main() -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_real_import import py2_pickle

    from pressurepose.body import load_body_model
    from pressurepose.data.pressurepose_real import import_pressurepose_real
    from pressurepose.data.slp import frame_to_mat
    from pressurepose.eval.metrics import vpe_to_cloud

    rng = np.random.default_rng(0)
    pm = rng.uniform(0, 50, (192, 84))
    t = timed(lambda: [frame_to_mat(pm, 70.0, "weight") for _ in range(100)]) / 100
    print(f"| SLP frame -> 64 x 27 (weight calibration) | {t * 1e3:.2f} ms |")

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "S103"
        folder.mkdir()
        (folder / "participant_info_red.p").write_bytes(
            py2_pickle({"gender": "f", "height_in": 65.0, "weight_lbs": 150.0})
        )
        frames = [rng.uniform(0, 10, 1728) for _ in range(48)]
        clouds = [rng.uniform(0, 1, (20000, 3)) for _ in range(48)]
        (folder / "prescribed.p").write_bytes(py2_pickle({"images": frames, "pc": clouds}))
        t = timed(lambda: import_pressurepose_real(folder, Path(tmp) / "o.npz", pose_sets=("prescribed",)), 3)
        print(f"| PressurePose real participant, 48 frames x 20,000 points | {t:.2f} s ({t / 48 * 1e3:.0f} ms/frame) |")

    body = load_body_model("anny")
    from pressurepose.body import BodyParams

    out = body(BodyParams.zeros(1, body.default_shape(1)))
    v = out.vertices[0]
    # A Kinect-like cloud: 20,000 noisy samples (5 mm) of the body's upper surface.
    g = torch.Generator().manual_seed(0)
    top = v[v[:, 2] > v[:, 2].median()]
    cloud = top[torch.randint(len(top), (20000,), generator=g)] + 0.005 * torch.randn(20000, 3, generator=g)
    t = timed(lambda: vpe_to_cloud(v, out.faces, cloud))
    print(f"| 3DVPE, one Anny mesh vs 20,000 points (1 cm voxels) | {t * 1e3:.0f} ms |")
    print(f"({torch.get_num_threads()} torch threads)")


if __name__ == "__main__":
    main()
