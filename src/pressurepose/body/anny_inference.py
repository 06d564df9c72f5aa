"""Anny without autograd (evaluate, predict): the posed and rest meshes by blocked skinning
and the T-pose joints in closed form, mixed into `AnnyBody`; with autograd each method falls
back to the differentiable `BodyModel` one (same numbers to float rounding, tests/test_body.py).

The posed mesh: the change of axes (Anny -> SMPL), the root rotation and the translation are
folded into the bone transforms before skinning (a vertex's weights sum to 1, so a common
affine map passes through the blend), and `BlockedSkinning` writes the mesh in one pass.
`AnnyBody._shape_pass` keeps the last batch of shapes' skeleton pass, so the IK's T-pose
joints and then the mesh of the same bodies compute it once.
"""

from __future__ import annotations

import torch

from pressurepose.body.anny_skinning import BlockedSkinning, wants_grad
from pressurepose.body.joints import NUM_JOINTS
from pressurepose.body.params import BodyOutput, BodyParams, place_in_mat, root_matrix

_CACHES = ("_shape_memo", "_blocked", "_chains", "_phenotype")  # rebuilt on demand; not copied or pickled


class AnnyInference:
    """Mixin of AnnyBody (uses its skeletons, shape pass and buffers)."""

    def __getstate__(self):
        state = super().__getstate__()
        return {k: v for k, v in state.items() if k not in _CACHES}

    def rest_joints(self, shape: torch.Tensor) -> torch.Tensor:
        """As BodyModel.rest_joints, without the forward kinematics: at the zero pose a bone's
        accumulated rotation is its T-pose correction G_b, so its head is the sum of
        G_parent(a) offset_a over the bones a on its chain (one product with a 0/1 matrix)."""
        self.check_params(BodyParams.zeros(shape.shape[0], shape))
        sk = self.light
        _, _, _, offsets, G = self._shape_pass(shape, sk)
        if "_chains" not in self.__dict__:  # [b, a] = 1 when a is b or an ancestor of b below the root
            parents, n = sk.parents.tolist(), len(sk.parents)
            chains = torch.zeros(n, n)
            for b in range(1, n):
                a = b
                while a > 0:
                    chains[b, a], a = 1.0, parents[a]
            self.__dict__["_chains"] = chains
        heads = self.__dict__["_chains"].to(offsets) @ (G[:, sk.parents] @ offsets[..., None])[..., 0]
        joints = torch.einsum("jk,bkx->bjx", self.joint_regressor[:, sk.bones], heads) @ self.c_smpl_to_anny
        return joints - joints[:, :1]

    @torch.no_grad()
    def rest_pose_joints(self, shape: torch.Tensor) -> torch.Tensor:
        """(B, 24, 3) the J24 joints of Anny's rest pose (the bone heads as the blendshapes place
        them, Anny axes), without the rest orientations and T-pose corrections `rest_joints`
        needs: the same bones' lengths for the trunk and legs within a few millimetres (sd 2.5 mm
        over the chain of `net.stature.chain_length`), at ~1 ms against 2.7 for one body and 18 against
        28 ms for 256 (docs/benchmarks.md, session 38). For quantities
        the pose does not change (bone lengths); not a pose."""
        self.check_params(BodyParams.zeros(shape.shape[0], shape))
        m = self.anny
        heads = m.template_bone_heads + torch.einsum("ba,akx->bkx", self._coefficients(shape), m.bone_heads_blendshapes)
        return torch.einsum("jk,bkx->bjx", self.joint_regressor[:, self.full.bones], heads)

    def forward(self, params: BodyParams) -> BodyOutput:
        """As BodyModel.forward; without autograd by `_blocked_mesh`."""
        self.check_params(params)
        if wants_grad(params.shape, params.pose, params.root_rotation, params.root_translation):
            return super().forward(params)
        frame = root_matrix(params.root_rotation) @ self.c_smpl_to_anny.T  # Anny axes -> mat frame
        vertices, joints = self._blocked_mesh(params.shape, params.pose, frame, params.root_translation)
        return BodyOutput(
            vertices=vertices,
            joints=place_in_mat(joints, joints[:, 0], params),
            faces=self.faces,
            part_labels=self.part_labels,
            skinning_weights=self.skinning_weights,
        )

    def rest_vertices(self, shape: torch.Tensor) -> torch.Tensor:
        if wants_grad(shape):
            return super().rest_vertices(shape)
        self.check_params(BodyParams.zeros(shape.shape[0], shape))
        frame = self.c_smpl_to_anny.T.expand(shape.shape[0], 3, 3)  # Anny axes -> SMPL body axes
        return self._blocked_mesh(shape, shape.new_zeros(shape.shape[0], NUM_JOINTS - 1, 3), frame, None)[0]

    @torch.no_grad()
    def _blocked_mesh(self, shape, pose, frame, pelvis_to):
        """Posed mesh (B, V, 3) by `BlockedSkinning`, rotated by frame (B, 3, 3) from Anny's
        axes and moved so the pelvis lands at pelvis_to (B, 3) (None: the origin), both
        folded into the bone transforms; and the J24 joints in SMPL body axes."""
        coeffs, rest_heads, A, rot, heads, joints = self._skeleton_pass(shape, pose, self.full)
        shift = -(frame @ self.c_smpl_to_anny @ joints[:, 0, :, None])[..., 0]
        shift = shift if pelvis_to is None else shift + pelvis_to
        T = frame[:, None] @ rot @ A  # skinning x -> T x + t: rest to posed, then into the frame
        t = (frame[:, None] @ heads[..., None])[..., 0] - (T @ rest_heads[..., None])[..., 0] + shift[:, None]
        key, cached = (self.dtype, self.device), self.__dict__.get("_blocked")
        if cached is None or cached[0] != key:  # built on first use for the model's dtype and device
            cached = self.__dict__["_blocked"] = (key, BlockedSkinning.of_anny(self.anny, self.skin_matrix))
        return cached[1].pose(coeffs, T, t), joints


__all__ = ["AnnyInference"]
