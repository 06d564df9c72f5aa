"""Where the Anny joints-only forward time goes (B = 128, float32, no grad).

    .venv/bin/python benchmarks/anny_joints_breakdown.py

Times each stage of `AnnyBody.body_frame(..., with_vertices=False)` alone (median of 10).
"""

from __future__ import annotations

import statistics
import time

import roma
import torch

from pressurepose.body import BodyParams, load_body_model


def timed(name: str, fn, repeats: int = 10):
    result = fn()
    samples = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t)
    print(f"| {name} | {statistics.median(samples) * 1e3:.1f} |")
    return result


def main(B: int = 128) -> None:
    model = load_body_model("anny")
    sk = model.light
    shape = model.default_shape(B)
    pose = torch.randn(B, 23, 3, generator=torch.Generator().manual_seed(0)) * 0.3
    print(
        f"Anny joints-only, B = {B}, {len(sk.bones)} of {len(model.bone_labels)} bones, "
        f"{torch.get_num_threads()} threads"
    )
    print("| stage | ms |")
    print("| --- | --- |")
    with torch.no_grad():
        coeffs = timed("phenotypes -> blendshape coefficients", lambda: model._coefficients(shape))
        heads, R = timed("rest skeleton (heads + orientations)", lambda: model._rest_skeleton(coeffs, sk))
        anny = model.anny
        M = anny.bone_template_orientation_matrices[sk.bones] + torch.einsum(
            "ba,akij->bkij", coeffs, anny.bone_orientation_blendshapes[:, sk.bones]
        )
        timed("  of which special Procrustes (3x3 SVD)", lambda: roma.special_procrustes(M[:, 1:]))
        _, offsets = timed("reference offsets", lambda: model._reference_offsets(heads, R, sk))
        G = timed("T-pose corrections", lambda: model._t_pose_corrections(offsets, sk))
        local = timed("local rotations", lambda: model._local_rotations(pose, G, sk))
        timed("forward kinematics", lambda: model._forward_kinematics(offsets, local, sk))
        params = BodyParams.zeros(B, shape).replace(pose=pose)
        timed("joints() end to end", lambda: model.joints(params))


if __name__ == "__main__":
    main()
