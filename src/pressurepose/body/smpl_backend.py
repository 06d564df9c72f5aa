"""SMPL through `smplx` (extra `pressurepose[smpl]`) from model files the user provides.

SMPL's files cannot be redistributed, so none ship here. Put `SMPL_NEUTRAL`, `SMPL_MALE`
and/or `SMPL_FEMALE` (`.npz`, or the official `.pkl`) in `$PRESSUREPOSE_SMPL_DIR`, else in
`<cache>/smpl`. Official `.pkl` files hold chumpy and scipy objects; we read them with a
restricted unpickler that rebuilds plain numpy arrays from their state and refuses anything
else, so neither chumpy nor arbitrary code is ever loaded.
"""

from __future__ import annotations

import io
import os
import pickle
from pathlib import Path

import numpy as np
import torch

from pressurepose.body.joints import J24_PARENTS, NUM_JOINTS
from pressurepose.body.model import BodyModel
from pressurepose.body.rotations import axis_angle_to_matrix
from pressurepose.body.shape_ranges import SMPL_BETA_RANGE, beta_bounds
from pressurepose.cache import cache_dir
from pressurepose.errors import UserError
from pressurepose.files import atomic_write
from pressurepose.validate import BoundedUnpickler

ENV_VAR = "PRESSUREPOSE_SMPL_DIR"
GENDERS = ("neutral", "male", "female")
NUM_BETAS = 10
MAX_DENSE = 64 * 200_000  # values of the largest dense matrix a model file can need (joints x vertices)
_KEYS = ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f")


class SmplFileError(UserError):
    """An SMPL model file is missing, unreadable or malformed (a user error)."""


def smpl_dir() -> Path:
    return Path(os.environ.get(ENV_VAR) or cache_dir() / "smpl")


def find_smpl_file(model_dir: Path, gender: str) -> Path:
    for ext in (".npz", ".pkl"):
        path = model_dir / f"SMPL_{gender.upper()}{ext}"
        if path.is_file():
            return path
    raise SmplFileError(
        f"SMPL model file SMPL_{gender.upper()}.npz or .pkl not found in {model_dir}; SMPL files "
        f"cannot be redistributed: download them from https://smpl.is.tue.mpg.de and put them "
        f"there, or set {ENV_VAR} to their folder (or use the default backend, anny)"
    )


class _State:
    """Stand-in for a chumpy or scipy.sparse object: keeps its pickled state only."""

    def __init__(self, *args, **kwargs) -> None:
        self.state = None

    def __setstate__(self, state) -> None:
        self.state = state


class _ChumpyState(_State):
    def to_array(self) -> np.ndarray:
        if not isinstance(self.state, dict) or "x" not in self.state:
            raise SmplFileError("SMPL file holds a chumpy object without an array")
        return np.asarray(self.state["x"])


class _SparseState(_State):
    compressed_axis = 1  # csc: indptr runs over columns; csr overrides with 0

    def to_array(self) -> np.ndarray:
        s = self.state if isinstance(self.state, dict) else {}
        if not {"data", "indices", "indptr"} <= set(s):
            raise SmplFileError("SMPL file holds a sparse matrix without data/indices/indptr")
        shape = s.get("_shape", s.get("shape"))
        if not (
            isinstance(shape, (tuple, list))
            and len(shape) == 2
            and all(isinstance(d, (int, np.integer)) and not isinstance(d, bool) and d >= 0 for d in shape)
        ):
            raise SmplFileError(f"SMPL file holds a sparse matrix whose shape {shape!r} is not two sizes")
        shape = (int(shape[0]), int(shape[1]))
        if shape[0] * shape[1] > MAX_DENSE:
            raise SmplFileError(
                f"SMPL file holds a sparse matrix of shape {shape}, larger than any SMPL model "
                f"needs ({MAX_DENSE} values); not a valid model file"
            )
        data, indices, indptr = (np.asarray(s[k]) for k in ("data", "indices", "indptr"))
        major_size = shape[1] if self.compressed_axis == 1 else shape[0]
        minor_size = shape[0] if self.compressed_axis == 1 else shape[1]
        if (
            indptr.ndim != 1
            or len(indptr) != major_size + 1
            or indices.shape != data.shape
            or data.ndim != 1
            or indptr.dtype.kind not in "iu"
            or indices.dtype.kind not in "iu"
            or data.dtype.kind not in "fiu"
            or indptr[0] != 0
            or indptr[-1] != len(data)
            or (np.diff(indptr) < 0).any()
            or (len(indices) and (indices.min() < 0 or indices.max() >= minor_size))
        ):
            raise SmplFileError(
                f"SMPL file holds a sparse matrix of shape {shape} whose data/indices/indptr do not describe it"
            )
        dense = np.zeros(shape, dtype=np.float64)
        major = np.repeat(np.arange(len(indptr) - 1), np.diff(indptr))
        where = (indices, major) if self.compressed_axis == 1 else (major, indices)
        np.add.at(dense, where, data)  # duplicate entries add up, as in scipy
        return dense


