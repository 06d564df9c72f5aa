"""How well a network reads postures on simulated data: its body's and its readout's.

    PYTHONPATH=src .venv/bin/python benchmarks/posture.py --model RUN --data DIR [--split test] [--n 2000]

For a heatmap network with a posture readout (`train --posture-weight`), on DIR's split:
the posture of the estimated body (from its root, `eval.real`'s reading) and of the readout
against the true body's (from the true root), per true posture, and MPJPE, with and without
`NetConfig.posture_consistent` (the body made to agree with the readout where they differ by
left and right alone). Simulated data only: the choice of that reading is made here, never on
PmatData (docs/network.md).
"""

from __future__ import annotations

import argparse
import dataclasses

import torch

from pressurepose.net.model import NetInputs
from pressurepose.net.posture import POSTURES, posture_index, roll_from_root
from pressurepose.train.checkpoint import load_network
from pressurepose.train.data import collate, open_dataset


def read(net, batch: dict, chunk: int = 256) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(body posture index, readout index, per-sample MPJPE m) over the batch."""
    body, readout, err = [], [], []
    with torch.no_grad():
        for lo in range(0, len(batch["pressure_mmhg"]), chunk):
            sl = slice(lo, lo + chunk)
            inputs = NetInputs(
                batch["pressure_mmhg"][sl],
                gender=batch["gender"][sl],
                height_m=batch["height_m"][sl],
                mass_kg=batch["mass_kg"][sl],
            )
            est = net(inputs, mesh=False)[-1]
            body.append(posture_index(roll_from_root(est.params.root_rotation.double())))
            readout.append(est.localisation.posture_logits.argmax(-1))
            err.append((est.joints - batch["joints"][sl]).norm(dim=-1).mean(-1))
    return torch.cat(body), torch.cat(readout), torch.cat(err)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--split", default="test")
    parser.add_argument("--n", type=int, default=2000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    net, _ = load_network(args.model)
    if not net.config.posture_head:
        parser.error(f"{args.model} has no posture readout (train it with --posture-weight or --posture-only)")
    dataset = open_dataset(args.data, split=args.split)
    idx = torch.linspace(0, len(dataset) - 1, min(args.n, len(dataset))).round().long().unique().tolist()
    batch = collate([dataset[i] for i in idx])
    true = posture_index(roll_from_root(batch["root_rotation"].double()))
    counts = torch.bincount(true, minlength=len(POSTURES)).tolist()
    print(f"{len(idx)} samples of {args.data} ({args.split}); true postures {dict(zip(POSTURES, counts))}")
    print("| reading | body posture | readout | " + " | ".join(f"body on {p}" for p in POSTURES) + " | MPJPE (mm) |")
    print("| --- | --- | --- |" + " --- |" * len(POSTURES) + " --- |")
    for consistent in (False, True):
        net.config = dataclasses.replace(net.config, posture_consistent=consistent)
        body, readout, err = read(net, batch)
        per = [
            float((body[true == k] == k).float().mean()) if (true == k).any() else float("nan")
            for k in range(len(POSTURES))
        ]
        print(
            f"| {'posture_consistent' if consistent else 'as trained'} | {float((body == true).float().mean()):.3f} | "
            f"{float((readout == true).float().mean()):.3f} | "
            + " | ".join(f"{v:.3f}" for v in per)
            + f" | {1000 * float(err.mean()):.1f} |"
        )


if __name__ == "__main__":
    main()
