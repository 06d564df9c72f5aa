"""What in a real frame turns a network (issue 22): PmatData frames altered and read again.

    PYTHONPATH=src .venv/bin/python benchmarks/real_probe.py --model RUN [--groups BCD] [--bands] [--sim DATASET]
        [--placement]

Each variant alters every frame of the chosen groups the same way - the first k loaded rows
(head end) zeroed or narrowed to a head's width, a share of the loaded rows zeroed at either end, the pressure made uniform on
the loaded taxels, the peaks clipped, the foot end's rows scaled - and the network reads them again. Prints per variant the
posture accuracy, the median signed height error (cm), how many supine frames read prone, and
per PmatData group "correct / read prone". With --sim DATASET (a generated dataset folder), the
same cuts on its test split's supine images (moved up until their first k loaded rows leave the
mat; the foot end cut): whether the network reads its own images the way it reads the real ones.
The measures of docs/network.md "Real frames span the mat" (session 33); "default" is the packaged
model. With --placement, every frame moved k rows along the bed and read again (the real frames
and, with --sim, the simulated test images; docs/network.md "Where a real body lies changes its
reading", session 53): how much of a reading is the body and how much where it lies.
"""

from __future__ import annotations

import argparse
import collections
from pathlib import Path

import numpy as np
import torch

from pressurepose.body.joints import TRUNK_JOINTS
from pressurepose.data.pmatdata import distinct_frames, load_images, load_index
from pressurepose.eval.real import GROUP_POSTURE, posture_of, read_bodies, roll_deg
from pressurepose.samples import PMATDATA, resolve_pmatdata
from pressurepose.train.checkpoint import load_network


def loaded_rows(image: torch.Tensor) -> tuple[int, int]:
    """First and one-past-last loaded row of a (64, 27) image."""
    rows = (image.sum(-1) > 0).nonzero()[:, 0]
    return int(rows.min()), int(rows.max()) + 1


def zero_head_rows(k: int):
    def f(x):
        x = x.clone()
        for i in range(len(x)):
            a, _ = loaded_rows(x[i])
            x[i, a : a + k] = 0
        return x

    return f


def zero_share(lo: float, hi: float):
    """Zero the loaded rows between shares lo and hi of the loaded extent (0 = head end)."""

    return scale_share(lo, hi, 0.0)


def power(gamma: float):
    """Each reading raised to `gamma`, each image scaled back to its force (a sensor whose
    readings grow as the pressure^(1 / gamma))."""

    def f(x):
        y = x.clamp(min=0) ** gamma
        return y * x.sum((1, 2), keepdim=True) / y.sum((1, 2), keepdim=True).clamp(min=1e-12)

    return f


def scale_share(lo: float, hi: float, gain: float):
    """Scale the loaded rows between shares lo and hi of the loaded extent (0 = head end)."""

    def f(x):
        x = x.clone()
        for i in range(len(x)):
            a, b = loaded_rows(x[i])
            n = b - a
            x[i, a + int(lo * n) : a + int(hi * n)] *= gain
        return x

    return f


def narrow_head_rows(k: int, width: int):
    """Keep, in the first k loaded rows, only the `width` columns about their force centroid
    (a head's width instead of a pillow's)."""

    def f(x):
        x = x.clone()
        cols = torch.arange(x.shape[-1], dtype=x.dtype)
        for i in range(len(x)):
            a, _ = loaded_rows(x[i])
            band = x[i, a : a + k]
            centre = float((band.sum(0) * cols).sum() / band.sum().clamp(min=1e-9))
            x[i, a : a + k] = band * ((cols - centre).abs() <= width / 2)
        return x

    return f


def move_up(k: int):
    """Move each image up until its first k loaded rows leave the mat (the rest kept)."""

    def f(x):
        out = torch.zeros_like(x)
        for i in range(len(x)):
            s = loaded_rows(x[i])[0] + k
            out[i, : x.shape[1] - s] = x[i, s:]
        return out

    return f


