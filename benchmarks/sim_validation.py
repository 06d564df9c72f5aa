"""Sim #2 (static Newton solve) against an explicit dynamic simulation of the same mattress
(issue 4, item 4): several poses, image correlation (target >= 0.95) and total force (target
within 2%). The reference integrates a grid of spring-loaded nodes struck by the falling
rigid body, rotated exactly and re-rasterised as it moves (sim/reference.py).

    .venv/bin/python benchmarks/sim_validation.py
"""

from __future__ import annotations

import math
import time

import torch

from pressurepose.body import load_body_model
from pressurepose.body.capsules import home_pose
from pressurepose.body.params import BodyParams
from pressurepose.mat import MatSpec
from pressurepose.sampling.partitions import SamplingConfig
from pressurepose.sampling.sampler import PoseSampler
from pressurepose.sim.foundation import simulate_pressure
from pressurepose.sim.objects import capsule_mesh
from pressurepose.sim.reference import dynamic_reference, image_correlation
from pressurepose.sim.settle import settle

D = torch.float64


def cases(model):
    out = []
    v, f = capsule_mesh(0.4, 0.06, centre=(0.9, 0.37, 0.07))
    v[:, 2] += 0.05 * (v[:, 0] - 0.9)
    out.append(("capsule 40 cm, 9.1 kg, tilted", v, f, 9.1))
    v, f = capsule_mesh(0.2, 0.05, centre=(0.5, 0.2, 0.06))
    out.append(("capsule 20 cm, 2.3 kg", v, f, 2.3))
    shape = model.default_shape(2)
    shape[1, 0] = 1.0
    p = BodyParams.zeros(2, shape).replace(
        pose=home_pose(2, dtype=D), root_translation=torch.tensor([[0.85, 0.37, 0.2]] * 2, dtype=D)
    )
    body = model(p)
    mass = model.measure(shape).mass_kg
    out.append(("supine male, home pose", body.vertices[0], body.faces, float(mass[0])))
    out.append(("supine female, home pose", body.vertices[1], body.faces, float(mass[1])))
    for partition in ("general", "prone_hands_up"):
        init = (
            PoseSampler(
                model,
                SamplingConfig(partition=partition, gender="male", seed=0, over_bed=partition == "prone_hands_up"),
            )
            .sample([3])
            .params
        )
        rest = settle(model, init)
        if rest.ok[0]:
            b = model(rest.params)
            out.append(
                (
                    f"{partition} #3 after sim #1",
                    b.vertices[0],
                    b.faces,
                    float(model.measure(rest.params.shape).mass_kg[0]),
                )
            )
    return out


def main() -> None:
    torch.set_num_threads(1)
    model = load_body_model("anny", dtype=D)
    mat = MatSpec()
    print("| pose | correlation | force sim #2 (N) | force reference (N) | difference | reference steps | time (s) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    worst_r, worst_f = 1.0, 0.0
    for name, v, f, mass in cases(model):
        quasi = simulate_pressure(v[None], f, torch.tensor([mass], dtype=D), mat=mat)
        t = time.perf_counter()
        ref = dynamic_reference(v, f, mass, mat=mat)
        secs = time.perf_counter() - t
        r = image_correlation(ref.pressure_pa, quasi.pressure_pa[0])
        force = float(quasi.pressure_pa.sum()) * mat.taxel_area_m2
        diff = abs(ref.force_n - force) / force
        worst_r, worst_f = min(worst_r, r), max(worst_f, diff)
        print(
            f"| {name} | {r:.4f} | {force:.1f} | {ref.force_n:.1f} | {diff:.2%} | {ref.steps}{'' if ref.at_rest else ' (not at rest)'} | {secs:.1f} |"
        )
    ok = worst_r >= 0.95 and worst_f <= 0.02
    print(
        f"worst correlation {worst_r:.4f} (target >= 0.95), worst force difference {worst_f:.2%} (target <= 2%): "
        + ("PASS" if ok else "FAIL")
    )
    if not math.isfinite(worst_r):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
