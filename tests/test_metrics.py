"""Evaluation metrics against naive loops, zero for identical inputs, known errors for known
motions, symmetry, and bad input."""

import math

import pytest
import torch

from pressurepose.body.rotations import axis_angle_to_matrix
from pressurepose.eval.metrics import (
    camera_facing,
    mpjpe,
    pa_mpjpe,
    per_vertex_error,
    procrustes_align,
    root_orientation_error,
    root_position_error,
    vertex_normals_and_areas,
    voxel_downsample,
    vpe,
    vpe_to_cloud,
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
    loop = torch.tensor(
        [sum(float((est[b, j] - true[b, j]).norm()) for j in range(24)) / 24 for b in range(3)], dtype=D
    )
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


def reference_vpe(est, true, faces, camera):
    """3DVPE as it was computed before the exact pruned search (eval.nearest): per sample,
    brute-force nearest neighbours between the camera-facing vertices."""
    from pressurepose.eval.nearest import nearest_brute

    mask_e, area_e = camera_facing(est, faces, camera)
    mask_t, area_t = camera_facing(true, faces, camera)
    out = []
    for i in range(est.shape[0]):
        e, t = est[i][mask_e[i]], true[i][mask_t[i]]
        we, wt = area_e[i][mask_e[i]], area_t[i][mask_t[i]]
        out.append(((nearest_brute(e, t) * we).sum() / we.sum() + (nearest_brute(t, e) * wt).sum() / wt.sum()) / 2)
    return torch.stack(out)


def posed_bodies(body, n, seed, dtype):
    from pressurepose.body.params import BodyParams

    gen = torch.Generator().manual_seed(seed)
    params = BodyParams.zeros(n, body.default_shape(n), dtype=dtype)
    pose = 0.3 * torch.randn(n, 23, 3, generator=gen, dtype=D).to(dtype)
    trans = (torch.tensor([1.0, 0.4, 0.2], dtype=D) + 0.05 * torch.randn(n, 3, generator=gen, dtype=D)).to(dtype)
    return body(params.replace(pose=pose, root_translation=trans)).vertices


def test_vpe_of_body_meshes_matches_the_brute_force_reference(anny64, anny32):
    from pressurepose.eval.metrics import CAMERA_M, facing_meshes, vpe_between

    est, true = posed_bodies(anny64, 3, 0, D), posed_bodies(anny64, 3, 1, D)
    want = reference_vpe(est, true, anny64.faces, CAMERA_M)
    assert float((vpe(est, true, anny64.faces) - want).abs().max()) <= 1e-9
    # One mesh (a baseline's) against several, packed once.
    one = facing_meshes(est[:1], anny64.faces)
    many = facing_meshes(true, anny64.faces)
    assert (
        float(
            (vpe_between(one, many) - reference_vpe(est[:1].expand(3, -1, -1), true, anny64.faces, CAMERA_M))
            .abs()
            .max()
        )
        <= 1e-9
    )
    with pytest.raises(ValueError, match="batch size"):
        vpe_between(facing_meshes(est[:2], anny64.faces), many)
    # float32, as evaluate runs: equal to round-off.
    est32, true32 = posed_bodies(anny32, 2, 2, torch.float32), posed_bodies(anny32, 2, 3, torch.float32)
    torch.testing.assert_close(
        vpe(est32, true32, anny32.faces), reference_vpe(est32, true32, anny32.faces, CAMERA_M), rtol=1e-5, atol=1e-8
    )


def test_cloud_vpe_matches_the_brute_force_reference(anny64):
    from pressurepose.eval.nearest import nearest_brute

    est = posed_bodies(anny64, 1, 4, D)[0]
    gen = torch.Generator().manual_seed(5)
    cloud = posed_bodies(anny64, 1, 6, D)[0] + 0.003 * torch.randn(est.shape, generator=gen, dtype=D)
    mask, area = camera_facing(est[None], anny64.faces)
    e, w = est[mask[0]], area[0][mask[0]]
    c = voxel_downsample(cloud)
    want = ((nearest_brute(e, c) * w).sum() / w.sum() + nearest_brute(c, e).mean()) / 2
    assert abs(float(vpe_to_cloud(est, anny64.faces, cloud)) - float(want)) <= 1e-9
