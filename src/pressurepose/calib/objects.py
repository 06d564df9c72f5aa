"""Calibration objects (seed A.4) and the simulated scenes they make.

A calibration *scene* is one pressure image of several rigid objects resting on the bed at
once (the seed dropped its capsules together so one image calibrates several weights). Our
objects are horizontal capsules (`CalibObject`); sim #2 rests each one on the mattress. In
sim #2 two objects interact only through the mat's load spreading, which is linear, so a
scene's covered-grid pressure is the sum of its objects' pressures (exact as long as the
objects do not touch; `measurements.py` rejects layouts whose loss regions overlap). The
sensor law, which is not linear, is applied to the summed pressure, as the real mat sees it.
"""

from __future__ import annotations

import dataclasses
import math

import torch

from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.sim.foundation import simulate_pressure
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.objects import capsule_mesh
from pressurepose.sim.sensor import sensing_area, taxel_reading

# Seed A.4: capsules of L = 20 cm and 40 cm and the weights each was loaded with (kg).
SEED_WEIGHTS_KG = {0.20: (1.3, 2.3, 4.5, 9.1, 14.0), 0.40: (1.3, 4.5, 9.1, 14.0, 18.0)}
# The seed does not give the radius; 5 cm (a 10 cm pipe) is our assumption, stated in the docs.
SEED_RADIUS_M = 0.05
# Mesh resolution of the simulated capsules: the same for every capsule, so a scene is a
# batch of equal-sized meshes (362 vertices; finer meshes change sinking depths by < 0.3 mm).
_MESH = {"n_around": 24, "n_cap": 4, "n_along": 8}


@dataclasses.dataclass(frozen=True)
class CalibObject:
    """One rigid capsule lying on the bed: axis horizontal, `length_m` between the centres of
    its end spheres (the seed's L), `radius_m`, total `mass_kg`. Placement: its centre at
    (x_m, y_m) in the mat frame (x along the bed from the head end of the sensing area, y
    across, docs/conventions.md) and its axis at `yaw_deg` from the bed's long axis
    (90 = across the bed)."""

    length_m: float
    radius_m: float
    mass_kg: float
    x_m: float
    y_m: float
    yaw_deg: float = 90.0
    name: str = ""

    def __post_init__(self) -> None:
        label = f"object {self.name!r}" if self.name else "object"
        for field in ("length_m", "radius_m", "mass_kg", "x_m", "y_m", "yaw_deg"):
            v = getattr(self, field)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise UserError(f"{label}: {field} must be a finite number, got {v!r}")
        if self.mass_kg <= 0:
            raise UserError(f"{label}: mass_kg must be > 0, got {self.mass_kg}")
        if self.radius_m <= 0 or self.length_m < 0:
            raise UserError(f"{label}: need radius_m > 0 and length_m >= 0, got {self.radius_m}, {self.length_m}")

    def axis_ends_m(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """(x, y) of the two end-sphere centres."""
        a = math.radians(self.yaw_deg)
        dx, dy = 0.5 * self.length_m * math.cos(a), 0.5 * self.length_m * math.sin(a)
        return (self.x_m - dx, self.y_m - dy), (self.x_m + dx, self.y_m + dy)

    def mesh(self, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
        """Closed capsule mesh at its placement, 1 cm above the mattress: (V, 3), (F, 3)."""
        v, f = capsule_mesh(self.length_m, self.radius_m, dtype=dtype, **_MESH)
        a = math.radians(self.yaw_deg)
        rot = torch.tensor(
            [[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]], dtype=dtype
        )
        centre = torch.tensor([self.x_m, self.y_m, self.radius_m + 0.01], dtype=dtype)
        return v @ rot.T + centre, f


def seed_objects(mat: MatSpec | None = None, radius_m: float = SEED_RADIUS_M) -> list[list[CalibObject]]:
    """The seed's ten capsule-weight pairs as two scenes of five: the 20 cm capsules, then the
    40 cm ones, each lying across the bed, centred, spaced evenly along it."""
    mat = mat or MatSpec()
    scenes = []
    for length, weights in SEED_WEIGHTS_KG.items():
        n = len(weights)
        step = mat.sensing_length_m / n
        scenes.append(
            [
                CalibObject(
                    length,
                    radius_m,
                    m,
                    x_m=step * (i + 0.5),
                    y_m=mat.sensing_width_m / 2,
                    yaw_deg=90.0,
                    name=f"L{round(length * 100)}cm_{m:g}kg",
                )
                for i, m in enumerate(weights)
            ]
        )
    return scenes


@dataclasses.dataclass(frozen=True)
class SceneResult:
    """What the simulated bed shows for S scenes holding N objects in all."""

    reading_mmhg: torch.Tensor  # (S, rows, cols) sensor readings of each scene
    pressure_pa: torch.Tensor  # (S, covered_rows, covered_cols) summed pressure before the sensor
    compression_m: torch.Tensor  # (N,) each object's deepest compression of the mattress
    failure: list[str]  # (N,) "" or why the object found no rest (foundation.FAIL_*)


class SceneSimulator:
    """Rests the objects of several scenes on the simulated bed for given MattressParams.

    The meshes are built once; `__call__` runs sim #2 on all objects as one batch (no
    gradients: CMA-ES needs values only), sums them per scene and applies the sensor.
    """

    def __init__(self, scenes: list[list[CalibObject]], mat: MatSpec | None = None, sub: int = 2, dtype=torch.float64):
        if not scenes or any(not s for s in scenes):
            raise UserError("need at least one scene, each with at least one object")
        self.mat = mat or MatSpec()
        self.sub = sub
        self.objects = [o for s in scenes for o in s]
        self.scene_of = torch.tensor([i for i, s in enumerate(scenes) for _ in s])
        self.n_scenes = len(scenes)
        meshes = [o.mesh(dtype) for o in self.objects]
        self.vertices = torch.stack([v for v, _ in meshes])  # (N, V, 3)
        self.faces = meshes[0][1]
        self.mass_kg = torch.tensor([o.mass_kg for o in self.objects], dtype=dtype)

    def __call__(self, params: MattressParams, generator: torch.Generator | None = None) -> SceneResult:
        with torch.no_grad():
            res = simulate_pressure(self.vertices, self.faces, self.mass_kg, params, self.mat, sub=self.sub)
            covered = torch.zeros((self.n_scenes,) + tuple(res.pressure_pa.shape[1:]), dtype=res.pressure_pa.dtype)
            covered.index_add_(0, self.scene_of, res.pressure_pa)
            # The spread tails (1e-10 Pa) must not count as load: round-off can make them
            # slightly negative, which the sensor rejects.
            covered = covered.clamp(min=0.0)
            reading = taxel_reading(sensing_area(covered, self.mat), params, self.mat, generator)
        return SceneResult(reading, covered, res.max_compression_m, list(res.failure))


__all__ = ["CalibObject", "SEED_RADIUS_M", "SEED_WEIGHTS_KG", "SceneResult", "SceneSimulator", "seed_objects"]
