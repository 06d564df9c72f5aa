"""`pressurepose calibrate`: fit the bed model to measurements of rigid objects (seed A.4, A.5).

Writes into `out/`: `params.json` (the best parameters as a MattressParams file, which
`simulate --params` and `generate` read), `cma_state.npz` (the resumable CMA-ES state, after
every generation), `convergence.png` and `calibrate.json` (config, result, per-object loss
terms, and the sim #1 / sim #2 sinking check of every object).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from pathlib import Path

import numpy as np
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from pressurepose.calib.cmaes import CMAResult, CMASettings, minimise
from pressurepose.calib.coupling import coupling_check
from pressurepose.calib.evaluator import Evaluator
from pressurepose.calib.loss import DEFAULT_FREE, CalibrationLoss, ParamSpace
from pressurepose.calib.measurements import load_measurements
from pressurepose.commands.outputs import Written, flat_config
from pressurepose.errors import UserError
from pressurepose.files import write_text
from pressurepose.mat import MatSpec
from pressurepose.sim.mattress import MattressParams
from pressurepose.viz.calibration import convergence_plot


@dataclasses.dataclass(frozen=True)
class CalibrateConfig:
    """Calibrate mattress, mat and sensor parameters with CMA-ES (seed A.4 settings).

    Attributes:
        measurements: Measurement file (docs/calibration.md: objects, images, compressions).
        out: Output folder (params.json, cma_state.npz, convergence.png, calibrate.json).
        start: Parameter file to start from and to take the fixed parameters from (default:
            the built-in MattressParams).
        free: MattressParams fields to calibrate.
        popsize: CMA-ES population size.
        max_iter: Maximum number of generations.
        max_fevals: Maximum number of loss evaluations.
        cmean: Mean learning rate.
        tolfun: Function tolerance.
        tolfunhist: Function history tolerance.
        tolx: X-change tolerance (scaled units).
        maxstd: Maximum standard deviation (scaled units).
        tolstagnation: Stagnation tolerance (generations).
        sigma0: Initial step size (scaled units: fraction of each parameter's typical size).
        seed: Seed of the CMA-ES normal draws.
        workers: Processes evaluating candidates in parallel (0 = one per CPU core).
        margin_m: Each object's loss region: taxels within this distance of its outline.
        sub: Sim #2 grid cells per taxel side.
        restart: Ignore an existing state in `out` and start over.
        stop_after: Stop (resumably) after this many generations in this run (0 = run to the end).
        coupling_check: Settle every object in sim #1 with the result and compare its sinking
            depth with sim #2's.
    """

    measurements: Path
    out: Path = Path("out/calibrate")
    start: Path | None = None
    free: tuple[str, ...] = DEFAULT_FREE
    popsize: int = 50
    max_iter: int = 3000
    max_fevals: int = 100_000_000
    cmean: float = 0.25
    tolfun: float = 1e-3
    tolfunhist: float = 1e-12
    tolx: float = 5e-4
    maxstd: float = 4.0
    tolstagnation: int = 100
    sigma0: float = 0.3
    seed: int = 0
    workers: int = 0
    margin_m: float = 0.06
    sub: int = 2
    restart: bool = False
    stop_after: int = 0
    coupling_check: bool = True

    def settings(self) -> CMASettings:
        return CMASettings(
            popsize=self.popsize,
            max_iter=self.max_iter,
            max_fevals=self.max_fevals,
            cmean=self.cmean,
            tolfun=self.tolfun,
            tolfunhist=self.tolfunhist,
            tolx=self.tolx,
            maxstd=self.maxstd,
            tolstagnation=self.tolstagnation,
            sigma0=self.sigma0,
            seed=self.seed,
        )


def run_calibrate(cfg: CalibrateConfig, progress: bool = True) -> Written:
    mat = MatSpec()
    measurements = load_measurements(cfg.measurements, mat)
    base = MattressParams.load(cfg.start) if cfg.start else MattressParams()
    space = ParamSpace(tuple(cfg.free), base)
    settings = cfg.settings()
    if cfg.workers < 0 or cfg.sub < 1 or cfg.stop_after < 0:
        raise UserError("workers and stop_after must be >= 0 and sub >= 1")
    loss = CalibrationLoss(measurements, space, cfg.margin_m, mat, cfg.sub)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    state = out / "cma_state.npz"
    if cfg.restart and state.exists():
        state.unlink()
    signature = {
        "free": list(space.free),
        "base": base.to_dict(),
        "margin_m": cfg.margin_m,
        "sub": cfg.sub,
        "measurements_sha256": hashlib.sha256(Path(cfg.measurements).read_bytes()).hexdigest(),
    }
    workers = cfg.workers or (os.cpu_count() or 1)
    x0 = space.encode(base)
    t0 = time.perf_counter()
    evaluator = Evaluator(loss, workers)
    try:
        result = _minimise_with_progress(evaluator, x0, settings, state, signature, cfg, progress)
    finally:
        evaluator.close()
    seconds = time.perf_counter() - t0
    best = space.params(result.best_x)
    paths = {"params": out / "params.json", "state": state}
    best.save(paths["params"])
    paths["plot"] = convergence_plot(result, space, out / "convergence.png")
    breakdown = loss.breakdown(result.best_x)
    finished = not (cfg.stop_after and not result.stop)
    record = {
        "config": flat_config(cfg),
        "finished": finished,
        "stop": result.stop,
        "iterations": result.iterations,
        "evaluations": result.evaluations,
        "resumed_from_generation": result.resumed_from,
        "seconds_this_run": round(seconds, 2),
        "workers": workers,
        "best_loss": result.best_f,
        "start_loss": float(result.history_f[0].min()) if len(result.history_f) else None,
        "params": best.to_dict(),
        "start_params": base.to_dict(),
        "objects": [
            {
                "name": o.name,
                "mass_kg": o.mass_kg,
                "length_m": o.length_m,
                "LF": _num(breakdown.force[i]),
                "LC": _num(breakdown.contact[i]),
                "LQ": _num(breakdown.compression[i]),
            }
            for i, o in enumerate(loss.sim.objects)
        ],
    }
    if cfg.coupling_check and finished:
        record["coupling"] = coupling_check(loss, best)
    text = json.dumps(record, indent=2) + "\n"
    paths["record"] = write_text(out / "calibrate.json", text)
    return Written(paths, record)


def _num(v) -> float | None:
    return None if not np.isfinite(v) else round(float(v), 6)


def _minimise_with_progress(evaluator, x0, settings, state, signature, cfg, progress) -> CMAResult:
    columns = (
        TextColumn("calibrate"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[info]}"),
        TimeElapsedColumn(),
    )
    with Progress(*columns, disable=not progress, transient=False) as bar:
        task = bar.add_task("cma", total=settings.max_iter, info="")

        def report(it, best_f, sigma):
            bar.update(task, completed=it, info=f"best {best_f:.4g} sigma {sigma:.3g}")

        return minimise(
            evaluator,
            x0,
            settings,
            state,
            signature,
            resume=not cfg.restart,
            stop_after=cfg.stop_after,
            on_generation=report,
        )


def calibrate(cfg: CalibrateConfig) -> None:
    """Calibrate mattress, mat and sensor parameters to measurements of rigid objects with
    CMA-ES (seed A.4); resumable; writes params.json for `simulate --params`."""
    written = run_calibrate(cfg)
    record = written.record
    state = "finished" if record["finished"] else "stopped (resume with the same command)"
    print(
        f"{state} after {record['iterations']} generations, {record['evaluations']} evaluations: loss "
        f"{record['start_loss']:.4g} -> {record['best_loss']:.4g}; parameters -> {written['params']}"
    )


__all__ = ["CalibrateConfig", "calibrate", "run_calibrate"]
