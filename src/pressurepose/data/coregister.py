"""Camera-mat co-registration (seed A.6): the camera's 6-DoF pose from marked mat corners.

The original put 1" tungsten cubes on the pressure mat's corners, clicked them in the camera
image and searched the camera pose with CMA-ES. Here: the markers' pixel positions (and,
optionally, their depth) plus the camera intrinsics give a direct solution - a plane-to-image
homography for coplanar markers (or the closed-form 3D-3D fit when depths are known) - refined
by Levenberg-Marquardt on the reprojection error (or by CMA-ES, `method="cma"`, as the seed did).
The pose maps mat-frame points into camera coordinates, X_cam = R X_mat + t (camera axes:
x right, y down, z forward, as OpenCV and the Kinect use); point clouds go the other way.

Marker file (JSON, documented in docs/real_data.md):
    {"format": "pressurepose.coregistration/1",
     "intrinsics": {"fx": 365.0, "fy": 365.0, "cx": 256.0, "cy": 212.0},
     "markers": [{"name": "head_left", "pixel": [u, v], "depth_m": 1.61 (optional),
                  "mat_xyz_m": [x, y, z] (optional: default the named corner)}, ...]}
Named corners are the sensing area's corners in the mat frame, on top of 1" cubes:
head_left (0, 0), head_right (0, W), foot_left (L, 0), foot_right (L, W), z = 1.27 cm.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import roma
import torch

from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.validate import read_json, read_npy

FORMAT = "pressurepose.coregistration/1"
CUBE_M = 0.0254  # the seed's 1" tungsten cubes; a marker sits at the cube's centre


def corner_markers(mat: MatSpec | None = None) -> dict[str, np.ndarray]:
    """Mat-frame positions (m) of the four named corner markers."""
    mat = mat or MatSpec()
    L, W, z = mat.sensing_length_m, mat.sensing_width_m, CUBE_M / 2
    return {
        "head_left": np.array([0.0, 0.0, z]),
        "head_right": np.array([0.0, W, z]),
        "foot_left": np.array([L, 0.0, z]),
        "foot_right": np.array([L, W, z]),
    }


@dataclasses.dataclass(frozen=True)
class Intrinsics:
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclasses.dataclass(frozen=True)
class Markers:
    """N >= 4 markers: mat-frame positions (N, 3) m, pixels (N, 2), depths (N,) m or NaN."""

    names: tuple[str, ...]
    mat_xyz_m: np.ndarray
    pixel: np.ndarray
    depth_m: np.ndarray
    intrinsics: Intrinsics


@dataclasses.dataclass(frozen=True)
class CameraPose:
    """X_cam = R X_mat + t; residuals per marker in pixels."""

    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,) m
    rms_px: float
    residual_px: np.ndarray  # (N,)

    @property
    def position_m(self) -> np.ndarray:
        """The camera centre in the mat frame."""
        return -self.R.T @ self.t

    def to_mat(self, points_cam: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points -> mat frame."""
        return (np.asarray(points_cam, dtype=np.float64) - self.t) @ self.R

    def to_camera(self, points_mat: np.ndarray) -> np.ndarray:
        return np.asarray(points_mat, dtype=np.float64) @ self.R.T + self.t

    def to_dict(self) -> dict:
        return {
            "format": "pressurepose.camera_pose/1",
            "R": self.R.tolist(),
            "t_m": self.t.tolist(),
            "camera_position_in_mat_m": self.position_m.tolist(),
            "rms_px": self.rms_px,
            "residual_px": self.residual_px.tolist(),
            "convention": "X_cam = R X_mat + t; camera x right, y down, z forward",
        }


