"""Fuzzed boundaries (issue #24): property-based mutations of valid files - truncated, bytes
flipped, fields dropped or retyped, huge numbers, wrong shapes - and the one promise each
must keep: the command succeeds, or it exits 2 with one line naming the problem and no
traceback (in-process readers: they return, or raise a UserError naming the file).

Deterministic and bounded: `derandomize=True` (the same examples on every run and in CI),
`max_examples` small, no deadline. EXAMPLES is the count docs/reliability.md reports.
"""

import io
import json
import pickle
import shutil

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_data import make_fake_dataset

from pressurepose.cli import main
from pressurepose.errors import UserError

EXAMPLES = {
    "manifest": 40,
    "run_config": 12,
    "metrics": 12,
    "model": 12,
    "measurements": 40,
    "pressure_npy": 40,
    "pressure_text": 30,
    "pressure_array": 40,
    "pickle": 40,
}


def fuzz(name):
    return settings(
        max_examples=EXAMPLES[name],
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=list(HealthCheck),
    )


# --- mutations ------------------------------------------------------------------------------

WEIRD = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**30), 10**30),
    st.sampled_from([0, -1, 2**63, 10**400 // 10**380]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([1e308, -1e308, 1e-308]),
    st.text(max_size=12),
    st.sampled_from(["../../etc/passwd", "/etc/passwd", "", "shards/../../x", "\x00"]),
    st.lists(st.integers(-3, 3), max_size=3),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
)


def _paths(doc, prefix=()):
    yield prefix
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc[:4]):
            yield from _paths(v, prefix + (i,))


def mutate_json(data, doc):
    """A copy of a JSON document with one field dropped or replaced by a weird value."""
    doc = json.loads(json.dumps(doc))
    paths = [p for p in _paths(doc) if p]
    path = data.draw(st.sampled_from(paths), label="path")
    parent = doc
    for k in path[:-1]:
        parent = parent[k]
    if data.draw(st.booleans(), label="drop") and isinstance(parent, dict):
        del parent[path[-1]]
    else:
        parent[path[-1]] = data.draw(WEIRD, label="value")
    return doc


def mutate_bytes(data, blob: bytes) -> bytes:
    """Truncated, bits flipped, or bytes inserted."""
    blob = bytearray(blob)
    action = data.draw(st.sampled_from(["truncate", "flip", "insert", "flip_many"]), label="action")
    if action == "truncate":
        return bytes(blob[: data.draw(st.integers(0, max(len(blob) - 1, 0)), label="keep")])
    if action == "insert":
        at = data.draw(st.integers(0, len(blob)), label="at")
        return bytes(blob[:at] + data.draw(st.binary(min_size=1, max_size=8), label="junk") + blob[at:])
    for _ in range(1 if action == "flip" else data.draw(st.integers(2, 12), label="flips")):
        at = data.draw(st.integers(0, len(blob) - 1), label="at")
        blob[at] ^= 1 << data.draw(st.integers(0, 7), label="bit")
    return bytes(blob)


def dump(doc) -> str:
    try:
        return json.dumps(doc)
    except (ValueError, OverflowError):
        return json.dumps(str(doc))


