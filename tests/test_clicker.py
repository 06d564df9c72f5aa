"""`pressurepose click`: the clicking page's API writes coregister's marker file (and the pose
from it is the camera's), refuses bad saves without writing, reads depth at clicks, edits an
existing file; bad images and intrinsics; and the page in headless Chromium: clicks on a
synthetic image land within a pixel of the true marker positions."""

import json
import math
import socket
import urllib.error
import urllib.request
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
import torch
from served import Served, opened
from webdriver import WebDriver, needs_chromium

from pressurepose.body.rotations import rotation_angle
from pressurepose.cli import main
from pressurepose.data.coregister import FORMAT, corner_markers, project, read_markers, solve_camera_pose
from pressurepose.viz.click_image import load_image
from pressurepose.viz.clicker import ClickConfig, make_click_server

INTR = {"fx": 365.0, "fy": 365.0, "cx": 256.0, "cy": 212.0}  # a Kinect v2 depth camera
K = np.array([[INTR["fx"], 0, INTR["cx"]], [0, INTR["fy"], INTR["cy"]], [0, 0, 1.0]])
W, H = 512, 424
CORNERS = corner_markers()


def camera_pose():
    """R, t (X_cam = R X_mat + t) of a camera 1.9 m above the bed looking down at its middle."""
    position, target = np.array([0.75, 0.42, 1.9]), np.array([0.92, 0.37, 0.0])
    z = (target - position) / np.linalg.norm(target - position)
    x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ position


R_TRUE, T_TRUE = camera_pose()
PIXELS = {name: project(K, R_TRUE, T_TRUE, X[None])[0] for name, X in CORNERS.items()}
DOT = {
    "head_left": (255, 60, 60),
    "head_right": (255, 220, 40),
    "foot_left": (40, 200, 255),
    "foot_right": (90, 255, 80),
}


@pytest.fixture(scope="module")
def picture(tmp_path_factory) -> Path:
    """A grey 512 x 424 image with a coloured dot (radius 3 px) centred on each projected corner
    (pixel centres at integer (u, v), as coregister counts them)."""
    img = np.full((H, W, 3), 90, np.uint8)
    vv, uu = np.mgrid[0:H, 0:W]
    for name, (u, v) in PIXELS.items():
        assert 10 < u < W - 10 and 10 < v < H - 10  # the pose keeps every corner in view
        img[(uu - u) ** 2 + (vv - v) ** 2 <= 9] = DOT[name]
    path = tmp_path_factory.mktemp("click") / "frame.png"
    matplotlib.image.imsave(path, img)
    return path


class Clicker(Served):
    """The click server on a free port, serving in a thread."""

    def __init__(self, image: Path, out: Path, **kwargs) -> None:
        super().__init__(make_click_server(ClickConfig(image=image, out=out, port=0, open=False, **kwargs)))

    def get(self, route: str) -> bytes:
        with urllib.request.urlopen(self.url + route, timeout=30) as r:
            return r.read()

    def post(self, payload, headers=None, raw: bytes | None = None) -> tuple[int, dict]:
        body = raw if raw is not None else json.dumps(payload).encode()
        req = urllib.request.Request(
            self.url + "api/save",
            data=body,
            method="POST",
            headers={"Content-Type": "application/json", **(headers or {})},
        )
        try:
            with urllib.request.urlopen(req, timeout=30) as r:
                return r.status, json.loads(r.read())
        except urllib.error.HTTPError as exc:
            return exc.code, json.loads(exc.read())


@pytest.fixture
def clicker():
    yield from opened(Clicker)


def payload(pixels=PIXELS, intrinsics=INTR, **extra):
    markers = [{"name": n, "pixel": [float(p[0]), float(p[1])]} for n, p in pixels.items()]
    return {"intrinsics": intrinsics, "markers": markers + extra.get("more", [])}


def angle_deg(R1, R2):
    """Angle between two rotation matrices (numpy), exact near 0 and pi (unlike acos of the trace)."""
    return math.degrees(
        float(rotation_angle(torch.as_tensor(R1, dtype=torch.float64), torch.as_tensor(R2, dtype=torch.float64)))
    )


# --- API -----------------------------------------------------------------------------------------


