"""`pressurepose click IMAGE --out markers.json`: a local page to click the mat's corner markers.

`pressurepose coregister` (seed A.6) reads the markers' pixel positions from a JSON file
(`data/coregister.py`); this page makes that file. It runs on the viewer's server machinery
(`viz.viewer.LocalServer`: Python's standard library, 127.0.0.1 only, the Host check) and
serves one static page (`viz/static/clicker.{html,js}`, no third-party code, nothing fetched
from the internet):

    GET  /                 the page (clicker.html, clicker.js)
    GET  /api/info         image size, intrinsics, the markers so far, the named corners
    GET  /api/image.png    the image as PNG (a depth image rendered with a colour map)
    GET  /api/depth?u=&v=  {"depth_m": the depth image's reading at pixel (u, v), or null}
    POST /api/save         {"intrinsics": {...}, "markers": [...]} -> validated as coregister's
                           loader does, written atomically to --out; answers the written
                           document, the pose it gives and the next command

Pixel convention (coregister's: `depth_to_points` puts pixel (row v, column u) at (u, v)):
u right, v down, in the original image's pixels, (0, 0) = the CENTRE of the top-left pixel;
its outer corner is (-0.5, -0.5). Sub-pixel values are kept (3 decimals).

A depth image (.npy, (H, W), metres or millimetres) is shown with a colour map and each
marker's `depth_m` is its reading at the nearest pixel, when that reading is valid (> 0,
finite); an RGB image's markers keep a `depth_m` only if the loaded --out file had one and the
marker has not moved.
"""

from __future__ import annotations

import dataclasses
import io
import json
import logging
import shlex
import threading
from pathlib import Path
from typing import Literal
from urllib.parse import urlparse

import tyro

from pressurepose.data.coregister import (
    FORMAT,
    _number,
    _vector,
    corner_markers,
    parse_markers,
    project,
    solve_camera_pose,
)
from pressurepose.errors import UserError
from pressurepose.files import atomic_write
from pressurepose.validate import read_json
from pressurepose.viz.click_image import ClickImage, load_image
from pressurepose.viz.viewer import LocalHandler, LocalServer

log = logging.getLogger(__name__)

STATIC = {
    "/": ("clicker.html", "text/html; charset=utf-8"),
    "/clicker.js": ("clicker.js", "text/javascript; charset=utf-8"),
}
MAX_BODY = 1 << 20  # a save request is a few hundred bytes per marker
INTRINSIC_KEYS = ("fx", "fy", "cx", "cy")


@dataclasses.dataclass(frozen=True)
class ClickConfig:
    """Click the mat's corner markers in a camera image and write coregister's marker file."""

    image: tyro.conf.Positional[Path]
    """RGB image (.png, .jpg) or depth image (.npy, (H, W), metres or millimetres; clicks then
    record the marker's depth)."""
    out: Path = Path("markers.json")
    """Marker file to write; an existing one is loaded for editing."""
    fx: float | None = None
    """Focal length along u (pixels)."""
    fy: float | None = None
    """Focal length along v (pixels)."""
    cx: float | None = None
    """Principal point u (pixels; pixel centres at integers)."""
    cy: float | None = None
    """Principal point v (pixels)."""
    intrinsics: Path | None = None
    """JSON with fx, fy, cx, cy (top level or under "intrinsics"); flags override it."""
    depth_unit: Literal["auto", "m", "mm"] = "auto"
    """Unit of a depth .npy (auto: integers or values over 20 are millimetres)."""
    port: int = 8765
    """Port on 127.0.0.1 (0: any free port)."""
    open: bool = True
    """Open the page in the default web browser."""


def _intrinsics_from(data, what: str) -> dict[str, float]:
    if isinstance(data, dict) and isinstance(data.get("intrinsics"), dict):
        data = data["intrinsics"]
    if not isinstance(data, dict):
        raise UserError(f"{what} must be a JSON object with fx, fy, cx, cy")
    return {k: _number(data[k], f"{what}: {k}") for k in INTRINSIC_KEYS if data.get(k) is not None}


def check_intrinsics(values: dict[str, float], what: str = "intrinsics") -> dict[str, float]:
    """All four numbers, focal lengths > 0 (as coregister's loader demands)."""
    missing = [k for k in INTRINSIC_KEYS if k not in values]
    if missing:
        raise UserError(f"{what}: {', '.join(missing)} missing; give --fx --fy --cx --cy or --intrinsics FILE.json")
    out = {k: _number(values[k], f"{what}: {k}") for k in INTRINSIC_KEYS}
    if out["fx"] <= 0 or out["fy"] <= 0:
        raise UserError(f"{what}: focal lengths must be > 0, got fx={out['fx']}, fy={out['fy']}")
    return out


