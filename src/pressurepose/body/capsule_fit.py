"""Capsules fitted per shape to the T-pose mesh and its part labels (`body.capsules`)."""

from __future__ import annotations

import dataclasses
import math
import weakref

import torch

from pressurepose.body.capsule_layout import (
    CAPSULE_JOINTS,
    CAPSULES,
    NUM_CAPSULES,
    CapsuleSpec,
)
from pressurepose.body.joints import J24_NAMES
from pressurepose.body.kinematics import forward_kinematics
from pressurepose.body.model import BodyModel
from pressurepose.body.params import BodyParams, root_matrix

_J = J24_NAMES.index


@dataclasses.dataclass(frozen=True)
class Capsules:
    """Capsule geometry of B bodies in their T-pose, body axes, pelvis at the origin."""

    start: torch.Tensor  # (B, 20, 3) axis end points, metres
    end: torch.Tensor  # (B, 20, 3)
    radius: torch.Tensor  # (B, 20)
    rest: torch.Tensor  # (B, 24, 3) T-pose J24 joints the capsules ride on

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

    def posed(
        self,
        pose: torch.Tensor,
        root_rotation: torch.Tensor | None = None,
        root_translation: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Axis end points (B, 20, 3) x 2 for a (B, 23, 3) pose; with a root rotation
        ((B, 3) axis-angle on top of the supine reference) and translation they are in the
        mat frame, otherwise in body axes with the pelvis at the origin."""
        R0 = None if root_rotation is None else root_matrix(root_rotation)
        rot, pos = forward_kinematics(self.rest, pose, R0)
        return self.place(rot, pos, root_translation)

    def place(
        self, rot: torch.Tensor, pos: torch.Tensor, translation: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
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

    index: torch.Tensor  # (n,) vertices whose dominant part is one of the capsule's parts
    template: torch.Tensor  # (1, 3 n) their template positions, coordinate-major
    blendshapes: torch.Tensor  # (A, 3 n)
    bones: torch.Tensor  # (k,) bones that skin them
    weights: torch.Tensor  # (k, n - rigid) dense skinning weights of the vertices after the rigid ones
    rigid: int = 0  # the first `rigid` vertices ride bone bones[rigid_bone] alone (weight 1)
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
            raise ValueError(
                f"body model {model.name!r} has no vertices on the {spec.name} part; cannot fit its capsule"
            )
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
            plan.append(
                _CapsuleVertices(
                    index=idx,
                    template=mesh.template[idx].T.reshape(1, -1).contiguous(),
                    blendshapes=mesh.blendshapes[:, idx].permute(0, 2, 1).reshape(A, -1).contiguous(),
                    bones=bones,
                    weights=w[n_rigid:].T.contiguous(),
                    rigid=n_rigid,
                    rigid_bone=rigid_bone,
                )
            )
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
    model.check_params(params)
    plan = _fit_plan(model)
    B = shape.shape[0]
    linear = bool(plan) and isinstance(plan[0], _CapsuleVertices)
    if linear:
        skin = model.zero_pose_skinning(params.shape)
        joints = skin.joints
    else:
        all_vertices, joints = model.body_frame(params.shape, params.pose, with_vertices=True)
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
            aff4 = torch.cat(
                [Qt[:, None] @ skin.transforms[:, p.bones], (Qt[:, None] @ skin.translations[:, p.bones, :, None])], -1
            )
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
    out_band = (t < band_lo[:, None]).logical_or_(t > band_hi[:, None])
    out_band &= ~out_band.all(1, keepdim=True)  # a part with no vertex mid-segment: use them all
    # (dist is this call's own: filled in place unless autograd needs it as it is)
    fill = dist.masked_fill if dist.requires_grad else dist.masked_fill_
    r = fill(out_band, float("nan")).nanmedian(1).values
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
