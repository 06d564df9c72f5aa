"""The body-model interface: every backend turns BodyParams into a BodyOutput the same way.

A backend implements only `body_frame` (joints, and optionally vertices, in SMPL's body axes
with the shape's own pelvis position) and its shape checks; placing the body in the mat frame,
the joints-only path, measurements and validation live here once.
"""

from __future__ import annotations

import abc
import dataclasses

import numpy as np
import torch

from pressurepose.body.joints import NUM_JOINTS
from pressurepose.body.params import BodyOutput, BodyParams, place_in_mat

# Body density used for mass = volume x density (Anny's anthropometry uses the same value).
BODY_DENSITY_KG_M3 = 980.0


@dataclasses.dataclass(frozen=True)
class BodyMeasurements:
    height_m: torch.Tensor  # (B,) top of the head to the soles, standing T-pose
    volume_m3: torch.Tensor  # (B,) enclosed mesh volume
    mass_kg: torch.Tensor  # (B,) volume x BODY_DENSITY_KG_M3


@dataclasses.dataclass(frozen=True)
class LinearMesh:
    """A backend's rest mesh, linear in per-shape coefficients c (B, A):
    x = template + c @ blendshapes, skinned with the fixed sparse weights (V, K) over K bones."""

    template: torch.Tensor  # (V, 3)
    blendshapes: torch.Tensor  # (A, V, 3)
    skinning: torch.Tensor  # (V, K) sparse, rows sum to 1 (to float32 precision)


@dataclasses.dataclass(frozen=True)
class ZeroPoseSkinning:
    """The zero-pose (T-pose) mesh of B shapes as linear blend skinning of the LinearMesh:
    vertex v of body b = sum_k W[v, k] (transforms[b, k] x[b, v] + translations[b, k]), in
    SMPL's body axes (the pelvis not yet at the origin)."""

    coeffs: torch.Tensor  # (B, A)
    transforms: torch.Tensor  # (B, K, 3, 3)
    translations: torch.Tensor  # (B, K, 3)
    joints: torch.Tensor  # (B, 24, 3) J24, same axes and origin as the vertices


