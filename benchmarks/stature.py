"""The height from the localised skeleton (net.stature; docs/network.md "Height from the
localised skeleton"): measure the share on simulated data, and optionally write a copy of the
model that uses it.

    PYTHONPATH=src .venv/bin/python benchmarks/stature.py --model default --data DIR [--split test]
        [--no-head | --edge] [--write OUT]

Reads the split's images with the model's regression head and localised joints; prints the sd of
the head's height error and of the height implied by the joints' bone chain
(`stature_from_joints` with weight 1), their correlation, the MSE-optimal share
(`optimal_weight`), and MPJPE and the height error with the body moved by that share (before the
IK, as inference does). `--write OUT` saves the model with `stature_weight` set to that share in
its config record (weights unchanged). `--no-head`: the chain from the neck down
(`NetConfig.stature_head` False). `--edge` (a diagnostic): the same on the images moved toward the
head end until the load's first row lies 0-4 rows beyond the mat's edge, as PmatData's loads reach
it - whether a head end cut by the edge misleads the regression head's height (session 45: it
does not; docs/network.md "Height from the localised skeleton").
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import torch

from pressurepose.eval.evaluation import _batches, open_split
from pressurepose.eval.realism import EXTENT_SHARE
from pressurepose.net.model import NetInputs
from pressurepose.net.stature import optimal_weight, stature_from_joints
from pressurepose.train.checkpoint import load_network, read_model, save_model


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="default")
    ap.add_argument("--data", type=Path, required=True, help="a generated dataset the model was not trained on")
    ap.add_argument("--split", default="test")
    ap.add_argument("--write", type=Path, default=None, help="save the model with the measured share here")
    ap.add_argument(
        "--no-head", action="store_true", help="the chain from the neck down (NetConfig.stature_head False)"
    )
    ap.add_argument(
        "--edge",
        action="store_true",
        help="measure on images whose load reaches the mat's head edge: each image moved toward the head end "
        "until its load's first row lies 0-4 rows beyond the edge; the chain from the neck down (no --write)",
    )
    args = ap.parse_args()
    if args.edge and args.write is not None:
        raise SystemExit("--edge measures only: the share for whole images comes without it (drop --write)")
    net, record = load_network(Path(args.model))
    if net.config.arch != "heatmap" or net.config.backend != "anny":
        raise SystemExit(f"{args.model}: the height from the skeleton needs an arch heatmap network on Anny")
    head = not (args.no_head or args.edge)
    net.config = dataclasses.replace(net.config, stature_weight=0.0, stature_head=head)
    heights = {"head": [], "joints": [], "true": []}
    batches = []
    with torch.no_grad():
        for _, b in _batches(open_split(args.data, args.split), 64, None):
            if args.edge:
                b = dict(b, pressure_mmhg=to_head_edge(b["pressure_mmhg"]))
            x = net.channels(NetInputs(pressure_mmhg=b["pressure_mmhg"].float()))
            raw, loc = net.mod1(x)
            shape = net.head(raw, None).shape
            heights["head"].append(net.body.measure(shape).height_m)
            heights["joints"].append(
                net.body.measure(stature_from_joints(net.body, shape, loc.joints, 1.0, head=head)).height_m
            )
            heights["true"].append(net.body.measure(b["shape"].to(shape)).height_m)
            batches.append(b)
    h = {k: torch.cat(v).double() for k, v in heights.items()}
    err_head, err_joints = h["head"] - h["true"], h["joints"] - h["true"]
    corr = torch.corrcoef(torch.stack([err_head, err_joints]))[0, 1]
    w = optimal_weight(err_head, err_joints)
    print(
        f"{args.data} ({args.split}, {len(err_head)} samples): height error sd head {err_head.std() * 100:.2f} cm, "
        f"joints {err_joints.std() * 100:.2f} cm, correlation {corr:.2f}; optimal share {w:.3f}"
    )
    for share in (0.0, w):
        net.config = dataclasses.replace(net.config, stature_weight=round(share, 3))
        err, est_h = [], []
        with torch.no_grad():
            for b in batches:
                est = net(NetInputs(pressure_mmhg=b["pressure_mmhg"].float()), mesh=False, maps=False)[-1]
                err.append((est.joints - b["joints"].to(est.joints)).norm(dim=-1).mean(-1))
                est_h.append(net.body.measure(est.params.shape).height_m)
        e, he = torch.cat(err), torch.cat(est_h).double() - h["true"]
        mpjpe = "n/a (the labels are not moved with the images)" if args.edge else f"{e.mean() * 1000:.1f} mm"
        print(
            f"  share {share:.3f}: MPJPE {mpjpe}, height error median {he.median() * 100:+.1f} cm, "
            f"mean absolute {he.abs().mean() * 100:.2f} cm"
        )
    if args.write is not None:
        weights, rec = read_model(Path(args.model))
        rec = dict(rec, net=dict(rec["net"], stature_weight=round(w, 3), stature_head=head))
        net.config = dataclasses.replace(net.config, stature_weight=round(w, 3))
        save_model(args.write, net, rec, state=weights)
        print(f"  wrote {args.write} (stature_weight {round(w, 3)}, stature_head {head})")


def to_head_edge(pressure: torch.Tensor) -> torch.Tensor:
    """(B, rows, cols) images moved toward the head end (row 0) until the load's first row (>=
    EXTENT_SHARE of the force, as the realism report counts the load's length) lies k rows beyond
    the mat's edge, k = 0..4 in turn over the batch; what leaves the mat is lost."""
    out = torch.zeros_like(pressure)
    rows = pressure.sum(-1)
    for i in range(len(pressure)):
        first = int((rows[i] >= EXTENT_SHARE * rows[i].sum()).nonzero()[0, 0]) if rows[i].sum() > 0 else 0
        s = min(first + i % 5, pressure.shape[1])
        out[i, : pressure.shape[1] - s] = pressure[i, s:]
    return out


if __name__ == "__main__":
    main()
