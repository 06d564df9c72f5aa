"""Sim #1's MJCF: one MuJoCo model per capsule body (`sim.settle`, docs/physics.md)."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from pressurepose.bed import BedShape
from pressurepose.body.capsules import (
    CAPSULE_JOINTS,
    CAPSULE_NAMES,
    CAPSULE_PARENTS,
    HINGE_JOINTS,
    CapsuleBody,
    collision_pairs,
    segment_distance,
)
from pressurepose.body.params import BodyParams
from pressurepose.body.rotations import axis_angle_to_matrix, matrix_to_quaternion, quaternion_to_axis_angle
from pressurepose.mat import MatSpec
from pressurepose.sim.mattress import GRAVITY_M_S2
from pressurepose.sim.settle_config import (
    SettleConfig,
)


def cross3(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (N, 3) arrays (np.cross is slow on small arrays)."""
    return np.stack(
        [
            u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1],
            u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2],
            u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0],
        ],
        1,
    )


def axis_angle_quats(v: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) -> unit quaternions (N, 4) as (w, x, y, z), w >= 0 (for
    angles up to pi). Per body in numpy, so a body's numbers never depend on its batch."""
    theta = np.sqrt((v * v).sum(1))
    half = theta / 2
    # sin(theta / 2) / theta, with its series near 0 (where the axis is undefined).
    small = theta < 1e-6
    k = np.where(small, 0.5 - theta**2 / 48, np.sin(half) / np.where(small, 1.0, theta))
    q = np.concatenate([np.cos(half)[:, None], v * k[:, None]], 1)
    return np.where(q[:, :1] < 0, -q, q)


def matrix_quat(R: torch.Tensor) -> np.ndarray:
    return matrix_to_quaternion(R).double().numpy()


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    q = q / q.norm()
    return axis_angle_to_matrix(quaternion_to_axis_angle(q))


def _fmt(v) -> str:
    return " ".join(f"{x:.9g}" for x in np.ravel(v).tolist())


def _walls(
    mat: MatSpec, bed: BedShape | None = None, top_m: float = -0.03, depth_m: float = 1.0, thick_m: float = 0.2
) -> str:
    """The mattress's sides as MuJoCo boxes (the top is the foundation law): a limb hanging
    over the edge rests against the side instead of swinging in under the mattress top. On a
    bent bed each section has its own side walls (and end wall), in the section's frame."""
    bed = bed or BedShape()
    (x0, x1), (y0, y1) = mat.mattress_bounds_m
    hinge = np.array([bed.hinge_x(mat), 0.0, 0.0])
    hz = (depth_m + top_m) / 2  # the walls reach from -depth_m up to top_m (section frame)
    zc = top_m - hz
    lines = []
    for k, (R, s0, s1) in enumerate(bed.sections(mat)):
        a, b = max(x0, s0), min(x1, s1)
        boxes = [
            ((a + b) / 2, y0 - thick_m / 2, (b - a) / 2, thick_m / 2),
            ((a + b) / 2, y1 + thick_m / 2, (b - a) / 2, thick_m / 2),
        ]
        if a == x0:
            boxes.append((x0 - thick_m / 2, (y0 + y1) / 2, thick_m / 2, (y1 - y0) / 2 + thick_m))
        if b == x1:
            boxes.append((x1 + thick_m / 2, (y0 + y1) / 2, thick_m / 2, (y1 - y0) / 2 + thick_m))
        quat = matrix_quat(torch.from_numpy(R))
        for j, (cx, cy, hx, hy) in enumerate(boxes):
            pos = hinge + R @ (np.array([cx, cy, zc]) - hinge)
            lines.append(
                f'    <geom name="side{k}_{j}" type="box" pos="{_fmt(pos)}" quat="{_fmt(quat)}" '
                f'size="{hx:.6g} {hy:.6g} {hz:.6g}" contype="1" conaffinity="0"/>'
            )
    return "\n".join(lines)


def initial_pairs(body: CapsuleBody, params: BodyParams) -> list[list[tuple[int, int]]]:
    """Per body, the sampler's self-collision pairs (distal capsules vs non-adjacent ones)
    that are apart in the initial pose: MuJoCo keeps them apart while the body settles.
    Body by body (torch's batched kernels could move a gap's last bits with the batch)."""
    caps = body.capsules
    pairs = collision_pairs()
    p0, p1 = pairs[:, 0], pairs[:, 1]
    pl = [(int(x), int(y)) for x, y in pairs]
    out = []
    for i in range(caps.batch_size):
        one = dataclasses.replace(caps, **{f.name: getattr(caps, f.name)[i : i + 1] for f in dataclasses.fields(caps)})
        a, b = one.posed(params.pose[i : i + 1].to(caps.rest.dtype))
        d = segment_distance(a[:, p0], b[:, p0], a[:, p1], b[:, p1])
        gap = (d - one.radius[:, p0] - one.radius[:, p1])[0].numpy()
        out.append([pl[k] for k in np.flatnonzero(gap > 0.0)])
    return out


