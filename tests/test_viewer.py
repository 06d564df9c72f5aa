"""`pressurepose view`: the JSON API on a dataset, an evaluate report (its predictions.npz
re-posed to the report's own numbers), a training run and a .npz of images; bad paths and
ports; Ctrl-C; and the page end to end in headless Chromium over the W3C WebDriver protocol
(urllib only) with a screenshot check of the heat map and the WebGL canvas."""

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
from served import Served, opened
from webdriver import WebDriver, needs_chromium

from pressurepose.body import BodyParams
from pressurepose.cli import main
from pressurepose.commands.evaluate import EvaluateConfig, run_evaluate
from pressurepose.commands.train import run_train as train  # the loop + metrics.png
from pressurepose.data.manifest import write_manifest
from pressurepose.data.schema import SampleBatch, to_table
from pressurepose.data.shards import table_bytes, write_shard
from pressurepose.eval.evaluation import read_predictions
from pressurepose.train.config import TrainConfig
from pressurepose.train.data import synthetic_arrays, write_npz
from pressurepose.viz.viewer import ViewConfig, make_server

# Every test shares the module's fixture (sim #2 samples, a smoke training run and its report):
# ~15 s of CPU, more on a loaded machine.
pytestmark = pytest.mark.slow


def write_dataset(root: Path, arrays: dict[str, torch.Tensor]) -> None:
    """A generated-format test split (shards + manifest) of `synthetic_arrays` samples (real
    bodies and pressure images from the sampler and sim #2), one shard per gender."""
    a = {k: v.numpy() for k, v in arrays.items()}
    genders = np.where(a["gender"] > 0.5, "female", "male").astype(object)
    records = []
    for gender in ("female", "male"):
        sel = genders == gender
        c = int(sel.sum())
        f64 = {
            k: a[k][sel].astype(np.float64)
            for k in ("shape", "root_rotation", "root_translation", "pose", "mass_kg", "height_m")
        }
        batch = SampleBatch(
            split=np.array(["test"] * c, object),
            partition=np.array(["supine"] * c, object),
            gender=genders[sel],
            over_bed=np.zeros(c, bool),
            index=np.arange(c, dtype=np.int64),
            pressure_mmhg=a["pressure_mmhg"][sel],
            depth_mm=a["depth_mm"][sel],
            contact=(a["contact"][sel] > 0).astype(np.uint8),
            joints_m=a["joints"][sel].astype(np.float64),
            head_angle_deg=np.zeros(c),
            settle_steps=np.zeros(c, np.int32),
            sink_mm=np.zeros(c, np.float32),
            **f64,
        )
        rec = {
            "split": "test",
            "partition": "supine",
            "gender": gender,
            "over_bed": False,
            "number": 0,
            "first_slot": 0,
            "count": c,
            "candidates": c,
            "rejections": {},
            "sampling_rejections": {},
        }
        records.append(write_shard(root, f"test-supine-{gender}-free-00000", table_bytes(to_table(batch)), rec))
    write_manifest(root, {"config": {"preset": "test", "backend": "anny"}}, records)


@pytest.fixture(scope="module")
def folders(anny64, tmp_path_factory):
    """A dataset (test split), a smoke-trained run (on the same samples as a training .npz:
    the network's accuracy is not the point) and the run's evaluate report on the dataset
    (no train split there, so no baselines: they would triple the report's time; 2 samples:
    its 3DVPE takes ~0.5 s a sample here)."""
    root = tmp_path_factory.mktemp("view")
    arrays = synthetic_arrays(4, seed=2, body=anny64)
    write_dataset(root / "data", arrays)
    (root / "train").mkdir()
    write_npz(root / "train" / "train.npz", arrays)
    run = train(TrainConfig.smoke(data=root / "train", out=root / "run", epochs=1, progress=False, val_fraction=0.2))
    run_evaluate(EvaluateConfig(model=run, data=root / "data", out=root / "report", batch=8, failures=1, limit=2))
    return {"data": root / "data", "run": run, "report": root / "report", "root": root, "n": len(arrays["shape"])}


