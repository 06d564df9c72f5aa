"""Anny (PyPI `anny`, Apache-2.0 code, CC0 data): the default, embedded body model.

Anny's rig has 104 bones in metres, Z up, facing -Y, `.L` bones on +X; its identity pose is
a reference A-pose (upper arms ~49 deg down, elbows ~40 deg bent forward). pressurepose
parameters are SMPL-style (docs/conventions.md): J24 rotations in SMPL's body axes relative
to a T-pose. The bridge, per bone b with J24 rotation R_b (identity for unmapped bones):

    anny_local_b = G_parent(b)^T  (C R_b C^T)  G_b

where C maps SMPL's axes to Anny's and G_b rotates bone b from Anny's reference pose into the
T-pose (identity except on the arms: G = the smallest rotation laying the upper arm, then the
forearm, along +-x). G depends on the shape, so it is recomputed per sample from the rest
skeleton. The elbow rotation is split into swing (on `lowerarm01`) and twist about the forearm
(on `lowerarm02`), because twisting `lowerarm01` kinks the elbow.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import io
import logging

import numpy as np
import torch

from pressurepose.body.anny_inference import AnnyInference
from pressurepose.body.anny_phenotype import phenotype_coefficients
from pressurepose.body.anny_skeleton import Skeleton
from pressurepose.body.anny_skinning import skin_matrix, sparse_linear_blend_skinning
from pressurepose.body.joints import J24_NAMES, NUM_JOINTS
from pressurepose.body.model import BodyModel, LinearMesh, ZeroPoseSkinning, part_weights_onto_j24
from pressurepose.body.params import all_finite
from pressurepose.body.procrustes import nearest_rotation
from pressurepose.body.rotations import axis_angle_to_matrix, rotation_between, swing_twist
from pressurepose.body.shape_ranges import anny_bounds, anny_powers
from pressurepose.cache import cache_dir, file_lock

log = logging.getLogger(__name__)

ANNY_SHAPE_NAMES = ("gender", "age", "muscle", "weight", "height", "proportions")
# gender 0 = male, 1 = female; age 0.667 = young adult, 1 = old (Anny's anchors).
ANNY_DEFAULT_SHAPE = (0.5, 0.75, 0.5, 0.5, 0.5, 0.5)
DEFAULT_TOPOLOGY = "anny-noeyes-notongue"  # one watertight part: exact volumes, no eyeballs

# SMPL body axes -> Anny axes: x stays the left, SMPL's up (y) is Anny's +z, front (z) is -y.
C_SMPL_TO_ANNY = ((1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0))


# J24 joint -> Anny bones whose head gives its position (averaged).
_POSITION_BONES: dict[str, list[str]] = {
    "pelvis": ["root"],
    "spine1": ["spine04"],
    "spine2": ["spine02"],
    "spine3": ["spine01"],
    "neck": ["neck01"],
    "head": ["head"],
}
# J24 joint -> Anny bones that take its rotation.
_ROTATION_BONES: dict[str, list[str]] = {
    "spine1": ["spine04"],
    "spine2": ["spine02"],
    "spine3": ["spine01"],
    "neck": ["neck01"],
    "head": ["head"],
}
for _side, _s in (("left", "L"), ("right", "R")):
    _pos = {
        "hip": [f"upperleg01.{_s}"],
        "knee": [f"lowerleg01.{_s}"],
        "ankle": [f"foot.{_s}"],
        "foot": [f"toe{i}-1.{_s}" for i in range(1, 6)],
        "collar": [f"clavicle.{_s}"],
        "shoulder": [f"upperarm01.{_s}"],
        "elbow": [f"lowerarm01.{_s}"],
        "wrist": [f"wrist.{_s}"],
        "hand": [f"finger{i}-1.{_s}" for i in range(2, 6)],
    }
    for _joint, _bones in _pos.items():
        _POSITION_BONES[f"{_side}_{_joint}"] = _bones
        _ROTATION_BONES[f"{_side}_{_joint}"] = list(_bones)
    # Hands flex every finger, thumb included; elbows are handled by swing/twist.
    _ROTATION_BONES[f"{_side}_hand"] = [f"finger{i}-1.{_s}" for i in range(1, 6)]
    del _ROTATION_BONES[f"{_side}_elbow"]


def load_anny(topology: str = DEFAULT_TOPOLOGY):
    """Anny model (float64, CPU) from the project cache, building the cache on first use.

    The build (about a minute, ~2 GB of RAM, ~0.8 GB written) leaves a ~50 MB compact file;
    the intermediate files are deleted afterwards. A lock lets parallel processes wait for
    one build instead of racing.
    """
    import anny
    import anny.paths

    root = cache_dir() / "anny"
    anny.paths.set_anny_cache_path(root)
    stamp = root / f"ready-{topology}-anny{importlib.metadata.version('anny')}"
    with file_lock(root / ".lock"):
        if not stamp.exists():
            log.warning(
                "Building the Anny body-model cache in %s (first use only: about a minute "
                "and 2 GB of RAM; set PRESSUREPOSE_CACHE to put it elsewhere)",
                root,
            )
        with contextlib.redirect_stdout(io.StringIO()):  # Anny and Warp print banners on stdout
            model = anny.Anny(topology=topology, skinning_method="lbs")
        if not stamp.exists():
            for pattern in ("*/build_model_data_*", "*/load_data_*"):
                for path in root.glob(pattern):
                    path.unlink()  # only the compact file is read afterwards
            stamp.touch()
    return model


class AnnyBody(AnnyInference, BodyModel):
    """Anny behind the BodyModel interface. Shape = 6 phenotypes in [0, 1]."""

    name = "anny"
    shape_names = ANNY_SHAPE_NAMES

    def __init__(
        self,
        topology: str = DEFAULT_TOPOLOGY,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str = "cpu",
    ) -> None:
        super().__init__()
        model = load_anny(topology)
        if list(model.phenotype_labels) != list(ANNY_SHAPE_NAMES):
            raise RuntimeError(f"unexpected Anny phenotypes {model.phenotype_labels}")
        self.anny = model
        self.topology = topology
        labels = list(model.bone_labels)
        self.bone_labels = labels
        idx = labels.index

        # J24 positions as an average of bone heads: (24, num_bones) regressor.
        regressor = torch.zeros(NUM_JOINTS, len(labels), dtype=torch.float64)
        for j, name in enumerate(J24_NAMES):
            bones = _POSITION_BONES[name]
            for bone in bones:
                regressor[j, idx(bone)] = 1.0 / len(bones)
        self.register_buffer("joint_regressor", regressor, persistent=False)

        # Which J24 rotation drives each bone (-1: none).
        driver = torch.full((len(labels),), -1, dtype=torch.long)
        for j, name in enumerate(J24_NAMES):
            for bone in _ROTATION_BONES.get(name, []):
                driver[idx(bone)] = j
        self.register_buffer("bone_driver", driver, persistent=False)

        # Bones needed for J24 alone (ancestors of the position bones and the arm chains).
        needed = {b for name in J24_NAMES for b in map(idx, _POSITION_BONES[name])}
        needed |= {idx(f"{bone}.{s}") for s in "LR" for bone in ("lowerarm02", "wrist")}
        closure = set()
        for b in needed:
            while b >= 0 and b not in closure:
                closure.add(b)
                b = model.bone_parents[b] if b else -1
        self.full = Skeleton(list(range(len(labels))), model.bone_parents, labels)
        self.light = Skeleton(sorted(closure), model.bone_parents, labels)
        self.register_buffer("reference_orientations", model.reference_bone_orientations.clone(), persistent=False)
        self.register_buffer(
            "skin_matrix",
            skin_matrix(model.vertex_bone_weights, model.vertex_bone_indices, len(model.bone_labels)),
            persistent=False,
        )

        # Body part of each bone: the J24 joint of its nearest mapped ancestor (or itself).
        part_of_bone = torch.zeros(len(labels), dtype=torch.long)
        owner = {b: j for j, name in enumerate(J24_NAMES) for b in map(idx, _POSITION_BONES[name])}
        owner[idx("lowerarm02.L")] = J24_NAMES.index("left_elbow")
        owner[idx("lowerarm02.R")] = J24_NAMES.index("right_elbow")
        for b in range(len(labels)):
            a = b
            while a not in owner:
                a = model.bone_parents[a]
            part_of_bone[b] = owner[a]
        weights = part_weights_onto_j24(model.vertex_bone_weights, model.vertex_bone_indices, part_of_bone)
        self.register_buffer("skinning_weights", weights, persistent=False)
        self.register_buffer("part_labels", weights.argmax(-1), persistent=False)
        self.register_buffer("faces", model.faces.long().clone(), persistent=False)
        self.register_buffer("c_smpl_to_anny", torch.tensor(C_SMPL_TO_ANNY, dtype=torch.float64), persistent=False)
        self.to(dtype=dtype, device=device)

    # --- shape ----------------------------------------------------------------------------
    def default_shape(self, batch_size: int = 1) -> torch.Tensor:
        return torch.tensor(ANNY_DEFAULT_SHAPE, dtype=self.dtype, device=self.device).expand(batch_size, -1).clone()

    @classmethod
    def shape_bounds(cls, gender: str, shape_names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        return anny_bounds(gender, shape_names)

    @classmethod
    def shape_powers(cls, shape_names: tuple[str, ...]) -> np.ndarray:
        return anny_powers(shape_names)

    def female_fraction(self, shape: torch.Tensor) -> torch.Tensor:
        return shape[:, ANNY_SHAPE_NAMES.index("gender")]  # Anny's gender phenotype: 1 female

    def average_shape(self, female: torch.Tensor) -> torch.Tensor:
        shape = self.default_shape(female.shape[0])
        shape[:, ANNY_SHAPE_NAMES.index("gender")] = female
        return shape

    size_dim = 3  # height, weight, muscle, each a sigmoid into [0, 1]

    def with_size(self, shape: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        sized = shape.clone()
        sized[:, [ANNY_SHAPE_NAMES.index(n) for n in ("height", "weight", "muscle")]] = torch.sigmoid(z)
        return sized

    def shape_from_dict(self, values: dict[str, float], batch_size: int = 1) -> torch.Tensor:
        """(B, 6) shape from phenotype names; the others take the default adult's value."""
        unknown = set(values) - set(ANNY_SHAPE_NAMES)
        if unknown:
            raise ValueError(
                f"unknown phenotype name(s) {sorted(unknown)}; expected some of {', '.join(ANNY_SHAPE_NAMES)}"
            )
        shape = self.default_shape(batch_size)
        for name, value in values.items():
            shape[:, ANNY_SHAPE_NAMES.index(name)] = torch.as_tensor(value, dtype=self.dtype)
        self.validate_shape(shape)
        return shape

    def validate_shape(self, shape: torch.Tensor) -> None:
        if not all_finite(shape):
            raise ValueError("shape (Anny phenotypes) contains NaN or infinite values")
        lo, hi = (float(v) for v in torch.aminmax(shape.detach()))
        if lo < 0 or hi > 1:
            bad = ((shape < 0) | (shape > 1)).any(0).nonzero().flatten().tolist()
            names = ", ".join(ANNY_SHAPE_NAMES[i] for i in bad)
            raise ValueError(
                f"shape (Anny phenotypes) must lie in [0, 1]; {names} out of range (min {lo:.3g}, max {hi:.3g})"
            )

    # --- skeleton -------------------------------------------------------------------------
    def _coefficients(self, shape: torch.Tensor) -> torch.Tensor:
        return phenotype_coefficients(self.anny, shape, self.__dict__)

    def _rest_skeleton(self, coeffs: torch.Tensor, sk: Skeleton) -> tuple[torch.Tensor, torch.Tensor]:
        """Rest bone heads (B, n, 3) and orientations (B, n, 3, 3) of the bones `sk.bones`,
        computed without the rest mesh (Anny's 'cached' orientation: a special Procrustes of
        a cross-covariance that is linear in the blendshape coefficients)."""
        m = self.anny
        bones = slice(None) if sk is self.full else sk.bones  # the full skeleton: views, no gathers
        heads = m.template_bone_heads[bones] + torch.einsum("ba,akx->bkx", coeffs, m.bone_heads_blendshapes[:, bones])
        M = m.bone_template_orientation_matrices[bones] + torch.einsum(
            "ba,akij->bkij", coeffs, m.bone_orientation_blendshapes[:, bones]
        )
        R = nearest_rotation(M[:, 1:])  # roma.special_procrustes's numbers; roma itself under autograd
        eye = torch.eye(3, dtype=R.dtype, device=R.device).expand(R.shape[0], 1, 3, 3)
        return heads, torch.cat([eye, R], 1)  # the root keeps an identity rest orientation

    def _reference_offsets(self, heads, R, sk):
        """A_b = U_b R_b^T (rest -> reference rotation) and each bone's head offset from its
        parent's head in Anny's reference pose, (B, n, 3)."""
        A = self.reference_orientations[sk.bones] @ R.transpose(-1, -2)
        offsets = (A[:, sk.parents] @ (heads - heads[:, sk.parents])[..., None])[..., 0]
        return A, offsets

    def _t_pose_corrections(self, offsets: torch.Tensor, sk: Skeleton) -> torch.Tensor:
        """(B, n, 3, 3) G_b: Anny's reference pose -> T-pose, per bone (Anny axes); both arms at once."""
        B = offsets.shape[0]
        target = offsets.new_tensor([[arm["sign"], 0.0, 0.0] for arm in sk.arms]).expand(B, -1, -1)
        upper = offsets[:, [arm["upper_chain"] for arm in sk.arms]].sum(2)  # (B, arms, 3) shoulder -> elbow
        fore = offsets[:, [arm["fore_chain"] for arm in sk.arms]].sum(2)  # elbow -> wrist
        G_upper = rotation_between(upper, target)
        G_fore = rotation_between((G_upper @ fore[..., None])[..., 0], target) @ G_upper
        eye = torch.eye(3, dtype=offsets.dtype, device=offsets.device).expand(B, 1, 3, 3)
        return torch.cat([eye, G_upper, G_fore], 1)[:, sk.correction_source]

    def _local_rotations(self, pose: torch.Tensor, G: torch.Tensor, sk: Skeleton) -> torch.Tensor:
        """J24 pose (B, 23, 3) in SMPL axes -> Anny local-ref rotations (B, n, 3, 3).

        C R(r) C^T = R(C r) (C = c_smpl_to_anny, a proper rotation): the rotation vectors and
        the elbows' twist axis are turned into Anny's axes before the matrices are made."""
        B = pose.shape[0]
        C = self.c_smpl_to_anny
        pose = pose @ C.T  # Anny axes
        eye = torch.eye(3, dtype=pose.dtype, device=pose.device)
        R_all = torch.cat([eye.expand(B, 1, 3, 3), axis_angle_to_matrix(pose)], 1)  # J24-indexed
        R = R_all[:, self.bone_driver[sk.bones].clamp(min=0)]  # a bone no joint drives: J24's root, I
        elbows = [arm["elbow_joint"] - 1 for arm in sk.arms]
        swing, twist = swing_twist(pose[:, elbows], C[:, 0])  # about SMPL's x axis, in Anny's axes
        R[:, [arm["elbow"] for arm in sk.arms]] = swing
        R[:, [arm["twist"] for arm in sk.arms]] = twist
        return G[:, sk.parents].transpose(-1, -2) @ R @ G

    @staticmethod
    def _forward_kinematics(offsets, local, sk):
        """Posed accumulated rotations (B, n, 3, 3) and heads (B, n, 3), level by level.

        With world-aligned ('local-ref') deltas D, a bone's accumulated rotation is its
        parent's times D, and its head is the parent's head plus the parent's accumulated
        rotation applied to the reference offset; the root stays at the origin. The bones are
        taken in level order once (`sk.order`), so a level reads only the one above it.
        """
        local_levels = local[:, sk.order].split(sk.level_sizes, 1)
        offset_levels = offsets[:, sk.order, :, None].split(sk.level_sizes, 1)
        rot, heads = [local_levels[0]], [offsets.new_zeros(local.shape[0], 1, 3, 1)]
        for parent, loc, off in zip(sk.level_parents, local_levels[1:], offset_levels[1:]):
            rot_p = rot[-1][:, parent]
            rot.append(rot_p @ loc)
            heads.append(heads[-1][:, parent] + rot_p @ off)
        order = sk.inverse_order
        return torch.cat(rot, 1)[:, order], torch.cat(heads, 1)[:, order, :, 0]

    def _shape_pass(self, shape, sk):
        """The pose-independent part of a pass: blendshape coefficients, rest bone heads,
        rest -> reference rotations A, reference offsets and T-pose corrections G of `sk`.

        With grad mode off the full skeleton's is computed once per batch of shapes and kept
        (the last one; IK and then the mesh of the same bodies reuse it), and a smaller
        skeleton's is read from it (its bones keep their parents: the same numbers). With grad
        mode on it is always computed afresh (a kept inference tensor could not be saved for
        the backward of a pose that wants gradients)."""
        if torch.is_grad_enabled():
            coeffs = self._coefficients(shape)
            rest_heads, rest_R = self._rest_skeleton(coeffs, sk)
            A, offsets = self._reference_offsets(rest_heads, rest_R, sk)
            return coeffs, rest_heads, A, offsets, self._t_pose_corrections(offsets, sk)
        memo = self.__dict__.get("_shape_memo")
        same = memo is not None and memo[0].dtype == shape.dtype and memo[0].device == shape.device
        if not (same and memo[0].shape == shape.shape and torch.equal(memo[0], shape)):
            with torch.no_grad():
                full = self.full
                coeffs = self._coefficients(shape)
                rest_heads, rest_R = self._rest_skeleton(coeffs, full)
                A, offsets = self._reference_offsets(rest_heads, rest_R, full)
                memo = (shape.clone(), (coeffs, rest_heads, A, offsets, self._t_pose_corrections(offsets, full)))
            self.__dict__["_shape_memo"] = memo
        if sk is self.full:
            return memo[1]
        coeffs, rest_heads, A, offsets, G = memo[1]
        return coeffs, rest_heads[:, sk.bones], A[:, sk.bones], offsets[:, sk.bones], G[:, sk.bones]

    def _skeleton_pass(self, shape, pose, sk):
        """Blendshape coefficients, rest bone heads, rest -> reference rotations A, posed
        accumulated rotations and heads (Anny axes) and the J24 joints (SMPL body axes)."""
        coeffs, rest_heads, A, offsets, G = self._shape_pass(shape, sk)
        rot, heads = self._forward_kinematics(offsets, self._local_rotations(pose, G, sk), sk)
        C = self.c_smpl_to_anny
        joints = torch.einsum("jk,bkx->bjx", self.joint_regressor[:, sk.bones], heads) @ C
        return coeffs, rest_heads, A, rot, heads, joints

    def body_frame(self, shape, pose, with_vertices):
        sk = self.full if with_vertices else self.light
        coeffs, rest_heads, A, rot, heads, joints = self._skeleton_pass(shape, pose, sk)
        if not with_vertices:
            return None, joints
        # Skinning transforms x -> T x + t mapping rest to posed: T = rot A, t = head - T h.
        T = rot @ A
        t = heads - (T @ rest_heads[..., None])[..., 0]
        rest_vertices = self.anny.get_rest_vertices(coeffs)
        return sparse_linear_blend_skinning(rest_vertices, self.skin_matrix, T, t) @ self.c_smpl_to_anny, joints

    def linear_mesh(self) -> LinearMesh:
        return LinearMesh(
            template=self.anny.template_vertices, blendshapes=self.anny.blendshapes, skinning=self.skin_matrix
        )

    def zero_pose_skinning(self, shape: torch.Tensor) -> ZeroPoseSkinning:
        sk = self.full
        pose = shape.new_zeros(shape.shape[0], NUM_JOINTS - 1, 3)
        coeffs, rest_heads, A, rot, heads, joints = self._skeleton_pass(shape, pose, sk)
        T = rot @ A
        t = heads - (T @ rest_heads[..., None])[..., 0]
        # Into SMPL's body axes (v_smpl = C^T v_anny; C permutes and negates axes: exact).
        Ct = self.c_smpl_to_anny.T
        return ZeroPoseSkinning(coeffs=coeffs, transforms=Ct @ T, translations=t @ self.c_smpl_to_anny, joints=joints)

    def native_rest_pose(self, shape: torch.Tensor) -> torch.Tensor:
        """(B, 23, 3) pose that reproduces Anny's own reference (A-)pose for these shapes.

        The bridge gives anny_local_b = I when C R_b C^T = G_parent G_b^T.
        """
        from pressurepose.body.rotations import matrix_to_axis_angle

        self.validate_shape(shape)
        sk = self.full
        heads, R = self._rest_skeleton(self._coefficients(shape), sk)
        G = self._t_pose_corrections(self._reference_offsets(heads, R, sk)[1], sk)
        C = self.c_smpl_to_anny
        R_smpl = C.T @ (G[:, sk.parents] @ G.transpose(-1, -2)) @ C  # (B, K, 3, 3)
        pose = shape.new_zeros(shape.shape[0], NUM_JOINTS - 1, 3)
        for j, name in enumerate(J24_NAMES[1:], start=1):
            bones = _ROTATION_BONES.get(name)
            if bones is not None:
                pose[:, j - 1] = matrix_to_axis_angle(R_smpl[:, self.bone_labels.index(bones[0])])
        for arm in sk.arms:
            elbow = R_smpl[:, arm["elbow"]] @ R_smpl[:, arm["twist"]]
            pose[:, arm["elbow_joint"] - 1] = matrix_to_axis_angle(elbow)
        return pose
