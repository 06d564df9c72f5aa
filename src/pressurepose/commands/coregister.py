"""`pressurepose coregister`: the camera's pose from clicked corner markers (seed A.6):
camera.json, coregister.png and, with --cloud, the point cloud in the mat frame."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Literal

import numpy as np

from pressurepose.commands.outputs import Written
from pressurepose.data.coregister import load_cloud, read_markers, solve_camera_pose
from pressurepose.files import atomic_write, write_text
from pressurepose.viz.coregister import plot_coregistration


@dataclasses.dataclass(frozen=True)
class CoregisterConfig:
    """Co-register a camera with the mat from clicked corner markers (seed A.6)."""

    markers: Path
    """Marker file (JSON, format pressurepose.coregistration/1; see docs/real_data.md)."""
    out: Path = Path("out/coregister")
    """Output folder: camera.json, coregister.png and, with --cloud, cloud_mat.npy."""
    cloud: Path | None = None
    """Camera-frame point cloud (.npy, (N, 3) m) or depth image (.npy, (H, W) m) to bring into
    the mat frame."""
    method: Literal["lm", "cma"] = "lm"
    """lm (direct solution + Levenberg-Marquardt) or cma (+ CMA-ES, as the seed)."""


def run_coregister(cfg: CoregisterConfig) -> Written:
    mk = read_markers(cfg.markers)
    pose = solve_camera_pose(mk, cfg.method)
    cloud = load_cloud(cfg.cloud, mk.intrinsics) if cfg.cloud is not None else None
    cfg.out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    record = {**pose.to_dict(), "markers": list(mk.names), "method": cfg.method}
    if cloud is not None:
        in_mat = pose.to_mat(cloud)
        paths["cloud"] = atomic_write(cfg.out / "cloud_mat.npy", lambda tmp: np.save(tmp, in_mat.astype(np.float32)))
        record["cloud_points"] = int(in_mat.shape[0])
    paths["figure"] = atomic_write(cfg.out / "coregister.png", lambda tmp: plot_coregistration(tmp, mk, pose, cloud))
    paths["camera"] = write_text(cfg.out / "camera.json", json.dumps(record, indent=1))
    return Written(paths, record)


def coregister(cfg: CoregisterConfig) -> None:
    """Co-register a camera with the mat from clicked corner markers (seed A.6): camera.json
    (pose), coregister.png and, with --cloud, the point cloud in the mat frame."""
    record = run_coregister(cfg).record
    print(
        f"camera at {[round(v, 3) for v in record['camera_position_in_mat_m']]} m in the mat frame, "
        f"reprojection RMS {record['rms_px']:.2f} px -> {cfg.out}"
    )


__all__ = ["CoregisterConfig", "coregister", "run_coregister"]