def test_saved_clicks_give_back_the_camera_pose(picture, tmp_path, clicker):
    out = tmp_path / "sub" / "markers.json"
    c = clicker(picture, out, fx=INTR["fx"], fy=INTR["fy"], cx=INTR["cx"], cy=INTR["cy"])
    info = json.loads(c.get("api/info"))
    assert (info["width"], info["height"], info["has_depth"]) == (W, H, False)
    assert info["intrinsics"] == INTR and info["markers"] == []
    assert {k: np.array(v) for k, v in info["corners"].items()}.keys() == CORNERS.keys()
    # the PNG the page shows is the image, pixel for pixel (so page pixels are image pixels)
    import io

    shown = matplotlib.image.imread(io.BytesIO(c.get("api/image.png")), format="png")[..., :3]
    np.testing.assert_array_equal((shown * 255).round(), (matplotlib.image.imread(picture)[..., :3] * 255).round())
    assert c.get("").startswith(b"<!doctype html>") and b"api/save" in c.get("clicker.js")
    # a JPEG of the same picture (through Pillow) reads as the same image, give or take compression
    matplotlib.image.imsave(tmp_path / "frame.jpg", matplotlib.image.imread(picture)[..., :3])
    jpg = load_image(tmp_path / "frame.jpg")
    assert jpg.size == (W, H) and jpg.depth_m is None
    u, v = np.round(PIXELS["head_left"]).astype(int)
    assert np.abs(jpg.rgb[v, u].astype(int) - DOT["head_left"]).max() < 40

    custom = {
        "name": "pillow",
        "pixel": project(K, R_TRUE, T_TRUE, np.array([[0.3, 0.2, 0.05]]))[0].tolist(),
        "mat_xyz_m": [0.3, 0.2, 0.05],
    }
    status, reply = c.post(payload(more=[custom]))
    assert status == 200, reply
    saved = json.loads(out.read_text())
    assert saved == reply["document"] and saved["format"] == FORMAT and saved["intrinsics"] == INTR
    assert [m["name"] for m in saved["markers"]] == [*PIXELS, "pillow"]
    assert saved["markers"][-1]["mat_xyz_m"] == [0.3, 0.2, 0.05]
    assert not any("depth_m" in m for m in saved["markers"])  # an RGB image has no depth
    # coregister's own loader and solver on the written file recover the camera
    mk = read_markers(out)
    np.testing.assert_allclose(mk.pixel[:4], np.stack(list(PIXELS.values())), atol=5e-4)  # 3 decimals
    pose = solve_camera_pose(mk)
    assert angle_deg(pose.R, R_TRUE) < 0.01 and np.abs(pose.t - T_TRUE).max() < 1e-3
    assert reply["pose"]["rms_px"] < 0.01
    np.testing.assert_allclose(reply["pose"]["camera_position_in_mat_m"], -R_TRUE.T @ T_TRUE, atol=1e-3)
    np.testing.assert_allclose(reply["pose"]["reprojected"], mk.pixel, atol=0.01)
    assert reply["command"] == f"pressurepose coregister --markers {out} --out out/coregister"


def test_bad_saves_write_nothing(picture, tmp_path, clicker):
    out = tmp_path / "markers.json"
    c = clicker(picture, out)  # no intrinsics yet: the page asks for them
    assert json.loads(c.get("api/info"))["intrinsics"] is None
    four = dict(PIXELS)
    three = dict(list(PIXELS.items())[:3])
    cases = [
        (payload(intrinsics={}), "intrinsics missing"),
        (payload(intrinsics={"fx": 365.0, "fy": 365.0, "cx": 256.0}), "cy missing"),
        (payload(intrinsics={**INTR, "fx": -1.0}), "focal lengths must be > 0"),
        (payload(three), "at least 4"),
        (payload(four, more=[{"name": "head_left", "pixel": [5.0, 5.0]}]), "names repeat"),
        (payload(four, more=[{"name": "pillow", "pixel": [5.0, 5.0]}]), "give its mat_xyz_m"),
        (payload({**three, "foot_right": np.array([W - 0.4, 10.0])}), "outside the 512 x 424 image"),
        (payload({**three, "foot_right": np.array([float("nan"), 10.0])}), "finite"),
        ({"markers": "all of them"}, "intrinsics missing"),
        (payload(four, more=[{"pixel": [1.0, 2.0]}]), "needs a name"),
    ]
    for body, message in cases:
        status, reply = c.post(body)
        assert status == 400 and message in reply["error"], (message, reply)
    assert c.post(None, raw=b"{not json")[0] == 400
    assert c.post(payload(), headers={"Content-Type": "text/plain"})[0] == 415
    assert c.post(payload(), headers={"Origin": "http://evil.example"})[0] == 403
    assert c.post(payload(), headers={"Host": "evil.example:80"})[0] == 403
    assert not out.exists() and list(tmp_path.iterdir()) == []
    # a good save, then bad ones leave it as it is
    assert c.post(payload(), headers={"Origin": c.url.rstrip("/")})[0] == 200
    before = out.read_bytes()
    assert c.post(payload(three))[0] == 400
    assert out.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["markers.json"]


