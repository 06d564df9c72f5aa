"""Real frames with point clouds: the file `pressurepose evaluate-real --data` reads (seed B.4,
Table 5 "real"; issue 9; the report: `commands.evaluate_real`).

`pressurepose evaluate-real --data FILE.npz` on a file written by `import-pressurepose-real`
(or any .npz with pressure_mmhg, subject, cloud_points, cloud_offsets): the network estimates
each frame's body (gender, height and mass from the file when the network takes them), and
`metrics.vpe_to_cloud` compares its camera-facing vertices with the frame's cloud (1 cm voxel
downsampled, in the mat frame). As released, the error is averaged per participant and then
over participants; the mean over frames is reported too. Height and mass estimated from the
body shape are compared with the participants' values.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pressurepose.errors import UserError

REQUIRED = ("pressure_mmhg", "subject", "cloud_points", "cloud_offsets")


def load_cloud_file(path: Path) -> dict[str, np.ndarray]:
    """The arrays of an imported real-data .npz with point clouds, checked."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except FileNotFoundError:
        raise UserError(f"no file at {path}") from None
    except (OSError, ValueError, EOFError) as exc:
        raise UserError(f"{path}: not a readable .npz file without pickles ({exc})") from None
    missing = [k for k in REQUIRED if k not in arrays]
    if missing:
        raise UserError(f"{path}: missing arrays {missing}; write it with `pressurepose import-pressurepose-real`")
    n = len(arrays["pressure_mmhg"])
    off = arrays["cloud_offsets"]
    pts = arrays["cloud_points"]
    if (
        off.shape != (n + 1,)
        or off[0] != 0
        or off[-1] != len(pts)
        or (np.diff(off) <= 0).any()
        or pts.ndim != 2
        or pts.shape[1:] != (3,)
    ):
        raise UserError(
            f"{path}: cloud_offsets must be (N + 1,) increasing from 0 to len(cloud_points), every "
            "frame with at least one point, and cloud_points (P, 3)"
        )
    for k in ("subject", "gender", "height_m", "mass_kg"):
        if k in arrays and len(arrays[k]) != n:
            raise UserError(f"{path}: {k} has {len(arrays[k])} entries for {n} images")
    return arrays


__all__ = ["REQUIRED", "load_cloud_file"]
