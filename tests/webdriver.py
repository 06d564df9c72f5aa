"""The few W3C WebDriver commands the page tests need (headless Chromium + chromedriver),
over HTTP with urllib: no Selenium. Shared by test_viewer.py and test_clicker.py."""

import base64
import functools
import io
import json
import os
import shutil
import socket
import subprocess
import tempfile
import time
import urllib.request

import numpy as np
import pytest

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"


def in_ci() -> bool:
    """CI=true (or any value but empty / 0 / false / no), as CI services set it."""
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


def browser_missing() -> str:
    """Why the page tests cannot run here ("" when Chromium and chromedriver are installed)."""
    missing = [p for p in (CHROMIUM, CHROMEDRIVER) if not os.access(p, os.X_OK)]
    if not missing:
        return ""
    return f"needs headless Chromium ({', '.join(missing)} not found): apt-get install chromium chromium-driver"


def needs_chromium(test):
    """A page test: skipped without a browser, except under CI, where that is a failure (the
    CI entry point .ci/run installs one, so CI always runs these tests)."""

    @functools.wraps(test)
    def run(*args, **kwargs):
        why = browser_missing()
        if why and in_ci():
            pytest.fail(f"CI: {why}", pytrace=False)
        if why:
            pytest.skip(why)
        return test(*args, **kwargs)

    return run


class WebDriver:
    """The few W3C WebDriver commands the test needs, over HTTP with urllib."""

    def __init__(self) -> None:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        self.proc = subprocess.Popen(
            [CHROMEDRIVER, f"--port={port}"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        self.base = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 30
        while True:
            try:
                if self.call("GET", "/status")["ready"]:
                    break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)
        # Root (CI) needs --no-sandbox; a fresh profile and no background traffic keep a
        # closed network from stalling the start (sync, component updates, first-run pages).
        self.profile = tempfile.mkdtemp(prefix="pp-chromium-")
        args = [
            "--headless=new",
            "--no-sandbox",
            "--disable-gpu",
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--window-size=1400,1000",
            "--disable-dev-shm-usage",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--no-first-run",
            "--no-default-browser-check",
            f"--user-data-dir={self.profile}",
        ]
        caps = {
            "capabilities": {
                "alwaysMatch": {"browserName": "chrome", "goog:chromeOptions": {"binary": CHROMIUM, "args": args}}
            }
        }
        self.session = self.call("POST", "/session", caps)["sessionId"]

    def call(self, method: str, path: str, body=None):
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(
            self.base + path, data=data, method=method, headers={"Content-Type": "application/json"}
        )
        with urllib.request.urlopen(req, timeout=120) as r:
            return json.loads(r.read() or b"{}").get("value")

    def cmd(self, method: str, path: str, body=None):
        return self.call(method, f"/session/{self.session}{path}", body)

    def js(self, script: str):
        return self.cmd("POST", "/execute/sync", {"script": script, "args": []})

    def wait(self, script: str, timeout: float = 60, state: str = "return window.viewerState"):
        """Poll `script` until truthy; on time-out the assertion shows what `state` returns."""
        deadline = time.monotonic() + timeout
        while not self.js(script):
            assert time.monotonic() < deadline, f"timed out waiting for {script}: {self.js(state)}"
            time.sleep(0.1)

    def click(self, css: str) -> None:
        element = self.cmd("POST", "/element", {"using": "css selector", "value": css})
        self.cmd("POST", f"/element/{next(iter(element.values()))}/click", {})

    def screenshot(self) -> np.ndarray:
        import matplotlib.image

        png = base64.b64decode(self.cmd("GET", "/screenshot"))
        return (matplotlib.image.imread(io.BytesIO(png), format="png")[..., :3] * 255).round().astype(np.uint8)

    def actions(self, pointer: list[dict]) -> None:
        """Perform one mouse's action sequence (pointerMove / pointerDown / pointerUp / pause)."""
        self.cmd(
            "POST",
            "/actions",
            {
                "actions": [
                    {"type": "pointer", "id": "mouse", "parameters": {"pointerType": "mouse"}, "actions": pointer}
                ]
            },
        )
        self.cmd("DELETE", "/actions")

    def close(self) -> None:
        try:
            self.cmd("DELETE", "")
        finally:
            self.proc.terminate()
            self.proc.wait(timeout=30)
            shutil.rmtree(self.profile, ignore_errors=True)