def build_mjcf(
    body: CapsuleBody,
    i: int,
    config: SettleConfig,
    pairs: list[tuple[int, int]] = (),
    mat: MatSpec | None = None,
    bed: BedShape | None = None,
) -> str:
    """MJCF of capsule body `i` of `body` in its T-pose (body axes), free root; with `mat`,
    the mattress sides as walls."""
    caps = body.capsules
    rest = caps.rest[i].double().numpy()
    start, end = caps.start[i].double().numpy(), caps.end[i].double().numpy()
    radius = caps.radius[i].double().numpy()
    mass = body.mass_kg[i].double().numpy()
    inertia = body.inertia[i].double().numpy()
    stiff = body.stiffness[i].double().numpy()
    damp = body.damping[i].double().numpy()
    children: dict[int, list[int]] = {}
    for c, p in enumerate(CAPSULE_PARENTS):
        children.setdefault(p, []).append(c)

    # All capsules at once: origins, axis ends in the body frame, full inertias.
    jc = np.array(CAPSULE_JOINTS)
    pc = np.array(CAPSULE_PARENTS)
    origin = rest[jc]
    rel_pos = origin - np.where((pc >= 0)[:, None], rest[jc[np.maximum(pc, 0)]], 0.0)
    a_all, b_all = start - origin, end - origin
    axis = b_all - a_all
    length = np.sqrt((axis**2).sum(1))
    u = np.where((length > 1e-9)[:, None], axis / np.maximum(length, 1e-12)[:, None], np.array([1.0, 0.0, 0.0]))
    # Principal axes: capsule axis + two perpendiculars -> full inertia in the body frame.
    tmp = np.where((np.abs(u[:, 2]) < 0.9)[:, None], np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    v = cross3(u, tmp)
    v /= np.sqrt((v**2).sum(1))[:, None]
    w = cross3(u, v)
    Rm = np.stack([u, v, w], 2)
    I_all = np.einsum("cik,ck,cjk->cij", Rm, inertia, Rm)
    full_all = I_all[:, [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]

    def body_xml(c: int, indent: str) -> str:
        j = CAPSULE_JOINTS[c]
        p = CAPSULE_PARENTS[c]
        pos, a, b, full = rel_pos[c], a_all[c], b_all[c], full_all[c]
        lines = [f'{indent}<body name="{CAPSULE_NAMES[c]}" pos="{_fmt(pos)}">']
        if p < 0:
            lines.append(f'{indent}  <freejoint name="root"/>')
        elif j in HINGE_JOINTS:
            lines.append(
                f'{indent}  <joint name="j{j}" type="hinge" axis="{_fmt(HINGE_JOINTS[j])}" '
                f'stiffness="{stiff[j - 1]:.9g}" damping="{damp[j - 1]:.9g}" springref="0"/>'
            )
        else:
            lines.append(
                f'{indent}  <joint name="j{j}" type="ball" stiffness="{stiff[j - 1]:.9g}" damping="{damp[j - 1]:.9g}"/>'
            )
        lines.append(f'{indent}  <inertial pos="{_fmt((a + b) / 2)}" mass="{mass[c]:.9g}" fullinertia="{_fmt(full)}"/>')
        if length[c] > 1e-9:
            lines.append(
                f'{indent}  <geom name="{CAPSULE_NAMES[c]}" type="capsule" size="{radius[c]:.9g}" fromto="{_fmt(np.concatenate([a, b]))}"/>'
            )
        else:
            lines.append(
                f'{indent}  <geom name="{CAPSULE_NAMES[c]}" type="sphere" size="{radius[c]:.9g}" pos="{_fmt(a)}"/>'
            )
        for ch in children.get(c, []):
            lines.append(body_xml(ch, indent + "  "))
        lines.append(f"{indent}</body>")
        return "\n".join(lines)

    pair_xml = "\n".join(f'    <pair geom1="{CAPSULE_NAMES[a]}" geom2="{CAPSULE_NAMES[b]}"/>' for a, b in pairs)
    return f"""<mujoco model="pressurepose_capsule_body">
  <option timestep="{config.timestep_s:.9g}" integrator="implicitfast" gravity="0 0 {-GRAVITY_M_S2}">
    <flag energy="enable"/>
  </option>
  <default><geom contype="0" conaffinity="1"/></default>
  <worldbody>
{_walls(mat, bed) if mat is not None else ""}
{body_xml(0, "    ")}
  </worldbody>
  <contact>
{pair_xml}
  </contact>
</mujoco>
"""
