"""Where a heatmap network's predict spends its time, stage by stage (wall time, median).

    OMP_NUM_THREADS=1 PYTHONPATH=src taskset -c 1 .venv/bin/python benchmarks/predict_stages.py \
        [--model default] [--batch 1] [--n 150] [--threads 1]

Runs the stages of `PressureNet._localise_and_fit` one after the other on random pressure images
(a third of the cells loaded, up to 60 mmHg): input channels, encoder-decoder (`mod1`), parameter
head, posture agreement (when the model's config asks for it), height blend (`stature_weight`),
IK, and the mesh (`estimate` with the mesh, no PMR maps, as `predict` runs it); then the whole
forward on other images, which should match the stages' sum. The flip test is not broken down
(`benchmarks/net.py --flip-test` times it whole). At batch 1 the time is mostly per-operation
overhead on small tensors, so each stage's share, not the convolutions' FLOPs, says where to work
(docs/benchmarks.md, sessions 55 and 57).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from pressurepose.net.ik import IKConfig, fit_to_joints
from pressurepose.net.model import NetInputs
from pressurepose.net.stature import stature_from_joints
from pressurepose.train.checkpoint import load_network

STAGES = ("channels", "encoder-decoder", "head", "posture agreement", "height blend", "IK", "mesh")


def _images(batch: int, seed: int) -> NetInputs:
    g = torch.Generator().manual_seed(seed)
    load = torch.rand(batch, 64, 27, generator=g) * 60
    return NetInputs(load * (torch.rand(batch, 64, 27, generator=g) > 0.6))


def _stages(net, inputs: NetInputs) -> list[float]:
    """The seconds of each of STAGES for one batch (0 for a stage the config skips)."""
    cfg, clock = net.config, [time.perf_counter()]
    x = net.channels(inputs, False, None)
    clock.append(time.perf_counter())
    raw, loc = net.mod1(x)
    clock.append(time.perf_counter())
    params = net.head(raw, None)
    clock.append(time.perf_counter())
    if cfg.posture_consistent:
        raw, loc, params = net._agree_with_readout(raw, loc, params, None)
    clock.append(time.perf_counter())
    if cfg.stature_weight > 0:
        shape = stature_from_joints(net.body, params.shape, loc.joints, cfg.stature_weight, head=cfg.stature_head)
        params = params.replace(shape=shape)
    clock.append(time.perf_counter())
    if cfg.ik_steps > 0:
        ik = IKConfig(steps=cfg.ik_steps)
        params = fit_to_joints(net.body, params, loc.joints, ik.weights(loc.spread_m2), ik)
    clock.append(time.perf_counter())
    net.estimate(raw, None, True, False, params=params, localisation=loc)
    clock.append(time.perf_counter())
    return [b - a for a, b in zip(clock[:-1], clock[1:])]


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
    times: list[list[float]] = []
    whole: list[float] = []
    warm = 20
    with torch.inference_mode():
        for i in range(warm + args.n):
            stages = _stages(net, _images(args.batch, i))
            start = time.perf_counter()
            net(_images(args.batch, 10_000 + i), mesh=True, maps=False)
            if i >= warm:
                times.append(stages)
                whole.append(time.perf_counter() - start)
    medians = [statistics.median(column) * 1e3 for column in zip(*times)]
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), batch {args.batch}, median of {args.n}")
    print("| stage | ms |\n| --- | --- |")
    for name, ms in zip(STAGES, medians):
        print(f"| {name} | {ms:.2f} |")
    print(f"| sum of the stages | {sum(medians):.2f} |")
    print(f"| whole forward (mesh, no maps) | {statistics.median(whole) * 1e3:.2f} |")


if __name__ == "__main__":
    main()
