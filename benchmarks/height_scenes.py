"""A model's height error on PmatData frames against simulated images of the same scenes (issue 22:
the +10 cm PmatData heights). Separates "the network mis-reads bodies like these" (the error on the
simulated twins) from "real images differ from simulated ones" (the difference between the two).

    PYTHONPATH=src .venv/bin/python benchmarks/height_scenes.py --model RUN [--postures supine,left,right]
        [--bmi 21.5] [--floor 0 2.5] [--save DIR]

Scenes as `pressurepose realism` builds them (one Anny body per real frame, fitted to the subject's
height and weight, in the posture's resting pose, lying where the frame's load lay, rested by the
default articulated sim #2 on that set's mattress preset). --bmi refits every subject at that BMI
(same heights): how much the subjects' build moves the error. --floor T zeroes simulated readings
below T mmHg (the real frames' normalisation leaves no taxel below ~3-4 mmHg). Prints, per
posture and mattress: median signed height error and MAE (cm) and posture accuracy, real and
simulated.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np
import torch

from pressurepose.commands.realism import RealismConfig, load_real, real_scenes, simulate_subjects
from pressurepose.eval.real import read_bodies
from pressurepose.train.checkpoint import load_network


def estimate(net, images: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Estimated heights (N,) m and postures of (N, 64, 27) mmHg images."""
    read = read_bodies(net, torch.as_tensor(np.asarray(images), dtype=torch.float32).clamp(max=100.0), batch=64)
    return read.height_m.numpy(), read.postures


def summary(est_h: np.ndarray, true_h: np.ndarray, postures: list[str], posture: str) -> str:
    d = (est_h - true_h) * 100
    acc = np.mean([p == posture for p in postures])
    return f"{np.median(d):+5.1f} / {np.mean(np.abs(d)):4.1f} / {acc:.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default="default")
    ap.add_argument("--postures", default="supine,left,right")
    ap.add_argument("--bmi", type=float, default=None, help="refit every subject at this BMI (same height)")
    ap.add_argument("--floor", type=float, nargs="*", default=[0.0], help="zero simulated readings below (mmHg)")
    ap.add_argument("--save", type=Path, default=None, help="write the simulated images here (.npz per set)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    net, _ = load_network(Path(args.model))
    real, subjects = load_real(Path("pmatdata"), 20.0)
    if args.bmi is not None:
        subjects = [dataclasses.replace(s, mass_kg=args.bmi * s.height_m**2) for s in subjects]
    height = {s.subject: s.height_m for s in subjects}
    postures = args.postures.split(",")
    scenes = {k: v for k, v in real_scenes(real, RealismConfig()).items() if k[0] in postures}
    sims = simulate_subjects(subjects, RealismConfig(), scenes=scenes)
    floors = " | ".join(f"sim, floor {t:g} mmHg" for t in args.floor)
    print(f"model {args.model}, BMI {args.bmi or 'as recorded'}; median signed height error / MAE (cm) / posture")
    print(f"| posture | mattress | frames | real | {floors} |")
    print("| --- | --- | --- | --- |" + " --- |" * len(args.floor))
    for key in sorted(scenes):
        imgs, _, subj = real[key]
        true_h = np.array([height[int(s)] for s in subj])
        h, p = estimate(net, imgs)
        cols = [summary(h, true_h, p, key[0])]
        sim_imgs, sim_h = sims[key][0], sims[key][1]
        if args.save:
            args.save.mkdir(parents=True, exist_ok=True)
            np.savez(args.save / f"sim_{key[0]}_{key[1]}.npz", images=sim_imgs, heights=sim_h)
        for t in args.floor:
            h, p = estimate(net, np.where(sim_imgs < t, 0.0, sim_imgs))
            cols.append(summary(h, sim_h, p, key[0]))
        print(f"| {key[0]} | {key[1]} | {len(imgs)} / {len(sim_imgs)} | " + " | ".join(cols) + " |", flush=True)


if __name__ == "__main__":
    main()
