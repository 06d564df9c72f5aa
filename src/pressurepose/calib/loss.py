"""The calibration loss (seed eq. 13-16), its penalties, and the parameter space CMA-ES searches.

Per object o of weight k (seed A.4), over the T taxels of the object's region:

    LF = 1/2 sum|u - u'| / sum(u + u') + 1/2 |sum(u - u')| / sum(u + u')    (eq. 14, readings u)
    LC = the same with the contact indicators c = [u > 0]                  (eq. 15)
    LQ = |q - q'| / (|q| + |q'|)                                          (eq. 16, compressions)

with u, c, q simulated and u', c', q' measured; the loss is the sum over all objects of
LF + LC + LQ (eq. 13). Each term lies in [0, 1]; a term whose denominator is zero (nothing
loaded in both images, or no compression in both) is 0: the two agree.

An object's region is the sensing taxels whose centres lie within `margin_m` of its footprint
(the capsule's outline seen from above): the seed's T, a fifth of the mat for its five objects.

Penalties (seed A.4, for parameters that break the simulation): a proposal with a negative
parameter (or one MattressParams rejects) costs PENALTY + its distance into the invalid region
and is not simulated; a parameter outside its plausible range adds 10 x its deviation from
the range (in units of the parameter's scale: the seed's rule for its spring stiffness ratios,
which our model does not have); objects that find no rest (sank through the mattress, tipped,
Newton did not converge within its iteration cap - our "unstable or too slow rollout") cost
PENALTY + the fraction of objects that failed.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from pressurepose.calib.measurements import Measurements
from pressurepose.calib.objects import CalibObject, SceneSimulator
from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.sim.mattress import MattressParams

PENALTY = 1.0e3
# What the static capsule images and compressions determine (docs/calibration.md): the
# foundation law, the mat's load spreading and the taxel law. mat_stiffness only rescales
# c1 and c2 (unidentifiable by construction); thickness, damping and friction never enter a
# static rest that does not bottom out.
DEFAULT_FREE = ("k1_pa_per_m", "k3_pa_per_m3", "spread_m", "c0_mmhg", "c1_mmhg_per_mm", "c2_mmhg_per_mm2")
# Typical magnitude of each field: CMA-ES works on theta / scale, so one sigma means alike.
SCALES = {
    "k1_pa_per_m": 2.0e4,
    "k3_pa_per_m3": 6.0e7,
    "spread_m": 0.01,
    "thickness_m": 0.15,
    "mat_stiffness_pa_per_mm": 133.322,
    "c0_mmhg": 1.0,
    "c1_mmhg_per_mm": 1.0,
    "c2_mmhg_per_mm2": 0.01,
    "noise_mmhg": 1.0,
    "damping_s": 0.05,
    "friction": 0.5,
}
# Plausible ranges: outside them the range penalty applies. c0 > 0 would make every taxel
# that the load spreading reaches at all (its Gaussian tails run to 3 sigma) read >= c0, so
# the contact area would follow the truncation of the Gaussian: c0 is a threshold, <= 0.
RANGES = {
    "k1_pa_per_m": (1.0e3, 2.0e5),
    "k3_pa_per_m3": (0.0, 2.0e9),
    "spread_m": (0.0, 0.05),
    "thickness_m": (0.03, 0.5),
    "mat_stiffness_pa_per_mm": (1.0, 1.0e4),
    "c0_mmhg": (-20.0, 0.0),
    "c1_mmhg_per_mm": (0.05, 20.0),
    "c2_mmhg_per_mm2": (0.0, 1.0),
    "noise_mmhg": (0.0, 20.0),
    "damping_s": (0.0, 1.0),
    "friction": (0.0, 2.0),
}
_MAY_BE_NEGATIVE = ("c0_mmhg",)


def _ratio(num, den) -> float:
    return float(num) / float(den) if den > 0 else 0.0


def force_term(u_sim: np.ndarray, u_real: np.ndarray) -> float:
    """LF (eq. 14) of two readings (T,) over one object's region."""
    den = float(np.sum(u_sim + u_real))
    return 0.5 * _ratio(np.abs(u_sim - u_real).sum(), den) + 0.5 * _ratio(abs(np.sum(u_sim - u_real)), den)


def contact_term(c_sim: np.ndarray, c_real: np.ndarray) -> float:
    """LC (eq. 15) of two contact indicators (T,) (0/1)."""
    return force_term(np.asarray(c_sim, dtype=np.float64), np.asarray(c_real, dtype=np.float64))


def compression_term(q_sim: float, q_real: float) -> float:
    """LQ (eq. 16) of two compressions (m, signed)."""
    return _ratio(abs(q_sim - q_real), abs(q_sim) + abs(q_real))