class Viewer(Served):
    """A viewer server on a free port, serving in a thread."""

    def __init__(self, path: Path, **kwargs) -> None:
        super().__init__(make_server(ViewConfig(path=path, port=0, open=False, **kwargs)))

    def get(self, route: str):
        with urllib.request.urlopen(self.url + route, timeout=60) as r:
            return r.read(), r.headers

    def json(self, route: str):
        return json.loads(self.get(route)[0])

    def status(self, route: str) -> tuple[int, str]:
        try:
            self.get(route)
            return 200, ""
        except urllib.error.HTTPError as exc:
            return exc.code, json.loads(exc.read())["error"]


@pytest.fixture
def viewer():
    yield from opened(Viewer)


def vertices(v: Viewer, i: int) -> dict[str, np.ndarray]:
    data, headers = v.get(f"api/mesh/{i}")
    layers = [x for x in headers["X-Layers"].split(",") if x]
    V = int(headers["X-Vertices"])
    flat = np.frombuffer(data, dtype="<f4")
    assert flat.size == len(layers) * V * 3
    return {name: flat[k * V * 3 : (k + 1) * V * 3].reshape(V, 3) for k, name in enumerate(layers)}


# --- API -----------------------------------------------------------------------------------------


def test_report_predictions_repose_to_the_reports_numbers(folders, viewer, anny32):
    report = json.loads((folders["report"] / "report.json").read_text())
    index, est = read_predictions(folders["report"] / "predictions.npz")
    n = report["count"]
    assert index.tolist() == list(range(n)) and est.batch_size == n
    v = viewer(folders["report"])
    info = v.json("api/info")
    assert (info["kind"], info["count"], info["has_truth"], info["has_estimate"]) == ("report", n, True, True)
    assert "cases.png" in info["images"] and v.get("files/cases.png")[0][:4] == b"\x89PNG"
    faces = np.frombuffer(v.get("api/faces")[0], dtype="<u4").reshape(-1, 3)
    assert np.array_equal(faces, anny32.faces.numpy())
    worst = v.json("api/list?order=vpe_m&limit=2")["items"]
    assert worst[0]["vpe_m"] == round(max(report["per_sample"]["vpe_m"]), 4) and worst[0]["vpe_m"] >= worst[1]["vpe_m"]
    for i in range(n):
        s = v.json(f"api/sample/{i}")
        assert len(s["pressure"]) == 64 * 27 and s["meta"]["split"] == "test"
        # The estimate re-posed from predictions.npz gives the report's own MPJPE for this sample.
        assert np.mean(s["joint_errors_m"]) == pytest.approx(report["per_sample"]["mpjpe_m"][i], abs=2e-5)
        assert s["meta"]["gender"] == report["per_sample"]["gender"][i]
    meshes = vertices(v, 1)
    assert set(meshes) == {"true", "estimated"} and len(meshes["true"]) == anny32.num_vertices
    with torch.no_grad():
        want = anny32(est.index([1])).vertices[0].numpy()
    np.testing.assert_allclose(meshes["estimated"], want, atol=1e-5)


def test_dataset_is_listed_without_reading_samples(folders, viewer, anny32):
    from pressurepose.data.dataset import PressurePoseDataset

    v = viewer(folders["data"])
    ds = v.server.browser.dataset
    info = v.json("api/info")
    assert (info["kind"], info["count"], info["has_estimate"]) == ("dataset", len(ds), False)
    page = v.json("api/list?offset=1&limit=2")
    assert page["total"] == len(ds) and [e["i"] for e in page["items"]] == [1, 2]
    full = v.json("api/list?limit=1000")["items"]
    assert len(ds._cache) == 0  # the list came from the manifest: no row group was read
    plain = PressurePoseDataset(folders["data"], columns=("split", "gender", "joints_m"))
    for e in full:
        assert (e["split"], e["gender"]) == (plain[e["i"]]["split"], plain[e["i"]]["gender"])
    last = len(ds) - 1  # a male sample, in the second shard
    s = v.json(f"api/sample/{last}")
    assert s["joint_errors_m"] is None and s["meta"]["gender"] == full[last]["gender"] == "male"
    np.testing.assert_allclose(s["joints_true"], plain[last]["joints_m"].numpy(), atol=1e-4)
    meshes = vertices(v, last)
    assert list(meshes) == ["true"] and meshes["true"].shape == (anny32.num_vertices, 3)
    # the mesh is the body model's for the stored parameters: its joints are the stored joints
    item = ds[last]
    params = BodyParams(**{k: item[k].float()[None] for k in ("shape", "root_rotation", "root_translation", "pose")})
    with torch.no_grad():
        np.testing.assert_allclose(meshes["true"], anny32(params).vertices[0].numpy(), atol=1e-5)
    assert v.status(f"api/sample/{len(ds)}")[0] == 404
    assert v.status("api/sample/x")[0] == 400
    assert v.status("files/../manifest.json")[0] == 404
    rebound = urllib.request.Request(v.url + "api/info", headers={"Host": "evil.example:80"})
    with pytest.raises(urllib.error.HTTPError, match="403"):
        urllib.request.urlopen(rebound, timeout=30)
    assert v.get("")[0].startswith(b"<!doctype html>") and b'getContext("webgl"' in v.get("viewer.js")[0]


