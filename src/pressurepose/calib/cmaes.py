"""CMA-ES (the `cma` package) with the seed's settings, a resumable state file without
pickles, parallel evaluations and a progress bar.

Resuming: after every generation the state file (`.npz`, arrays only, written atomically)
holds the strategy's summary - mean, step size sigma, covariance, iteration, evaluations, the
best point and value, the random generator's seed and draw count - and every generation's
candidates and their losses. A resumed run rebuilds the strategy by replaying that history
through a fresh `cma.CMAEvolutionStrategy` (ask, then tell the stored losses, no evaluations):
the replayed candidates must equal the stored ones and the rebuilt mean, sigma and covariance
the stored summary, so the resumed run continues exactly as the uninterrupted one would.
(Setting mean, sigma and covariance alone would drop the evolution paths and the fitness
history that the step-size rule and the termination criteria use.) The normal draws come
from `CountedNormal`: draw k is `numpy.random.default_rng((seed, k))`, a pure function of the
seed and the count.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pressurepose.errors import UserError
from pressurepose.files import atomic_write

log = logging.getLogger(__name__)
STATE_FORMAT = "pressurepose.cma-state/1"


@dataclasses.dataclass(frozen=True)
class CMASettings:
    """The seed's CMA-ES settings (A.4) as defaults; `sigma0` is in the scaled parameter units
    of loss.ParamSpace (0.3 = 30% of each parameter's typical magnitude)."""

    popsize: int = 50
    max_iter: int = 3000
    max_fevals: int = 100_000_000
    cmean: float = 0.25  # mean learning rate
    tolfun: float = 1e-3  # function tolerance
    tolfunhist: float = 1e-12  # function history tolerance
    tolx: float = 5e-4  # x-change tolerance
    maxstd: float = 4.0  # max standard deviation
    tolstagnation: int = 100  # stagnation tolerance (iterations)
    # Not in the seed: cma stops after 1 generation of equal values by default; penalised
    # proposals share values, so a plateau of a few generations is tolerated.
    tolflatfitness: int = 10
    sigma0: float = 0.3
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("popsize", "max_iter", "max_fevals", "tolstagnation", "tolflatfitness"):
            if int(getattr(self, name)) < 1:
                raise UserError(f"CMA setting {name} must be >= 1, got {getattr(self, name)}")
        if self.popsize < 2:
            raise UserError(f"popsize must be >= 2, got {self.popsize}")
        for name in ("cmean", "tolfun", "tolx", "maxstd", "sigma0"):
            if not getattr(self, name) > 0:
                raise UserError(f"CMA setting {name} must be > 0, got {getattr(self, name)}")

    def options(self, randn) -> dict:
        return {
            "popsize": self.popsize,
            "maxiter": self.max_iter,
            "maxfevals": self.max_fevals,
            "CMA_cmean": self.cmean,
            "tolfun": self.tolfun,
            "tolfunhist": self.tolfunhist,
            "tolx": self.tolx,
            "maxstd": self.maxstd,
            "tolstagnation": self.tolstagnation,
            "tolflatfitness": self.tolflatfitness,
            "randn": randn,
            "verbose": -9,
            "verb_disp": 0,
            "verb_log": 0,
        }


class CountedNormal:
    """randn(lam, N) for cma: draw k comes from default_rng((seed, k)); `count` draws so far."""

    def __init__(self, seed: int, count: int = 0):
        self.seed, self.count = int(seed), int(count)

    def __call__(self, *shape):
        rng = np.random.default_rng((self.seed, self.count))
        self.count += 1
        return rng.standard_normal(shape)


@dataclasses.dataclass
class CMAResult:
    best_x: np.ndarray
    best_f: float
    mean: np.ndarray
    sigma: float
    iterations: int
    evaluations: int
    stop: dict
    history_f: np.ndarray  # (G, popsize) every generation's losses
    history_mean: np.ndarray  # (G, N) the mean after each generation
    history_std: np.ndarray  # (G,) the largest coordinate standard deviation (sigma x sqrt(C_ii))
    resumed_from: int  # generations replayed from the state file (0 = fresh start)


def _new_strategy(x0: np.ndarray, settings: CMASettings):
    import cma

    randn = CountedNormal(settings.seed)
    es = cma.CMAEvolutionStrategy(np.asarray(x0, dtype=np.float64), settings.sigma0, settings.options(randn))
    return es, randn


def _covariance(es) -> np.ndarray:
    C = np.asarray(es.sm.C, dtype=np.float64)
    return C if C.ndim == 2 else np.diag(C)


def minimise(
    evaluate: Callable[[list[np.ndarray]], list[float]],
    x0: np.ndarray,
    settings: CMASettings,
    state_path: Path | None = None,
    signature: dict | None = None,
    resume: bool = True,
    stop_after: int = 0,
    on_generation: Callable[[int, float, float], None] | None = None,
) -> CMAResult:
    """Minimise with CMA-ES; `evaluate` maps a generation's candidates to their losses.

    `state_path`: the state file (written after every generation; resumed from when it exists
    and `resume`). `signature`: what must match for a resume (settings, parameters, data
    hash); a mismatch is a ValueError. `stop_after` > 0 stops (resumably) after that many new
    generations. `on_generation(iteration, best_f, sigma)` reports progress.
    """
    import cma

    signature = dict(
        signature or {}, settings=dataclasses.asdict(settings), x0=[float(v) for v in x0], cma_version=cma.__version__
    )
    es, randn = _new_strategy(x0, settings)
    X_hist: list[np.ndarray] = []
    F_hist: list[np.ndarray] = []
    means, sigmas = [], []
    resumed = 0
    if state_path is not None and resume and Path(state_path).exists():
        X_hist, F_hist, means, sigmas = _replay(es, Path(state_path), signature)
        resumed = len(X_hist)
        log.info("resumed CMA-ES from %s after %d generations", state_path, resumed)
    new = 0
    while not es.stop():
        if stop_after and new >= stop_after:
            break
        X = es.ask()
        F = np.asarray(evaluate(X), dtype=np.float64)
        es.tell(X, F.tolist())
        X_hist.append(np.asarray(X))
        F_hist.append(F)
        means.append(np.asarray(es.mean, dtype=np.float64).copy())
        sigmas.append(float(np.max(es.stds)))
        new += 1
        if state_path is not None:
            _save_state(Path(state_path), es, randn, signature, X_hist, F_hist)
        if on_generation is not None:
            on_generation(es.countiter, float(es.best.f), float(es.sigma))
    stop = {k: (v if isinstance(v, (int, float, str)) else str(v)) for k, v in dict(es.stop()).items()}
    return CMAResult(
        best_x=np.asarray(es.best.x, dtype=np.float64),
        best_f=float(es.best.f),
        mean=np.asarray(es.mean).copy(),
        sigma=float(es.sigma),
        iterations=int(es.countiter),
        evaluations=int(es.countevals),
        stop=stop,
        history_f=np.array(F_hist).reshape(len(F_hist), -1),
        history_mean=np.array(means).reshape(len(means), -1),
        history_std=np.array(sigmas),
        resumed_from=resumed,
    )


def _save_state(path: Path, es, randn: CountedNormal, signature: dict, X_hist, F_hist) -> None:
    arrays = {
        "format": np.array(STATE_FORMAT),
        "signature": np.array(json.dumps(signature, sort_keys=True)),
        "mean": np.asarray(es.mean, dtype=np.float64),
        "sigma": np.array(float(es.sigma)),
        "covariance": _covariance(es),
        "iteration": np.array(int(es.countiter)),
        "evaluations": np.array(int(es.countevals)),
        "best_x": np.asarray(es.best.x, dtype=np.float64),
        "best_f": np.array(float(es.best.f)),
        "rng_seed": np.array(randn.seed),
        "rng_count": np.array(randn.count),
        "candidates": np.stack(X_hist),
        "losses": np.stack(F_hist),
    }

    def write(tmp):
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)

    atomic_write(path, write)


