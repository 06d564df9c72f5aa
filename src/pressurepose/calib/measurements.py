"""Calibration measurements: the real pressure images and mattress compressions of rigid
objects on a bed, in one JSON file (docs/calibration.md has the format with an example).

    {"format": "pressurepose.calib-measurements/1",
     "scenes": [{"name": "short capsules",
                 "pressure_mmhg": [[...27 numbers...], ... 64 rows ...],   # row 0 = head end
                 "objects": [{"name": "L20cm_1.3kg", "shape": "capsule", "length_m": 0.2,
                              "radius_m": 0.05, "mass_kg": 1.3, "x_m": 0.18, "y_m": 0.37,
                              "yaw_deg": 90, "compression_m": 0.021}, ...]}, ...]}

Pure JSON (no pickles, no binary side files): a 64 x 27 image is ~10-30 KB of text. Every
field is checked on load; a bad file raises a ValueError naming the scene, object and field.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path

import numpy as np
import torch

from pressurepose.calib.objects import CalibObject, SceneSimulator
from pressurepose.errors import UserError
from pressurepose.files import atomic_write
from pressurepose.mat import MatSpec
from pressurepose.sim.mattress import MattressParams
from pressurepose.validate import read_json

FORMAT = "pressurepose.calib-measurements/1"
_OBJECT_FIELDS = ("length_m", "radius_m", "mass_kg", "x_m", "y_m", "compression_m")


@dataclasses.dataclass(frozen=True)
class Scene:
    """One recording: objects resting on the bed together, the mat's image of them
    (mmHg, (rows, cols), row 0 at the head end) and each object's measured compression of
    the mattress (m, >= 0: how far its lowest point sank below the unloaded top)."""

    objects: tuple[CalibObject, ...]
    pressure_mmhg: np.ndarray
    compression_m: np.ndarray
    name: str = ""


@dataclasses.dataclass(frozen=True)
class Measurements:
    scenes: tuple[Scene, ...]

    @property
    def n_objects(self) -> int:
        return sum(len(s.objects) for s in self.scenes)

    def object_scenes(self) -> list[list[CalibObject]]:
        return [list(s.objects) for s in self.scenes]

    def to_json(self) -> dict:
        scenes = []
        for s in self.scenes:
            objs = []
            for o, q in zip(s.objects, s.compression_m):
                objs.append(
                    {
                        "name": o.name,
                        "shape": "capsule",
                        "length_m": o.length_m,
                        "radius_m": o.radius_m,
                        "mass_kg": o.mass_kg,
                        "x_m": o.x_m,
                        "y_m": o.y_m,
                        "yaw_deg": o.yaw_deg,
                        "compression_m": float(q),
                    }
                )
            scenes.append({"name": s.name, "pressure_mmhg": s.pressure_mmhg.tolist(), "objects": objs})
        return {"format": FORMAT, "scenes": scenes}

    def save(self, path: str | os.PathLike) -> Path:
        text = json.dumps(self.to_json()) + "\n"
        return atomic_write(Path(path), lambda tmp: Path(tmp).write_text(text))


def load_measurements(path: str | os.PathLike, mat: MatSpec | None = None) -> Measurements:
    """Read and check a measurement file (format above)."""
    path = Path(path)
    return parse_measurements(read_json(path, "measurement file"), mat, source=str(path))


def parse_measurements(doc, mat: MatSpec | None = None, source: str = "measurements") -> Measurements:
    mat = mat or MatSpec()
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise UserError(
            f'{source}: not a pressurepose measurement file (expected "format": "{FORMAT}"; see docs/calibration.md)'
        )
    scenes = doc.get("scenes")
    if not isinstance(scenes, list) or not scenes:
        raise UserError(f'{source}: "scenes" must be a non-empty list')
    out = []
    for i, s in enumerate(scenes):
        where = f"{source}: scene {i}"
        if not isinstance(s, dict):
            raise UserError(f'{where} must be an object with "pressure_mmhg" and "objects"')
        for key in ("pressure_mmhg", "objects"):
            if key not in s:
                raise UserError(f'{where} is missing "{key}"')
        try:
            image = np.asarray(s["pressure_mmhg"], dtype=np.float64)
        except (TypeError, ValueError):
            raise UserError(f"{where}: pressure_mmhg must be a {mat.rows} x {mat.cols} array of numbers") from None
        if image.shape != mat.shape:
            raise UserError(
                f"{where}: pressure_mmhg must have shape {mat.shape} (rows along the bed, head first), "
                f"got {image.shape}"
            )
        if not np.isfinite(image).all() or image.min() < 0 or image.max() > mat.max_pressure_mmhg:
            raise UserError(f"{where}: pressure_mmhg must be finite and within [0, {mat.max_pressure_mmhg:g}] mmHg")
        if not isinstance(s["objects"], list) or not s["objects"]:
            raise UserError(f'{where}: "objects" must be a non-empty list')
        objects, q = [], []
        for j, o in enumerate(s["objects"]):
            obj, comp = _parse_object(o, f"{where}, object {j}", mat)
            objects.append(obj)
            q.append(comp)
        out.append(Scene(tuple(objects), image, np.asarray(q, dtype=np.float64), str(s.get("name", ""))))
    return Measurements(tuple(out))


def _parse_object(o, where: str, mat: MatSpec) -> tuple[CalibObject, float]:
    if not isinstance(o, dict):
        raise UserError(f"{where} must be an object")
    shape = o.get("shape", "capsule")
    if shape != "capsule":
        raise UserError(f'{where}: shape {shape!r} is not supported (only "capsule")')
    for key in _OBJECT_FIELDS:
        if key not in o:
            raise UserError(f'{where} is missing "{key}"')
        v = o[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise UserError(f"{where}: {key} must be a finite number, got {v!r}")
    if o["mass_kg"] <= 0:
        raise UserError(f"{where}: mass_kg must be > 0 (a weight in kg), got {o['mass_kg']}")
    if o["compression_m"] < 0 or o["compression_m"] > 1.0:
        raise UserError(
            f"{where}: compression_m is the sinking depth in metres, >= 0 (and < 1), got {o['compression_m']}"
        )
    yaw = o.get("yaw_deg", 90.0)
    try:
        obj = CalibObject(
            float(o["length_m"]),
            float(o["radius_m"]),
            float(o["mass_kg"]),
            float(o["x_m"]),
            float(o["y_m"]),
            yaw,
            str(o.get("name", "")),
        )
    except ValueError as exc:
        raise UserError(f"{where}: {exc}") from None
    (xa, ya), (xb, yb) = obj.axis_ends_m()
    (x0, x1), (y0, y1) = mat.mattress_bounds_m
    r = obj.radius_m
    if min(xa, xb) - r < x0 or max(xa, xb) + r > x1 or min(ya, yb) - r < y0 or max(ya, yb) + r > y1:
        raise UserError(
            f"{where}: the capsule at ({obj.x_m}, {obj.y_m}) m does not lie wholly on the mattress "
            f"(x in [{x0:.3f}, {x1:.3f}], y in [{y0:.3f}, {y1:.3f}] m in the mat frame)"
        )
    return obj, float(o["compression_m"])


def synthetic_measurements(
    scenes: list[list[CalibObject]],
    params: MattressParams,
    noise_mmhg: float = 0.0,
    compression_noise_m: float = 0.0,
    seed: int = 0,
    mat: MatSpec | None = None,
    sub: int = 2,
) -> Measurements:
    """Measurements made by our own simulator with `params` (the hidden truth), sensor noise
    of `noise_mmhg` on loaded taxels and Gaussian noise of `compression_noise_m` on the
    measured compressions (the proof that calibration recovers known parameters)."""
    mat = mat or MatSpec()
    sim = SceneSimulator(scenes, mat, sub)
    gen = torch.Generator().manual_seed(seed)
    res = sim(params.replace(noise_mmhg=noise_mmhg), generator=gen)
    bad = [f"{o.name or i}: {f}" for i, (o, f) in enumerate(zip(sim.objects, res.failure)) if f]
    if bad:
        raise UserError(f"the hidden parameters give no rest for some objects ({'; '.join(bad)})")
    q = (
        res.compression_m.numpy()
        + compression_noise_m * torch.randn(len(sim.objects), generator=gen, dtype=torch.float64).numpy()
    )
    q = np.maximum(q, 0.0)
    out, k = [], 0
    for i, objs in enumerate(scenes):
        out.append(
            Scene(
                tuple(objs),
                res.reading_mmhg[i].numpy().astype(np.float64),
                q[k : k + len(objs)].copy(),
                name=f"scene {i}",
            )
        )
        k += len(objs)
    return Measurements(tuple(out))


__all__ = ["FORMAT", "Measurements", "Scene", "load_measurements", "parse_measurements", "synthetic_measurements"]
