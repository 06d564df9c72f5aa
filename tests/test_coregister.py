"""Camera-mat co-registration: recovers a known camera pose from noisy synthetic clicks, with
and without depth; point clouds into the mat frame; bad marker files."""

import json
import math

import numpy as np
import pytest
import torch

from pressurepose.body.rotations import rotation_angle
from pressurepose.data.coregister import (
    FORMAT,
    Intrinsics,
    corner_markers,
    depth_to_points,
    parse_markers,
    project,
    read_markers,
    solve_camera_pose,
)

K = Intrinsics(fx=365.0, fy=365.0, cx=256.0, cy=212.0)  # a Kinect v2 depth camera


def look_at(position, target):
    """R, t of a camera at `position` (mat frame) looking at `target` (x right, y down, z forward)."""
    z = np.asarray(target, float) - position
    z /= np.linalg.norm(z)
    x = np.cross(z, [1.0, 0.0, 0.0])  # image x across the bed
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ position


def marker_file(R, t, noise_px=0.0, depth=False, extra=(), seed=0):
    rng = np.random.default_rng(seed)
    corners = corner_markers()
    pts = dict(corners)
    pts.update({name: np.asarray(x, float) for name, x in extra})
    items = []
    for name, X in pts.items():
        uv = project(K.K, R, t, X[None])[0] + rng.normal(0, noise_px, 2)
        item = {"name": name, "pixel": uv.tolist()}
        if name not in corners:
            item["mat_xyz_m"] = X.tolist()
        if depth:
            item["depth_m"] = float((R @ X + t)[2] + rng.normal(0, 0.002))
        items.append(item)
    return {"format": FORMAT, "intrinsics": {"fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy}, "markers": items}


def angle_deg(R1, R2):
    """Angle between two rotation matrices (numpy), exact near 0 and pi (unlike acos of the trace)."""
    return math.degrees(
        float(rotation_angle(torch.as_tensor(R1, dtype=torch.float64), torch.as_tensor(R2, dtype=torch.float64)))
    )


@pytest.mark.parametrize("method", ["lm", "cma"])
def test_recovers_a_known_pose_from_noisy_clicks(method):
    R, t = look_at(np.array([0.7, 0.45, 1.9]), [0.9, 0.37, 0.0])
    extra = [("pillow_marker", [0.3, 0.1, 0.0]), ("side_marker", [1.2, 0.7, 0.0])]
    grid = np.stack(np.meshgrid(np.linspace(0, 1.83, 7), np.linspace(0, 0.74, 4), [0.0, 0.3]), -1).reshape(-1, 3)
    errs = []
    for seed in range(5):
        pose = solve_camera_pose(parse_markers(marker_file(R, t, noise_px=0.5, extra=extra, seed=seed)), method)
        # What users need: points the camera sees land where they are on the mat.
        mapped = np.abs(pose.to_mat(grid @ R.T + t) - grid).max()
        errs.append((angle_deg(pose.R, R), mapped))
        assert pose.rms_px < 1.5
    rot, mapped = np.array(errs).T
    assert rot.max() < 1.0 and mapped.max() < 0.015, errs  # 0.5 px clicks: < 1 deg, < 1.5 cm on the bed
    exact = solve_camera_pose(parse_markers(marker_file(R, t)), method)
    assert angle_deg(exact.R, R) < 1e-4 and np.abs(exact.t - t).max() < 1e-5


def test_depth_markers_fix_the_pose_and_clouds_come_to_the_mat_frame():
    R, t = look_at(np.array([0.9, 0.37, 2.1]), [0.9, 0.37, 0.0])
    pose = solve_camera_pose(parse_markers(marker_file(R, t, noise_px=0.3, depth=True)))
    assert angle_deg(pose.R, R) < 0.5
    # A body-sized blob on the mat, seen by the camera, comes back where it was.
    X = np.random.default_rng(1).uniform([0.5, 0.2, 0.0], [1.3, 0.5, 0.25], (500, 3))
    back = pose.to_mat(X @ R.T + t)
    assert np.abs(back - X).max() < 0.02
    # Depth image round trip: points from a synthetic depth image.
    depth = np.zeros((424, 512))
    depth[200, 300], depth[10, 20] = 1.5, 2.0
    pts = depth_to_points(depth, K)
    assert pts.shape == (2, 3)
    uv = pts @ K.K.T
    np.testing.assert_allclose(np.sort(uv[:, 0] / uv[:, 2]), [20.0, 300.0])


def test_bad_marker_files_are_refused(tmp_path):
    R, t = look_at(np.array([0.9, 0.37, 2.0]), [0.9, 0.37, 0.0])
    good = marker_file(R, t)
    cases = {
        "not a marker file": {**good, "format": "other"},
        "intrinsics": {k: v for k, v in good.items() if k != "intrinsics"},
        "at least 4": {**good, "markers": good["markers"][:3]},
        "finite number": {
            **good,
            "markers": [{**good["markers"][0], "pixel": [float("nan"), 1.0]}] + good["markers"][1:],
        },
        "not a named corner": {**good, "markers": good["markers"] + [{"name": "elbow", "pixel": [1, 2]}]},
        "focal lengths": {**good, "intrinsics": {"fx": -1, "fy": 1, "cx": 0, "cy": 0}},
        "collinear": {
            **good,
            "markers": [{"name": f"m{k}", "pixel": [k, k], "mat_xyz_m": [0.1 * k, 0, 0]} for k in range(4)],
        },
    }
    for message, data in cases.items():
        with pytest.raises(ValueError, match=message):
            parse_markers(json.loads(json.dumps(data)))
    path = tmp_path / "m.json"
    path.write_text("{")
    with pytest.raises(ValueError, match="not readable JSON"):
        read_markers(path)
    with pytest.raises(ValueError, match="no marker file"):
        read_markers(tmp_path / "missing.json")


def test_coregister_cli_writes_pose_cloud_and_figure(tmp_path):
    import subprocess
    import sys

    from pressurepose.cli import main

    R, t = look_at(np.array([0.9, 0.37, 2.0]), [0.9, 0.37, 0.0])
    (tmp_path / "m.json").write_text(json.dumps(marker_file(R, t, noise_px=0.2)))
    X = np.random.default_rng(0).uniform([0.4, 0.1, 0.0], [1.4, 0.6, 0.2], (300, 3))
    np.save(tmp_path / "cloud.npy", X @ R.T + t)
    out = tmp_path / "out"
    assert (
        main(
            [
                "coregister",
                "--markers",
                str(tmp_path / "m.json"),
                "--cloud",
                str(tmp_path / "cloud.npy"),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    record = json.loads((out / "camera.json").read_text())
    np.testing.assert_allclose(record["camera_position_in_mat_m"], [0.9, 0.37, 2.0], atol=0.03)
    assert np.abs(np.load(out / "cloud_mat.npy") - X).max() < 0.02
    assert (out / "coregister.png").read_bytes()[:4] == b"\x89PNG"
    np.save(tmp_path / "bad.npy", np.zeros((2, 2, 2)))
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "pressurepose.cli",
            "coregister",
            "--markers",
            str(tmp_path / "m.json"),
            "--cloud",
            str(tmp_path / "bad.npy"),
            "--out",
            str(tmp_path / "o2"),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr and "depth image" in r.stderr
