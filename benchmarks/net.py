"""PressureNet speed: training images/s (Mod1, Mod2; paper, fast and heatmap archs), inference latency
at batch 1 and throughput at batch 128 (CNN + body model + mesh, what `predict` runs).

    .venv/bin/python benchmarks/net.py [--archs fast paper] [--batch 128] [--steps 3] [--device cpu]
                                       [--threads N] [--flip-test] [--shift-test] [--stature-weight W] [--antialias]
                                       [--width N] [--bf16]

Training steps use the real loop's loss (`train.loop.step_loss`) on random pressure images and
targets of the right shapes (speed does not depend on the values); Mod2 steps include Mod1's
frozen pass, both meshes, PMR and the PMR losses. Median over `--steps` timed steps after one
warm-up step. `--bf16` adds a heatmap training row under training's --bf16 (the encoder-decoder
under bfloat16 autocast), timed in alternation with the float32 row.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from pressurepose.net import NetConfig, NetInputs, PressureNet
from pressurepose.net.losses import Targets
from pressurepose.train.config import TrainConfig
from pressurepose.train.loop import step_loss
from pressurepose.train.precision import train_in_bf16


def _batch(B: int, device, seed: int = 0) -> tuple[NetInputs, Targets]:
    g = torch.Generator().manual_seed(seed)
    p = torch.rand(B, 64, 27, generator=g) * 60 * (torch.rand(B, 64, 27, generator=g) > 0.6)
    inputs = NetInputs(p.to(device), gender=(torch.rand(B, generator=g) > 0.5).float().to(device))
    joints = torch.rand(B, 24, 3, generator=g) * torch.tensor([1.8, 0.7, 0.2])
    shape = torch.rand(B, 6, generator=g) * 0.5 + 0.25
    depth = torch.randn(B, 64, 27, generator=g) * 30
    return inputs, Targets(joints.to(device), shape.to(device), depth.to(device), (depth < 0).float().to(device))


def _sync(device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def _median_time(fn, steps: int, device) -> tuple[float, float]:
    """(median wall seconds, median CPU seconds of this process) per call."""
    fn()
    _sync(device)
    wall, cpu = [], []
    for _ in range(steps):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        _sync(device)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def train_step(body, arch: str, module: int, B: int, device, width: int = 1, bf16: bool = False):
    """One training step of the network (a closure), as `train.loop` runs it."""
    net = PressureNet(NetConfig(arch=arch, modules=module, width=width), body=body).to(device)
    if module == 2:
        net.freeze_mod1()
    if bf16:
        train_in_bf16(net, device)
    net.train()
    opt = torch.optim.Adam([p for p in net.parameters() if p.requires_grad], lr=1e-5)
    cfg = TrainConfig(preset="fast", module=module, mod1="x" if module == 2 else None).resolved()
    inputs, targets = _batch(B, device)

    def step():
        loss, _, _ = step_loss(net, inputs, targets, cfg, True, None)
        opt.zero_grad()
        loss.backward()
        opt.step()

    return step


def train_speeds(steps_by_label: dict, B: int, steps: int, device, rounds: int = 2) -> dict:
    """{label: (images/s wall, images/s per CPU-s)}: each step timed in `rounds` alternating
    rounds (a machine's drift falls on all alike), the median of all timed steps."""
    wall: dict = {k: [] for k in steps_by_label}
    cpu: dict = {k: [] for k in steps_by_label}
    for _ in range(rounds):
        for label, step in steps_by_label.items():
            w, c = _median_time(step, steps, device)
            wall[label].append(w)
            cpu[label].append(c)
    return {k: (B / statistics.median(wall[k]), B / statistics.median(cpu[k])) for k in steps_by_label}


def predict_speed(
    body,
    arch: str,
    module: int,
    B: int,
    steps: int,
    device,
    **options,
) -> tuple[float, float]:
    """Seconds per batch of B: network + body model + mesh (+ PMR for Mod2's input); options are
    NetConfig fields (width, flip_test, shift_test, stature_weight, antialias)."""
    config = NetConfig(arch=arch, modules=module, **options)
    net = PressureNet(config, body=body).to(device).eval()
    # A new batch each call, as in `predict`: nothing computed for one batch's bodies (the
    # body model keeps the last shapes' skeleton pass) may be reused by the next.
    batches = [_batch(B, device, seed)[0] for seed in range(4)]
    calls = iter(range(10**9))

    def run():
        with torch.inference_mode():
            net(batches[next(calls) % len(batches)], mesh=True, maps=False)

    return _median_time(run, steps, device)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--archs", nargs="+", default=["fast", "paper"])
    parser.add_argument("--batch", type=int, default=128)
    parser.add_argument("--steps", type=int, default=3)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument("--flip-test", action="store_true", help="heatmap: also predict with the flip test")
    parser.add_argument("--shift-test", action="store_true", help="heatmap: also predict with the shift test")
    parser.add_argument(
        "--stature-weight", type=float, default=0.0, help="heatmap: also predict with this stature_weight (net.stature)"
    )
    parser.add_argument(
        "--antialias", action="store_true", help="heatmap: also predict with anti-aliased subsampling (NetConfig)"
    )
    parser.add_argument("--width", type=int, default=1, help="channel multiplier of every network (NetConfig)")
    parser.add_argument("--bf16", action="store_true", help="heatmap: also train under --bf16 (bfloat16 trunk)")
    args = parser.parse_args()
    if args.threads:
        # On a machine shared with other jobs, OpenMP threads that wait for a descheduled
        # sibling at every barrier can make 2 threads 10-100x slower than 1.
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    from pressurepose.body import load_body_model

    body = load_body_model("anny", device=device)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device {device}, batch {args.batch}")
    # Wall time suffers from other jobs on a shared machine; CPU time (process time, all
    # threads) says what the work costs: with 1 thread, CPU-time rates are one dedicated core's.
    print(
        "| arch | module | training img/s (wall / per CPU-s) | predict batch 1 ms (wall / CPU) "
        "| predict batch 128 img/s (wall / per CPU-s) |"
    )
    print("| --- | --- | --- | --- | --- |")
    for arch in args.archs:
        for module in (1,) if arch == "heatmap" else (1, 2):  # heatmap: one module
            steps = {"": train_step(body, arch, module, args.batch, device, args.width)}
            if args.bf16 and arch == "heatmap":
                steps[", bf16"] = train_step(body, arch, module, args.batch, device, args.width, bf16=True)
            speeds = train_speeds(steps, args.batch, args.steps, device)
            ips_w, ips_c = speeds[""]
            lat_w, lat_c = predict_speed(body, arch, module, 1, max(10, args.steps), device, width=args.width)
            thr_w, thr_c = predict_speed(body, arch, module, 128, args.steps, device, width=args.width)
            print(
                f"| {arch} | {module} | {ips_w:.1f} / {ips_c:.1f} | {1000 * lat_w:.1f} / {1000 * lat_c:.1f} "
                f"| {128 / thr_w:.1f} / {128 / thr_c:.1f} |",
                flush=True,
            )
            if ", bf16" in speeds:
                ips_w, ips_c = speeds[", bf16"]
                print(f"| {arch}, bf16 (training only) | {module} | {ips_w:.1f} / {ips_c:.1f} | - | - |", flush=True)
            # heatmap inference options, each a row of its own
            options = [("flip test", {"flip_test": True})] if args.flip_test else []
            if args.stature_weight > 0:
                options.append((f"stature weight {args.stature_weight}", {"stature_weight": args.stature_weight}))
                if args.flip_test:  # the shipped model read with the flip test
                    both = {"flip_test": True, "stature_weight": args.stature_weight}
                    options.append((f"flip test, stature weight {args.stature_weight}", both))
                if args.shift_test:  # the shipped model read with the shift test
                    both = {"shift_test": True, "stature_weight": args.stature_weight}
                    options.append((f"shift test, stature weight {args.stature_weight}", both))
                if args.shift_test and args.flip_test:  # and with both tests
                    both = {"flip_test": True, "shift_test": True, "stature_weight": args.stature_weight}
                    options.append((f"flip and shift tests, stature weight {args.stature_weight}", both))
            elif args.shift_test:
                options.append(("shift test", {"shift_test": True}))
            if args.antialias:  # with --stature-weight's blend when one is given (0 otherwise)
                options.append(
                    (
                        "antialias" + (f", stature weight {args.stature_weight}" if args.stature_weight else ""),
                        {"antialias": True, "stature_weight": args.stature_weight},
                    )
                )
            for label, option in options if arch == "heatmap" else []:
                lat_w, lat_c = predict_speed(
                    body, arch, module, 1, max(10, args.steps), device, width=args.width, **option
                )
                thr_w, thr_c = predict_speed(body, arch, module, 128, args.steps, device, width=args.width, **option)
                print(
                    f"| {arch}, {label} | {module} | - | {1000 * lat_w:.1f} / {1000 * lat_c:.1f} "
                    f"| {128 / thr_w:.1f} / {128 / thr_c:.1f} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
