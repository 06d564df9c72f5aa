import json
import subprocess
import sys

from pressurepose.cli import main


def run(*args):
    return subprocess.run([sys.executable, "-m", "pressurepose.cli", *args], capture_output=True, text=True)


def test_help_lists_subcommands():
    r = run("--help")
    assert r.returncode == 0
    for command in ("demo", "cache"):
        assert command in r.stdout


def test_demo_writes_png_and_json(tmp_path):
    assert main(["demo", "--out", str(tmp_path / "d")]) == 0
    png = (tmp_path / "d" / "body.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    record = json.loads((tmp_path / "d" / "body.json").read_text())
    assert record["body_model"] == "anny" and len(record["pose"]) == 23
    assert 1.5 < record["height_m"] < 2.1
    head_x = record["joints_m"]["head"][0]
    assert 0 <= head_x <= 10 * 0.0286  # head over rows 0-10


def test_user_errors_exit_2_without_traceback(tmp_path):
    r = run("demo", "--backend", "smpl", "--smpl-dir", str(tmp_path))
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    assert "SMPL_NEUTRAL.npz or .pkl not found" in r.stderr
    r = run("demo", "--backend", "star")
    assert r.returncode == 2 and "Traceback" not in r.stderr
