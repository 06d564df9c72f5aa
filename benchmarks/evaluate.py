"""3DVPE speed: the exact k-d tree nearest-neighbour search (eval.nearest) against the brute force.

    .venv/bin/python benchmarks/evaluate.py                          # posed Anny bodies
    .venv/bin/python benchmarks/evaluate.py --data data/gen20k      # the packaged network's
                                                                     # estimates on a test split

Prints per pair of meshes (camera-facing vertices, two-way) the milliseconds of the brute
force and of the k-d tree search (trees built included), the largest difference between them
(to the float32 brute force, itself only round-off exact, and to a float64 one); then 3DVPE per sample as `pressurepose evaluate` computes it
(three comparisons: the estimate, the mean body, another mesh), batched. Without --data the
"estimates" are the true bodies with noisy poses and pelvis positions and the other mesh
another random body; with --data the other mesh is a training sample's body. Float32, torch's
thread count (pin with taskset for one core). The numbers in docs/benchmarks.md come from it.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from pressurepose.body.params import BodyParams
from pressurepose.eval import metrics as M
from pressurepose.eval import nearest as N


def timed(fn, repeats: int) -> tuple[float, object]:
    out = fn()  # warm-up
    samples = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t)
    return statistics.median(samples) * 1e3, out


def posed(body, n: int, seed: int) -> BodyParams:
    g = torch.Generator().manual_seed(seed)
    return BodyParams.zeros(n, body.default_shape(n)).replace(
        pose=0.3 * torch.randn(n, 23, 3, generator=g),
        root_translation=torch.tensor([1.0, 0.45, 0.15]) + 0.02 * torch.randn(n, 3, generator=g),
    )


def meshes(args) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(true, estimated, mean body (1, V, 3), third, faces)."""
    if args.data is None:
        from pressurepose.body import load_body_model

        body = load_body_model("anny")
        true = posed(body, args.n, 0)
        g = torch.Generator().manual_seed(1)
        est = true.replace(
            pose=true.pose + 0.15 * torch.randn(true.pose.shape, generator=g),
            root_translation=true.root_translation + 0.03 * torch.randn(args.n, 3, generator=g),
        )
        with torch.no_grad():
            return (
                body(true).vertices,
                body(est).vertices,
                body(BodyParams.zeros(1, body.default_shape(1))).vertices + torch.tensor([1.0, 0.45, 0.1]),
                body(posed(body, args.n, 2)).vertices,
                body.faces,
            )
    from pressurepose.eval import evaluation as R
    from pressurepose.net.model import NetInputs
    from pressurepose.train.checkpoint import load_network

    net, _ = load_network(Path("default"))
    body = net.body
    _, b = next(R._batches(R.open_split(args.data, "test"), args.n, args.n))
    mean, _, bodies = R._baseline_data(R.open_split(args.data, "train"), 512, torch.float32)
    with torch.no_grad():
        est = net(
            NetInputs(
                pressure_mmhg=b["pressure_mmhg"], gender=b["gender"], height_m=b["height_m"], mass_kg=b["mass_kg"]
            ),
            mesh=False,
        )[-1].params
        return (
            body(R._as_params(b, torch.float32)).vertices,
            body(est).vertices,
            body(mean).vertices,
            body(bodies.index(torch.arange(args.n))).vertices,
            body.faces,
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="a generated dataset (test and train splits)")
    parser.add_argument("--n", type=int, default=16, help="samples")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    true, est, mean, third, faces = meshes(args)
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, {args.n} samples, "
        f"{'test split of ' + str(args.data) if args.data else 'posed Anny bodies'}"
    )
    print(
        "| meshes | facing vertices (mean) | brute force (ms) | k-d trees (ms) | speed-up | max diff to brute force, "
        "float32 / float64 (m) |"
    )
    print("| --- | --- | --- | --- | --- | --- |")
    mask_t, _ = M.camera_facing(true, faces)
    for name, other in (
        ("estimate vs truth", est),
        ("mean body vs truth", mean.expand(args.n, -1, -1)),
        ("other body vs truth", third),
    ):
        mask_o, _ = M.camera_facing(other, faces)
        sets = [(other[k][mask_o[k]], true[k][mask_t[k]]) for k in range(args.n)]
        brute_ms, brute = timed(lambda: [(N.nearest_brute(a, b), N.nearest_brute(b, a)) for a, b in sets], 1)
        tree_ms, fast = timed(
            lambda: [N.nearest_pairs(N.PointSets([a]), N.PointSets([b]), [(0, 0)])[0] for a, b in sets],
            args.repeats,
        )
        diff = max(float((x - y).abs().max()) for p, q in zip(brute, fast) for x, y in zip(p, q))
        # The float32 brute force is itself only round-off exact (|p|^2 - 2 q.p); in float64 both agree.
        diff64 = max(
            max(
                float((N.nearest_brute(a.double(), b.double()) - x.double()).abs().max()),
                float((N.nearest_brute(b.double(), a.double()) - y.double()).abs().max()),
            )
            for (a, b), (x, y) in zip(sets, fast)
        )
        facing = statistics.mean((a.shape[0] + b.shape[0]) / 2 for a, b in sets)
        print(
            f"| {name} | {facing:.0f} | {brute_ms / args.n:.1f} | {tree_ms / args.n:.1f} | "
            f"{brute_ms / tree_ms:.1f}x | {diff:.1e} / {diff64:.1e} |"
        )

    def evaluate_like():
        true_f = M.facing_meshes(true, faces)
        mean_f = M.facing_meshes(mean, faces)  # evaluate packs it once per run; here once per batch
        return [
            M.vpe_between(M.facing_meshes(est, faces), true_f),
            M.vpe_between(mean_f, true_f),
            M.vpe_between(M.facing_meshes(third, faces), true_f),
        ]

    ms, _ = timed(evaluate_like, args.repeats)
    print(
        f"\nthree 3DVPE per sample, batched as in evaluate (facing vertices and packing included): "
        f"{ms / args.n:.1f} ms per sample"
    )


if __name__ == "__main__":
    main()