REAL_VARIANTS = {
    "as recorded": lambda x: x,
    **{f"first {k} loaded rows zeroed": zero_head_rows(k) for k in (2, 4, 6, 8)},
    **{f"first 6 rows narrowed to {w} columns": narrow_head_rows(6, w) for w in (4, 6, 10)},
    "first 15% of the rows zeroed": zero_share(0.0, 0.15),
    "last 20% (calves, heels) zeroed": zero_share(0.8, 1.0),
    "uniform on the loaded taxels": lambda x: torch.where(
        x > 0, x.sum((1, 2), keepdim=True) / (x > 0).sum((1, 2), keepdim=True), 0
    ),
    **{f"clipped at {c} mmHg": (lambda c: lambda x: x.clamp(max=c))(c) for c in (30, 40, 60)},
    **{f"pressure^{g}, force kept": (lambda g: power(g))(g) for g in (0.7, 1.5, 2.0)},
    **{f"last 10% x {g}": (lambda g: scale_share(0.9, 1.0, g))(g) for g in (0.25, 0.5, 2.0)},
    **{f"last 20% x {g}": (lambda g: scale_share(0.8, 1.0, g))(g) for g in (0.5, 2.0)},
}
SIM_VARIANTS = {
    "as generated": lambda x: x,
    **{f"moved up, first {k} rows off the mat": move_up(k) for k in (2, 4, 6)},
    "last 10% zeroed": zero_share(0.9, 1.0),
    "last 20% zeroed": zero_share(0.8, 1.0),
}


def real_frames(root: Path, groups: str) -> tuple[list, torch.Tensor]:
    """PmatData's distinct frames of the chosen groups: their records and (N, 64, 27) images."""
    records = distinct_frames([r for r in load_index(root) if r.group in groups])
    return records, torch.from_numpy(load_images(records))


def sim_test_batch(folder: Path, n: int | None = None) -> dict[str, torch.Tensor]:
    """The first n (all: None) samples of a generated dataset's test split, stacked by column."""
    from pressurepose.train.data import KEYS, open_dataset, standardise

    ds = open_dataset(folder, "test")
    items = [standardise(ds[i]) for i in range(len(ds) if n is None else min(n, len(ds)))]
    return {k: torch.stack([it[k] for it in items]) for k in KEYS}


def probe_real(net, root: Path, groups: str) -> None:
    records, images = real_frames(root, groups)
    heights = torch.tensor([r.height_cm / 100 for r in records])
    truth = [GROUP_POSTURE[r.group] for r in records]
    print(f"PmatData groups {groups}: {len(records)} frames")
    for name, alter in REAL_VARIANTS.items():
        read = read_bodies(net, alter(images))
        got = read.postures
        acc = np.mean([g == t for g, t in zip(got, truth)])
        prone = sum(g == "prone" and t == "supine" for g, t in zip(got, truth))
        per = collections.defaultdict(lambda: [0, 0])
        for r, g, t in zip(records, got, truth):
            per[f"{r.group}{r.index}"][0] += g == t
            per[f"{r.group}{r.index}"][1] += g == "prone"
        groups_txt = " ".join(
            f"{k}:{v[0]}/{v[1]}" for k, v in sorted(per.items(), key=lambda kv: (kv[0][0], int(kv[0][1:])))
        )
        height = float((read.height_m - heights).median()) * 100
        sure = _trunk_spread(read)
        print(
            f"  {name:34s} accuracy {acc:.3f}  height {height:+5.1f} cm  supine read prone {prone:3d}{sure} | {groups_txt}"
        )


def _trunk_spread(read) -> str:
    """For a heatmap network: the median heatmap spread of the head and torso joints, and the share
    of them under 10 cm (docs/network.md "How far to trust a joint")."""
    if read.spread_m is None:
        return ""
    s = read.spread_m[:, list(TRUNK_JOINTS)] * 100
    return f"  trunk spread {float(s.median()):4.1f} cm ({float((s < 10).double().mean()) * 100:3.0f}% < 10)"


def probe_bands(net, root: Path, groups: str, rows: int = 4) -> None:
    """Zero one band of `rows` rows at each 5% of every frame's loaded extent and read again:
    how many reads the band turns right (fixed) and wrong (broke) - where a network's answer on
    real frames comes from (docs/network.md "Flip test, IK settings and occlusion")."""
    records, images = real_frames(root, groups)
    truth = [GROUP_POSTURE[r.group] for r in records]
    ok = np.array([g == t for g, t in zip(read_bodies(net, images).postures, truth)])
    extent = [loaded_rows(x) for x in images]
    print(f"PmatData groups {groups}: {len(records)} frames, accuracy {ok.mean():.3f}; a {rows}-row band zeroed at")
    for share in np.arange(0.0, 1.0, 0.05):
        cut = images.clone()
        for i, (a, b) in enumerate(extent):
            start = a + int(share * (b - a))
            cut[i, start : start + rows] = 0
        got = np.array([g == t for g, t in zip(read_bodies(net, cut).postures, truth)])
        print(
            f"  {share:4.2f} of the extent: accuracy {got.mean():.3f}  fixed {int((~ok & got).sum()):3d}  broke {int((ok & ~got).sum()):3d}"
        )