def assert_ok_or_one_line(code, capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert code in (0, 2)
    if code == 2:
        assert len(err) == 1 and err[0].startswith("pressurepose: error:"), err
    return code


# --- datasets ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz") / "ds"
    make_fake_dataset(root, [("train", "supine", "female", 3), ("test", "general", "male", 2)])
    return root


def test_fuzzed_manifests(small_dataset, tmp_path_factory, capsys):
    manifest = json.loads((small_dataset / "manifest.json").read_text())
    text = (small_dataset / "manifest.json").read_bytes()
    outcomes = []

    @fuzz("manifest")
    @given(st.data())
    def check(data):
        folder = tmp_path_factory.mktemp("m") / "ds"
        shutil.copytree(small_dataset, folder)
        if data.draw(st.booleans(), label="as bytes"):
            (folder / "manifest.json").write_bytes(mutate_bytes(data, text))
        else:
            (folder / "manifest.json").write_text(dump(mutate_json(data, manifest)))
        capsys.readouterr()
        outcomes.append(assert_ok_or_one_line(main(["info", str(folder), "--sheet", "0"]), capsys))

    check()
    assert outcomes.count(2) >= len(outcomes) // 2  # most mutations are refused, not accepted


# --- run folders and network files ----------------------------------------------------------


@pytest.fixture(scope="module")
def run_folder(small_dataset, tmp_path_factory):
    from test_bad_inputs import make_run

    return make_run(small_dataset, tmp_path_factory.mktemp("runs") / "run")


def _resume(run, dataset):
    return ["train", "--data", str(dataset), "--out", str(run), "--preset", "smoke", "--epochs", "1"]


@pytest.mark.parametrize("name", ["run_config", "metrics"])
def test_fuzzed_run_config_and_metrics(name, run_folder, small_dataset, tmp_path_factory, capsys):
    file = {"run_config": "config.json", "metrics": "metrics.jsonl"}[name]
    original = (run_folder / file).read_bytes()

    @fuzz(name)
    @given(st.data())
    def check(data):
        run = tmp_path_factory.mktemp("r") / "run"
        shutil.copytree(run_folder, run)
        if file == "config.json" and not data.draw(st.booleans(), label="as bytes"):
            text = dump(mutate_json(data, json.loads(original)))
        else:
            text = mutate_bytes(data, original).decode("latin1")
        (run / file).write_text(text)
        capsys.readouterr()
        assert_ok_or_one_line(main(_resume(run, small_dataset)), capsys)

    check()


def test_fuzzed_model_files(tmp_path_factory, capsys):
    from safetensors import safe_open
    from safetensors.torch import save_file

    from pressurepose.models import default_model_dir

    with safe_open(str(default_model_dir() / "model.safetensors"), framework="pt") as f:
        tensors = {k: f.get_tensor(k) for k in f.keys()}
        meta = dict(f.metadata())
    config = json.loads(meta["config"])
    names = sorted(tensors)
    folder = tmp_path_factory.mktemp("img")
    image = np.zeros((64, 27), np.float32)
    image[10:50, 8:19] = 30.0
    np.save(folder / "one.npy", image)

    @fuzz("model")
    @given(st.data())
    def check(data):
        run = tmp_path_factory.mktemp("model")
        action = data.draw(st.sampled_from(["config", "shape", "drop", "bytes"]), label="action")
        t, m = dict(tensors), dict(meta)
        if action == "config":
            m["config"] = dump(mutate_json(data, config))
        elif action in ("shape", "drop"):
            name = data.draw(st.sampled_from(names), label="tensor")
            if action == "drop":
                del t[name]
            else:
                t[name] = t[name].flatten()[: data.draw(st.integers(1, 5), label="size")].clone()
        save_file(t, str(run / "model.safetensors"), metadata=m)
        if action == "bytes":
            blob = (run / "model.safetensors").read_bytes()
            (run / "model.safetensors").write_bytes(mutate_bytes(data, blob[:4096]) + blob[4096:])
        capsys.readouterr()
        assert_ok_or_one_line(
            main(
                [
                    "predict",
                    "--model",
                    str(run),
                    "--out",
                    str(run / "p"),
                    "--no-figures",
                    "--no-meshes",
                    str(folder / "one.npy"),
                ]
            ),
            capsys,
        )

    check()


# --- measurement files, pressure files, pickles: their readers ---------------------------------


def raises_user_error_naming(path, call):
    """call() returns, or raises a UserError whose message names `path`; anything else fails."""
    try:
        return call()
    except UserError as exc:
        assert str(path) in str(exc) or path.name in str(exc), str(exc)
        assert "\n" not in str(exc).strip(), str(exc)
        return None


@pytest.fixture(scope="module")
def measurement_doc():
    from pressurepose.calib.measurements import FORMAT
    from pressurepose.mat import MatSpec

    mat = MatSpec()
    pressure = np.zeros((mat.rows, mat.cols))
    pressure[20:25, 10:15] = 20.0
    obj = {
        "name": "a",
        "shape": "capsule",
        "length_m": 0.2,
        "radius_m": 0.05,
        "mass_kg": 4.5,
        "x_m": 0.6,
        "y_m": 0.37,
        "yaw_deg": 90.0,
        "compression_m": 0.01,
    }
    return {"format": FORMAT, "scenes": [{"name": "s", "pressure_mmhg": pressure.tolist(), "objects": [obj]}]}


def test_fuzzed_measurement_files(measurement_doc, tmp_path):
    from pressurepose.calib.measurements import load_measurements

    path = tmp_path / "measurements.json"
    path.write_text(json.dumps(measurement_doc))
    assert load_measurements(path).n_objects == 1  # the unmutated file is valid
    text = path.read_bytes()

    @fuzz("measurements")
    @given(st.data())
    def check(data):
        if data.draw(st.booleans(), label="as bytes"):
            path.write_bytes(mutate_bytes(data, text))
        else:
            path.write_text(dump(mutate_json(data, measurement_doc)))
        raises_user_error_naming(path, lambda: load_measurements(path))

    check()


def _image():
    image = np.zeros((64, 27), np.float32)
    image[10:50, 8:19] = 30.0
    return image


def _check_images(images):
    from pressurepose.net.inputs import MAX_PLAUSIBLE_MMHG

    assert images.dtype == np.float32 and images.ndim == 3 and images.shape[1:] == (64, 27)
    assert np.isfinite(images).all() and (images >= 0).all() and (images <= MAX_PLAUSIBLE_MMHG).all()


def test_fuzzed_pressure_npy_bytes(tmp_path):
    from pressurepose.net.inputs import read_pressure_file

    buf = io.BytesIO()
    np.save(buf, _image())
    blob = buf.getvalue()
    path = tmp_path / "image.npy"

    @fuzz("pressure_npy")
    @given(st.data())
    def check(data):
        path.write_bytes(mutate_bytes(data, blob))
        images = raises_user_error_naming(path, lambda: read_pressure_file(path))
        if images is not None:
            _check_images(images)

    check()


def test_fuzzed_pressure_text_frames(tmp_path):
    from pressurepose.net.inputs import read_pressure_file

    raw = (_image()[::-1] * 10).astype(int)
    text = "\n".join(" ".join(str(v) for v in row) for row in raw).encode()
    path = tmp_path / "frame.txt"

    @fuzz("pressure_text")
    @given(st.data())
    def check(data):
        path.write_bytes(mutate_bytes(data, text))
        units = data.draw(st.sampled_from(["raw", "mmhg"]), label="units")
        images = raises_user_error_naming(path, lambda: read_pressure_file(path, units))
        if images is not None:
            _check_images(images)

    check()


ARRAYS = st.one_of(
    st.tuples(st.integers(0, 3), st.integers(0, 70), st.integers(0, 30)).map(lambda s: np.ones(s, np.float32)),
    st.sampled_from([1e30, 1e36, 1e300, -1.0, np.nan, np.inf, 2000.0, 999.0, 0.0]).map(
        lambda v: np.where(_image() > 0, v, 0.0)
    ),
    st.sampled_from(["int8", "uint64", "float16", "complex64", "bool", "U3"]).map(lambda d: _image().astype(d)),
    st.just(np.ones((64, 27, 1))),
    st.just(np.ones((2, 2, 64, 27))),
    st.just(np.ones((0, 64, 27))),
)


def test_fuzzed_pressure_arrays(tmp_path):
    from pressurepose.net.inputs import read_pressure_file

    @fuzz("pressure_array")
    @given(ARRAYS, st.sampled_from([".npy", ".npz", ".parquet"]))
    def check(array, suffix):
        path = tmp_path / f"image{suffix}"
        if suffix == ".npy":
            np.save(path, array)
        elif suffix == ".npz":
            np.savez(path, pressure_mmhg=array)
        else:
            import pyarrow as pa
            import pyarrow.parquet as pq

            try:
                column = pa.array(list(array.reshape(len(array), -1).astype(np.float64)) if array.ndim >= 1 else [])
            except (ValueError, TypeError):
                return
            pq.write_table(pa.table({"pressure_mmhg": column}), path)
        images = raises_user_error_naming(path, lambda: read_pressure_file(path))
        if images is not None:
            _check_images(images)

    check()


def test_fuzzed_original_pickles(tmp_path):
    from pressurepose.data.importer import read_original

    n = 2
    doc = {
        "images": [np.ones(64 * 27) for _ in range(n)],
        "markers_xyz_m": [np.zeros(72) for _ in range(n)],
        "body_shape": [np.zeros(10) for _ in range(n)],
        "joint_angles": [np.zeros(72) for _ in range(n)],
        "root_xyz_shift": [np.zeros(3) for _ in range(n)],
        "body_mass": [70.0] * n,
    }
    blob = pickle.dumps(doc, protocol=2)
    path = tmp_path / "train_roll0_f_lay_set1_2.p"
    path.write_bytes(blob)
    assert len(read_original(path)[0]) == n  # the unmutated file is valid

    @fuzz("pickle")
    @given(st.data())
    def check(data):
        path.write_bytes(mutate_bytes(data, blob))
        raises_user_error_naming(path, lambda: read_original(path))

    check()


def test_the_suite_counts_its_fuzzed_cases():
    """docs/reliability.md reports how many bad inputs the suite tries; keep it in step."""
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[1] / "docs" / "reliability.md").read_text()
    assert f"{sum(EXAMPLES.values())} fuzzed" in doc