def test_existing_file_is_loaded_for_editing(picture, tmp_path, clicker):
    out = tmp_path / "markers.json"
    doc = {
        "format": FORMAT,
        "intrinsics": INTR,
        "markers": [{"name": n, "pixel": p.round(2).tolist(), "depth_m": 1.9} for n, p in PIXELS.items()],
    }
    out.write_text(json.dumps(doc))
    info = json.loads(clicker(picture, out).get("api/info"))
    assert info["intrinsics"] == INTR and info["markers"] == doc["markers"]
    # flags override single numbers; the file's others stay
    intr_file = tmp_path / "k.json"
    intr_file.write_text(json.dumps({"fx": 500.0, "fy": 501.0, "cx": 300.0, "cy": 200.0}))
    info = json.loads(clicker(picture, out, intrinsics=intr_file, cy=199.5).get("api/info"))
    assert info["intrinsics"] == {"fx": 500.0, "fy": 501.0, "cx": 300.0, "cy": 199.5}
    # an RGB image keeps depths the page sends back (those of markers that did not move)
    c = clicker(picture, out)
    status, reply = c.post({"intrinsics": INTR, "markers": info["markers"]})
    assert status == 200 and [m["depth_m"] for m in reply["document"]["markers"]] == [1.9] * 4


def test_depth_image_clicks_record_depth(tmp_path, clicker):
    rng = np.random.default_rng(0)
    depth_mm = rng.integers(1500, 2100, (H, W)).astype(np.uint16)
    depth_mm[:40, :40] = 0  # no reading there
    path = tmp_path / "depth.npy"
    np.save(path, depth_mm)
    img = load_image(path)
    assert img.rgb.shape == (H, W, 3) and (img.rgb[:40, :40] == 0).all()
    out = tmp_path / "m.json"
    c = clicker(path, out, **INTR)
    info = json.loads(c.get("api/info"))
    assert info["has_depth"] and info["depth_range_m"] == [
        depth_mm[depth_mm > 0].min() / 1000,
        depth_mm[depth_mm > 0].max() / 1000,
    ]
    clicks = {
        "head_left": [100.4, 50.6],
        "head_right": [400.0, 60.49],
        "foot_left": [20.2, 10.0],  # no reading
        "foot_right": [510.7, 423.2],
    }
    # the page's depth look-up and the saved file: the reading at the nearest pixel, in metres
    assert json.loads(c.get("api/depth?u=100.4&v=50.6"))["depth_m"] == depth_mm[51, 100] / 1000
    assert json.loads(c.get("api/depth?u=20&v=10"))["depth_m"] is None
    with pytest.raises(urllib.error.HTTPError, match="400"):
        c.get("api/depth?u=left")
    status, reply = c.post(payload({k: np.array(v) for k, v in clicks.items()}))
    assert status == 200, reply
    got = {m["name"]: m.get("depth_m") for m in json.loads(out.read_text())["markers"]}
    assert got == {
        "head_left": depth_mm[51, 100] / 1000,
        "head_right": depth_mm[60, 400] / 1000,
        "foot_left": None,
        "foot_right": depth_mm[423, 511] / 1000,
    }
    assert read_markers(out).depth_m[0] == depth_mm[51, 100] / 1000
    assert f"--cloud {path}" in reply["command"]
    # float depth in metres is taken as metres; the same numbers in mm as mm
    np.save(tmp_path / "m.npy", depth_mm.astype(np.float32) / 1000)
    np.testing.assert_allclose(load_image(tmp_path / "m.npy").depth_m, load_image(path).depth_m, rtol=1e-6)
    np.save(tmp_path / "mm.npy", depth_mm.astype(np.float32))
    np.testing.assert_allclose(load_image(tmp_path / "mm.npy").depth_m, load_image(path).depth_m, rtol=1e-6)


