"""An explicit dynamic simulation of sim #2's mattress model, to validate the static solver.

Nothing here is solved for equilibrium: a grid of foundation nodes (one per sim #2 cell, each
a small mass on the foundation law p(w) A with a damper) is struck by the rigid body, which
falls under gravity with three degrees of freedom (height, roll, pitch; its horizontal place
and yaw are kept, as in sim #2) and is rotated exactly (its mesh is re-rasterised every step,
no small-angle form). Body and nodes meet through a stiff penalty contact. Time is integrated
with semi-implicit Euler at a small step until everything is at rest; the node forces then
give the pressure, spread and pooled exactly as sim #2 does. Agreement with
`simulate_pressure` (image correlation, total force) checks the Newton solution, its
linearisation and the force bookkeeping (benchmarks/sim_validation.py, tests).
"""

from __future__ import annotations

import dataclasses

import torch
import torch.nn.functional as F

from pressurepose.blur import gaussian_blur
from pressurepose.maps import EMPTY_HEIGHT_M, cell_centres, mesh_centroid, underside_height
from pressurepose.mat import MatSpec
from pressurepose.sim.mattress import GRAVITY_M_S2, MattressParams


@dataclasses.dataclass
class ReferenceResult:
    pressure_pa: torch.Tensor  # (covered_rows, covered_cols)
    force_n: float
    steps: int
    at_rest: bool
    vertices: torch.Tensor


def dynamic_reference(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    mass_kg: float,
    params: MattressParams | None = None,
    mat: MatSpec | None = None,
    sub: int = 2,
    dt: float = 1e-3,
    max_steps: int = 60_000,
    node_mass_kg: float = 0.05,
    contact_stiffness: float = 5.0e3,
    tol_speed: float = 1e-3,
    body_damping: float = 20.0,
    refresh: int = 5,
) -> ReferenceResult:
    """Drop one rigid mesh (V, 3) (float64, mat frame) onto the node grid and run to rest."""
    params = params or MattressParams()
    mat = mat or MatSpec()
    v0 = vertices.detach().double()
    com0 = mesh_centroid(v0[None], faces)[0]
    X, Y = cell_centres(mat, sub, covered=True, dtype=torch.float64)
    area = mat.pitch_row_m * mat.pitch_col_m / sub**2
    # Rotational inertia from the vertex spread (only the path to rest depends on it).
    d = v0 - com0
    Ix = mass_kg * float((d[:, 1] ** 2 + d[:, 2] ** 2).mean())
    Iy = mass_kg * float((d[:, 0] ** 2 + d[:, 2] ** 2).mean())
    k1, k3, nu = float(params.k1_pa_per_m), float(params.k3_pa_per_m3), 0.05
    # Start with the lowest point on the mattress top.
    z = -float(underside_height(v0[None], faces, mat, sub=sub).min())
    a = b = 0.0
    vz = va = vb = 0.0
    w = torch.zeros_like(X)  # node compression (m, down)
    wd = torch.zeros_like(X)  # node velocity (down)
    c_contact = 2.0 * (contact_stiffness * node_mass_kg) ** 0.5
    weight = mass_kg * GRAVITY_M_S2
    steps, at_rest = 0, False
    for steps in range(1, max_steps + 1):
        com = com0 + torch.tensor([0.0, 0.0, z], dtype=torch.float64)
        if (steps - 1) % refresh == 0:
            # Exact rigid pose, re-rasterised; in between, heights follow the motion to first
            # order (the next refresh removes any drift).
            verts = _pose(v0, com0, z, a, b)
            h_exact = underside_height(verts[None], faces, mat, sub=sub)[0]
            body = (h_exact < EMPTY_HEIGHT_M).double()
            q_ref = (z, a, b)
        h = h_exact + (z - q_ref[0]) + (a - q_ref[1]) * (Y - com[1]) - (b - q_ref[2]) * (X - com[0])
        # Penalty contact between the node tops (z = -w) and the body's underside.
        pen = torch.relu(-w - h) * body
        vel_body = vz + va * (Y - com[1]) - vb * (X - com[0])  # underside velocity (up)
        rel = (-wd - vel_body) * (pen > 0)
        fc = torch.relu(contact_stiffness * pen + c_contact * rel)  # pushes the node down, body up
        spring = (k1 * torch.relu(w) + k3 * torch.relu(w) ** 3) * area
        k_loc = (k1 + 3 * k3 * w**2) * area
        damper = nu * k_loc * wd
        acc_w = (fc - spring - damper) / node_mass_kg
        wd = wd + dt * acc_w
        w = w + dt * wd
        Fz = float(fc.sum())
        tx = float((fc * (Y - com[1])).sum())
        ty = float(-(fc * (X - com[0])).sum())
        # Body: gravity + contact, light viscous damping on its three coordinates.
        vz += dt * ((Fz - weight) / mass_kg - body_damping * vz)
        va += dt * (tx / Ix - body_damping * va)
        vb += dt * (ty / Iy - body_damping * vb)
        z += dt * vz
        a += dt * va
        b += dt * vb
        if steps % 200 == 0:
            # At rest: the body still and carried (the nodes keep a tiny jitter from the
            # periodic re-rasterisation, which does not move the body).
            still = max(abs(vz), abs(va), abs(vb)) < tol_speed
            if still and abs(Fz - weight) < 5e-3 * weight:
                at_rest = True
                break
    spring = k1 * torch.relu(w) + k3 * torch.relu(w) ** 3
    spread = gaussian_blur(
        spring[None], params.spread_m / (mat.pitch_row_m / sub), params.spread_m / (mat.pitch_col_m / sub)
    )
    pressure = F.avg_pool2d(spread[:, None], sub)[0, 0]
    return ReferenceResult(
        pressure_pa=pressure,
        force_n=float(spring.sum()) * area,
        steps=steps,
        at_rest=at_rest,
        vertices=_pose(v0, com0, z, a, b),
    )


def _pose(v0, com0, z, a, b):
    a_, b_ = torch.tensor(a, dtype=torch.float64), torch.tensor(b, dtype=torch.float64)
    ca, sa, cb, sb = torch.cos(a_), torch.sin(a_), torch.cos(b_), torch.sin(b_)
    Rx = torch.tensor([[1, 0, 0], [0, ca, -sa], [0, sa, ca]], dtype=torch.float64)
    Ry = torch.tensor([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]], dtype=torch.float64)
    R = Ry @ Rx
    return (v0 - com0) @ R.T + com0 + torch.tensor([0.0, 0.0, z], dtype=torch.float64)


def image_correlation(a: torch.Tensor, b: torch.Tensor) -> float:
    """Pearson correlation of two images over the taxels loaded in either."""
    mask = (a > 0) | (b > 0)
    x, y = a[mask].double(), b[mask].double()
    x, y = x - x.mean(), y - y.mean()
    return float((x * y).sum() / (x.norm() * y.norm()).clamp(min=1e-30))


__all__ = ["ReferenceResult", "dynamic_reference", "image_correlation"]