class _CsrState(_SparseState):
    compressed_axis = 0


class _RestrictedUnpickler(BoundedUnpickler):
    _ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
        ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "scalar"),
        ("copy_reg", "_reconstructor"),
        ("copyreg", "_reconstructor"),
        ("__builtin__", "object"),
        ("builtins", "object"),
        ("_codecs", "encode"),  # how protocol-2 pickles written by Python 3 store bytes
    }

    def allowed(self, module: str, name: str):
        if module.startswith("chumpy"):
            return _ChumpyState
        if module.startswith("scipy.sparse"):
            return _CsrState if name.startswith("csr") else _SparseState
        if (module, name) in self._ALLOWED:
            module = {"copy_reg": "copyreg", "__builtin__": "builtins"}.get(module, module)
            return pickle.Unpickler.find_class(self, module, name)
        raise SmplFileError(f"SMPL file {self.source} refers to {module}.{name}, which is not allowed in a model file")


def read_smpl_file(path: Path) -> dict[str, np.ndarray]:
    """The arrays of an SMPL model file (.npz or .pkl), checked; never runs code from it."""
    try:
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as data:
                raw = {k: data[k] for k in data.files}
        else:
            data = path.read_bytes()
            raw = _RestrictedUnpickler(io.BytesIO(data), budget=len(data), source=path, encoding="latin1").load()
    except UserError as exc:
        raise SmplFileError(str(exc) if str(path) in str(exc) else f"SMPL model file {path}: {exc}") from None
    except Exception as exc:  # corrupt, truncated, or not a model file at all
        raise SmplFileError(f"cannot read SMPL model file {path}: {exc}") from None
    if not isinstance(raw, dict):
        raise SmplFileError(f"SMPL model file {path} does not hold a dict of arrays")
    missing = [k for k in _KEYS if k not in raw]
    if missing:
        raise SmplFileError(f"SMPL model file {path} lacks {', '.join(missing)}")
    try:
        arrays = {k: raw[k].to_array() if isinstance(raw[k], _State) else np.asarray(raw[k]) for k in _KEYS}
    except SmplFileError as exc:
        raise SmplFileError(f"SMPL model file {path}: {exc}") from None
    for key, a in arrays.items():
        if a.dtype.kind not in "fiu":
            raise SmplFileError(f"SMPL model file {path}: {key} is not numeric (dtype {a.dtype})")
    V = arrays["v_template"].shape[0]
    expected = {
        "v_template": (V, 3),
        "J_regressor": (NUM_JOINTS, V),
        "weights": (V, NUM_JOINTS),
        "kintree_table": (2, NUM_JOINTS),
    }
    for key, shape in expected.items():
        if arrays[key].shape != shape:
            raise SmplFileError(f"SMPL model file {path}: {key} has shape {arrays[key].shape}, expected {shape}")
    if (
        arrays["shapedirs"].ndim != 3
        or arrays["shapedirs"].shape[:2] != (V, 3)
        or arrays["shapedirs"].shape[2] < NUM_BETAS
    ):
        raise SmplFileError(
            f"SMPL model file {path}: shapedirs has shape {arrays['shapedirs'].shape}, expected ({V}, 3, >={NUM_BETAS})"
        )
    if arrays["posedirs"].shape != (V, 3, 9 * (NUM_JOINTS - 1)):
        raise SmplFileError(
            f"SMPL model file {path}: posedirs has shape {arrays['posedirs'].shape}, expected ({V}, 3, 207)"
        )
    for key in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights"):
        if not np.isfinite(arrays[key]).all():
            raise SmplFileError(f"SMPL model file {path}: {key} contains NaN or infinite values")
    return arrays