def _read_existing(out: Path) -> tuple[list[dict], dict[str, float]]:
    """Markers and intrinsics of an existing --out file, checked field by field (a file with
    fewer than 4 markers is still editable)."""
    data = read_json(out, "marker file")
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise UserError(f"{out} exists and is not a marker file ({FORMAT}); choose another --out")
    items = data.get("markers", [])
    if not isinstance(items, list):
        raise UserError(f'{out}: "markers" must be a list')
    markers = []
    for k, m in enumerate(items):
        if not isinstance(m, dict) or "pixel" not in m:
            raise UserError(f'{out}: marker {k} needs a "pixel": [u, v]')
        name = str(m.get("name", f"marker{k}"))
        item = {"name": name, "pixel": _vector(m["pixel"], 2, f"{out}: marker {name} pixel").tolist()}
        if m.get("depth_m") is not None:
            item["depth_m"] = _number(m["depth_m"], f"{out}: marker {name} depth_m")
        if "mat_xyz_m" in m:
            item["mat_xyz_m"] = _vector(m["mat_xyz_m"], 3, f"{out}: marker {name} mat_xyz_m").tolist()
        markers.append(item)
    intr = data.get("intrinsics")
    return markers, (_intrinsics_from(intr, f"{out} intrinsics") if isinstance(intr, dict) else {})


class ClickSession:
    """The image, the intrinsics and the markers being edited; `save` validates and writes."""

    def __init__(self, cfg: ClickConfig) -> None:
        self.cfg = cfg
        self.out = Path(cfg.out)
        if self.out.is_dir():
            raise UserError(f"--out {self.out} is a folder; give the marker file's name, e.g. {self.out}/markers.json")
        self.image = load_image(cfg.image, cfg.depth_unit)
        markers, intr = _read_existing(self.out) if self.out.exists() else ([], {})
        if cfg.intrinsics is not None:
            intr.update(
                _intrinsics_from(read_json(cfg.intrinsics, "intrinsics file"), f"intrinsics file {cfg.intrinsics}")
            )
        flags = {k: getattr(cfg, k) for k in INTRINSIC_KEYS if getattr(cfg, k) is not None}
        intr.update({k: _number(v, f"--{k}") for k, v in flags.items()})
        # None: the page asks for them (saving needs all four); partial or bad: an error now.
        self.intrinsics = check_intrinsics(intr) if intr else None
        self.markers = markers
        self.lock = threading.Lock()
        self._png: bytes | None = None

    def png(self) -> bytes:
        if self._png is None:
            import matplotlib.image

            buf = io.BytesIO()
            matplotlib.image.imsave(buf, self.image.rgb, format="png")
            self._png = buf.getvalue()
        return self._png

    def command(self) -> str:
        cloud = f" --cloud {shlex.quote(str(self.cfg.image))}" if self.image.depth_m is not None else ""
        return f"pressurepose coregister --markers {shlex.quote(str(self.out))}{cloud} --out out/coregister"

    def info(self) -> dict:
        w, h = self.image.size
        info = {
            "image": str(self.cfg.image),
            "width": w,
            "height": h,
            "out": str(self.out),
            "has_depth": self.image.depth_m is not None,
            "intrinsics": self.intrinsics,
            "markers": self.markers,
            "command": self.command(),
            "corners": {k: [round(float(x), 4) for x in v] for k, v in corner_markers().items()},
        }
        if self.image.depth_m is not None:
            valid = self.image.depth_m[self.image.depth_m > 0]
            info["depth_range_m"] = [round(float(valid.min()), 4), round(float(valid.max()), 4)]
        return info

    def document(self, payload) -> dict:
        """The marker file for a save request; ValueError (nothing written) if coregister's
        loader would refuse it or a pixel lies outside the image."""
        if not isinstance(payload, dict):
            raise UserError('expected {"intrinsics": {...}, "markers": [...]}')
        intr = payload.get("intrinsics")
        if not isinstance(intr, dict) or not intr:
            raise UserError("intrinsics missing: fill in fx, fy, cx, cy")
        intr = check_intrinsics(_intrinsics_from(intr, "intrinsics"))
        items = payload.get("markers")
        if not isinstance(items, list):
            raise UserError('"markers" must be a list')
        w, h = self.image.size
        markers = []
        for k, m in enumerate(items):
            if not isinstance(m, dict):
                raise UserError(f"marker {k} must be an object with name and pixel")
            name = m.get("name")
            if not isinstance(name, str) or not name.strip():
                raise UserError(f"marker {k} needs a name")
            name = name.strip()
            u, v = _vector(m.get("pixel"), 2, f"marker {name} pixel")
            if not (-0.5 <= u <= w - 0.5 and -0.5 <= v <= h - 0.5):
                raise UserError(f"marker {name} pixel ({u:.1f}, {v:.1f}) lies outside the {w} x {h} image")
            item = {"name": name, "pixel": [round(float(u), 3), round(float(v), 3)]}
            if self.image.depth_m is not None:
                d = self.image.depth_at(u, v)
            else:
                d = _number(m["depth_m"], f"marker {name} depth_m") if m.get("depth_m") is not None else None
            if d is not None:
                item["depth_m"] = d
            if m.get("mat_xyz_m") is not None:
                item["mat_xyz_m"] = _vector(m["mat_xyz_m"], 3, f"marker {name} mat_xyz_m").tolist()
            markers.append(item)
        doc = {"format": FORMAT, "intrinsics": intr, "markers": markers}
        parse_markers(doc)  # exactly coregister's checks: >= 4, distinct names, known corners, ...
        return doc

    def save(self, payload) -> dict:
        doc = self.document(payload)
        text = json.dumps(doc, indent=1)
        with self.lock:
            self.out.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(self.out, lambda tmp: Path(tmp).write_text(text))
            self.markers, self.intrinsics = doc["markers"], doc["intrinsics"]
        reply = {"saved": str(self.out), "document": doc, "command": self.command()}
        try:  # feedback on the clicks: the pose they give and how well it reprojects them
            mk = parse_markers(doc)
            pose = solve_camera_pose(mk)
            reply["pose"] = {
                "rms_px": round(pose.rms_px, 3),
                "camera_position_in_mat_m": [round(float(x), 4) for x in pose.position_m],
                "reprojected": project(mk.intrinsics.K, pose.R, pose.t, mk.mat_xyz_m).round(3).tolist(),
            }
        except ValueError as exc:
            reply["pose_error"] = str(exc)
        return reply


