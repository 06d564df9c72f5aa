"""Evaluation metrics against naive loops, zero for identical inputs, known errors for known
motions, symmetry, and bad input."""

import math

import pytest
import torch

from pressurepose.body.rotations import axis_angle_to_matrix
from pressurepose.eval.metrics import (
    camera_facing, mpjpe, pa_mpjpe, per_vertex_error, procrustes_align, root_orientation_error,
    root_position_error, vertex_normals_and_areas, voxel_downsample, vpe, vpe_to_cloud,
)

D = torch.float64
g = torch.Generator().manual_seed(0)


def grid_mesh(n=9, spacing=0.05, z=0.0):
    """An upward-facing square grid (n x n vertices) in the plane z."""
    ii, jj = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    v = torch.stack([ii.flatten() * spacing, jj.flatten() * spacing, torch.full((n * n,), z)], -1).to(D)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            faces += [(a, b, c), (a, c, d)]
    return v, torch.tensor(faces)


def blob(anny_vertices=None):
    """A closed mesh: an icosphere-like UV sphere of radius 0.1 m, outward faces."""
    n_lat, n_lon = 10, 16
    verts = [(0.0, 0.0, 0.1)]
    for i in range(1, n_lat):
        th = math.pi * i / n_lat
        for j in range(n_lon):
            ph = 2 * math.pi * j / n_lon
            verts.append((0.1 * math.sin(th) * math.cos(ph), 0.1 * math.sin(th) * math.sin(ph), 0.1 * math.cos(th)))
    verts.append((0.0, 0.0, -0.1))
    faces = []
    for j in range(n_lon):
        faces.append((0, 1 + j, 1 + (j + 1) % n_lon))
    for i in range(n_lat - 2):
        for j in range(n_lon):
            a, b = 1 + i * n_lon + j, 1 + i * n_lon + (j + 1) % n_lon
            c, d = a + n_lon, b + n_lon
            faces += [(a, c, d), (a, d, b)]
    last = len(verts) - 1
    base = 1 + (n_lat - 2) * n_lon
    for j in range(n_lon):
        faces.append((last, base + (j + 1) % n_lon, base + j))
    return torch.tensor(verts, dtype=D), torch.tensor(faces)


def naive_vpe(est, true, faces, camera):
    def facing(v):
        normals = [torch.zeros(3, dtype=D) for _ in range(len(v))]
        areas = [0.0] * len(v)
        for f in faces.tolist():
            a, b, c = (v[k] for k in f)
            cr = torch.linalg.cross(b - a, c - a)
            for k in f:
                normals[k] = normals[k] + cr
                areas[k] += float(cr.norm()) / 6
        cam = torch.tensor(camera, dtype=D)
        keep = [k for k in range(len(v)) if float((cam - v[k]) @ normals[k]) > 0]
        return keep, areas

    def directed(a, ka, wa, b, kb):
        num = sum(wa[i] * min(float((a[i] - b[j]).norm()) for j in kb) for i in ka)
        return num / sum(wa[i] for i in ka)

    ke, ae = facing(est)
    kt, at = facing(true)
    return (directed(est, ke, ae, true, kt) + directed(true, kt, at, est, ke)) / 2


def test_vpe_matches_a_naive_loop_and_is_symmetric():
    v, f = blob()
    cam = (0.3, 0.1, 1.0)
    est = (v + 0.01 * torch.randn(v.shape, generator=g, dtype=D))[None]
    true = (v * 1.1 + torch.tensor([0.02, -0.01, 0.0], dtype=D))[None]
    ours = vpe(est, true, f, camera=cam)
    assert float(ours[0]) == pytest.approx(naive_vpe(est[0], true[0], f, cam), rel=1e-10)
    torch.testing.assert_close(vpe(true, est, f, camera=cam), ours)
    assert float(vpe(true, true, f, camera=cam)[0]) == 0.0


def test_vpe_of_a_surface_lifted_along_its_normal_is_the_lift():
    v, f = grid_mesh()
    lifted = v + torch.tensor([0.0, 0.0, 0.013], dtype=D)
    assert float(vpe(v[None], lifted[None], f, camera=(0.2, 0.2, 2.0))[0]) == pytest.approx(0.013, rel=1e-12)


