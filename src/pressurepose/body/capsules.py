"""The capsulised body (seed A.1, A.2): 20 capsules on J24 for collisions and settling.

Layout (SMPLify's): one capsule per J24 part that moves on its own, riding that joint rigidly.
- Limbs, collars, neck and head: the axis runs from the joint to its child joint; the head,
  hands and feet, which end the chains, extend to the far end of their vertices (the feet
  also back to the heel).
- Torso (pelvis, spine1, spine2, spine3): the axis runs across the body (body x), centred on
  the part's vertices, as SMPLify does: a row of crosswise capsules gives the back its width,
  so a supine body rests stably instead of rolling on a line of spine capsules.
Each capsule is fitted per shape from the T-pose mesh: its vertices are those whose dominant
skinning part is the capsule's part, the radius is the median distance of the vertices in the
middle of the segment to the axis (robust to the joint regions shared with neighbours).

Volumes share overlapping space fractionally (seed A.2): a point inside n capsules counts 1/n
for each. `capsule_volumes(method="voxel")` is the seed's 2 mm voxelisation; the default
"qmc" integrates the same quantity on fixed Sobol points inside each capsule (exact capsule
volume times the mean of 1/n) and agrees with it within 1% (test) at a fraction of the cost.

Masses follow seed eq. 11-12: within a body segment R (trunk, head, thigh, ...), capsule c of a
body with shape beta gets m_c = m_g X_R,g V_c / V_R,g(average body). Departure: the masses are
then scaled by one factor so that they sum to the body model's mass (mesh volume x 980 kg/m^3),
the weight sim #2 presses into the mattress - both simulations must carry the same weight.
Inertia is analytic (uniform solid capsule). Joint stiffness is the seed's per-joint value times
m / 70.45 kg, damping 15 k, equilibrium = the home pose (arms at the sides, legs straight).
"""

from __future__ import annotations

import dataclasses
import math
import weakref

import torch

from pressurepose.body.joints import J24_NAMES, J24_PARENTS, NUM_POSE_JOINTS
from pressurepose.body.kinematics import forward_kinematics
from pressurepose.body.model import BodyModel
from pressurepose.body.params import BodyParams, root_matrix

_J = J24_NAMES.index


@dataclasses.dataclass(frozen=True)
class CapsuleSpec:
    name: str
    joint: int                  # J24 joint the capsule rides on
    child: int | None           # axis end joint (None: crosswise torso capsule)
    parts: tuple[int, ...]      # J24 parts whose vertices fit the capsule
    segment: str                # body segment for the mass distribution
    extend_end: bool = False    # grow the far end to the last vertex (head, hands, feet)
    extend_start: bool = False  # grow the near end back to the first vertex (heels)

    @property
    def crosswise(self) -> bool:
        """Torso capsules lie across the body (SMPLify); the head has no child but an axis."""
        return self.child is None and self.name != "head"


def _layout() -> tuple[CapsuleSpec, ...]:
    specs = [
        CapsuleSpec("pelvis", _J("pelvis"), None, (_J("pelvis"),), "trunk"),
        CapsuleSpec("spine1", _J("spine1"), None, (_J("spine1"),), "trunk"),
        CapsuleSpec("spine2", _J("spine2"), None, (_J("spine2"),), "trunk"),
        CapsuleSpec("spine3", _J("spine3"), None, (_J("spine3"),), "trunk"),
        CapsuleSpec("neck", _J("neck"), _J("head"), (_J("neck"),), "head"),
        CapsuleSpec("head", _J("head"), None, (_J("head"),), "head", extend_end=True),
    ]
    for s in ("left", "right"):
        specs += [
            CapsuleSpec(f"{s}_collar", _J(f"{s}_collar"), _J(f"{s}_shoulder"), (_J(f"{s}_collar"),), "trunk"),
            CapsuleSpec(f"{s}_upper_arm", _J(f"{s}_shoulder"), _J(f"{s}_elbow"), (_J(f"{s}_shoulder"),), "upper_arm"),
            CapsuleSpec(f"{s}_forearm", _J(f"{s}_elbow"), _J(f"{s}_wrist"), (_J(f"{s}_elbow"),), "forearm"),
            CapsuleSpec(f"{s}_hand", _J(f"{s}_wrist"), _J(f"{s}_hand"), (_J(f"{s}_wrist"), _J(f"{s}_hand")),
                        "hand", extend_end=True),
            CapsuleSpec(f"{s}_thigh", _J(f"{s}_hip"), _J(f"{s}_knee"), (_J(f"{s}_hip"),), "thigh"),
            CapsuleSpec(f"{s}_calf", _J(f"{s}_knee"), _J(f"{s}_ankle"), (_J(f"{s}_knee"),), "shank"),
            CapsuleSpec(f"{s}_foot", _J(f"{s}_ankle"), _J(f"{s}_foot"), (_J(f"{s}_ankle"), _J(f"{s}_foot")),
                        "foot", extend_end=True, extend_start=True),
        ]
    return tuple(specs)