class SmplBody(BodyModel):
    """SMPL (10 betas) behind the BodyModel interface; skinning by smplx's `lbs`."""

    name = "smpl"
    shape_names = tuple(f"beta{i}" for i in range(NUM_BETAS))

    def __init__(
        self,
        model_dir: str | Path | None = None,
        gender: str = "neutral",
        dtype: torch.dtype = torch.float32,
        device: torch.device | str = "cpu",
    ) -> None:
        super().__init__()
        try:
            from smplx.lbs import batch_rigid_transform, lbs
        except ImportError:
            raise SmplFileError("the smpl backend needs the smplx package: pip install 'pressurepose[smpl]'") from None
        self._lbs, self._rigid = lbs, batch_rigid_transform
        if gender not in GENDERS:
            raise ValueError(f"unknown SMPL gender {gender!r}; expected one of {', '.join(GENDERS)}")
        self.gender = gender
        path = find_smpl_file(Path(model_dir) if model_dir else smpl_dir(), gender)
        a = read_smpl_file(path)
        parents = a["kintree_table"][0].astype(np.int64)
        if tuple(parents[1:]) != J24_PARENTS[1:]:
            raise SmplFileError(f"SMPL model file {path}: kintree_table is not SMPL's J24 tree")
        t = lambda x: torch.as_tensor(np.ascontiguousarray(x), dtype=torch.float64)  # noqa: E731
        shapedirs = t(a["shapedirs"][:, :, :NUM_BETAS])
        self.register_buffer("v_template", t(a["v_template"]), persistent=False)
        self.register_buffer("shapedirs", shapedirs, persistent=False)
        self.register_buffer("posedirs", t(a["posedirs"]).reshape(-1, 207).T.contiguous(), persistent=False)
        self.register_buffer("J_regressor", t(a["J_regressor"]), persistent=False)
        # Joints are linear in the betas: regress them once for the joints-only path.
        self.register_buffer("J_template", self.J_regressor @ self.v_template, persistent=False)
        self.register_buffer("J_shapedirs", torch.einsum("jv,vxb->jxb", self.J_regressor, shapedirs), persistent=False)
        self.register_buffer("skinning_weights", t(a["weights"]), persistent=False)
        self.register_buffer("part_labels", self.skinning_weights.argmax(-1), persistent=False)
        self.register_buffer("faces", torch.as_tensor(a["f"].astype(np.int64)), persistent=False)
        self.register_buffer("parents", torch.as_tensor(np.r_[-1, parents[1:]]), persistent=False)
        self.to(dtype=dtype, device=device)

    def default_shape(self, batch_size: int = 1) -> torch.Tensor:
        return torch.zeros(batch_size, NUM_BETAS, dtype=self.dtype, device=self.device)

    def validate_shape(self, shape: torch.Tensor) -> None:
        if not torch.isfinite(shape).all():
            raise ValueError("shape (SMPL betas) contains NaN or infinite values")

    @classmethod
    def shape_bounds(cls, gender: str, shape_names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        return beta_bounds(len(shape_names))  # either gender: the model file sets it

    @property
    def fixed_gender(self) -> str | None:
        return None if self.gender == "neutral" else self.gender

    def female_fraction(self, shape: torch.Tensor) -> torch.Tensor:
        value = {"female": 1.0, "male": 0.0}.get(self.gender, 0.5)  # the neutral model: 0.5
        return torch.full((shape.shape[0],), value, dtype=shape.dtype, device=shape.device)

    def average_shape(self, female: torch.Tensor) -> torch.Tensor:
        return self.default_shape(female.shape[0])  # the gender is the model file's

    size_dim = 2  # the first two betas, each 3 tanh(z / 3) in (-3, 3)

    def with_size(self, shape: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        sized = shape.clone()
        sized[:, :2] = SMPL_BETA_RANGE[1] * torch.tanh(z / SMPL_BETA_RANGE[1])
        return sized

    def _rotations(self, pose: torch.Tensor) -> torch.Tensor:
        B = pose.shape[0]
        eye = torch.eye(3, dtype=pose.dtype, device=pose.device).expand(B, 1, 3, 3)
        return torch.cat([eye, axis_angle_to_matrix(pose)], 1)  # (B, 24, 3, 3), root = I

    def body_frame(self, shape, pose, with_vertices):
        rot = self._rotations(pose)
        if not with_vertices:
            J = self.J_template + torch.einsum("jxb,nb->njx", self.J_shapedirs, shape)
            posed, _ = self._rigid(rot, J, self.parents, dtype=shape.dtype)
            return None, posed
        vertices, joints = self._lbs(
            shape,
            rot,
            self.v_template,
            self.shapedirs,
            self.posedirs,
            self.J_regressor,
            self.parents,
            self.skinning_weights,
            pose2rot=False,
        )
        return vertices, joints


def write_synthetic_smpl_file(path: str | Path, seed: int = 0, num_vertices: int = 6890) -> Path:
    """Write an SMPL-format .npz with a human-like T-pose skeleton and random details.

    For tests and benchmarks only (no licensed data): each vertex belongs to one joint and
    lies in a small cloud around the midpoint of that joint's bone, so the mesh has the
    right shapes and a sensible layout (left on +x, head on +y, front on +z).
    """
    rng = np.random.default_rng(seed)
    # Approximate SMPL rest joints (m), body axes: x = left, y = up, z = front.
    J = np.array(
        [
            [0, 0, 0],
            [0.06, -0.09, 0],
            [-0.06, -0.09, 0],
            [0, 0.11, -0.02],
            [0.1, -0.47, 0],
            [-0.1, -0.47, 0],
            [0, 0.24, -0.01],
            [0.09, -0.87, -0.03],
            [-0.09, -0.87, -0.03],
            [0, 0.29, 0],
            [0.11, -0.93, 0.1],
            [-0.11, -0.93, 0.1],
            [0, 0.51, -0.02],
            [0.08, 0.42, -0.01],
            [-0.08, 0.42, -0.01],
            [0, 0.6, 0.03],
            [0.18, 0.45, -0.02],
            [-0.18, 0.45, -0.02],
            [0.44, 0.45, -0.03],
            [-0.44, 0.45, -0.03],
            [0.7, 0.45, -0.02],
            [-0.7, 0.45, -0.02],
            [0.79, 0.45, -0.02],
            [-0.79, 0.45, -0.02],
        ]
    )
    parents = np.array((-1,) + J24_PARENTS[1:])
    owner = rng.integers(0, NUM_JOINTS, num_vertices)
    child_of = {int(p): c for c, p in enumerate(parents) if p >= 0}
    centre = np.array([(J[j] + J[child_of.get(j, j)]) / 2 for j in range(NUM_JOINTS)])
    v = centre[owner] + rng.normal(0, 0.03, (num_vertices, 3))
    weights = np.zeros((num_vertices, NUM_JOINTS))
    weights[np.arange(num_vertices), owner] = 1.0
    J_regressor = np.zeros((NUM_JOINTS, num_vertices))
    for j in range(NUM_JOINTS):
        members = np.flatnonzero(owner == j)
        J_regressor[j, members] = 1.0 / len(members)
    # Shift each joint's cloud so the regressed joints land exactly on J.
    v += (J - J_regressor @ v)[owner]
    faces = np.stack([rng.permutation(np.flatnonzero(owner == owner[i]))[:3] for i in range(0, num_vertices, 3)])
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {
        "v_template": v,
        "f": faces.astype(np.int64),
        "weights": weights,
        "J_regressor": J_regressor,
        "kintree_table": np.stack([np.r_[4294967295, parents[1:]], np.arange(NUM_JOINTS)]).astype(np.int64),
        "shapedirs": rng.normal(0, 0.01, (num_vertices, 3, NUM_BETAS)),
        "posedirs": rng.normal(0, 0.001, (num_vertices, 3, 207)),
    }
    atomic_write(path, lambda tmp: np.savez(tmp, **arrays))
    return path
