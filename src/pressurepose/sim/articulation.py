"""The articulated body of sim #2 (`sim.articulated`): its unknowns, springs, part masses,
and how a small motion of the unknowns moves the parts and becomes pose parameters.

Unknowns (`Dofs`): the vertical shift, and rotations about horizontal axes through the
joints - the root's roll and pitch through the centre of mass, the bed's x and y axes at
ball joints, the hinge axis at knees and elbows. A rotation theta about axis u through pivot
p lifts a point r of the joint's subtree by theta (u x (r - p))_z = theta a . (1, x, y)
(`dof_geometry`); `apply_motion` turns a motion into exact pose parameters (world rotations
applied top-down about the joints).
"""

from __future__ import annotations

import torch

from pressurepose.body.capsules import HINGE_JOINTS, JOINT_STIFFNESS, STIFFNESS_REFERENCE_MASS_KG
from pressurepose.body.joints import J24_NAMES, J24_PARENTS, NUM_JOINTS
from pressurepose.body.kinematics import compose_down
from pressurepose.body.limits import JointLimits
from pressurepose.body.model import BODY_DENSITY_KG_M3
from pressurepose.body.params import BodyParams, supine_rotation
from pressurepose.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle

# Sim #1's springs (seed A.2, body.capsules): the capsule chain has no foot or hand joint, so
# those parts here take their ankle's and wrist's stiffness.
_STIFFNESS = {**JOINT_STIFFNESS, "foot": JOINT_STIFFNESS["ankle"], "hand": JOINT_STIFFNESS["wrist"]}
# Hinge joint -> the index of its axis in SMPL body axes (knees about x, elbows about y).
_HINGE_AXIS = {j: axis.index(1.0) for j, axis in HINGE_JOINTS.items()}


