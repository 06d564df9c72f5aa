"""`pressurepose view PATH`: a local web viewer of samples and predictions.

Python's standard library only on the server: a `ThreadingHTTPServer` bound to 127.0.0.1 that
serves one static page (`viz/static/`, shipped as package data; it fetches nothing from the
internet - the 3D view is plain WebGL written for it) and a small API over a
`viz.view_data.Browser`:

    GET /                       the page (viewer.html, viewer.js)
    GET /api/info               what PATH is: kind, sample count, body model, curves, images
    GET /api/list?offset=&limit=&order=   list entries (labels, 3DVPE / MPJPE where known)
    GET /api/sample/<i>         pressure image (64 x 27 mmHg, row-major), labels, joints, errors
    GET /api/mesh/<i>           float32 vertices of each layer (true, estimated), one after the
                                other; headers X-Layers (names) and X-Vertices (per layer)
    GET /api/faces              the body model's triangles, uint32 (F, 3), sent once
    GET /files/<name>           metrics.png, cases.png, ... of PATH

Errors come back as JSON {"error": message} with status 400/404/500.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import logging
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from typing import Literal
from urllib.parse import parse_qs, urlparse

import tyro

from pressurepose.errors import UserError
from pressurepose.viz.view_data import IMAGES, Browser

log = logging.getLogger(__name__)

STATIC = {
    "/": ("viewer.html", "text/html; charset=utf-8"),
    "/viewer.js": ("viewer.js", "text/javascript; charset=utf-8"),
}
MAX_LIST = 500  # list entries per request: the page pages through big datasets


@dataclasses.dataclass(frozen=True)
class ViewConfig:
    """Browse samples and predictions in a local web page."""

    path: tyro.conf.Positional[Path]
    """Dataset folder (manifest.json), `evaluate` report folder, training run folder, or a .npz
    of pressure images (import-pmatdata)."""
    port: int = 8765
    """Port on 127.0.0.1 (0: any free port; the address is printed)."""
    open: bool = True
    """Open the page in the default web browser."""
    data: Path | None = None
    """Dataset of a report or run, when the path recorded in it is not found."""
    model: Path | None = None
    """Training run whose network estimates the bodies shown (datasets, .npz images)."""
    backend: Literal["anny", "smpl"] | None = None
    """Body model (default: the dataset's or run's, else anny)."""
    smpl_dir: Path | None = None
    """Folder with the SMPL files for --backend smpl."""


def static_file(name: str) -> bytes:
    return resources.files("pressurepose.viz").joinpath("static", name).read_bytes()


class LocalHandler(BaseHTTPRequestHandler):
    """What every page served on 127.0.0.1 shares (the viewer, `pressurepose click`): quiet
    logging, sending bytes and JSON, and the Host check."""

    protocol_version = "HTTP/1.1"

    def log_message(self, fmt, *args) -> None:  # the default writes every request to stderr
        log.debug("%s " + fmt, self.address_string(), *args)

    def _send(self, status: int, body: bytes, ctype: str, headers: dict | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.end_headers()
        self.wfile.write(body)

    def _json(self, obj, status: int = 200) -> None:
        self._send(status, json.dumps(obj, allow_nan=False).encode(), "application/json")

    STATIC: dict[str, tuple[str, str]] = {}  # route -> (file under viz/static, content type)

    def do_GET(self) -> None:  # noqa: N802 (http.server's name)
        """The Host check, the static files, then `_get` (False: 404); a page that went away is
        ignored, a bug answers 500 and the server keeps serving."""
        if not self._local():
            return
        url = urlparse(self.path)
        try:
            if url.path in self.STATIC:
                name, ctype = self.STATIC[url.path]
                self._send(200, static_file(name), ctype)
            elif not self._get(url.path, parse_qs(url.query)):
                self._json({"error": f"no such page: {url.path}"}, 404)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the page went away (next/previous clicked quickly)
        except Exception as exc:  # a bug: keep serving, say what happened
            log.exception("request %s failed", self.path)
            self._json({"error": f"{type(exc).__name__}: {exc}"}, 500)

    def _get(self, route: str, query: dict[str, list[str]]) -> bool:
        """Answer an API route; False if there is no such route."""
        return False

    def _local(self) -> bool:
        """False (after answering 403) unless the request names this machine as its Host."""
        host = (self.headers.get("Host") or "").rsplit(":", 1)[0]
        if host not in ("127.0.0.1", "localhost", "[::1]"):
            # another site's page reaching this port through a rebound DNS name: not ours to serve
            self._json({"error": f"this page answers to 127.0.0.1 or localhost, not {host!r}"}, 403)
            return False
        return True


class _Handler(LocalHandler):
    server: ViewerServer
    STATIC = STATIC

    def _get(self, route: str, query: dict[str, list[str]]) -> bool:
        b = self.server.browser
        try:
            if route == "/api/info":
                self._json(b.info())
            elif route == "/api/list":
                offset = int(query.get("offset", ["0"])[0])
                limit = min(MAX_LIST, int(query.get("limit", ["100"])[0]))
                order = query.get("order", ["index"])[0]
                ids = b.order(order)[offset : offset + limit]
                entries = (
                    {e["i"]: e for e in b.labels(min(ids, default=0), max(ids, default=-1) + 1)}
                    if order == "index"
                    else {i: b.labels(i, i + 1)[0] for i in ids}
                )
                self._json({"total": len(b), "offset": offset, "items": [entries[i] for i in ids]})
            elif route.startswith("/api/sample/"):
                self._json(b.sample(int(route.rsplit("/", 1)[1])))
            elif route.startswith("/api/mesh/"):
                layers, data = b.meshes(int(route.rsplit("/", 1)[1]))
                n = len(data) // (12 * len(layers)) if layers else 0
                self._send(200, data, "application/octet-stream", {"X-Layers": ",".join(layers), "X-Vertices": str(n)})
            elif route == "/api/faces":
                data = b.faces()
                self._send(200, data, "application/octet-stream", {"X-Faces": str(len(data) // 12)})
            elif route.startswith("/files/") and route[7:] in IMAGES and (b.path / route[7:]).is_file():
                self._send(200, (b.path / route[7:]).read_bytes(), "image/png")
            else:
                return False
        except (IndexError, KeyError) as exc:
            self._json({"error": str(exc).strip("'\"")}, 404)
        except ValueError as exc:  # bad numbers in the URL, a corrupt shard, ...
            self._json({"error": str(exc)}, 400)
        return True


class LocalServer(ThreadingHTTPServer):
    """An HTTP server on 127.0.0.1 only; `url` after construction, `serve_forever()` to run.
    A port in use or not allowed is a ValueError naming --port."""

    daemon_threads = True
    allow_reuse_address = False  # a second server on the same port must fail, not share it

    def __init__(self, port: int, handler: type[LocalHandler]) -> None:
        if not 0 <= port <= 65535:
            raise UserError(f"--port must be in 0..65535, got {port}")
        try:
            super().__init__(("127.0.0.1", port), handler)
        except OSError as exc:
            if exc.errno in (errno.EADDRINUSE, errno.EACCES):
                why = "in use" if exc.errno == errno.EADDRINUSE else "not allowed"
                raise UserError(
                    f"port {port} on 127.0.0.1 is {why}; choose another with --port N (--port 0 picks a free one)"
                ) from None
            raise

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server_address[1]}/"


class ViewerServer(LocalServer):
    """The viewer's server over a `Browser`."""

    def __init__(self, browser: Browser, port: int = 8765) -> None:
        self.browser = browser
        super().__init__(port, _Handler)


def make_server(cfg: ViewConfig) -> ViewerServer:
    """Open cfg.path (ValueError if it is none of what the viewer reads) and bind the server."""
    browser = Browser(cfg.path, data=cfg.data, backend=cfg.backend, smpl_dir=cfg.smpl_dir, model=cfg.model)
    return ViewerServer(browser, cfg.port)


def serve(cfg: ViewConfig, ready=None) -> None:
    """Run the viewer until Ctrl-C. `ready(url)` is called once the server listens."""
    run_local(make_server(cfg), cfg.open, ready)


def run_local(server: LocalServer, open_browser: bool, ready=None) -> None:
    """Serve until Ctrl-C, then close; `ready(url)` once listening; optionally open a browser."""
    if ready is not None:
        ready(server.url)
    if open_browser:
        import webbrowser

        threading.Thread(target=webbrowser.open, args=(server.url,), daemon=True).start()
    try:
        server.serve_forever(poll_interval=0.2)
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()


__all__ = [
    "LocalHandler",
    "LocalServer",
    "ViewConfig",
    "ViewerServer",
    "make_server",
    "run_local",
    "serve",
    "static_file",
]
