"""Parameters of the simulated bed: mattress foundation, mat and cover coupling, sensor, and
sim #1's contact damping and friction. One frozen dataclass, saved and loaded as JSON (the
parameter file `pressurepose calibrate` writes and `simulate` / `generate` read).

Units are SI except the sensor law, which maps mat-layer compression in mm to mmHg as the
BT3510 readings are in mmHg. Fields may hold torch tensors instead of floats when gradients
with respect to the parameters are wanted (sim #2 is differentiable in them).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path

from pressurepose.errors import UserError
from pressurepose.units import GRAVITY_M_S2, MMHG_PA  # re-exported: sim's modules read them here


@dataclasses.dataclass(frozen=True)
class MattressParams:
    """The bed model shared by sim #1 and sim #2 (docs/physics.md).

    Foundation law (per unit area of the mattress top, w = local compression in m):
        p(w) = k1 w + k3 w^3            [Pa]
    Lateral coupling: the mat and cover spread the foundation's load over neighbouring
    taxels with a Gaussian of standard deviation `spread_m` (force and centre of pressure
    are preserved). Sensor: the mat layer compresses d = p / mat_stiffness (mm) and a taxel
    reads c0 + c1 d + c2 d^2 mmHg for d > 0 (the seed's quadratic taxel law), clipped to
    [0, 100]; `noise_mmhg` adds Gaussian noise on the loaded taxels; a taxel reading below
    `floor_mmhg` reads 0 (the mat's detection floor: PmatData's frames report nothing below
    3.0-3.8 mmHg, docs/realism.md "The sensor's floor in the generator").

    Air cells: an air mattress is a row of tubes across the bed, so its top is not flat - the
    body rests on the tubes' crests and bridges the seams between them. With `cell_pitch_m` and
    `cell_depth_m` > 0 the top lies at z(x) = -depth (1 - cos(2 pi (x - crest) / pitch)) / 2
    (`top_height`): crests at z = 0 at x = `cell_crest_m` + k pitch, seams `depth` lower, half
    way between (docs/physics.md, "Air cells"). Sim #2 (both rests) measures the compression
    from this top; sim #1 (MuJoCo) treats the top as flat.
    """

    # Defaults: k1, k3, spread fitted to PmatData's sponge (foam) mattress, supine subjects
    # (docs/calibration.md: benchmarks/realism_fit.py; before that fit: 2e4, 6e7, 0.008).
    k1_pa_per_m: float = 2.77e4
    k3_pa_per_m3: float = 5.89e7
    spread_m: float = 0.0235
    thickness_m: float = 0.15
    # The mat as a tensioned membrane on the foam (m): the screening length sqrt(T / k) over which
    # it carries a contact's load beyond the contact's edge (`sim.membrane`); 0: no membrane.
    membrane_m: float = 0.0
    # The foundation's stiffness under the membrane (Pa/m) over air cells: the mat bridges the
    # tubes' seams and is pressed into them only where the load is deep enough (`sim.membrane`);
    # 0: the membrane reads as over a flat top. Used only with membrane_m > 0 and air cells.
    membrane_support_pa_per_m: float = 0.0
    # Over air cells: the relative wave of the tubes' stiffness under the mat along the bed, k (1 +
    # a cos(2 pi (x - crest) / pitch)) - stiffest on a tube's crest, softest at the seams; the mat
    # smooths the load, so the crests read a times more than the mean in any load (`sim.membrane`).
    membrane_wave: float = 0.0
    # The foam's densification (Pa): its collapsed cells add densify_pa (u / thickness)^9 to the
    # pressure at compression u - nothing below half the thickness (< 0.2%), all of densify_pa
    # at full compression (docs/physics.md "Densification"); 0: the cubic law alone.
    densify_pa: float = 0.0
    mat_stiffness_pa_per_mm: float = MMHG_PA  # 1 mmHg compresses the mat layer 1 mm by default
    c0_mmhg: float = -1.0  # taxels below ~1 mmHg read 0, as a real mat's threshold does
    c1_mmhg_per_mm: float = 1.0
    c2_mmhg_per_mm2: float = 0.0
    noise_mmhg: float = 0.0
    # The sensor's floor (mmHg): readings below it read 0. 0: the reading law's own threshold
    # (c0 < 0 zeroes d < -c0 / c1) alone, which reads down to ~0 mmHg on a contact's fringe.
    floor_mmhg: float = 0.0
    # Soft tissue in series with the foam (Pa/m of compression per unit area; 0: a rigid body
    # surface). Used by the articulated sim #2 (sim/articulated.py); the rigid rest ignores it.
    tissue_pa_per_m: float = 3.0e5
    # sim #1 contact: damping time constant (s) of the foundation, friction coefficient.
    damping_s: float = 0.05
    friction: float = 0.5
    # Air cells across the bed (0: a flat top): pitch along the bed, depth of the seams below the
    # crests, x of one crest in the mat frame (m).
    cell_pitch_m: float = 0.0
    cell_depth_m: float = 0.0
    cell_crest_m: float = 0.0
    # Air support (the articulated rest; 0 stiffness: the foam law): the tubes' inflation
    # pressure P0 (Pa) and the air's volume stiffness kappa (Pa per m^3 displaced), `sim.air_law`.
    air_pressure_pa: float = 0.0
    air_stiffness_pa_per_m3: float = 0.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            try:
                v = _scalar(value)
            except (TypeError, ValueError):
                raise UserError(f"MattressParams.{f.name} must be a number, got {value!r}") from None
            if not math.isfinite(v):
                raise UserError(f"MattressParams.{f.name} must be finite, got {v}")
            if f.name not in ("c0_mmhg", "cell_crest_m") and v < 0:
                raise UserError(f"MattressParams.{f.name} must be >= 0, got {v}")
        for name in ("k1_pa_per_m", "thickness_m", "mat_stiffness_pa_per_mm"):
            if _scalar(getattr(self, name)) <= 0:
                raise UserError(f"MattressParams.{name} must be > 0, got {getattr(self, name)}")
        if not _scalar(self.membrane_wave) < 1:
            raise UserError(
                f"MattressParams.membrane_wave must be < 1 (a share of the mean stiffness), got {self.membrane_wave}"
            )
        if _scalar(self.membrane_wave) > 0 and _scalar(self.membrane_support_pa_per_m) > 0:
            raise UserError(
                "MattressParams.membrane_wave and membrane_support_pa_per_m are two models of the tubes under "
                "the mat (a stiffness wave, or seams the mat bridges): set one of them"
            )
        if not _scalar(self.floor_mmhg) < MAX_FLOOR_MMHG:
            raise UserError(
                f"MattressParams.floor_mmhg must be < {MAX_FLOOR_MMHG} mmHg (a detection floor, not a "
                f"saturation), got {self.floor_mmhg}"
            )
        if _scalar(self.cell_depth_m) > 0 and _scalar(self.cell_pitch_m) <= 0:
            raise UserError(
                f"MattressParams.cell_depth_m is {_scalar(self.cell_depth_m)} but cell_pitch_m is 0: "
                "air cells need a pitch (or set the depth to 0 for a flat top)"
            )

    def replace(self, **changes) -> MattressParams:
        return dataclasses.replace(self, **changes)

    def foundation_pressure(self, w):
        """p(w) in Pa for compression w (m, >= 0); works on floats and tensors."""
        p = self.k1_pa_per_m * w + self.k3_pa_per_m3 * w**3
        return p + self.densification(w)[0] if _scalar(self.densify_pa) > 0 else p

    def foundation_stiffness(self, w):
        """dp/dw (Pa/m)."""
        k = self.k1_pa_per_m + 3.0 * self.k3_pa_per_m3 * w**2
        return k + self.densification(w)[1] if _scalar(self.densify_pa) > 0 else k

    def densification(self, u):
        """The foam's densification term at foam compression u (m; floats, arrays, tensors):
        its pressure densify_pa (u / T)^9 (Pa), that pressure's derivative (Pa/m) and its stored
        energy per unit area (J/m^2) - every engine's one formula."""
        n, t = DENSIFY_EXPONENT, self.thickness_m
        r = u / t
        r8 = r ** (n - 1)
        return self.densify_pa * r8 * r, n * self.densify_pa / t * r8, self.densify_pa * t / (n + 1) * r8 * r * r

    @property
    def has_air_support(self) -> bool:
        """True when the articulated rest's cells press on air at one pressure (`sim.air_law`)
        instead of the foam (k1, k3)."""
        return _scalar(self.air_stiffness_pa_per_m3) > 0

    @property
    def has_cells(self) -> bool:
        """True when the top is not flat (air cells, `top_height`)."""
        return _scalar(self.cell_depth_m) > 0 and _scalar(self.cell_pitch_m) > 0

    def top_height(self, x):
        """Height (m, <= 0) of the mattress top at x along the bed (m, mat frame; a tensor): 0 on
        a flat top, else the air cells' profile (class doc)."""
        import torch

        if not self.has_cells:
            return torch.zeros_like(x)
        return -0.5 * self.cell_depth_m * (1 - torch.cos(self._cell_phase(x)))

    def tube_stiffness_wave(self, x):
        """The relative change of the tubes' stiffness under the mat at x along the bed (m, mat
        frame; a tensor): `membrane_wave` cos(phase), +a on a crest, -a in a seam (`sim.membrane`)."""
        import torch

        return self.membrane_wave * torch.cos(self._cell_phase(x))

    def _cell_phase(self, x):
        """2 pi (x - crest) / pitch: the air cells' phase at x."""
        return (x - self.cell_crest_m) * (2 * math.pi / self.cell_pitch_m)

    def to_dict(self) -> dict:
        """The fields as numbers; a flat top leaves out the air cells' fields, a foam bed the
        air support's, a foam without densification `densify_pa` and a mat without `membrane_m` (or
        `membrane_support_pa_per_m`, `membrane_wave`) and a sensor without `floor_mmhg`, so the files and dataset
        settings of such beds are those written before the fields existed."""
        skip = (() if self.has_cells else _CELL_FIELDS) + (() if self.has_air_support else _AIR_FIELDS)
        skip += () if _scalar(self.densify_pa) > 0 else ("densify_pa",)
        skip += () if _scalar(self.membrane_m) > 0 else ("membrane_m",)
        skip += () if _scalar(self.membrane_support_pa_per_m) > 0 else ("membrane_support_pa_per_m",)
        skip += () if _scalar(self.membrane_wave) > 0 else ("membrane_wave",)
        skip += () if _scalar(self.floor_mmhg) > 0 else ("floor_mmhg",)
        return {f.name: _scalar(getattr(self, f.name)) for f in dataclasses.fields(self) if f.name not in skip}

    def save(self, path: str | os.PathLike) -> None:
        from pressurepose.files import atomic_write

        text = json.dumps({"format": "pressurepose.mattress/1", "params": self.to_dict()}, indent=2) + "\n"
        atomic_write(Path(path), lambda tmp: Path(tmp).write_text(text))

    @classmethod
    def preset(cls, name: str) -> MattressParams:
        """A named bed: `PRESETS` (PmatData's mattresses fitted through the articulated sim #2,
        docs/realism.md)."""
        if name not in PRESETS:
            raise UserError(f"unknown mattress preset {name!r}; presets: {', '.join(PRESETS)}")
        return cls(**PRESETS[name])

    @classmethod
    def load(cls, path: str | os.PathLike) -> MattressParams:
        """A parameter file, or a preset's name (`PRESETS`) when no such file exists."""
        from pressurepose.validate import read_json

        if str(path) in PRESETS and not Path(path).exists():
            return cls.preset(str(path))
        path = Path(path)
        if not path.exists():
            raise UserError(f"mattress parameter file {path} does not exist (presets: {', '.join(PRESETS)})")
        doc = read_json(
            path, "mattress parameter file", "; write one with `pressurepose calibrate` or MattressParams.save"
        )
        if (
            not isinstance(doc, dict)
            or doc.get("format") != "pressurepose.mattress/1"
            or not isinstance(doc.get("params"), dict)
        ):
            raise UserError(
                f"{path} is not a pressurepose mattress parameter file "
                "(expected {'format': 'pressurepose.mattress/1', 'params': {...}})"
            )
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(doc["params"]) - known)
        if unknown:
            raise UserError(
                f"{path}: unknown mattress parameters {', '.join(unknown)}; valid ones: {', '.join(sorted(known))}"
            )
        return cls(**doc["params"])


