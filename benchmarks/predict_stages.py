"""Where a heatmap network's predict spends its time, stage by stage (wall time, median).

    OMP_NUM_THREADS=1 PYTHONPATH=src taskset -c 1 .venv/bin/python benchmarks/predict_stages.py \
        [--model default] [--batch 1] [--n 150] [--threads 1]

Runs the network's own forward (`PressureNet._localise_and_fit`, mesh without PMR maps, as
`predict` runs it) on random pressure images (a third of the cells loaded, up to 60 mmHg) with a
clock around each stage it calls: input channels, encoder-decoder (`mod1`), parameter head,
posture agreement (when the config asks for it), height blend (`stature_from_joints`), IK
(`fit_to_joints`) and the mesh (`estimate`); what no stage covers is reported as the rest. The
flip test, when the model's config sets it, falls inside the encoder-decoder. At batch 1 the time
is mostly per-operation overhead on small tensors, so each stage's share, not the convolutions'
FLOPs, says where to work (docs/benchmarks.md, sessions 55 and 57).
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import time
from collections import defaultdict

import torch

import pressurepose.net.model as net_model
from pressurepose.net.model import NetInputs
from pressurepose.train.checkpoint import load_network

STAGES = ("channels", "encoder-decoder", "head", "posture agreement", "height blend", "IK", "mesh")


def _images(batch: int, seed: int) -> NetInputs:
    g = torch.Generator().manual_seed(seed)
    load = torch.rand(batch, 64, 27, generator=g) * 60
    return NetInputs(load * (torch.rand(batch, 64, 27, generator=g) > 0.6))


class _Clocks:
    """Seconds per stage of the current forward, from wrappers around what the forward calls."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)

    def wrap(self, name: str, fn):
        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds[name] += time.perf_counter() - start

        return timed

    def hooks(self, name: str, module: torch.nn.Module) -> list:
        starts: list[float] = []
        pre = module.register_forward_pre_hook(lambda *_: starts.append(time.perf_counter()))
        post = module.register_forward_hook(
            lambda *_: self.seconds.__setitem__(name, self.seconds[name] + time.perf_counter() - starts.pop())
        )
        return [pre, post]


@contextlib.contextmanager
def _instrumented(net, clocks: _Clocks):
    """The stages wrapped in clocks for the duration (the network's own code runs unchanged)."""
    saved = {k: getattr(net_model, k) for k in ("stature_from_joints", "fit_to_joints")}
    net_model.stature_from_joints = clocks.wrap("height blend", saved["stature_from_joints"])
    net_model.fit_to_joints = clocks.wrap("IK", saved["fit_to_joints"])
    methods = {"channels": "channels", "posture agreement": "_agree_with_readout", "mesh": "estimate"}
    for stage, method in methods.items():
        setattr(net, method, clocks.wrap(stage, getattr(net, method)))
    handles = clocks.hooks("encoder-decoder", net.mod1) + clocks.hooks("head", net.head)
    try:
        yield
    finally:
        for k, v in saved.items():
            setattr(net_model, k, v)
        for method in methods.values():
            delattr(net, method)  # the instance attribute; the class's method shows again
        for h in handles:
            h.remove()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="default")
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--n", type=int, default=150, help="timed batches (after 20 warm-up ones)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (0: torch's default)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    net, _ = load_network(args.model, torch.device("cpu"))
    if net.config.arch != "heatmap":
        raise SystemExit(f"predict_stages: {args.model} is arch {net.config.arch!r}; the stages are the heatmap arch's")
    times: dict[str, list[float]] = defaultdict(list)
    warm = 20
    clocks = _Clocks()
    with torch.inference_mode(), _instrumented(net, clocks):
        for i in range(warm + args.n):
            clocks.seconds.clear()
            start = time.perf_counter()
            net(_images(args.batch, i), mesh=True, maps=False)
            whole = time.perf_counter() - start
            if i >= warm:
                for stage in STAGES:
                    times[stage].append(clocks.seconds[stage])
                times["rest"].append(whole - sum(clocks.seconds[s] for s in STAGES))
                times["whole"].append(whole)
    med = {k: statistics.median(v) * 1e3 for k, v in times.items()}
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), batch {args.batch}, median of {args.n}")
    print("| stage | ms |\n| --- | --- |")
    for stage in (*STAGES, "rest"):
        print(f"| {stage} | {med[stage]:.2f} |")
    print(f"| whole forward (mesh, no maps) | {med['whole']:.2f} |")


if __name__ == "__main__":
    main()