# --- reading -------------------------------------------------------------------------------
def _number(value, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise UserError(f"{what} must be a finite number, got {value!r}")
    return float(value)


def _vector(value, n: int, what: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise UserError(f"{what} must be a list of {n} numbers, got {value!r}")
    return np.array([_number(v, what) for v in value])


def parse_markers(data: dict, mat: MatSpec | None = None) -> Markers:
    """Markers from the decoded JSON (see the module doc); ValueError naming what is wrong."""
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise UserError(f'not a marker file: expected {{"format": "{FORMAT}", ...}}')
    intr = data.get("intrinsics")
    if not isinstance(intr, dict):
        raise UserError('marker file has no "intrinsics" {"fx", "fy", "cx", "cy"}')
    K = Intrinsics(*(_number(intr.get(k), f"intrinsics.{k}") for k in ("fx", "fy", "cx", "cy")))
    if K.fx <= 0 or K.fy <= 0:
        raise UserError(f"focal lengths must be > 0, got fx={K.fx}, fy={K.fy}")
    items = data.get("markers")
    if not isinstance(items, list) or len(items) < 4:
        raise UserError(
            f'marker file needs "markers": a list of at least 4 (the mat corners), '
            f"got {0 if not isinstance(items, list) else len(items)}"
        )
    corners = corner_markers(mat)
    names, xyz, pix, depth = [], [], [], []
    for k, m in enumerate(items):
        if not isinstance(m, dict) or "pixel" not in m:
            raise UserError(f'marker {k} needs a "pixel": [u, v]')
        name = str(m.get("name", f"marker{k}"))
        if "mat_xyz_m" in m:
            xyz.append(_vector(m["mat_xyz_m"], 3, f"marker {name} mat_xyz_m"))
        elif name in corners:
            xyz.append(corners[name])
        else:
            raise UserError(f"marker {name!r} is not a named corner ({', '.join(corners)}); give its mat_xyz_m")
        pix.append(_vector(m["pixel"], 2, f"marker {name} pixel"))
        d = m.get("depth_m")
        if d is None:
            depth.append(math.nan)
        else:
            d = _number(d, f"marker {name} depth_m")
            if d <= 0:
                raise UserError(f"marker {name} depth_m must be > 0, got {d}")
            depth.append(d)
        names.append(name)
    if len(set(names)) != len(names):
        raise UserError("marker names repeat")
    xyz = np.stack(xyz)
    if np.linalg.matrix_rank(xyz[1:] - xyz[0], tol=1e-3) < 2:
        raise UserError("markers are collinear: they cannot fix the camera pose")
    return Markers(tuple(names), xyz, np.stack(pix), np.array(depth), K)


def read_markers(path: str | Path, mat: MatSpec | None = None) -> Markers:
    path = Path(path)
    if not path.is_file():
        raise UserError(f"no marker file at {path}")
    return parse_markers(read_json(path, "marker file"), mat)


# --- solving -------------------------------------------------------------------------------
def project(K: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(N, 2) pixels of mat-frame points (N, 3)."""
    c = X @ R.T + t
    if (c[:, 2] <= 0).any():
        return np.full((X.shape[0], 2), np.nan)
    uv = c @ K.T
    return uv[:, :2] / uv[:, 2:]


def _rodrigues(w: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) -> rotation matrix (3, 3)."""
    return roma.rotvec_to_rotmat(torch.from_numpy(np.asarray(w, dtype=np.float64))).numpy()


def _nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation nearest to M (3, 3) in Frobenius norm (special Procrustes)."""
    return roma.special_procrustes(torch.from_numpy(np.asarray(M, dtype=np.float64))).numpy()


def _kabsch(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimising |R A + t - B| for point sets (N, 3) (Kabsch)."""
    R, t = roma.rigid_points_registration(
        torch.from_numpy(A.astype(np.float64)), torch.from_numpy(B.astype(np.float64))
    )
    return R.numpy(), t.numpy()


def _initial_pose(mk: Markers) -> tuple[np.ndarray, np.ndarray]:
    K = mk.intrinsics.K
    rays = np.c_[mk.pixel, np.ones(len(mk.pixel))] @ np.linalg.inv(K).T  # (N, 3), z = 1
    if np.isfinite(mk.depth_m).sum() >= 3:
        ok = np.isfinite(mk.depth_m)
        return _kabsch(mk.mat_xyz_m[ok], rays[ok] * mk.depth_m[ok, None])
    # Coplanar markers: plane coordinates (a, b) -> homography to normalised image points.
    X = mk.mat_xyz_m
    c = X.mean(0)
    _, _, Vt = np.linalg.svd(X - c)
    e1, e2 = Vt[0], Vt[1]
    n = np.cross(e1, e2)  # a right-handed plane frame, so R below is a rotation
    ab = np.stack([(X - c) @ e1, (X - c) @ e2], 1)
    if np.abs((X - c) @ n).max() > 0.05:
        raise UserError(
            "markers are not coplanar and have no depth: give depth_m for at least 3, or use markers on the mat"
        )
    A = []
    for (a, b), (x, y, _) in zip(ab, rays):
        A.append([a, b, 1, 0, 0, 0, -x * a, -x * b, -x])
        A.append([0, 0, 0, a, b, 1, -y * a, -y * b, -y])
    H = np.linalg.svd(np.array(A))[2][-1].reshape(3, 3)
    scale = 2.0 / (np.linalg.norm(H[:, 0]) + np.linalg.norm(H[:, 1]))
    H = H * scale
    if H[2, 2] < 0:  # the plane's origin in front of the camera
        H = -H
    R_plane = _nearest_rotation(np.stack([H[:, 0], H[:, 1], np.cross(H[:, 0], H[:, 1])], 1))
    t_plane = H[:, 2]
    # X = c + a e1 + b e2 (+ 0 n): R_mat = R_plane [e1 e2 n]^T, t = t_plane - R_mat c.
    R = R_plane @ np.stack([e1, e2, n], 0)
    return R, t_plane - R @ c


def _residuals(mk: Markers, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    K = mk.intrinsics.K
    r = (project(K, R, t, mk.mat_xyz_m) - mk.pixel).ravel()
    ok = np.isfinite(mk.depth_m)
    if ok.any():  # depth in pixel-equivalent units: 1 cm ~ fx * 0.01 / depth px
        z = (mk.mat_xyz_m[ok] @ R.T + t)[:, 2]
        r = np.concatenate([r, (z - mk.depth_m[ok]) * mk.intrinsics.fx / mk.depth_m[ok]])
    return r


def _refine_lm(mk: Markers, R: np.ndarray, t: np.ndarray, iterations: int = 50) -> tuple[np.ndarray, np.ndarray]:
    lam = 1e-3
    r = _residuals(mk, R, t)
    for _ in range(iterations):
        J = np.zeros((r.size, 6))
        for k in range(6):
            d = np.zeros(6)
            d[k] = 1e-7
            J[:, k] = (_residuals(mk, _rodrigues(d[:3]) @ R, t + d[3:]) - r) / 1e-7
        g = J.T @ r
        step = -np.linalg.solve(J.T @ J + lam * np.diag(np.diag(J.T @ J) + 1e-12), g)
        R2, t2 = _rodrigues(step[:3]) @ R, t + step[3:]
        r2 = _residuals(mk, R2, t2)
        if np.all(np.isfinite(r2)) and (r2 @ r2) < (r @ r):
            R, t, r, lam = R2, t2, r2, lam / 3
            if np.abs(step).max() < 1e-12:
                break
        else:
            lam *= 10
            if lam > 1e8:
                break
    return R, t


def _refine_cma(mk: Markers, R: np.ndarray, t: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    import cma

    def loss(x):
        r = _residuals(mk, _rodrigues(x[:3]) @ R, t + x[3:])
        return float(r @ r) if np.all(np.isfinite(r)) else 1e12

    es = cma.CMAEvolutionStrategy(
        np.zeros(6), 0.01, {"seed": seed + 1, "verbose": -9, "tolfun": 1e-12, "tolx": 1e-12, "maxfevals": 20000}
    )
    es.optimize(loss)
    x = es.result.xbest
    return _rodrigues(x[:3]) @ R, t + x[3:]


def solve_camera_pose(mk: Markers, method: str = "lm") -> CameraPose:
    """The camera pose from N >= 4 markers: a direct solution refined by Levenberg-Marquardt
    ("lm") or CMA-ES ("cma", the seed's search, started from the direct solution)."""
    if method not in ("lm", "cma"):
        raise UserError(f"method must be 'lm' or 'cma', got {method!r}")
    R, t = _initial_pose(mk)
    R, t = _refine_lm(mk, R, t) if method == "lm" else _refine_cma(mk, R, t)
    res = project(mk.intrinsics.K, R, t, mk.mat_xyz_m) - mk.pixel
    if not np.isfinite(res).all():
        raise UserError("no camera pose puts every marker in front of the camera: check the pixels and names")
    per = np.linalg.norm(res, axis=1)
    return CameraPose(R=R, t=t, rms_px=float(np.sqrt((per**2).mean())), residual_px=per)


def depth_to_points(depth_m: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """(H, W) depth image (m; 0 or non-finite = no reading) -> (N, 3) camera-frame points."""
    depth_m = np.asarray(depth_m, dtype=np.float64)
    if depth_m.ndim != 2:
        raise UserError(f"depth image must be 2-D (H, W), got shape {depth_m.shape}")
    v, u = np.nonzero(np.isfinite(depth_m) & (depth_m > 0))
    z = depth_m[v, u]
    return np.stack([(u - intr.cx) * z / intr.fx, (v - intr.cy) * z / intr.fy, z], 1)


def load_cloud(path: Path, intr: Intrinsics) -> np.ndarray:
    """A camera-frame cloud (N, 3) m from an (N, 3) point cloud or (H, W) depth image .npy."""
    arr = read_npy(path, f"no point cloud or depth image at {path}")
    if arr.ndim == 2 and arr.shape[1] == 3:
        pts = arr.astype(np.float64)
        return pts[np.isfinite(pts).all(1)]
    if arr.ndim == 2:
        return depth_to_points(arr, intr)
    raise UserError(f"{path} must be an (N, 3) point cloud or an (H, W) depth image, got shape {arr.shape}")


__all__ = [
    "CUBE_M",
    "FORMAT",
    "CameraPose",
    "Intrinsics",
    "Markers",
    "corner_markers",
    "depth_to_points",
    "load_cloud",
    "parse_markers",
    "project",
    "read_markers",
    "solve_camera_pose",
]