class _Handler(LocalHandler):
    server: ClickServer

    STATIC = STATIC

    def _get(self, route: str, query: dict[str, list[str]]) -> bool:
        s = self.server.session
        try:
            if route == "/api/info":
                self._json(s.info())
            elif route == "/api/image.png":
                self._send(200, s.png(), "image/png")
            elif route == "/api/depth":
                self._json({"depth_m": s.image.depth_at(float(query["u"][0]), float(query["v"][0]))})
            else:
                return False
        except (KeyError, ValueError) as exc:
            self._json({"error": f"bad request: {exc}"}, 400)
        return True

    def do_POST(self) -> None:  # noqa: N802
        if not self._local():
            return
        # Another site's page may POST to 127.0.0.1 too: only JSON (which a foreign page
        # cannot send without a CORS preflight we never grant) from our own origin writes.
        origin = self.headers.get("Origin")
        port = self.server.server_address[1]
        if origin is not None and origin not in (f"http://127.0.0.1:{port}", f"http://localhost:{port}"):
            self._json({"error": f"saving is only allowed from this page, not from {origin}"}, 403)
            return
        if (self.headers.get("Content-Type") or "").split(";")[0].strip() != "application/json":
            self._json({"error": "send the markers as application/json"}, 415)
            return
        try:
            n = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            n = -1
        if not 0 < n <= MAX_BODY:
            self.close_connection = True  # the body (if any) is not read
            self._json({"error": f"a save request needs a JSON body of at most {MAX_BODY} bytes"}, 413)
            return
        body = self.rfile.read(n)
        if urlparse(self.path).path != "/api/save":
            self._json({"error": f"no such page: {self.path}"}, 404)
            return
        try:
            payload = json.loads(body)
            self._json(self.server.session.save(payload))
        except (ValueError, UnicodeDecodeError) as exc:  # JSONDecodeError is a ValueError
            self._json({"error": str(exc)}, 400)
        except OSError as exc:  # the folder is not writable, the disk is full, ...
            self._json({"error": f"could not write {self.server.session.out}: {exc}"}, 500)
        except Exception as exc:
            log.exception("save failed")
            self._json({"error": f"{type(exc).__name__}: {exc}"}, 500)


class ClickServer(LocalServer):
    """The clicking page's server over a `ClickSession`."""

    def __init__(self, session: ClickSession, port: int = 8765) -> None:
        self.session = session
        super().__init__(port, _Handler)


def make_click_server(cfg: ClickConfig) -> ClickServer:
    """Load the image, intrinsics and any existing --out file (ValueError if bad), bind the server."""
    return ClickServer(ClickSession(cfg), cfg.port)


__all__ = [
    "ClickConfig",
    "ClickImage",
    "ClickServer",
    "ClickSession",
    "check_intrinsics",
    "load_image",
    "make_click_server",
]