def test_bad_images_and_intrinsics(picture, tmp_path, capsys, monkeypatch):
    (tmp_path / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(200)))
    (tmp_path / "notes.txt").write_text("hello")
    np.save(tmp_path / "cube.npy", np.ones((4, 5, 6)))
    np.save(tmp_path / "zeros.npy", np.zeros((20, 30)))
    np.save(tmp_path / "names.npy", np.array(["a", "b"]))
    (tmp_path / "torn.npy").write_bytes(b"\x93NUMPY garbage")
    (tmp_path / "k.json").write_text("{ not json")
    (tmp_path / "other.json").write_text(json.dumps({"format": "something else"}))
    good = ["--fx", "365", "--fy", "365", "--cx", "256", "--cy", "212"]
    cases = [
        ([str(tmp_path / "missing.png")], "no image at"),
        ([str(tmp_path / "corrupt.png")], "not a readable image"),
        ([str(tmp_path / "notes.txt")], "must be a .png or .jpg"),
        ([str(tmp_path / "cube.npy")], "must be 2-D"),
        ([str(tmp_path / "zeros.npy")], "no valid reading"),
        ([str(tmp_path / "names.npy")], "numeric depth image"),
        ([str(tmp_path / "torn.npy")], "not a readable .npy"),
        ([str(picture), "--fx", "365"], "fy, cx, cy missing"),
        ([str(picture), *good[:-2], "--cy", "nan"], "finite"),
        ([str(picture), "--fx", "0", *good[2:]], "focal lengths must be > 0"),
        ([str(picture), "--intrinsics", str(tmp_path / "k.json")], "not readable JSON"),
        ([str(picture), "--intrinsics", str(tmp_path / "nothing.json")], "does not exist"),
        ([str(picture), "--out", str(tmp_path / "other.json")], "is not a marker file"),
        ([str(picture), "--out", str(tmp_path)], "is a folder"),
    ]
    for args, message in cases:
        with pytest.raises(ValueError, match=message):
            opts = {"out": tmp_path / "x.json"}
            it = iter(args[1:])
            for flag, value in zip(it, it):
                key = flag[2:]
                opts[key] = Path(value) if key in ("intrinsics", "out") else float(value)
            make_click_server(ClickConfig(image=Path(args[0]), port=0, open=False, **opts))
        assert main(["click", *args, "--port", "0", "--no-open"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and message.split()[0] in err and "Traceback" not in err
    # a good command line reaches the server (run_local stubbed: it would serve until Ctrl-C)
    served = []
    monkeypatch.setattr(
        "pressurepose.viz.viewer.run_local",
        lambda server, open_browser, ready: (served.append(server), server.server_close()),
    )
    assert main(["click", str(picture), *good, "--port", "0", "--no-open", "--out", str(tmp_path / "y.json")]) == 0
    assert served[0].session.intrinsics == INTR and served[0].session.image.size == (W, H)
    with socket.socket() as taken:  # the viewer's port handling
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        assert main(["click", str(picture), "--port", str(taken.getsockname()[1]), "--no-open"]) == 2
        assert "--port" in capsys.readouterr().err


# --- the page in headless Chromium ---------------------------------------------------------------


def view(driver: WebDriver) -> list[float]:
    """The canvas's place on the page and the page's displayed scale and offset (CSS px)."""
    return driver.js(
        "const r = document.getElementById('img').getBoundingClientRect();"
        "const c = window.clickerState; return [r.left, r.top, c.scale, c.offX, c.offY];"
    )


def screen_point(driver: WebDriver, u: float, v: float) -> tuple[int, int]:
    """Viewport position (whole CSS px, as WebDriver moves the pointer) nearest image point (u, v)."""
    left, top, scale, off_x, off_y = view(driver)
    return round(left + off_x + (u + 0.5) * scale), round(top + off_y + (v + 0.5) * scale)


def click_at(driver: WebDriver, u: float, v: float) -> np.ndarray:
    """Click nearest image point (u, v); the image point actually clicked, by the documented
    convention (pixel centres at integers), which the page must record."""
    left, top, scale, off_x, off_y = view(driver)
    x, y = screen_point(driver, u, v)
    driver.actions(
        [
            {"type": "pointerMove", "x": x, "y": y, "origin": "viewport", "duration": 0},
            {"type": "pointerDown", "button": 0},
            {"type": "pointerUp", "button": 0},
        ]
    )
    return np.array([(x - left - off_x) / scale - 0.5, (y - top - off_y) / scale - 0.5])


def markers(driver: WebDriver) -> dict[str, list[float]]:
    return {m["name"]: m["pixel"] for m in driver.js("return window.clickerState.markers")}


@needs_chromium
def test_clicking_in_headless_chromium(picture, tmp_path, clicker):
    out = tmp_path / "markers.json"
    c = clicker(picture, out, **INTR)
    driver = WebDriver()
    state = "return window.clickerState"
    try:
        driver.cmd("POST", "/url", {"url": c.url})
        driver.wait("return document.body.dataset.ready === '1'", state=state)
        st = driver.js(state)
        assert st["error"] == "" and st["active"] == "head_left" and st["scale"] > 1  # fitted, enlarged
        # The image is drawn where the page's scale and offset say: each dot's centre on screen,
        # mapped back with them (pixel centres at integers), is the dot's centre in the image.
        shot = driver.screenshot()
        left, top, dpr = driver.js(
            "const r = document.getElementById('img').getBoundingClientRect();"
            "return [r.left, r.top, window.devicePixelRatio];"
        )
        vv, uu = np.mgrid[0:H, 0:W]
        image = (matplotlib.image.imread(picture)[..., :3] * 255).round()
        for name, rgb in DOT.items():
            on_screen = np.argwhere(np.abs(shot.astype(int) - rgb).sum(-1) < 12)  # (row, col) device px
            assert len(on_screen) > 20, name
            y, x = (on_screen.mean(0) + 0.5) / dpr
            seen = np.array([(x - left - st["offX"]) / st["scale"] - 0.5, (y - top - st["offY"]) / st["scale"] - 0.5])
            mask = (image == rgb).all(-1)
            np.testing.assert_allclose(seen, [uu[mask].mean(), vv[mask].mean()], atol=0.3, err_msg=name)
        # head_left placed 15 px off, then dragged onto its dot (a move, not a second marker)
        u, v = PIXELS["head_left"]
        click_at(driver, u + 15, v + 10)
        assert list(markers(driver)) == ["head_left"] and driver.js(state)["active"] == "head_right"
        start, end = screen_point(driver, u + 15, v + 10), screen_point(driver, u, v)
        driver.actions(
            [
                {"type": "pointerMove", "x": start[0], "y": start[1], "origin": "viewport"},
                {"type": "pointerDown", "button": 0},
                {
                    "type": "pointerMove",
                    "x": (start[0] + end[0]) // 2,
                    "y": (start[1] + end[1]) // 2,
                    "origin": "viewport",
                    "duration": 50,
                },
                {"type": "pointerMove", "x": end[0], "y": end[1], "origin": "viewport", "duration": 50},
                {"type": "pointerUp", "button": 0},
            ]
        )
        assert np.abs(np.subtract(markers(driver)["head_left"], PIXELS["head_left"])).max() < 1
        # the others in turn (the page moves on to the next corner by itself); foot_left zoomed in
        click_at(driver, *PIXELS["head_right"])
        fl = screen_point(driver, *PIXELS["foot_left"])
        before = driver.js(state)["scale"]
        driver.cmd(
            "POST",
            "/actions",
            {
                "actions": [
                    {
                        "type": "wheel",
                        "id": "wheel",
                        "actions": [
                            {
                                "type": "scroll",
                                "x": fl[0],
                                "y": fl[1],
                                "deltaX": 0,
                                "deltaY": -500,
                                "origin": "viewport",
                            }
                        ],
                    }
                ]
            },
        )
        driver.wait(f"return window.clickerState.scale > {before} * 1.5", state=state)
        zoomed = click_at(driver, *PIXELS["foot_left"])
        assert driver.js(state)["scale"] > 4
        np.testing.assert_allclose(markers(driver)["foot_left"], zoomed, atol=0.01)
        driver.click("#fit")
        click_at(driver, *PIXELS["foot_right"])
        assert list(markers(driver)) == list(PIXELS)
        # undo takes foot_right away; clicking it again puts it back
        driver.click("#undo")
        assert list(markers(driver)) == list(PIXELS)[:3] and driver.js(state)["active"] == "foot_right"
        driver.click("#undo")
        driver.click("#undo")
        assert list(markers(driver)) == ["head_left"] and driver.js(state)["active"] == "head_right"
        clicked = {name: click_at(driver, *PIXELS[name]) for name in ("head_right", "foot_left", "foot_right")}
        driver.click("#save")
        driver.wait("return window.clickerState.saves === 1", state=state)
        assert driver.js(state)["error"] == ""
        assert "pressurepose coregister --markers" in driver.js("return document.getElementById('command').textContent")
    finally:
        driver.close()
    saved = {m["name"]: m["pixel"] for m in json.loads(out.read_text())["markers"]}
    assert list(saved) == list(PIXELS)
    for name, p in PIXELS.items():
        # where the pointer was, to the page's rounding; within half a pixel of the true marker
        if name in clicked:
            np.testing.assert_allclose(saved[name], clicked[name], atol=0.01, err_msg=name)
        assert np.abs(np.subtract(saved[name], p)).max() < 0.5, (name, saved[name], p)
    pose = solve_camera_pose(read_markers(out))
    assert angle_deg(pose.R, R_TRUE) < 1.0