DENSIFY_EXPONENT = 9  # `MattressParams.densify_pa`: the densification term's power of u / thickness


# PmatData experiment II's two mattresses, fitted through the articulated sim #2 (with
# self-contact and friction, 2026-11-25) with benchmarks/articulated_fit.py --bed-only
# --from-preset (docs/realism.md). The class defaults stay the rigid sim #2's
# fit (docs/calibration.md), which the generator's default uses.
PRESETS: dict[str, dict[str, float]] = {
    # Session 41's refit with the mat's membrane (`membrane_m`), adopted in session 42 with the
    # joints at 0.8 x the seed's and a 5 cm self-contact (docs/realism.md).
    "sponge": {
        "k1_pa_per_m": 51740.0,
        "k3_pa_per_m3": 10710000.0,
        "tissue_pa_per_m": 79360.0,
        "spread_m": 0.002092,
        "membrane_m": 0.02939,
        # The lowest reading of PmatData's sponge frames (`eval.realism.reading_floor`, session 44).
        "floor_mmhg": 3.31,
    },
    # Session 42's refit with the new joints, the mat's membrane on the tubes' stiffness wave
    # (`membrane_wave`), the rest's seams 2 mm deep (docs/realism.md). Pitch and crest measured
    # from the transverse bands of PmatData's air frames (docs/physics.md "Air cells"); the tubes'
    # air at one pressure ("Air support").
    "air": {
        "k1_pa_per_m": 68450.0,
        "k3_pa_per_m3": 25950000.0,
        "tissue_pa_per_m": 102900.0,
        "spread_m": 0.002804,
        "membrane_m": 0.01839,
        "membrane_wave": 0.2991,
        "cell_pitch_m": 0.1024,
        "cell_depth_m": 0.002,
        "cell_crest_m": 0.0013,
        "air_pressure_pa": 3101.0,
        "air_stiffness_pa_per_m3": 537100.0,
        "floor_mmhg": 3.61,  # PmatData's air frames' lowest reading
    },
}


MAX_FLOOR_MMHG = 50.0
_CELL_FIELDS = ("cell_pitch_m", "cell_depth_m", "cell_crest_m")
_AIR_FIELDS = ("air_pressure_pa", "air_stiffness_pa_per_m3")


def _scalar(value) -> float:
    """A float from a number or a one-element tensor (detached, for checks only)."""
    if hasattr(value, "detach"):
        if value.numel() != 1:
            raise UserError("expected one value")
        return float(value.detach())
    return float(value)


__all__ = ["GRAVITY_M_S2", "MMHG_PA", "MattressParams"]