def probe_sim(net, folder: Path) -> None:
    batch = sim_test_batch(folder)
    supine = torch.tensor([p == "supine" for p in posture_of(roll_deg(batch["root_rotation"].double()))])
    images, heights = batch["pressure_mmhg"].float()[supine], batch["height_m"][supine]
    print(f"{folder} test split: {len(images)} supine images")
    for name, alter in SIM_VARIANTS.items():
        read = read_bodies(net, alter(images))
        count = collections.Counter(read.postures)
        height = float((read.height_m - heights).median()) * 100
        print(f"  {name:34s} read {dict(count)}  height {height:+5.1f} cm{_trunk_spread(read)}")


def moved(images: torch.Tensor, k: int) -> torch.Tensor:
    """Every (N, rows, cols) image moved k rows toward the foot (k < 0: toward the head); rows
    leaving the grid are lost, those entering read 0 - the same body lying elsewhere on the mat."""
    out = torch.zeros_like(images)
    if k >= 0:
        out[:, k:] = images[:, : images.shape[1] - k]
    else:
        out[:, :k] = images[:, -k:]
    return out


PLACEMENT_ROWS = (-6, -4, -2, 2, 4, 6)


def probe_placement(net, images: torch.Tensor, heights: torch.Tensor, truth: list[str] | None, label: str) -> None:
    """Read the images as given and moved by each of PLACEMENT_ROWS rows: per move, the median
    signed height error, the median and median absolute change of the height read against as given,
    and (with `truth`) the posture accuracy and how many reads the move turned."""
    base = read_bodies(net, images)
    print(f"{label}: {len(images)} images moved along the bed and read again")
    for k in (0, *PLACEMENT_ROWS):
        read = base if k == 0 else read_bodies(net, moved(images, k))
        change = (read.height_m - base.height_m).double() * 100
        line = (
            f"  {k:+d} rows: height error {float((read.height_m - heights).median()) * 100:+5.1f} cm, "
            f"change {float(change.median()):+5.1f} (|change| median {float(change.abs().median()):4.1f}) cm"
        )
        if truth is not None:
            ok = np.array([g == t for g, t in zip(read.postures, truth)])
            turned = sum(a != b for a, b in zip(read.postures, base.postures))
            line += f", posture {ok.mean():.3f}, reads turned {turned}"
        print(line)


def real_placement(net, root: Path, groups: str) -> None:
    records, images = real_frames(root, groups)
    heights = torch.tensor([r.height_cm / 100 for r in records])
    for mattress in ("air", "sponge"):
        sel = [i for i, r in enumerate(records) if r.mattress == mattress]
        truth = [GROUP_POSTURE[records[i].group] for i in sel]
        probe_placement(net, images[sel], heights[sel], truth, f"PmatData groups {groups}, {mattress}")


def sim_placement(net, folder: Path, n: int = 600) -> None:
    batch = sim_test_batch(folder, n)
    truth = posture_of(roll_deg(batch["root_rotation"].double()))
    probe_placement(net, batch["pressure_mmhg"].float(), batch["height_m"], truth, f"{folder} test split")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="default")
    ap.add_argument("--groups", default="BCD", help="PmatData groups (B supine, C right, D left)")
    ap.add_argument("--pmatdata", default=PMATDATA, help="PmatData folder (default: the packaged copy)")
    ap.add_argument("--bands", action="store_true", help="also the sliding-band probe (probe_bands)")
    ap.add_argument("--sim", default=None, help="a generated dataset folder: the same cuts on its supine test images")
    ap.add_argument("--placement", action="store_true", help="only the frames moved along the bed (probe_placement)")
    args = ap.parse_args()
    net, _ = load_network(Path(args.model))
    if args.placement:
        real_placement(net, resolve_pmatdata(args.pmatdata), args.groups)
        if args.sim:
            sim_placement(net, Path(args.sim))
        return
    probe_real(net, resolve_pmatdata(args.pmatdata), args.groups)
    if args.bands:
        probe_bands(net, resolve_pmatdata(args.pmatdata), args.groups)
    if args.sim:
        probe_sim(net, Path(args.sim))


if __name__ == "__main__":
    main()