class Dofs:
    """The N degrees of freedom: joint index (subtree), stiffness index, pivot and axis."""

    def __init__(self, device, dtype):
        joint, axis_body, axis_world = [0, 0, 0], [None, None, None], [None, (1.0, 0.0), (0.0, 1.0)]
        for j in range(1, NUM_JOINTS):
            if j in _HINGE_AXIS:
                joint.append(j)
                axis_body.append(_HINGE_AXIS[j])
                axis_world.append(None)
            else:
                for ax in ((1.0, 0.0), (0.0, 1.0)):
                    joint.append(j)
                    axis_body.append(None)
                    axis_world.append(ax)
        self.joint = torch.tensor(joint, device=device)
        self.axis_body = axis_body
        self.hinge_axis = torch.tensor([-1 if a is None else a for a in axis_body], device=device)
        self.axis_world = axis_world
        self.n = len(joint)
        # desc[j, s] = 1 when part s moves with joint j (s in j's subtree); joint 0 moves all.
        desc = torch.zeros(NUM_JOINTS, NUM_JOINTS)
        for s in range(NUM_JOINTS):
            j = s
            while j >= 0:
                desc[j, s] = 1.0
                j = J24_PARENTS[j]
        self.desc = desc.to(device=device, dtype=dtype)
        # deeper[k, l]: the joint whose subtree is the overlap of DoF k's and l's (-1: none).
        jk = self.joint
        related_kl = desc[jk][:, jk].bool().to(device)  # l's joint in k's subtree
        related_lk = related_kl.T
        deeper = torch.where(
            related_kl,
            jk[None, :].expand(self.n, self.n),
            torch.where(
                related_lk, jk[:, None].expand(self.n, self.n), torch.full_like(related_kl, -1, dtype=torch.long)
            ),
        )
        self.deeper = deeper

    def axes(self, rot: torch.Tensor) -> torch.Tensor:
        """(B, N, 3) each DoF's rotation axis in the mat frame (the dz DoF: zero); rot: (B, 24,
        3, 3) the joints' world rotations (a hinge's axis turns with its joint)."""
        world = torch.tensor(
            [(0.0, 0.0) if a is None else a for a in self.axis_world], dtype=rot.dtype, device=rot.device
        )
        u = torch.cat([world, torch.zeros_like(world[:, :1])], -1).expand(rot.shape[0], -1, -1).clone()
        hinge = self.hinge_axis >= 0
        # A hinge's axis: column `axis_body` of its joint's rotation.
        u[:, hinge] = rot.transpose(-1, -2)[:, self.joint[hinge], self.hinge_axis[hinge]]
        return u

    def hinge_angles(self, pose: torch.Tensor) -> torch.Tensor:
        """(B, N) each DoF's joint angle about its hinge axis (pose (B, 23, 3)); meaningful on
        hinge DoFs only."""
        return pose[:, self.joint.clamp(min=1) - 1, self.hinge_axis.clamp(min=0)]

    def limits(self, dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
        """(N,) lower and upper bounds of each DoF's hinge angle: the joint limits on knees and
        elbows (no hyperextension), unbounded elsewhere (the springs hold the ball joints)."""
        limits = JointLimits.default(dtype, device)
        jj, ax = self.joint.clamp(min=1) - 1, self.hinge_axis.clamp(min=0)
        hinge = self.hinge_axis >= 0
        inf = torch.full((self.n,), float("inf"), dtype=dtype, device=device)
        return torch.where(hinge, limits.lower[jj, ax], -inf), torch.where(hinge, limits.upper[jj, ax], inf)


def joint_stiffness(
    mass_kg: torch.Tensor,
    dofs: Dofs,
    scale: float = 1.0,
    neck_scale: float = 1.0,
    spine_scale: float = 1.0,
    spine_lateral_scale: float = 1.0,
    roll_rad: torch.Tensor | None = None,
) -> torch.Tensor:
    """(B, N) spring stiffness (N m / rad) per DoF: the seed's per joint, x mass / 70.45 kg,
    x `scale` (x `neck_scale` on the neck and head, x `spine_scale` on spine1-3); 0 on the
    root's DoFs. With `roll_rad` (B,), the body's roll about the bed's long axis (0 supine,
    +-pi/2 on a side), the spine's DoF about the bed's cross axis - flexion on the back,
    lateral bending on a side - is further x cos^2(roll) + `spine_lateral_scale` sin^2(roll):
    the spine bends sideways under its own factor."""
    base, lateral = [], []
    for j, ax in zip(dofs.joint.tolist(), dofs.axis_world):
        if j == 0:
            base.append(0.0)
            lateral.append(False)
            continue
        name = J24_NAMES[j]
        k = _STIFFNESS[name.removeprefix("left_").removeprefix("right_")] * scale
        if name in ("neck", "head"):
            k *= neck_scale
        if name.startswith("spine"):
            k *= spine_scale
        base.append(k)
        lateral.append(name.startswith("spine") and ax == (0.0, 1.0))
    base_t = torch.tensor(base, dtype=mass_kg.dtype, device=mass_kg.device)
    k = base_t[None] * (mass_kg / STIFFNESS_REFERENCE_MASS_KG)[:, None]
    if roll_rad is not None and spine_lateral_scale != 1.0:
        s2 = torch.sin(roll_rad.to(k)) ** 2
        factor = 1.0 + (spine_lateral_scale - 1.0) * s2  # cos^2 + scale sin^2
        mask = torch.tensor(lateral, device=k.device)
        k = torch.where(mask[None], k * factor[:, None], k)
    return k


def lying_reference(pose: torch.Tensor, roll_rad: torch.Tensor, extension: tuple = ()) -> torch.Tensor:
    """(B, 23, 3, 3) the springs' rest rotations: `pose` (B, 23, 3), each joint named in
    `extension` ((J24 name, rad), ...) extended by its angle (about the body's left axis: the
    head or the upper body tipping back) x max(cos roll, 0)^2 - a body on its back lets its
    head back onto the bed and its back flatten, one on its side or front keeps the pose's.
    Anny's and SMPL's neutral spine and neck are a standing person's, the head held forward of
    the back (docs/realism.md "A lying neck")."""
    ref = axis_angle_to_matrix(pose)
    if not extension:
        return ref
    w = torch.clamp(torch.cos(roll_rad.to(pose)), min=0.0) ** 2
    ref = ref.clone()
    for name, rad in extension:
        angle = -rad * w  # extension: negative about x (flexion is positive)
        zero = torch.zeros_like(angle)
        j = J24_NAMES.index(name) - 1
        ref[:, j] = axis_angle_to_matrix(torch.stack([angle, zero, zero], -1)) @ ref[:, j]
    return ref


def part_mass_and_com(
    vertices: torch.Tensor, faces: torch.Tensor, face_part: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mass (B, 24) kg and centre of mass (B, 24, 3) of each J24 part of a closed mesh: each
    part's triangles with tetrahedra to the part's own centre (the mean of its triangles'
    centroids, inside the part), density BODY_DENSITY_KG_M3. The part surfaces are open where
    parts meet, so the parts' masses add up to the body's within a few per cent; callers
    scale them to the body's mass. Per part, its triangles' corners as (B, 3, n) rows (one
    contiguous slice of the faces sorted by part): no scatter over the faces. The rest calls
    `corner_mass_and_com` on corners it has gathered already (`sim.rest_setup`); this is the
    same from a mesh (tests, diagnostics)."""
    order = torch.argsort(face_part, stable=True)
    tri = faces[order]
    cols = vertices.transpose(1, 2).contiguous()  # (B, 3, V)
    return corner_mass_and_com(*(cols.index_select(2, tri[:, i]) for i in range(3)), face_part[order])


def corner_mass_and_com(v0, v1, v2, face_part: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """`part_mass_and_com` from the triangles' corners (three (B, 3, F)), the faces sorted by
    part (`face_part` (F,) sorted)."""
    B = v0.shape[0]
    mass = v0.new_zeros(B, NUM_JOINTS)
    com = v0.new_zeros(B, NUM_JOINTS, 3)
    for j, sl in _part_slices(face_part):
        a0, a1, a2 = v0[:, :, sl], v1[:, :, sl], v2[:, :, sl]
        corners = a0 + a1 + a2
        apex = corners.sum(2, keepdim=True) / (3 * a0.shape[2])  # (B, 3, 1)
        r0, r1, r2 = a0 - apex, a1 - apex, a2 - apex
        # Signed tetrahedron volumes (B, n): the triple product of the corners relative to the apex.
        cross = (
            r1[:, 1] * r2[:, 2] - r1[:, 2] * r2[:, 1],
            r1[:, 2] * r2[:, 0] - r1[:, 0] * r2[:, 2],
            r1[:, 0] * r2[:, 1] - r1[:, 1] * r2[:, 0],
        )
        vol = (r0[:, 0] * cross[0] + r0[:, 1] * cross[1] + r0[:, 2] * cross[2]) / 6.0
        volume = vol.sum(1)
        # sum vol x (apex + (r0 + r1 + r2) / 4): the tetrahedra's centroids weighted by volume.
        moment = ((corners - 3 * apex) @ vol[..., None])[..., 0] / 4.0  # (B, 3), about the apex
        mass[:, j] = volume * BODY_DENSITY_KG_M3
        centre = apex[..., 0] + moment / volume.clamp(min=1e-12 / BODY_DENSITY_KG_M3)[:, None]
        com[:, j] = torch.where(volume[:, None] > 0, centre, apex[..., 0])
    return mass.clamp(min=0), com


def _part_slices(labels: torch.Tensor) -> list[tuple[int, slice]]:
    """(part, slice) of each part's points; `labels` (P,) sorted by part."""
    counts = torch.bincount(labels, minlength=NUM_JOINTS).tolist()
    out, start = [], 0
    for j, n in enumerate(counts):
        if n:
            out.append((j, slice(start, start + n)))
        start += n
    return out


def to_part_frames(points, labels, rot, joints):
    """(B, P, 3) mat-frame points of the parts `labels` (P,, sorted by part) -> each part's
    joint frame (rot (B, 24, 3, 3), joints (B, 24, 3)). The result is a (B, P, 3) view of a
    coordinate-major (B, 3, P) buffer, the layout `from_part_frames` is fastest with."""
    if bool((labels[1:] < labels[:-1]).any()):
        raise ValueError("labels must be sorted by part")
    cols = points.transpose(1, 2)  # (B, 3, P)
    out = torch.empty(points.shape[0], 3, points.shape[1], dtype=points.dtype, device=points.device)
    for j, sl in _part_slices(labels):
        out[:, :, sl] = rot[:, j].transpose(-1, -2) @ (cols[:, :, sl] - joints[:, j, :, None])
    return out.transpose(1, 2)


def from_part_frames(local, labels, rot, joints):
    """Inverse of `to_part_frames`: joint-frame points back to the mat frame, (B, P, 3) (a view
    of a coordinate-major buffer: each coordinate of all points is contiguous). Per part one
    (3 x 3)(3 x n) product, the shape matrix products are fast at."""
    cols = local.transpose(1, 2).contiguous()  # no copy for `to_part_frames`'s output
    out = torch.empty_like(cols)
    for j, sl in _part_slices(labels):
        out[:, :, sl] = torch.baddbmm(joints[:, j, :, None], rot[:, j], cols[:, :, sl])
    return out.transpose(1, 2)


def tissue_depth(
    points: torch.Tensor, labels: torch.Tensor, joints: torch.Tensor, max_by_part: tuple = ()
) -> torch.Tensor:
    """(B, P) distance (m) of each surface point to its part's bone: the segments from the
    part's joint to its children's joints (leaf parts: to the part's point centroid), at most
    `max_by_part`'s depth for its parts ((J24 name, m) pairs: a wide bone - the ribcage around
    the thoracic spine - lies that close under the skin wherever the point is)."""
    out = torch.empty(points.shape[:2], dtype=points.dtype, device=points.device)
    children = {j: [c for c in range(NUM_JOINTS) if J24_PARENTS[c] == j] for j in range(NUM_JOINTS)}
    for j, sl in _part_slices(labels):
        pts = points[:, sl]
        ends = [joints[:, c] for c in children[j]] or [pts.mean(1)]
        a = joints[:, j, None]
        best = None
        r = pts - a
        for e in ends:
            ab = (e - joints[:, j])[:, None]
            t = ((r * ab).sum(-1) / (ab * ab).sum(-1).clamp(min=1e-12)).clamp(0, 1)
            d = (r - t[..., None] * ab).norm(dim=-1)
            best = d if best is None else torch.minimum(best, d)
        out[:, sl] = best
    for name, depth in max_by_part:
        sl = labels == J24_NAMES.index(name)
        out[:, sl] = out[:, sl].clamp(max=depth)
    return out


# The tissue modulus MattressParams.tissue_pa_per_m is that of a layer this deep over the bone;
# depths below 1 cm count as 1 cm.
TISSUE_REFERENCE_DEPTH_M = 0.05


def tissue_modulus(
    points, labels, joints, tissue_pa_per_m: float, by_part, use_depth: bool = True, max_depth_by_part: tuple = ()
):
    """(B, P) the tissue modulus (Pa/m) under each surface point: `tissue_pa_per_m` x its part's
    factor (`by_part`: (J24 name, factor) pairs, else 1) x (TISSUE_REFERENCE_DEPTH_M / its depth
    over the bone, `tissue_depth` with `max_depth_by_part`) with `use_depth`: stiff over bony
    prominences, soft over muscle and fat. None when tissue_pa_per_m is not > 0 (no tissue)."""
    if not float(tissue_pa_per_m) > 0:
        return None
    factor = torch.ones(NUM_JOINTS, dtype=points.dtype, device=points.device)
    for name, value in by_part:
        factor[J24_NAMES.index(name)] = value
    modulus = float(tissue_pa_per_m) * factor[labels].expand(points.shape[0], -1)
    if use_depth:
        depth = tissue_depth(points, labels, joints, max_depth_by_part)
        modulus = modulus * (TISSUE_REFERENCE_DEPTH_M / depth.clamp(min=0.01))
    return modulus


# The sag's reference depth: `ArticulatedConfig.tissue_sag_m` is the sag of tissue this deep.
SAG_REFERENCE_DEPTH_M = 0.10


def tissue_sag(points, labels, joints, sag_m: float, max_depth_by_part: tuple = ()):
    """(B, P) how far (m) each surface point's soft tissue hangs below where the bone holds it,
    under its own weight: `sag_m` x (depth / SAG_REFERENCE_DEPTH_M)^2 (a layer of depth d and
    shear modulus mu sags by rho g d^2 / (2 mu); `sag_m` 0.01 is mu ~ 4.9 kPa), at most half the
    depth; the depth is `tissue_depth`'s with `max_depth_by_part`. None when sag_m is not > 0."""
    if not float(sag_m) > 0:
        return None
    depth = tissue_depth(points, labels, joints, max_depth_by_part)
    return (float(sag_m) * (depth / SAG_REFERENCE_DEPTH_M) ** 2).minimum(0.5 * depth)


def dof_axes_pivots(dofs: Dofs, rot, joints, body_com) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, N, 3) x 2: each DoF's axis (zero for the vertical shift) and pivot in the mat frame;
    the root turns about the centre of mass."""
    pivot = joints[:, dofs.joint]
    pivot[:, dofs.joint == 0] = body_com[:, None]
    return dofs.axes(rot), pivot


def dof_geometry(dofs: Dofs, rot, joints, body_com, pose, ref_local):
    """Per DoF: a_k (B, N, 3) with d(height)/d(theta_k) = a_k . (1, x, y) inside its subtree,
    and e_k (B, N) the spring's present deflection about the DoF's axis."""
    u, pivot = dof_axes_pivots(dofs, rot, joints, body_com)
    # dz: height + theta; rotation: (u x (r - p))_z = u_x (y - p_y) - u_y (x - p_x)
    a = torch.stack([u[..., 1] * pivot[..., 0] - u[..., 0] * pivot[..., 1], -u[..., 1], u[..., 0]], -1)
    a[:, 0] = torch.tensor([1.0, 0.0, 0.0], dtype=a.dtype, device=a.device)
    # Deflection from the reference pose, in the world frame: parent's rotation applied to
    # the rotation vector of (local @ reference^T), then its component along u.
    local = axis_angle_to_matrix(pose)
    dev = matrix_to_axis_angle(local @ ref_local.transpose(-1, -2))  # (B, 23, 3) local frame
    par = torch.tensor([max(p, 0) for p in J24_PARENTS[1:]], device=rot.device)
    dev_world = (rot[:, par] @ dev[..., None])[..., 0]  # (B, 23, 3)
    jj = dofs.joint.clamp(min=1) - 1
    e = (dev_world[:, jj] * u).sum(-1) * (dofs.joint > 0)
    return a, e


def apply_motion(params: BodyParams, q, dofs: Dofs, rot, joints, body_com) -> BodyParams:
    """Turn the DoF motion q into new pose parameters: world rotations applied top-down about
    the joints (the root's about the centre of mass), plus the vertical shift."""
    B = q.shape[0]
    dtype, device = q.dtype, q.device
    # Rotation vector per joint: the sum of its DoFs' q x axis (the dz DoF's axis is zero).
    delta = q.new_zeros(B, NUM_JOINTS, 3).index_add_(1, dofs.joint, q[..., None] * dofs.axes(rot))
    D = axis_angle_to_matrix(delta)  # (B, 24, 3, 3) world-frame rotation at each joint
    U = compose_down(D)  # each joint's rotation of its subtree
    new_rot = U @ rot
    par = [max(p, 0) for p in J24_PARENTS[1:]]
    local = new_rot[:, par].transpose(-1, -2) @ new_rot[:, 1:]
    root_m = new_rot[:, 0] @ supine_rotation(dtype, device).T
    vectors = matrix_to_axis_angle(torch.cat([local, root_m[:, None]], 1))  # the joints', the root's
    pose, root = vectors[:, :-1].contiguous(), vectors[:, -1].contiguous()
    pelvis = params.root_translation
    moved = body_com + (U[:, 0] @ (pelvis - body_com)[..., None])[..., 0]
    moved = moved + torch.stack([torch.zeros_like(q[:, 0]), torch.zeros_like(q[:, 0]), q[:, 0]], -1)
    return params.replace(pose=pose, root_rotation=root, root_translation=moved)


__all__ = [
    "Dofs",
    "apply_motion",
    "corner_mass_and_com",
    "dof_axes_pivots",
    "dof_geometry",
    "from_part_frames",
    "joint_stiffness",
    "lying_reference",
    "part_mass_and_com",
    "tissue_depth",
    "tissue_sag",
    "tissue_modulus",
    "to_part_frames",
]