def test_run_folder_shows_curves_and_predicts(folders, viewer):
    v = viewer(folders["run"])
    info = v.json("api/info")
    rows = [json.loads(x) for x in (folders["run"] / "metrics.jsonl").read_text().splitlines()]
    assert info["kind"] == "run" and info["metrics"] == rows and "metrics.png" in info["images"]
    assert info["has_estimate"] and info["count"] == folders["n"]
    s = v.json("api/sample/0")
    assert len(s["joint_errors_m"]) == 24 and all(e > 0 for e in s["joint_errors_m"])
    assert set(vertices(v, 0)) == {"true", "estimated"}
    # a run whose dataset has moved: curves only, and the note says how to point at it
    moved = folders["root"] / "run_moved"
    shutil.copytree(folders["run"], moved)
    cfg = json.loads((moved / "config.json").read_text())
    cfg["train"]["data"] = str(folders["root"] / "gone")
    (moved / "config.json").write_text(json.dumps(cfg))
    info = viewer(moved).json("api/info")
    assert info["count"] == 0 and "--data" in info["note"] and info["metrics"] == rows


def test_npz_of_images(folders, tmp_path, viewer):
    rng = np.random.default_rng(0)
    np.savez(
        tmp_path / "pmat.npz",
        pressure_mmhg=rng.uniform(0, 40, (3, 64, 27)).astype(np.float32),
        subject=np.array(["S1", "S2", "S3"]),
        posture=np.array(["supine", "left", "right"]),
        height_m=np.full(3, 1.7),
    )
    v = viewer(tmp_path / "pmat.npz")
    info = v.json("api/info")
    assert (info["kind"], info["count"], info["has_truth"]) == ("images", 3, False)
    assert v.json("api/list")["items"][1]["posture"] == "left"
    s = v.json("api/sample/2")
    assert s["meta"]["subject"] == "S3" and s["joints_true"] is None
    np.testing.assert_allclose(
        np.reshape(s["pressure"], (64, 27)), np.load(tmp_path / "pmat.npz")["pressure_mmhg"][2], atol=0.01
    )
    # with --model, a run's network estimates the bodies of the images (no truth: no joint errors)
    v = viewer(tmp_path / "pmat.npz", model=folders["run"])
    assert v.json("api/info")["has_estimate"]
    s = v.json("api/sample/0")
    assert s["joint_errors_m"] is None and len(s["joints_est"]) == 24
    assert list(vertices(v, 0)) == ["estimated"]
    with pytest.raises(ValueError, match="not a training run"):
        make_server(ViewConfig(path=tmp_path / "pmat.npz", port=0, model=tmp_path))


