"""`--engine ray`: each shard is one Ray task running the same `make_shard` as the local engine.

Tasks return the shard's bytes to the driver, which writes them (no shared file system needed
on the cluster; only the driver's --out must be writable). Workers need pressurepose (and its
Anny cache, built by `pressurepose cache`) installed on every node. Without an address a local
Ray instance with `workers` CPUs is started and stopped; `--ray-address auto` joins a cluster
started with `ray start` (docs/generation.md).
"""

from __future__ import annotations

import os
from collections.abc import Iterator

from pressurepose.errors import UserError
from pressurepose.generate.allocator import ENV as ALLOCATOR_ENV
from pressurepose.generate.plan import ShardSpec
from pressurepose.generate.worker import WorkContext, make_shard


def _import_ray():
    try:
        import ray
    except ImportError:
        raise UserError("--engine ray needs Ray: pip install 'pressurepose[ray]'") from None
    return ray


def _task(spec: ShardSpec, ctx: WorkContext):
    import torch

    from pressurepose.generate.allocator import tune_allocator

    tune_allocator()
    torch.set_num_threads(1)
    return make_shard(spec, ctx)


def run_ray(pending: list[ShardSpec], ctx: WorkContext, workers: int, address: str | None) -> Iterator[tuple]:
    ray = _import_ray()
    started = False
    if not ray.is_initialized():
        options = dict(include_dashboard=False, log_to_driver=False, configure_logging=False)
        if address is None:
            # Local workers inherit this environment, PYTHONPATH included (a source checkout).
            env = {
                k: os.environ[k]
                for k in ("PYTHONPATH", "PRESSUREPOSE_CACHE", "ANNY_CACHE_DIR", ALLOCATOR_ENV)
                if k in os.environ
            }
            ray.init(num_cpus=workers, runtime_env={"env_vars": env} if env else None, **options)
        else:
            ray.init(address=address, **options)
        started = True
    try:
        # A failed task is retried (a lost node); a task's result is a pure function of its input.
        remote = ray.remote(num_cpus=1, max_retries=2)(_task)
        todo = list(pending)
        running: dict = {}
        while todo or running:
            while todo and len(running) < 2 * workers:
                spec = todo.pop(0)
                running[remote.remote(spec, ctx)] = spec
            done, _ = ray.wait(list(running), num_returns=1)
            for ref in done:
                spec = running.pop(ref)
                data, record = ray.get(ref)
                yield spec, data, record
    finally:
        if started:
            ray.shutdown()


__all__ = ["run_ray"]
