"""Rigid calibration objects (seed A.4: capsules of 20 and 40 cm, 1.3-18 kg) in both sims.

`capsule_mesh` gives sim #2 a closed triangle mesh; `settle_capsule` drops the same capsule
in sim #1 (MuJoCo, the foundation law on capsules) so the two sinking depths can be compared
(the agreement seed eq. 17 is about).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pressurepose.mat import MatSpec
from pressurepose.sim.mattress import GRAVITY_M_S2, MattressParams


def capsule_mesh(
    length_m: float,
    radius_m: float,
    centre=(0.0, 0.0, 0.0),
    n_around: int = 32,
    n_cap: int = 8,
    n_along: int = 16,
    dtype=torch.float64,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed, outward-oriented triangle mesh of a capsule lying along x: (V, 3), (F, 3)."""
    if not (length_m >= 0 and radius_m > 0):
        raise ValueError(f"capsule needs length >= 0 and radius > 0, got {length_m}, {radius_m}")
    rings = []  # (x, ring radius)
    for k in range(n_cap, 0, -1):  # left cap, from the pole (excluded) to the equator
        phi = math.pi / 2 * k / n_cap
        rings.append((-length_m / 2 - radius_m * math.sin(phi), radius_m * math.cos(phi)))
    for k in range(n_along + 1):
        rings.append((-length_m / 2 + length_m * k / n_along, radius_m))
    for k in range(1, n_cap + 1):
        phi = math.pi / 2 * k / n_cap
        rings.append((length_m / 2 + radius_m * math.sin(phi), radius_m * math.cos(phi)))
    rings = [r for r in rings if r[1] > 1e-9]
    theta = np.linspace(0, 2 * math.pi, n_around, endpoint=False)
    verts = [(-length_m / 2 - radius_m, 0.0, 0.0)]
    for x, rr in rings:
        verts += [(x, rr * math.cos(t), rr * math.sin(t)) for t in theta]
    verts.append((length_m / 2 + radius_m, 0.0, 0.0))
    faces = []
    n = n_around
    for i in range(n):
        faces.append((0, 1 + (i + 1) % n, 1 + i))
    for r in range(len(rings) - 1):
        a0, b0 = 1 + r * n, 1 + (r + 1) * n
        for i in range(n):
            j = (i + 1) % n
            faces.append((a0 + i, a0 + j, b0 + j))
            faces.append((a0 + i, b0 + j, b0 + i))
    last = len(verts) - 1
    base = 1 + (len(rings) - 1) * n
    for i in range(n):
        faces.append((last, base + i, base + (i + 1) % n))
    v = torch.tensor(verts, dtype=dtype) + torch.tensor(centre, dtype=dtype)
    return v, torch.tensor(faces, dtype=torch.long)


def settle_capsule(
    length_m: float,
    radius_m: float,
    mass_kg: float,
    xy=(0.9, 0.37),
    params: MattressParams | None = None,
    mat: MatSpec | None = None,
    timestep_s: float = 0.0103,
    max_steps: int = 3000,
    grid_sub: int = 1,
) -> dict:
    """Drop a horizontal rigid capsule (axis along the bed) onto sim #1's mattress and let it
    rest. Returns {"sink_m": deepest compression, "z_m": axis height, "steps", "settled"}."""
    import mujoco

    from pressurepose.sim.capsule_foundation import CapsuleFoundation

    params = params or MattressParams()
    mat = mat or MatSpec()
    xml = f"""<mujoco><option timestep="{timestep_s}" gravity="0 0 {-GRAVITY_M_S2}"/>
      <worldbody><body name="c" pos="{xy[0]} {xy[1]} {radius_m + 0.005}"><freejoint/>
      <geom type="capsule" size="{radius_m}" fromto="{-length_m / 2} 0 0 {length_m / 2} 0 0" mass="{mass_kg}"
        contype="0" conaffinity="0"/></body></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    found = CapsuleFoundation(mat, params, grid_sub)
    mass = m.body_mass[1:2].copy()
    inertia = m.body_inertia[1:2].min(1).copy()
    settled, wmax, step = False, 0.0, 0
    for step in range(max_steps):
        mujoco.mj_step1(m, d)  # current kinematics before the forces (see settle.py)
        R = d.xmat[1].reshape(3, 3)
        a = d.xpos[1] + R @ np.array([-length_m / 2, 0, 0])
        b = d.xpos[1] + R @ np.array([length_m / 2, 0, 0])
        d.xfrc_applied[:] = 0
        res = found.forces(
            a[None],
            b[None],
            np.array([radius_m]),
            d.cvel[1:2],
            d.subtree_com[0:1],
            d.xipos[1:2],
            mass,
            inertia,
            np.zeros(1, dtype=np.int64),
            timestep_s,
        )
        if res is not None:
            ft, _, w, _ = res
            wmax = float(w.max())
            d.xfrc_applied[1] = ft[0]
        mujoco.mj_step2(m, d)
        if step > 50 and np.abs(d.qvel).max() < 1e-3:
            settled = True
            break
    return {"sink_m": float(wmax), "z_m": float(d.xpos[1][2]), "steps": step + 1, "settled": settled}


__all__ = ["capsule_mesh", "settle_capsule"]