CAPSULES: tuple[CapsuleSpec, ...] = _layout()
CAPSULE_NAMES: tuple[str, ...] = tuple(c.name for c in CAPSULES)
NUM_CAPSULES = len(CAPSULES)  # 20
CAPSULE_JOINTS: tuple[int, ...] = tuple(c.joint for c in CAPSULES)


def capsule_index(name: str) -> int:
    if name not in CAPSULE_NAMES:
        raise ValueError(f"unknown capsule {name!r}; expected one of {', '.join(CAPSULE_NAMES)}")
    return CAPSULE_NAMES.index(name)


def _capsule_parents() -> tuple[int, ...]:
    """Parent capsule of each capsule (-1 for the pelvis): the capsule riding the nearest
    J24 ancestor that has one."""
    by_joint = {c.joint: i for i, c in enumerate(CAPSULES)}
    out = []
    for c in CAPSULES:
        j = J24_PARENTS[c.joint]
        while j >= 0 and j not in by_joint:
            j = J24_PARENTS[j]
        out.append(by_joint.get(j, -1))
    return tuple(out)


CAPSULE_PARENTS: tuple[int, ...] = _capsule_parents()

# Seed A.1: hands, forearms, feet and lower legs are checked against every other capsule
# except their neighbours in the capsule tree (a forearm overlaps its upper arm by design).
DISTAL_CAPSULES: tuple[str, ...] = tuple(
    f"{s}_{p}" for s in ("left", "right") for p in ("hand", "forearm", "foot", "calf")
)


def collision_pairs(checked: tuple[str, ...] = DISTAL_CAPSULES) -> torch.Tensor:
    """(P, 2) capsule index pairs to test: each checked capsule against every non-adjacent
    capsule, each pair once."""
    pairs = set()
    for name in checked:
        a = capsule_index(name)
        for b in range(NUM_CAPSULES):
            if b == a or CAPSULE_PARENTS[a] == b or CAPSULE_PARENTS[b] == a:
                continue
            pairs.add((min(a, b), max(a, b)))
    return torch.tensor(sorted(pairs), dtype=torch.long).reshape(-1, 2)


# --- mass distribution (REFERENCE.md, Tozeren) ---------------------------------------------
AVERAGE_MASS_KG = {"female": 62.5, "male": 78.4}
SEGMENT_FRACTIONS = {  # per side for limbs
    "female": {"trunk": .508, "head": .094, "thigh": .083, "shank": .055, "foot": .012,
               "upper_arm": .027, "forearm": .016, "hand": .005},
    "male": {"trunk": .483, "head": .071, "thigh": .105, "shank": .045, "foot": .015,
             "upper_arm": .033, "forearm": .019, "hand": .006},
}
STIFFNESS_REFERENCE_MASS_KG = 70.45
DAMPING_RATIO = 15.0  # damping = 15 x stiffness (N m s / rad)
# Seed A.2 joint stiffness (N m / rad) of an average person. The seed's shoulder is one joint;
# J24 splits it 1/3 collar : 2/3 shoulder, so we use two springs in series, collar 12 and
# shoulder 6: together 4 N m/rad, and a load bends them 1 : 2 as the sampling split does.
JOINT_STIFFNESS = {
    "hip": 6.0, "knee": 3.0, "ankle": 6.0, "collar": 12.0, "shoulder": 6.0, "elbow": 2.0,
    "wrist": 4.0, "spine1": 200.0, "spine2": 200.0, "spine3": 200.0, "neck": 200.0, "head": 200.0,
}
# Joints of the capsule chain: every joint a capsule rides on, except the root.
CHAIN_JOINTS: tuple[int, ...] = tuple(j for j in CAPSULE_JOINTS if j != 0)
HINGE_JOINTS = {  # joint -> hinge axis in SMPL body axes (knees flex about x, elbows about y)
    _J("left_knee"): (1.0, 0.0, 0.0), _J("right_knee"): (1.0, 0.0, 0.0),
    _J("left_elbow"): (0.0, 1.0, 0.0), _J("right_elbow"): (0.0, 1.0, 0.0),
}