class BodyModel(torch.nn.Module, abc.ABC):
    """Batched, differentiable body model (float32 or float64, CPU or CUDA).

    Subclasses register the buffers `faces` (F, 3), `part_labels` (V,) and
    `skinning_weights` (V, 24) and set `name` and `shape_names`.
    """

    name: str
    shape_names: tuple[str, ...]
    faces: torch.Tensor
    part_labels: torch.Tensor
    skinning_weights: torch.Tensor

    @property
    def shape_dim(self) -> int:
        return len(self.shape_names)

    @property
    def num_vertices(self) -> int:
        return self.part_labels.shape[0]

    @property
    def dtype(self) -> torch.dtype:
        return self.skinning_weights.dtype

    @property
    def device(self) -> torch.device:
        return self.skinning_weights.device

    # --- to implement -------------------------------------------------------------------
    @abc.abstractmethod
    def body_frame(
        self, shape: torch.Tensor, pose: torch.Tensor, with_vertices: bool
    ) -> tuple[torch.Tensor | None, torch.Tensor]:
        """(vertices (B, V, 3) or None, joints (B, 24, 3)) in body axes, zero root rotation."""

    @abc.abstractmethod
    def default_shape(self, batch_size: int = 1) -> torch.Tensor:
        """(B, S) shape of an average adult."""

    def validate_shape(self, shape: torch.Tensor) -> None:
        """Backend-specific range checks on (B, S) shape parameters (ValueError)."""

    # --- what the shape means: the population, gender and size (sampler, capsules, fits) --
    # Code outside the backends asks these instead of branching on `name`.
    @classmethod
    @abc.abstractmethod
    def shape_bounds(cls, gender: str, shape_names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) arrays (S,) of the box the pose sampler draws adults of `gender`
        ("female" or "male") from, for the shape entries `shape_names` (`body.shape_ranges`)."""

    @classmethod
    def shape_powers(cls, shape_names: tuple[str, ...]) -> np.ndarray:
        """(S,) power p of the sampler's draw of each shape entry on its interval: density ~
        t^(p - 1) over t in [0, 1] (1 = uniform, the default)."""
        return np.ones(len(shape_names))

    @property
    def fixed_gender(self) -> str | None:
        """The gender the model itself fixes ("female" or "male": SMPL's gendered files), or
        None when the shape sets it or the model is neutral."""
        return None

    @abc.abstractmethod
    def female_fraction(self, shape: torch.Tensor) -> torch.Tensor:
        """(B,) 1 for female, 0 for male bodies of (B, S) shapes (in between: a blend)."""

    @abc.abstractmethod
    def average_shape(self, female: torch.Tensor) -> torch.Tensor:
        """(B, S) the average adult (`default_shape`) of each (B,) female fraction; a backend
        whose gender is not a shape entry ignores `female`."""

    size_dim: int  # how many numbers `with_size` takes

    @abc.abstractmethod
    def with_size(self, shape: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """(B, S) `shape` with the entries that set height and mass replaced by a smooth,
        bounded function of the unconstrained z (B, size_dim): what `shape_for_height_mass`
        optimises (z = 0: the middle of their range)."""

    # --- optional fast path for per-shape fits on the T-pose mesh (capsules) --------------
    def linear_mesh(self) -> LinearMesh | None:
        """The rest mesh's linear structure, or None when the backend does not expose it
        (then `zero_pose_skinning` is not used and fits skin the whole mesh)."""
        return None

    def zero_pose_skinning(self, shape: torch.Tensor) -> ZeroPoseSkinning:
        """Per-shape coefficients and bone transforms of the T-pose (only with `linear_mesh`)."""
        raise NotImplementedError

    # --- shared ---------------------------------------------------------------------------
    def check_params(self, params: BodyParams) -> None:
        """ValueError unless `params` are BodyParams of this model's shape size, dtype, device
        and shape ranges."""
        if not isinstance(params, BodyParams):
            raise ValueError(f"expected BodyParams, got {type(params).__name__}")
        params.validate(self.shape_dim, self.dtype, self.device)
        self.validate_shape(params.shape)

    def forward(self, params: BodyParams) -> BodyOutput:
        """Posed mesh and J24 joints in the mat frame (metres)."""
        self.check_params(params)
        vertices, joints = self.body_frame(params.shape, params.pose, with_vertices=True)
        pelvis = joints[:, 0]
        return BodyOutput(
            vertices=place_in_mat(vertices, pelvis, params),
            joints=place_in_mat(joints, pelvis, params),
            faces=self.faces,
            part_labels=self.part_labels,
            skinning_weights=self.skinning_weights,
        )

    def joints(self, params: BodyParams) -> torch.Tensor:
        """J24 joints (B, 24, 3) in the mat frame, without skinning the mesh (fast path)."""
        self.check_params(params)
        _, joints = self.body_frame(params.shape, params.pose, with_vertices=False)
        return place_in_mat(joints, joints[:, 0], params)

    def rest_joints(self, shape: torch.Tensor) -> torch.Tensor:
        """(B, 24, 3) T-pose joints of (B, S) shapes in body axes, pelvis at the origin."""
        params = BodyParams.zeros(shape.shape[0], shape)
        self.check_params(params)
        _, joints = self.body_frame(params.shape, params.pose, with_vertices=False)
        return joints - joints[:, :1]

    def rest_pose_joints(self, shape: torch.Tensor) -> torch.Tensor:
        """(B, 24, 3) joints whose bone lengths are the body's (for quantities the pose does not
        change; `net.stature`): `rest_joints` here; a backend may answer from a cheaper rest
        skeleton (Anny: its rest bone heads)."""
        return self.rest_joints(shape)

    def rest_vertices(self, shape: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) zero-pose (T-pose) mesh in body axes, pelvis at the origin."""
        params = BodyParams.zeros(shape.shape[0], shape)
        self.check_params(params)
        vertices, joints = self.body_frame(params.shape, params.pose, with_vertices=True)
        return vertices - joints[:, :1]

    def measure(self, shape: torch.Tensor) -> BodyMeasurements:
        """Height, volume and mass of (B, S) shapes, differentiable."""
        vertices = self.rest_vertices(shape)
        volume = mesh_volume(vertices, self.faces)
        return BodyMeasurements(
            height_m=vertices[..., 1].amax(-1) - vertices[..., 1].amin(-1),
            volume_m3=volume,
            mass_kg=volume * BODY_DENSITY_KG_M3,
        )


def mesh_volume(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Enclosed volume (B,) of closed, outward-oriented triangle meshes (B, V, 3), (F, 3).
    Summed over blocks of faces, corners gathered as rows of a (V, B, 3) copy: mesh-sized
    temporaries and per-sample gathers cost ~5x more on a CPU at batch 128."""
    by_vertex = vertices.transpose(0, 1).contiguous()  # (V, B, 3)
    step = max(1024, (1 << 18) // max(1, vertices.shape[0]))
    total = vertices.new_zeros(vertices.shape[0])
    for start in range(0, faces.shape[0], step):
        v0, v1, v2 = (by_vertex.index_select(0, faces[start : start + step, k]) for k in range(3))
        total = total + (torch.linalg.cross(v0, v1, dim=-1) * v2).sum((0, 2))
    return total / 6.0


def part_weights_onto_j24(
    bone_weights: torch.Tensor, bone_indices: torch.Tensor, bone_to_j24: torch.Tensor
) -> torch.Tensor:
    """Sparse per-vertex bone weights (V, K) with bone ids (V, K) -> dense (V, 24) weights
    summed onto the J24 part each bone belongs to (`bone_to_j24`, (num_bones,))."""
    V = bone_weights.shape[0]
    out = torch.zeros(V, NUM_JOINTS, dtype=bone_weights.dtype, device=bone_weights.device)
    return out.scatter_add_(1, bone_to_j24[bone_indices.long()], bone_weights)
