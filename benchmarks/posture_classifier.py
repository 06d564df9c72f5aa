"""A small posture classifier of its own, trained on simulated images and read on PmatData
(issue 22; docs/network.md "A posture classifier of its own (session 38)").

    OMP_NUM_THREADS=1 PYTHONPATH=src python benchmarks/posture_classifier.py --data DIR [DIR ...]
        --test DIR --input maskblur [--epochs 12]

Trains a four-block CNN (16-64 channels, global pooling, 50% dropout, one linear layer) on the
training splits of the dataset folders, labels from the true root's roll (`net.posture`), with
the shift and mirror augmentations of `train` (+-12 rows, +-8 columns, half the images mirrored
with left and right postures swapped), AdamW and a one-cycle lr. After every epoch it prints the
accuracy on `--test`'s test split and, as a diagnostic only, on PmatData's flat-bed groups B-D
per mattress with the confusion. Inputs: `raw` (mmHg / 30), `blur2` (a 2-taxel Gaussian of it),
`mask` (loaded taxels), `maskblur` (both of the last two).
"""

from __future__ import annotations

import argparse
import glob
import time

import numpy as np
import pyarrow.parquet as pq
import torch
import torch.nn.functional as F
from torch import nn

from pressurepose.data.pmatdata import distinct_frames, load_images, load_index
from pressurepose.eval.real import GROUP_POSTURE
from pressurepose.net.posture import POSTURES, posture_index, roll_from_root
from pressurepose.samples import PMATDATA, resolve_pmatdata

MIRROR = torch.tensor([0, 2, 1, 3])  # supine, left, right, prone -> mirrored


def load_split(folders: list[str], split: str) -> tuple[torch.Tensor, torch.Tensor]:
    images, roots = [], []
    for folder in folders:
        for f in sorted(glob.glob(f"{folder}/shards/{split}-*.parquet")):
            t = pq.read_table(f, columns=["pressure_mmhg", "root_rotation"]).to_pydict()
            images += t["pressure_mmhg"]
            roots += t["root_rotation"]
    if not images:
        raise SystemExit(f"no {split} shards in {', '.join(folders)} (give generated dataset folders)")
    x = torch.tensor(np.asarray(images, dtype=np.float32).reshape(-1, 1, 64, 27))
    return x, posture_index(roll_from_root(torch.tensor(roots, dtype=torch.float64)))


def gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    n = 3 * int(np.ceil(sigma))
    k = torch.arange(-n, n + 1, dtype=x.dtype)
    g = torch.exp(-(k**2) / (2 * sigma**2))
    g = g / g.sum()
    x = F.conv2d(F.pad(x, (0, 0, n, n)), g.view(1, 1, -1, 1))
    return F.conv2d(F.pad(x, (n, n, 0, 0)), g.view(1, 1, 1, -1))


def prepare(x: torch.Tensor, kind: str) -> torch.Tensor:
    mask = (x > 0).to(x.dtype)
    return {
        "raw": lambda: x / 30.0,
        "blur2": lambda: gaussian_blur(x, 2.0) / 30.0,
        "mask": lambda: mask,
        "maskblur": lambda: torch.cat([mask, gaussian_blur(x, 2.0) / 30.0], 1),
    }[kind]()


def block(i: int, o: int) -> nn.Sequential:
    conv = lambda a, b: [nn.Conv2d(a, b, 3, padding=1), nn.BatchNorm2d(b), nn.ReLU()]  # noqa: E731
    return nn.Sequential(*conv(i, o), *conv(o, o))


def classifier(channels: int) -> nn.Sequential:
    return nn.Sequential(
        block(channels, 16), nn.MaxPool2d(2), block(16, 32), nn.MaxPool2d(2), block(32, 64), nn.MaxPool2d(2),
        block(64, 64), nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.Dropout(0.5), nn.Linear(64, len(POSTURES)),
    )  # fmt: skip


def augment(x: torch.Tensor, y: torch.Tensor, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    flip = torch.from_numpy(rng.random(len(x)) < 0.5)
    x = torch.where(flip[:, None, None, None], x.flip(-1), x)
    y = torch.where(flip, MIRROR[y], y)
    rows, cols = rng.integers(-12, 13, len(x)), rng.integers(-8, 9, len(x))
    return torch.stack([torch.roll(xi, (int(r), int(c)), (-2, -1)) for xi, r, c in zip(x, rows, cols)]), y


@torch.no_grad()
def predict(net: nn.Module, x: torch.Tensor, kind: str) -> torch.Tensor:
    net.eval()
    out = torch.cat([net(prepare(c, kind)).argmax(-1) for c in x.split(512)])
    net.train()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", nargs="+", required=True, help="generated dataset folders (training splits)")
    ap.add_argument("--test", required=True, help="a generated dataset folder (its test split)")
    ap.add_argument("--input", default="maskblur", choices=("raw", "blur2", "mask", "maskblur"))
    ap.add_argument("--epochs", type=int, default=12)
    ap.add_argument("--pmatdata", default=PMATDATA)
    args = ap.parse_args()
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    x_train, y_train = load_split(args.data, "train")
    x_test, y_test = load_split([args.test], "test")
    records = distinct_frames(
        [r for r in load_index(resolve_pmatdata(args.pmatdata)) if r.group in "BCD" and r.bed_incline_deg == 0]
    )
    x_real = torch.from_numpy(load_images(records))[:, None]
    y_real = torch.tensor([POSTURES.index(GROUP_POSTURE[r.group]) for r in records])
    mattress = np.array([r.mattress for r in records])
    net = classifier(2 if args.input == "maskblur" else 1)
    steps = args.epochs * (len(x_train) // 128)
    opt = torch.optim.AdamW(net.parameters(), 2e-3, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, 2e-3, total_steps=steps)
    print(f"input {args.input}: {len(x_train)} training, {len(x_test)} test, {len(x_real)} PmatData frames")
    for epoch in range(args.epochs):
        t0, perm, total = time.time(), torch.randperm(len(x_train)), 0.0
        for b in range(len(x_train) // 128):
            idx = perm[b * 128 : (b + 1) * 128]
            x, y = augment(x_train[idx], y_train[idx], rng)
            loss = F.cross_entropy(net(prepare(x, args.input)), y, label_smoothing=0.1)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item()
        test = (predict(net, x_test, args.input) == y_test).float().mean().item()
        got = predict(net, x_real, args.input)
        real = [(got[mattress == m] == y_real[mattress == m]).float().mean().item() for m in ("air", "sponge")]
        confusion = torch.zeros(len(POSTURES), len(POSTURES), dtype=torch.long)
        confusion.index_put_((y_real, got), torch.ones_like(got), accumulate=True)
        print(
            f"epoch {epoch + 1}: loss {total / (b + 1):.3f}, simulated test {test:.3f} | PmatData air {real[0]:.3f}"
            f" sponge {real[1]:.3f}, confusion (true supine/left/right rows) {confusion[:3].tolist()}"
            f" ({time.time() - t0:.0f} s)",
            flush=True,
        )


if __name__ == "__main__":
    main()
