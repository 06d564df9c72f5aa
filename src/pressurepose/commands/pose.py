"""`pressurepose pose`: the body model's default adult lying supine on the mat, drawn over the
sensing grid (top and side views) with its parameters, joints, height and mass - a first look at
the body model and the mat's coordinates, no physics.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from pathlib import Path
from typing import Literal

import torch

from pressurepose.body import BodyParams, load_body_model
from pressurepose.body.joints import J24_NAMES
from pressurepose.files import write_text
from pressurepose.mat import MatSpec
from pressurepose.viz.body_on_mat import plot_body_on_mat

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class PoseConfig:
    out: Path = Path("out/pose")
    """Output folder (created)."""
    backend: Literal["anny", "smpl"] = "anny"
    """Body model backend."""
    smpl_dir: Path | None = None
    """Folder with SMPL_*.npz/.pkl for backend=smpl (default $PRESSUREPOSE_SMPL_DIR)."""


def resting_pose(dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(1, 23, 3) a relaxed supine pose: arms along the body, elbows and knees slightly bent."""
    pose = torch.zeros(1, 23, 3, dtype=dtype)
    deg = math.pi / 180
    for side, sign in (("left", 1.0), ("right", -1.0)):
        pose[0, J24_NAMES.index(f"{side}_collar") - 1, 2] = -sign * 20 * deg
        pose[0, J24_NAMES.index(f"{side}_shoulder") - 1, 2] = -sign * 55 * deg
        pose[0, J24_NAMES.index(f"{side}_elbow") - 1, 1] = -sign * 15 * deg
        pose[0, J24_NAMES.index(f"{side}_knee") - 1, 0] = 8 * deg
        pose[0, J24_NAMES.index(f"{side}_hip") - 1, 2] = sign * 4 * deg
    return pose


def run_pose(cfg: PoseConfig) -> dict[str, Path]:
    """Pose the backend's default adult supine, centred on the mattress with its lowest
    point on the mattress top, and write body.png and body.json into cfg.out."""
    mat = MatSpec()
    options = {"model_dir": cfg.smpl_dir} if cfg.backend == "smpl" else {}
    model = load_body_model(cfg.backend, **options)
    params = BodyParams.zeros(1, model.default_shape(1)).replace(pose=resting_pose(model.dtype))
    with torch.no_grad():
        body = model(params)
        v = body.vertices[0]
        # Centre the body along and across the bed; rest its lowest point on z = 0.
        cx, cy = mat.centre_m
        shift = torch.tensor(
            [cx - (v[:, 0].max() + v[:, 0].min()) / 2, cy - (v[:, 1].max() + v[:, 1].min()) / 2, -v[:, 2].min()]
        )
        params = params.replace(root_translation=params.root_translation + shift)
        body = model(params)
        measures = model.measure(params.shape)
    cfg.out.mkdir(parents=True, exist_ok=True)
    title = (
        f"{model.name}: {measures.height_m.item():.2f} m, {measures.mass_kg.item():.1f} kg, "
        "supine on the mat (no physics)"
    )
    png = plot_body_on_mat(body.vertices[0].numpy(), body.joints[0].numpy(), mat, cfg.out / "body.png", title)
    record = {
        "config": {"backend": cfg.backend},
        "body_model": model.name,
        "shape_names": list(model.shape_names),
        "shape": params.shape[0].tolist(),
        "root_rotation": params.root_rotation[0].tolist(),
        "root_translation_m": params.root_translation[0].tolist(),
        "pose": params.pose[0].tolist(),
        "joints_m": dict(zip(J24_NAMES, body.joints[0].tolist())),
        "height_m": measures.height_m.item(),
        "mass_kg": measures.mass_kg.item(),
    }
    path = write_text(cfg.out / "body.json", json.dumps(record, indent=1))
    log.info("wrote %s and %s", png, path)
    return {"png": png, "json": path}


def pose(cfg: PoseConfig) -> None:
    """Pose the body model's default adult supine on the mat and draw it (body.png, body.json)."""
    paths = run_pose(cfg)
    print(f"wrote {paths['png']} and {paths['json']}")


__all__ = ["PoseConfig", "pose", "resting_pose", "run_pose"]