def _replay(es, path: Path, signature: dict):
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise UserError(f"CMA state file {path} is unreadable ({exc}); delete it or run with --restart") from None
    if str(data.get("format", "")) != STATE_FORMAT:
        raise UserError(f"{path} is not a pressurepose CMA state file; delete it or run with --restart")
    stored = json.loads(str(data["signature"]))
    if stored != json.loads(json.dumps(signature, sort_keys=True)):
        diff = sorted(
            k for k in set(stored) | set(signature) if stored.get(k) != json.loads(json.dumps(signature.get(k)))
        )
        raise UserError(
            f"{path} was written by a run with other settings ({', '.join(diff)} differ); "
            "use the same settings to resume, or --restart to start over"
        )
    X_all, F_all = data["candidates"], data["losses"]
    means, sigmas = [], []
    for g in range(X_all.shape[0]):
        X = es.ask()
        if not np.array_equal(np.asarray(X), X_all[g]):
            raise UserError(
                f"{path}: replaying generation {g} drew other candidates than were stored (another "
                "cma or numpy version?); use --restart to start over"
            )
        es.tell(X, F_all[g].tolist())
        means.append(np.asarray(es.mean, dtype=np.float64).copy())
        sigmas.append(float(np.max(es.stds)))
    if (
        int(es.countiter) != int(data["iteration"])
        or not np.array_equal(np.asarray(es.mean), data["mean"])
        or float(es.sigma) != float(data["sigma"])
        or not np.array_equal(_covariance(es), data["covariance"])
    ):
        raise UserError(
            f"{path}: the replayed strategy does not match the stored mean, sigma and covariance; "
            "use --restart to start over"
        )
    return [x for x in X_all], [f for f in F_all], means, sigmas


__all__ = ["CMAResult", "CMASettings", "CountedNormal", "minimise"]
