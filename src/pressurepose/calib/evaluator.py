"""Loss evaluations of one CMA-ES generation, in-process or on a process pool."""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp

import numpy as np
import torch

from pressurepose.calib.loss import CalibrationLoss, ParamSpace
from pressurepose.calib.measurements import Measurements

# One loss per worker process, built once by the pool initializer (the meshes and regions).
_WORKER_LOSS: CalibrationLoss | None = None


def _init_worker(measurements: Measurements, space: ParamSpace, margin_m: float, sub: int) -> None:
    torch.set_num_threads(1)
    global _WORKER_LOSS
    _WORKER_LOSS = CalibrationLoss(measurements, space, margin_m, sub=sub)


def _worker_eval(x: np.ndarray) -> float:
    return _WORKER_LOSS(x)


class Evaluator:
    """Evaluates a generation in-process (workers = 1) or on a process pool (spawned, so
    torch's threads in the parent cannot deadlock a fork)."""

    def __init__(self, loss: CalibrationLoss, workers: int):
        self.loss = loss
        self.workers = workers
        self.pool = None
        if workers > 1:
            self.pool = cf.ProcessPoolExecutor(
                workers,
                mp_context=mp.get_context("spawn"),
                initializer=_init_worker,
                initargs=(loss.measurements, loss.space, loss.margin_m, loss.sub),
            )

    def __call__(self, X) -> list[float]:
        if self.pool is None:
            # A few capsules per call: extra intra-op threads only add contention.
            n = torch.get_num_threads()
            torch.set_num_threads(1)
            try:
                return [self.loss(x) for x in X]
            finally:
                torch.set_num_threads(n)
        chunk = max(1, len(X) // (self.workers * 2))
        return list(self.pool.map(_worker_eval, X, chunksize=chunk))

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)


__all__ = ["Evaluator"]