def test_bad_paths_and_ports(folders, tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    (tmp_path / "notes.txt").write_text("hello")
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "manifest.json").write_text("{ not json")
    cases = {
        tmp_path / "missing": "does not exist",
        tmp_path / "empty": "empty folder",
        tmp_path / "notes.txt": "not a .npz",
        tmp_path / "broken": "not readable JSON",
    }
    # a report whose dataset is gone, a dataset whose shard is cut short
    shutil.copytree(folders["report"], tmp_path / "report")
    rec = json.loads((tmp_path / "report" / "report.json").read_text())
    rec["config"]["data"] = str(tmp_path / "gone")
    (tmp_path / "report" / "report.json").write_text(json.dumps(rec))
    cases[tmp_path / "report"] = "--data"
    shutil.copytree(folders["data"], tmp_path / "cut")
    shard = next((tmp_path / "cut" / "shards").glob("*.parquet"))
    shard.write_bytes(shard.read_bytes()[:100])
    cases[tmp_path / "cut"] = "truncated"
    for path, message in cases.items():
        with pytest.raises(ValueError, match=message):
            make_server(ViewConfig(path=path, port=0, open=False))
        assert main(["view", str(path), "--no-open", "--port", "0"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "Traceback" not in err
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(ValueError, match="--port"):
            make_server(ViewConfig(path=folders["data"], port=port, open=False))
        assert main(["view", str(folders["data"]), "--no-open", "--port", str(port)]) == 2
        assert f"port {port}" in capsys.readouterr().err


def test_ctrl_c_stops_the_cli_cleanly(folders):
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).parents[1] / "src"))
    # A shell's background job (CI runners, `cmd &`) starts with SIGINT ignored, and children
    # inherit that; give the viewer the default disposition a terminal user has.
    p = subprocess.Popen(
        [sys.executable, "-m", "pressurepose.cli", "view", str(folders["data"]), "--port", "0", "--no-open"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        line = p.stdout.readline()
        url = line.split(" at ")[1].split()[0]
        assert json.loads(urllib.request.urlopen(url + "api/info", timeout=30).read())["kind"] == "dataset"
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=30)
    finally:
        p.kill()
    assert p.returncode == 0 and "viewer stopped" in out and "Traceback" not in err


# --- the page in headless Chromium ---------------------------------------------------------------


def region(img: np.ndarray, driver: WebDriver, element_id: str) -> np.ndarray:
    r = driver.js(
        f"const r = document.getElementById('{element_id}').getBoundingClientRect();"
        "return [r.left, r.top, r.width, r.height, window.devicePixelRatio];"
    )
    x, y, w, h = (v * r[4] for v in r[:4])
    return img[int(y) + 1 : int(y + h) - 1, int(x) + 1 : int(x + w) - 1]


def colours(pixels: np.ndarray) -> int:
    return len(np.unique(pixels.reshape(-1, 3), axis=0))


@needs_chromium
def test_page_renders_in_headless_chromium(folders, viewer, anny32):
    v = viewer(folders["report"])
    faces = len(anny32.faces)
    driver = WebDriver()
    try:
        driver.cmd("POST", "/url", {"url": v.url})
        driver.wait("return document.body.dataset.ready === '1'")
        state = driver.js("return window.viewerState")
        assert state["error"] == "" and state["sample"] == 0
        assert state["layers"] == ["true", "estimated"] and state["triangles"] == 2 * faces
        first = driver.screenshot()
        heat, gl = region(first, driver, "pressure"), region(first, driver, "gl")
        # The heat map holds the colour map's many shades; the 3D canvas is not just its
        # background: shaded bodies (blue-grey and red) and the textured mat cover much of it.
        assert colours(heat) > 20
        background = np.array([223, 227, 234])  # clearColor(0.875, 0.89, 0.918)
        covered = (np.abs(gl.astype(int) - background).sum(-1) > 12).mean()
        assert covered > 0.05 and colours(gl) > 100
        reds = ((gl[..., 0] > 150) & (gl[..., 1] < 120) & (gl[..., 2] < 100)).mean()
        blues = ((gl[..., 2] > gl[..., 0] + 20) & (gl[..., 2] > 120)).mean()
        assert reds > 0.005 and blues > 0.005  # both bodies drawn, in their two colours
        rows = driver.js("return document.querySelectorAll('#joints tr').length")
        assert rows == 24
        driver.click("#next")
        driver.wait("return document.body.dataset.sample === '1'")
        state = driver.js("return window.viewerState")
        assert state["error"] == "" and state["triangles"] == 2 * faces and state["draws"] >= 2
        second = driver.screenshot()
        assert not np.array_equal(region(second, driver, "pressure"), heat)  # another sample's image
        assert driver.js("return document.querySelector('#list .sel').dataset.i") == "1"
    finally:
        driver.close()