def object_region(obj: CalibObject, mat: MatSpec, margin_m: float) -> np.ndarray:
    """(rows, cols) bool: sensing taxels whose centre lies within radius + margin of the
    capsule's axis segment (seen from above)."""
    centres = mat.taxel_centres_m()  # (rows, cols, 2)
    (xa, ya), (xb, yb) = obj.axis_ends_m()
    a, ab = np.array([xa, ya]), np.array([xb - xa, yb - ya])
    t = np.clip(((centres - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    d = np.linalg.norm(centres - (a + t[..., None] * ab), axis=-1)
    return d <= obj.radius_m + margin_m


@dataclasses.dataclass(frozen=True)
class ParamSpace:
    """Which MattressParams fields CMA-ES moves (`free`), from which parameter set (`base`,
    also holding the fixed fields). x = theta / scale (linear, so negative proposals exist
    and are penalised as in the seed)."""

    free: tuple[str, ...] = DEFAULT_FREE
    base: MattressParams = MattressParams()
    ranges: tuple[tuple[str, float, float], ...] = ()  # (name, lo, hi) overriding RANGES

    def __post_init__(self) -> None:
        known = {f.name for f in dataclasses.fields(MattressParams)}
        bad = [n for n in self.free if n not in known]
        if bad or not self.free or len(set(self.free)) != len(self.free):
            raise UserError(
                f"free parameters must be distinct MattressParams fields ({', '.join(sorted(known))}), "
                f"got {list(self.free)}"
            )

    @property
    def scales(self) -> np.ndarray:
        return np.array([SCALES[n] for n in self.free])

    def encode(self, params: MattressParams) -> np.ndarray:
        return np.array([float(getattr(params, n)) for n in self.free]) / self.scales

    def decode(self, x: np.ndarray) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.free, np.asarray(x, dtype=np.float64) * self.scales)}

    def params(self, x: np.ndarray) -> MattressParams:
        return self.base.replace(**self.decode(x))

    def penalty(self, x: np.ndarray) -> tuple[float, bool]:
        """(penalty, invalid): invalid proposals are not simulated."""
        values = self.decode(x)
        neg = sum(-v / SCALES[n] for n, v in values.items() if v < 0 and n not in _MAY_BE_NEGATIVE)
        if neg > 0:
            return PENALTY + neg, True
        try:
            self.params(x)
        except ValueError:
            return PENALTY, True
        out = 0.0
        ranges = dict(RANGES, **{n: (lo, hi) for n, lo, hi in self.ranges})
        for n, v in values.items():
            lo, hi = ranges[n]
            out += 10.0 * (max(lo - v, 0.0) + max(v - hi, 0.0)) / SCALES[n]
        return out, False


@dataclasses.dataclass(frozen=True)
class LossBreakdown:
    total: float
    force: np.ndarray  # (N,) LF per object (nan when not simulated)
    contact: np.ndarray  # (N,) LC
    compression: np.ndarray  # (N,) LQ
    penalty: float
    failures: tuple[str, ...]


class CalibrationLoss:
    """Eq. 13 over every object of the measurements, plus penalties, as a function of the
    CMA-ES vector x. Builds the simulator and the object regions once."""

    def __init__(
        self,
        measurements: Measurements,
        space: ParamSpace,
        margin_m: float = 0.06,
        mat: MatSpec | None = None,
        sub: int = 2,
    ):
        if not margin_m >= 0:
            raise UserError(f"region margin must be >= 0 m, got {margin_m}")
        self.mat = mat or MatSpec()
        self.space = space
        self.measurements = measurements
        self.margin_m, self.sub = margin_m, sub
        self.sim = SceneSimulator(measurements.object_scenes(), self.mat, sub)
        self.real = np.stack([s.pressure_mmhg for s in measurements.scenes])
        self.q_real = np.concatenate([s.compression_m for s in measurements.scenes])
        self.scene_of = self.sim.scene_of.numpy()
        self.regions = []
        for i, scene in enumerate(measurements.scenes):
            masks = [object_region(o, self.mat, margin_m) for o in scene.objects]
            for j in range(len(masks)):
                if not masks[j].any():
                    raise UserError(
                        f"scene {i}, object {j}: its region holds no sensing taxel; place it over the sensing area"
                    )
                for k in range(j):
                    if (masks[j] & masks[k]).any():
                        raise UserError(
                            f"scene {i}: objects {k} and {j} lie within {2 * margin_m:.3f} m of each "
                            "other, so their loss regions overlap; place them further apart or lower "
                            "the region margin"
                        )
            self.regions += masks

    def __call__(self, x: np.ndarray) -> float:
        return self.breakdown(x).total

    def breakdown(self, x: np.ndarray) -> LossBreakdown:
        n = len(self.regions)
        pen, invalid = self.space.penalty(x)
        nan = np.full(n, np.nan)
        if invalid:
            return LossBreakdown(pen, nan, nan, nan, pen, ())
        res = self.sim(self.space.params(x))
        failed = sum(bool(f) for f in res.failure)
        if failed:
            return LossBreakdown(
                PENALTY + failed / n + pen, nan, nan, nan, PENALTY + failed / n + pen, tuple(res.failure)
            )
        return self.terms(res.reading_mmhg.numpy(), res.compression_m.numpy(), pen, tuple(res.failure))

    def of_params(self, params: MattressParams) -> float:
        """Eq. 13 for a whole parameter set (fixed fields included; no range penalty)."""
        res = self.sim(params)
        failed = sum(bool(f) for f in res.failure)
        if failed:
            return PENALTY + failed / len(self.regions)
        return self.terms(res.reading_mmhg.numpy(), res.compression_m.numpy()).total

    def terms(self, reading: np.ndarray, q_sim: np.ndarray, penalty: float = 0.0, failures=()) -> LossBreakdown:
        """Eq. 13-16 of simulated readings (S, rows, cols) and compressions (N,)."""
        lf, lc, lq = (np.zeros(len(self.regions)) for _ in range(3))
        for i, mask in enumerate(self.regions):
            u, ur = reading[self.scene_of[i]][mask], self.real[self.scene_of[i]][mask]
            lf[i] = force_term(u, ur)
            lc[i] = contact_term(u > 0, ur > 0)
            lq[i] = compression_term(float(q_sim[i]), float(self.q_real[i]))
        total = float(lf.sum() + lc.sum() + lq.sum()) + penalty
        if not math.isfinite(total):
            total = PENALTY * 2
        return LossBreakdown(total, lf, lc, lq, penalty, tuple(failures))


__all__ = [
    "CalibrationLoss",
    "DEFAULT_FREE",
    "LossBreakdown",
    "PENALTY",
    "ParamSpace",
    "RANGES",
    "SCALES",
    "compression_term",
    "contact_term",
    "force_term",
    "object_region",
]