def home_pose(batch_size: int = 1, dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
    """(B, 23, 3) spring equilibrium: legs straight, arms down at the sides (seed A.2).

    Shoulders are bent 90 deg down about the body's front axis, split 1/3 collar, 2/3 shoulder
    (left arm: -z, right arm: +z)."""
    pose = torch.zeros(batch_size, NUM_POSE_JOINTS, 3, dtype=dtype, device=device)
    for side, sign in (("left", -1.0), ("right", 1.0)):
        pose[:, _J(f"{side}_collar") - 1, 2] = sign * math.pi / 6
        pose[:, _J(f"{side}_shoulder") - 1, 2] = sign * math.pi / 3
    return pose


@dataclasses.dataclass(frozen=True)
class Capsules:
    """Capsule geometry of B bodies in their T-pose, body axes, pelvis at the origin."""

    start: torch.Tensor   # (B, 20, 3) axis end points, metres
    end: torch.Tensor     # (B, 20, 3)
    radius: torch.Tensor  # (B, 20)
    rest: torch.Tensor    # (B, 24, 3) T-pose J24 joints the capsules ride on

    @property
    def batch_size(self) -> int:
        return self.radius.shape[0]

    @property
    def length(self) -> torch.Tensor:
        """(B, 20) axis length (capsule length minus the two caps)."""
        return (self.end - self.start).norm(dim=-1)

    def analytic_volume(self) -> torch.Tensor:
        """(B, 20) volume of each capsule alone, pi r^2 (L + 4 r / 3)."""
        r = self.radius
        return math.pi * r**2 * (self.length + 4.0 * r / 3.0)

    def posed(self, pose: torch.Tensor, root_rotation: torch.Tensor | None = None,
              root_translation: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Axis end points (B, 20, 3) x 2 for a (B, 23, 3) pose; with a root rotation
        ((B, 3) axis-angle on top of the supine reference) and translation they are in the
        mat frame, otherwise in body axes with the pelvis at the origin."""
        R0 = None if root_rotation is None else root_matrix(root_rotation)
        rot, pos = forward_kinematics(self.rest, pose, R0)
        return self.place(rot, pos, root_translation)

    def place(self, rot: torch.Tensor, pos: torch.Tensor,
              translation: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Capsule end points for given J24 world rotations (B, 24, 3, 3) and positions."""
        j = list(CAPSULE_JOINTS)
        R, p, r0 = rot[:, j], pos[:, j], self.rest[:, j]
        a = (R @ (self.start - r0)[..., None])[..., 0] + p
        b = (R @ (self.end - r0)[..., None])[..., 0] + p
        if translation is not None:
            a = a + translation[:, None]
            b = b + translation[:, None]
        return a, b


@dataclasses.dataclass(frozen=True)
class _CapsuleVertices:
    """What one capsule's fit reads of the T-pose mesh (for a LinearMesh backend)."""

    index: torch.Tensor        # (n,) vertices whose dominant part is one of the capsule's parts
    template: torch.Tensor     # (1, 3 n) their template positions, coordinate-major
    blendshapes: torch.Tensor  # (A, 3 n)
    bones: torch.Tensor        # (k,) bones that skin them
    weights: torch.Tensor      # (k, n - rigid) dense skinning weights of the vertices after the rigid ones
    rigid: int = 0             # the first `rigid` vertices ride bone bones[rigid_bone] alone (weight 1)
    rigid_bone: int = 0


_FIT_PLANS: weakref.WeakKeyDictionary[BodyModel, tuple] = weakref.WeakKeyDictionary()


def _fit_plan(model: BodyModel) -> list[torch.Tensor] | list[_CapsuleVertices]:
    """Per capsule, its vertex indices (any backend) or the slices of the linear mesh it
    needs (backends with `linear_mesh`); cached per model, dtype and device."""
    key = (model.dtype, model.device, model.part_labels.data_ptr())
    cached = _FIT_PLANS.get(model)
    if cached is not None and cached[0] == key:
        return cached[1]
    with torch.inference_mode(False):  # plain tensors even when first called in inference mode
        plan = _build_fit_plan(model)
    _FIT_PLANS[model] = (key, plan)
    return plan


def _build_fit_plan(model: BodyModel):
    labels = model.part_labels
    index = []
    for spec in CAPSULES:
        mask = torch.zeros_like(labels, dtype=torch.bool)
        for part in spec.parts:
            mask |= labels == part
        if not mask.any():
            raise ValueError(f"body model {model.name!r} has no vertices on the {spec.name} part; cannot fit its capsule")
        index.append(mask.nonzero()[:, 0])
    mesh = model.linear_mesh()
    if mesh is None:
        plan = index
    else:
        A = mesh.blendshapes.shape[0]
        W = mesh.skinning.to_dense()
        plan = []
        for idx in index:
            w = W[idx]  # (n, K)
            bones = (w != 0).any(0).nonzero()[:, 0]
            w = w[:, bones]
            # Vertices moved by one bone alone (most of the head): a rigid transform each, not
            # a blend over all the capsule's bones. Worth it where one bone carries many.
            alone = (w == 1).any(1)
            counts = torch.bincount(w[alone].argmax(1), minlength=bones.numel())
            rigid_bone = int(counts.argmax())
            rigid = alone & (w[:, rigid_bone] == 1)
            if int(rigid.sum()) < idx.numel() // 4:
                rigid[:] = False
            order = torch.cat([rigid.nonzero()[:, 0], (~rigid).nonzero()[:, 0]])
            idx, w = idx[order], w[order]
            n_rigid = int(rigid.sum())
            plan.append(_CapsuleVertices(
                index=idx,
                template=mesh.template[idx].T.reshape(1, -1).contiguous(),
                blendshapes=mesh.blendshapes[:, idx].permute(0, 2, 1).reshape(A, -1).contiguous(),
                bones=bones,
                weights=w[n_rigid:].T.contiguous(),
                rigid=n_rigid,
                rigid_bone=rigid_bone,
            ))
    return plan


# Elements per temporary in the fit: chunks of bodies small enough to stay in the CPU cache.
_FIT_CHUNK_ELEMENTS = 1 << 21


def fit_capsules(model: BodyModel, shape: torch.Tensor) -> Capsules:
    """Fit the 20 capsules to (B, S) shapes from the T-pose mesh and its part labels (every
    vertex: the extreme ones set the end caps).

    Each capsule reads only its own vertices, in its own frame (axis, two normals), as
    (B, 3, n) coordinate-major arrays. Backends with a linear rest mesh (Anny) build them
    capsule by capsule - blendshapes, then skinning by the few bones that move them, with the
    capsule's frame folded into the bone transforms - instead of skinning the whole mesh of
    every body at once (5.7 -> 1.5 ms per body at B = 64, one thread; the same result to
    float round-off)."""
    params = BodyParams.zeros(shape.shape[0], shape)
    model._check(params)
    plan = _fit_plan(model)
    B = shape.shape[0]
    linear = bool(plan) and isinstance(plan[0], _CapsuleVertices)
    if linear:
        skin = model._zero_pose_skinning(params.shape)
        joints = skin.joints
    else:
        all_vertices, joints = model._body_frame(params.shape, params.pose, with_vertices=True)
    rest = joints - joints[:, :1]
    start = rest.new_empty(B, NUM_CAPSULES, 3)
    end = rest.new_empty(B, NUM_CAPSULES, 3)
    radius = rest.new_empty(B, NUM_CAPSULES)
    for c, spec in enumerate(CAPSULES):
        # The capsule's frame Q = (u, n1, n2) (columns) and origin a0 (absolute body axes;
        # crosswise capsules: the pelvis, their centroid is found below).
        if spec.crosswise:
            Q = torch.eye(3, dtype=rest.dtype, device=rest.device).expand(B, 3, 3)
            origin = joints[:, 0]
            length = None
        else:
            if spec.name == "head":
                direction = rest[:, spec.joint] - rest[:, _J("neck")]
            else:
                direction = rest[:, spec.child] - rest[:, spec.joint]
            length = direction.norm(dim=-1)
            Q = _frame(direction / length[:, None])
            origin = joints[:, spec.joint]
        Qt = Q.transpose(1, 2)
        if linear:
            p = plan[c]
            n = p.index.shape[0]
            k = p.bones.shape[0]
            # Bone transforms into the capsule's frame: (B, k, 3, 4) = [T | t], and for the
            # blend (B, 12, k).
            aff4 = torch.cat([Qt[:, None] @ skin.transforms[:, p.bones],
                              (Qt[:, None] @ skin.translations[:, p.bones, :, None])], -1)
            aff = aff4.reshape(B, k, 12).transpose(1, 2).contiguous()
            off = (Qt @ origin[..., None])[..., 0]
            nr = p.rigid
        else:
            n = plan[c].shape[0]
        step = max(1, _FIT_CHUNK_ELEMENTS // (3 * n))
        for lo in range(0, B, step):
            hi = min(B, lo + step)
            Bc = hi - lo
            if linear:
                x = torch.addmm(p.template, skin.coeffs[lo:hi], p.blendshapes).view(Bc, 3, n)
                parts = []
                if nr:  # rigid vertices: T x + t - origin
                    A = aff4[lo:hi, p.rigid_bone]
                    parts.append(torch.baddbmm(A[:, :, 3:] - off[lo:hi, :, None], A[:, :, :3], x[:, :, :nr]))
                if nr < n:  # the others: blended transforms
                    bl = (aff[lo:hi].view(Bc * 12, k) @ p.weights).view(Bc, 3, 4, n - nr)
                    xs = x[:, None, :, nr:]
                    vs = bl[:, :, 3] - off[lo:hi, :, None]
                    vs.addcmul_(bl[:, :, 0], xs[:, :, 0]).addcmul_(bl[:, :, 1], xs[:, :, 1])
                    parts.append(vs.addcmul_(bl[:, :, 2], xs[:, :, 2]))
                v = torch.cat(parts, -1) if len(parts) > 1 else parts[0]
            else:
                v = Qt[lo:hi] @ (all_vertices[lo:hi, plan[c]] - origin[lo:hi, None]).transpose(1, 2)
            s_, e_, r_ = _fit_one(spec, v, None if length is None else length[lo:hi])
            # Back to body axes, pelvis at the origin.
            a0 = origin[lo:hi] - joints[lo:hi, 0]
            Qc = Q[lo:hi]
            start[lo:hi, c] = a0 + (Qc @ s_[..., None])[..., 0]
            end[lo:hi, c] = a0 + (Qc @ e_[..., None])[..., 0]
            radius[lo:hi, c] = r_
    return Capsules(start=start, end=end, radius=radius, rest=rest)


def _frame(u: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) orthonormal frames with first column u (B, 3) (unit)."""
    helper = torch.zeros_like(u)
    helper[:, 0] = torch.where(u[:, 0].abs() < 0.9, 1.0, 0.0)
    helper[:, 1] = 1.0 - helper[:, 0]
    n1 = torch.linalg.cross(u, helper, dim=-1)
    n1 = n1 / n1.norm(dim=-1, keepdim=True)
    n2 = torch.linalg.cross(u, n1, dim=-1)
    return torch.stack([u, n1, n2], -1)


def _fit_one(spec: CapsuleSpec, v: torch.Tensor, length: torch.Tensor | None):
    """One capsule from its vertices v (B, 3, n) in its frame: coordinate 0 along the axis
    from the capsule's joint (crosswise capsules: along body x, from the pelvis), 1 and 2
    across it; `length` (B,) the joint-to-child distance. Returns start (B, 3), end (B, 3)
    in the same frame, radius (B,)."""
    zero = v.new_zeros(v.shape[0], 3)
    if spec.crosswise:
        # Crosswise torso capsule through the part's centroid, along body x.
        centre = v.mean(-1)
        t = v[:, 0] - centre[:, :1]
        dist = torch.hypot(v[:, 1] - centre[:, 1:2], v[:, 2] - centre[:, 2:3])
        t_lo, t_hi = t.amin(1), t.amax(1)
        band_lo, band_hi = t_lo + 0.25 * (t_hi - t_lo), t_hi - 0.25 * (t_hi - t_lo)
    else:
        centre = zero
        t = v[:, 0]
        dist = torch.hypot(v[:, 1], v[:, 2])
        t_lo = t.amin(1) if spec.extend_start else torch.zeros_like(t[:, 0])
        t_hi = t.amax(1) if (spec.extend_end or spec.child is None) else length
        span = t_hi - t_lo
        band_lo, band_hi = t_lo + 0.2 * span, t_hi - 0.2 * span
    # Radius: median distance to the axis of the vertices in the middle of the segment (the
    # joint regions are shared with neighbours).
    in_band = (t >= band_lo[:, None]) & (t <= band_hi[:, None])
    in_band |= ~in_band.any(1, keepdim=True)  # a part with no vertex mid-segment: use them all
    r = torch.where(in_band, dist, torch.full_like(dist, float("nan"))).nanmedian(1).values
    if spec.crosswise:
        half = ((t_hi - t_lo) / 2 - r).clamp_min(0.0)
        mid = centre.clone()
        mid[:, 0] += (t_hi + t_lo) / 2
        s, e = mid.clone(), mid.clone()
        s[:, 0] -= half
        e[:, 0] += half
        return s, e, r
    # Ends: a capsule ending at a joint stops there (its cap covers the joint); an extended
    # end stops one radius before the last vertex so the cap just covers it.
    lo = (t_lo + r) if spec.extend_start else t_lo
    hi = (t_hi - r) if (spec.extend_end or spec.child is None) else t_hi
    lo = torch.minimum(lo, torch.zeros_like(lo)) if spec.extend_start else lo
    hi = torch.maximum(hi, lo)
    s, e = zero.clone(), zero.clone()
    s[:, 0], e[:, 0] = lo, hi
    return s, e, r


# --- geometry -------------------------------------------------------------------------------
def point_segment_distance(x: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Distance from points x (..., 3) to segments [a, b] (..., 3) (broadcast)."""
    d = b - a
    dd = (d * d).sum(-1)
    t = ((x - a) * d).sum(-1) / torch.where(dd > 0, dd, torch.ones_like(dd))
    t = t.clamp(0.0, 1.0)
    return (x - (a + t[..., None] * d)).norm(dim=-1)


def segment_distance(p1: torch.Tensor, q1: torch.Tensor, p2: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """Shortest distance between segments [p1, q1] and [p2, q2], (..., 3) each, broadcast.

    Closest points by clamping the line parameters (Ericson, Real-Time Collision Detection
    5.1.9), vectorised; degenerate (point-like) segments are handled.
    """
    eps = 1e-12
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a = (d1 * d1).sum(-1)
    e = (d2 * d2).sum(-1)
    f = (d2 * r).sum(-1)
    c = (d1 * r).sum(-1)
    b = (d1 * d2).sum(-1)
    denom = a * e - b * b
    safe = lambda z: torch.where(z > eps, z, torch.ones_like(z))  # noqa: E731
    # s on segment 1 from the lines' closest points (0 if parallel), then t, then re-clamp s.
    s = torch.where(denom > eps * a * e + eps, ((b * f - c * e) / safe(denom)).clamp(0, 1), torch.zeros_like(a))
    t = (b * s + f) / safe(e)
    s = torch.where(t < 0, (-c / safe(a)).clamp(0, 1), torch.where(t > 1, ((b - c) / safe(a)).clamp(0, 1), s))
    t = t.clamp(0, 1)
    # Degenerate segments.
    s = torch.where(a <= eps, torch.zeros_like(s), s)
    t = torch.where(e <= eps, torch.zeros_like(t), torch.where(a <= eps, (f / safe(e)).clamp(0, 1), t))
    s = torch.where((e <= eps) & (a > eps), (-c / safe(a)).clamp(0, 1), s)
    c1 = p1 + s[..., None] * d1
    c2 = p2 + t[..., None] * d2
    return (c1 - c2).norm(dim=-1)


def capsule_clearance(start: torch.Tensor, end: torch.Tensor, radius: torch.Tensor,
                      pairs: torch.Tensor) -> torch.Tensor:
    """(B, P) gap between the surfaces of capsule pairs (negative = interpenetrating)."""
    i, j = pairs[:, 0], pairs[:, 1]
    d = segment_distance(start[:, i], end[:, i], start[:, j], end[:, j])
    return d - radius[:, i] - radius[:, j]


# --- volumes --------------------------------------------------------------------------------
_QMC_CACHE: dict[tuple[int, torch.dtype], torch.Tensor] = {}


def _sobol(n: int, dtype: torch.dtype) -> torch.Tensor:
    key = (n, dtype)
    if key not in _QMC_CACHE:
        engine = torch.quasirandom.SobolEngine(3, scramble=True, seed=20200601)
        _QMC_CACHE[key] = engine.draw(n, dtype=torch.float64).to(dtype)
    return _QMC_CACHE[key]


def overlap_pairs(caps: Capsules) -> torch.Tensor:
    """(P, 2) ordered pairs (c, d), c != d, of capsules that intersect in any of the bodies."""
    i, j = torch.triu_indices(NUM_CAPSULES, NUM_CAPSULES, 1)
    pairs = torch.stack([i, j], -1)
    hit = (capsule_clearance(caps.start, caps.end, caps.radius, pairs) < 0).any(0)
    pairs = pairs[hit.cpu()]
    return torch.cat([pairs, pairs.flip(-1)], 0)


def _containing(points: torch.Tensor, owner: torch.Tensor, caps: Capsules, pairs: torch.Tensor) -> torch.Tensor:
    """Number of capsules containing points (B, C, N, 3) that lie in capsules `owner` (C,):
    1 (the owner) plus the overlapping capsules of `pairs` that contain them. (B, C, N)."""
    count = torch.ones(points.shape[:3], dtype=points.dtype, device=points.device)
    for slot, c in enumerate(owner.tolist()):
        others = pairs[pairs[:, 0] == c, 1]
        if others.numel() == 0:
            continue
        d = point_segment_distance(points[:, slot, :, None], caps.start[:, None, others], caps.end[:, None, others])
        count[:, slot] += (d <= caps.radius[:, None, others]).sum(-1).to(points.dtype)
    return count


def capsule_volumes(caps: Capsules, method: str = "qmc", resolution: float = 0.002,
                    points: int = 8192) -> torch.Tensor:
    """(B, 20) capsule volumes (m^3) with overlaps shared fractionally (seed A.2).

    method "voxel": voxel centres on a `resolution` grid (the seed's 2 mm), each voxel split
    equally between the capsules that contain it. method "qmc" (default): exact capsule volume
    times the mean of 1/n(x) over `points` fixed Sobol points inside the capsule (cylinder and
    caps integrated separately).
    """
    if method == "voxel":
        return _voxel_volumes(caps, resolution)
    if method != "qmc":
        raise ValueError(f"unknown volume method {method!r}; expected 'qmc' or 'voxel'")
    u = _sobol(points, caps.radius.dtype).to(caps.radius.device)
    a, b, r = caps.start, caps.end, caps.radius
    axis = b - a
    L = axis.norm(dim=-1)
    w = axis / L.clamp_min(1e-12)[..., None]
    # An orthonormal frame (w, e1, e2) per capsule.
    helper = torch.where((w[..., :1].abs() < 0.9), torch.tensor([1.0, 0, 0], dtype=w.dtype, device=w.device),
                         torch.tensor([0, 1.0, 0], dtype=w.dtype, device=w.device))
    e1 = torch.linalg.cross(w, helper, dim=-1)
    e1 = e1 / e1.norm(dim=-1, keepdim=True)
    e2 = torch.linalg.cross(w, e1, dim=-1)
    # Cylinder: rho = r sqrt(u0), phi = 2 pi u1, z = L u2.  Ball: radius r u0^(1/3), direction
    # from (u1, u2); its lower half sits on the start cap, its upper half on the end cap.
    rho, phi = u[:, 0].sqrt(), 2 * math.pi * u[:, 1]
    cyl = torch.stack([rho * phi.cos(), rho * phi.sin(), u[:, 2]], -1)  # unit radius/length
    rb = u[:, 0].pow(1 / 3)
    cz = 1 - 2 * u[:, 1]
    sz = (1 - cz**2).clamp_min(0).sqrt()
    ph2 = 2 * math.pi * u[:, 2]
    ball = torch.stack([rb * sz * ph2.cos(), rb * sz * ph2.sin(), rb * cz], -1)

    def to_world(z, x1, x2):  # (B, 20, N) each -> (B, 20, N, 3)
        return (a[:, :, None] + z[..., None] * w[:, :, None]
                + x1[..., None] * e1[:, :, None] + x2[..., None] * e2[:, :, None])

    rr = r[..., None]
    cyl_pts = to_world(cyl[:, 2] * L[..., None], cyl[:, 0] * rr, cyl[:, 1] * rr)
    upper = (ball[:, 2] > 0).to(r.dtype)
    ball_pts = to_world(ball[:, 2] * rr + upper * L[..., None], ball[:, 0] * rr, ball[:, 1] * rr)
    pairs = overlap_pairs(caps)
    owner = torch.arange(NUM_CAPSULES)
    inv = [(1.0 / _containing(pts, owner, caps, pairs)).mean(-1) for pts in (cyl_pts, ball_pts)]
    v_cyl = math.pi * r**2 * L
    v_ball = 4.0 / 3.0 * math.pi * r**3
    return v_cyl * inv[0] + v_ball * inv[1]


def _voxel_volumes(caps: Capsules, h: float) -> torch.Tensor:
    if not h > 0:
        raise ValueError(f"voxel resolution must be > 0, got {h}")
    out = torch.zeros_like(caps.radius)
    lo_all = torch.minimum(caps.start, caps.end) - caps.radius[..., None]
    hi_all = torch.maximum(caps.start, caps.end) + caps.radius[..., None]
    for bi in range(caps.batch_size):
        c1 = Capsules(caps.start[bi:bi + 1], caps.end[bi:bi + 1], caps.radius[bi:bi + 1], caps.rest[bi:bi + 1])
        pairs = overlap_pairs(c1)
        origin = lo_all[bi].amin(0)
        for c in range(NUM_CAPSULES):
            # Voxel centres of one global grid inside this capsule's bounding box.
            i0 = torch.floor((lo_all[bi, c] - origin) / h).long()
            i1 = torch.ceil((hi_all[bi, c] - origin) / h).long()
            axes = [origin[k] + (torch.arange(i0[k], i1[k] + 1, dtype=caps.radius.dtype) + 0.5) * h for k in range(3)]
            for xs in axes[0].split(max(1, 2_000_000 // (len(axes[1]) * len(axes[2])))):
                grid = torch.stack(torch.meshgrid(xs, axes[1], axes[2], indexing="ij"), -1).reshape(-1, 3)
                pts = grid[point_segment_distance(grid, c1.start[0, c], c1.end[0, c]) <= c1.radius[0, c]]
                if pts.shape[0]:
                    n = _containing(pts[None, None], torch.tensor([c]), c1, pairs)
                    out[bi, c] += (1.0 / n).sum() * h**3
    return out


# --- the physical body ----------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class CapsuleBody:
    """Everything sim #1 needs about B capsulised bodies (SI units, body axes, T-pose)."""

    capsules: Capsules
    volume_m3: torch.Tensor       # (B, 20) shared volume
    mass_kg: torch.Tensor         # (B, 20)
    inertia: torch.Tensor         # (B, 20, 3) principal moments about the centre (axis, perp, perp)
    stiffness: torch.Tensor       # (B, 23) N m / rad per J24 pose joint (0: not a chain joint)
    damping: torch.Tensor         # (B, 23) N m s / rad
    home_pose: torch.Tensor       # (B, 23, 3) spring equilibrium
    body_mass_kg: torch.Tensor    # (B,) = mass_kg.sum(-1)


def capsule_inertia(mass: torch.Tensor, radius: torch.Tensor, length: torch.Tensor) -> torch.Tensor:
    """(..., 3) principal moments (axial, transverse, transverse) of solid capsules of uniform
    density, about their centre: cylinder + two hemispherical caps."""
    vc = math.pi * radius**2 * length
    vs = 4.0 / 3.0 * math.pi * radius**3
    mc = mass * vc / (vc + vs)
    ms = mass - mc
    axial = mc * radius**2 / 2 + ms * 2 * radius**2 / 5
    perp = mc * (radius**2 / 4 + length**2 / 12) + ms * (2 * radius**2 / 5 + length**2 / 4 + 3 * length * radius / 8)
    return torch.stack([axial, perp, perp], -1)


def female_fraction(model: BodyModel, shape: torch.Tensor) -> torch.Tensor:
    """(B,) 1 for female, 0 for male bodies (Anny's gender phenotype; SMPL's model gender,
    0.5 for the neutral model)."""
    if model.name == "anny":
        return shape[:, 0]
    gender = getattr(model, "gender", "neutral")
    value = {"female": 1.0, "male": 0.0}.get(gender, 0.5)
    return torch.full((shape.shape[0],), value, dtype=shape.dtype, device=shape.device)


def _segment_table(female: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-capsule segment fraction X_R,g (B, 20) (blended by gender) and segment ids (20,)."""
    segments = sorted({c.segment for c in CAPSULES})
    seg_id = torch.tensor([segments.index(c.segment) for c in CAPSULES])
    f = torch.tensor([SEGMENT_FRACTIONS["female"][c.segment] for c in CAPSULES], dtype=female.dtype, device=female.device)
    m = torch.tensor([SEGMENT_FRACTIONS["male"][c.segment] for c in CAPSULES], dtype=female.dtype, device=female.device)
    return female[:, None] * f + (1 - female[:, None]) * m, seg_id.to(female.device)


def build_capsule_body(model: BodyModel, shape: torch.Tensor, volume_method: str = "qmc",
                       volume_points: int = 8192, one_by_one: bool = False) -> CapsuleBody:
    """Capsules, masses (seed eq. 11-12, summing to the body model's mass), inertia, joint
    stiffness and damping for (B, S) shapes. `volume_points`: Sobol points per capsule for the
    "qmc" shared volumes (2048 changes a capsule's volume by at most 0.3% against 8192 and
    costs a quarter; sim #1 uses it).

    one_by_one: build every body from its own shape alone (and the average body of each
    gender alone), so a body's numbers depend on its shape only. Batched, they also depend,
    in the last bits (~1e-16 relative), on the other shapes in the batch: torch picks matrix
    kernels by size. Sim #1 builds one by one (`settle`), ~2x the cost of a batched build."""
    model.validate_shape(shape)
    B = shape.shape[0]
    if not one_by_one or B == 0:
        return _build(model, shape, volume_method, volume_points, None)
    cache: dict = {}
    parts = [_build(model, shape[i : i + 1], volume_method, volume_points, cache) for i in range(B)]
    return _concat_bodies(parts)


def _build(model: BodyModel, shape: torch.Tensor, volume_method: str, volume_points: int,
           avg_cache: dict | None) -> CapsuleBody:
    """build_capsule_body of a batch; avg_cache (one-by-one builds): the average bodies'
    capsule volumes by shape, each computed alone."""
    caps = fit_capsules(model, shape)
    volume = capsule_volumes(caps, method=volume_method, points=volume_points)
    female = female_fraction(model, shape)
    # The average person of the same gender (seed: beta = 0): the backend's default shape.
    average_shape = model.default_shape(shape.shape[0])
    if model.name == "anny":
        average_shape[:, 0] = shape[:, 0]
    # One average body per distinct gender (datasets use exactly 0 and 1), not one per body.
    unique, inverse = torch.unique(average_shape, dim=0, return_inverse=True)
    if avg_cache is None:
        avg_volume = capsule_volumes(fit_capsules(model, unique), method=volume_method, points=volume_points)
    else:
        rows = []
        for u in unique:
            key = tuple(u.tolist())
            if key not in avg_cache:
                avg_cache[key] = capsule_volumes(fit_capsules(model, u[None]), method=volume_method,
                                                 points=volume_points)[0]
            rows.append(avg_cache[key])
        avg_volume = torch.stack(rows)
    avg_volume = avg_volume[inverse]
    fraction, seg_id = _segment_table(female)
    # V_R,g of the average body: sum of its capsule volumes over each segment (per side for
    # limbs: a left and a right segment are separate parts, each with fraction X_R).
    side = torch.tensor([0 if c.segment in ("trunk", "head") else (1 if c.name.startswith("left_") else 2)
                         for c in CAPSULES], device=shape.device)
    group = seg_id * 3 + side
    part_volume = torch.zeros(shape.shape[0], int(group.max()) + 1, dtype=volume.dtype, device=volume.device)
    part_volume.index_add_(1, group, avg_volume)
    raw = fraction * volume / part_volume[:, group]  # eq. 11-12 up to the factor m_g
    body_mass = model.measure(shape).mass_kg
    mass = raw * (body_mass / raw.sum(-1))[:, None]
    inertia = capsule_inertia(mass, caps.radius, caps.length)
    # Stiffness per J24 pose joint, scaled by the mass ratio; joints off the chain get 0.
    base = torch.zeros(NUM_POSE_JOINTS, dtype=shape.dtype, device=shape.device)
    for j in CHAIN_JOINTS:
        name = J24_NAMES[j].removeprefix("left_").removeprefix("right_")
        base[j - 1] = JOINT_STIFFNESS[name]
    stiffness = base[None] * (body_mass / STIFFNESS_REFERENCE_MASS_KG)[:, None]
    return CapsuleBody(
        capsules=caps, volume_m3=volume, mass_kg=mass, inertia=inertia, stiffness=stiffness,
        damping=DAMPING_RATIO * stiffness, home_pose=home_pose(shape.shape[0], shape.dtype, shape.device),
        body_mass_kg=mass.sum(-1),
    )


def _concat_bodies(parts: list[CapsuleBody]) -> CapsuleBody:
    def cat(objs):
        return type(objs[0])(**{f.name: cat([getattr(o, f.name) for o in objs])
                                if dataclasses.is_dataclass(getattr(objs[0], f.name))
                                else torch.cat([getattr(o, f.name) for o in objs])
                                for f in dataclasses.fields(objs[0])})
    return cat(parts)


__all__ = [
    "CAPSULES", "CAPSULE_NAMES", "CAPSULE_PARENTS", "CapsuleBody", "Capsules", "DISTAL_CAPSULES",
    "NUM_CAPSULES", "build_capsule_body", "capsule_clearance", "capsule_inertia", "capsule_volumes",
    "collision_pairs", "fit_capsules", "home_pose", "segment_distance",
]