def test_camera_facing_and_vertex_areas():
    v, f = blob()
    facing, areas = camera_facing(v[None], f, camera=(0.0, 0.0, 5.0))
    # The upper hemisphere faces a camera high above; the lower one does not.
    assert facing[0, v[:, 2] > 0.01].all() and not facing[0, v[:, 2] < -0.01].any()
    _, a2 = vertex_normals_and_areas(v[None], f)
    v0, v1, v2 = (v[f[:, k]] for k in range(3))
    total = torch.linalg.cross(v1 - v0, v2 - v0).norm(dim=-1).sum() / 2
    torch.testing.assert_close(a2.sum(), total)
    assert areas.shape == (1, v.shape[0])


def test_joint_and_vertex_errors_against_loops_and_known_translation():
    est = torch.randn(3, 24, 3, generator=g, dtype=D)
    true = torch.randn(3, 24, 3, generator=g, dtype=D)
    loop = torch.tensor([sum(float((est[b, j] - true[b, j]).norm()) for j in range(24)) / 24 for b in range(3)], dtype=D)
    torch.testing.assert_close(mpjpe(est, true), loop)
    torch.testing.assert_close(per_vertex_error(est, true), loop)
    t = torch.tensor([0.03, -0.04, 0.0], dtype=D)  # |t| = 5 cm
    torch.testing.assert_close(mpjpe(true + t, true), torch.full((3,), 0.05, dtype=D))
    assert float(mpjpe(true, true).abs().max()) == 0.0
    torch.testing.assert_close(mpjpe(est, true), mpjpe(true, est))


def test_pa_mpjpe_removes_similarity_transforms_only():
    true = torch.randn(2, 24, 3, generator=g, dtype=D)
    R = axis_angle_to_matrix(torch.tensor([[0.3, -0.2, 0.9], [1.0, 0.4, -0.5]], dtype=D))
    moved = 1.3 * true @ R.transpose(1, 2) + torch.tensor([0.5, -1.0, 2.0], dtype=D)
    assert float(pa_mpjpe(moved, true).abs().max()) < 1e-12
    torch.testing.assert_close(procrustes_align(moved, true), true)
    # A mirror image is not a similarity transform: some error remains.
    mirrored = true * torch.tensor([-1.0, 1.0, 1.0], dtype=D)
    assert (pa_mpjpe(mirrored, true) > 1e-3).all()
    noisy = true + 0.01 * torch.randn(true.shape, generator=g, dtype=D)
    assert (pa_mpjpe(noisy, true) <= mpjpe(noisy, true) + 1e-12).all()


def test_root_errors():
    a = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=D)
    b = torch.tensor([[0.0, 0.0, 0.5], [0.0, 0.0, 1.0]], dtype=D)
    torch.testing.assert_close(root_orientation_error(a, b), torch.tensor([0.5, 0.0], dtype=D))
    torch.testing.assert_close(root_orientation_error(b, a), torch.tensor([0.5, 0.0], dtype=D))
    near_pi = torch.tensor([[math.pi - 1e-3, 0, 0]], dtype=D)
    assert float(root_orientation_error(near_pi, -near_pi)[0]) == pytest.approx(2e-3, abs=1e-9)
    torch.testing.assert_close(root_position_error(a, b), torch.tensor([0.5, 0.0], dtype=D))


def test_cloud_vpe_and_voxel_downsampling():
    v, f = grid_mesh(n=11, spacing=0.02)
    v = v + 0.005  # grid points inside voxels, not on their boundaries
    cloud = v + torch.tensor([0.0, 0.0, 0.004], dtype=D)
    dense = torch.cat([cloud, cloud + 1e-4])  # duplicates within one voxel collapse
    assert voxel_downsample(dense, 0.01).shape[0] == cloud.shape[0]
    assert float(vpe_to_cloud(v, f, dense, camera=(0.1, 0.1, 2.0))) == pytest.approx(0.004 + 0.5e-4, abs=2e-5)
    with pytest.raises(ValueError, match="empty"):
        voxel_downsample(torch.full((4, 3), float("nan"), dtype=D))


def test_bad_inputs_are_refused():
    v, f = blob()
    with pytest.raises(ValueError, match="same body model"):
        mpjpe(torch.zeros(1, 24, 3), torch.zeros(1, 23, 3))
    with pytest.raises(ValueError, match="NaN"):
        per_vertex_error(torch.full((1, 5, 3), float("nan")), torch.zeros(1, 5, 3))
    with pytest.raises(ValueError, match=r"\(B, N, 3\)"):
        vpe(v, v, f)
    with pytest.raises(ValueError, match="batch size"):
        vpe(v[None], torch.stack([v, v]), f)
    with pytest.raises(ValueError, match="no camera-facing"):
        vpe(v[None], v[None], f, camera=(0.0, 0.0, 0.0))  # the camera inside the mesh sees nothing
