import json
import os
import subprocess
import sys

import numpy as np
import pytest

from pressurepose.cli import main


def run(*args):
    return subprocess.run([sys.executable, "-m", "pressurepose.cli", *args], capture_output=True, text=True)


def test_help_lists_subcommands():
    r = run("--help")
    assert r.returncode == 0
    for command in ("demo", "sample", "cache"):
        assert command in r.stdout


def test_pose_writes_png_and_json(tmp_path):
    assert main(["pose", "--out", str(tmp_path / "d")]) == 0
    png = (tmp_path / "d" / "body.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    record = json.loads((tmp_path / "d" / "body.json").read_text())
    assert record["body_model"] == "anny" and len(record["pose"]) == 23
    assert 1.5 < record["height_m"] < 2.1
    head_x = record["joints_m"]["head"][0]
    assert 0 <= head_x <= 10 * 0.0286  # head over rows 0-10


def test_user_errors_exit_2_without_traceback(tmp_path):
    r = run("pose", "--backend", "smpl", "--smpl-dir", str(tmp_path))
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    assert "SMPL_NEUTRAL.npz or .pkl not found" in r.stderr
    r = run("pose", "--backend", "star")
    assert r.returncode == 2 and "Traceback" not in r.stderr


def test_sample_writes_poses_and_figures(tmp_path):
    out = tmp_path / "s"
    assert (
        main(
            [
                "sample",
                "--out",
                str(out),
                "--n",
                "12",
                "--partition",
                "supine",
                "--gender",
                "male",
                "--batch",
                "5",
                "--figures",
                "4",
            ]
        )
        == 0
    )
    from pressurepose.commands.sample import load_poses

    arrays = load_poses(out / "poses.npz")
    assert arrays["pose"].shape == (12, 23, 3) and arrays["joints"].shape == (12, 24, 3)
    np.testing.assert_array_equal(arrays["index"], np.arange(12))
    assert set(k for k in arrays if k.startswith("rejections_")) == {
        "rejections_limb_draws_rejected",
        "rejections_limb_failures",
        "rejections_collisions",
        "rejections_shape_resamples",
        "rejections_cell_redraws",
        "rejections_sit_up_rejections",
    }
    np.testing.assert_array_equal(arrays["head_angle_deg"], np.zeros(12))  # flat bed
    record = json.loads((out / "config.json").read_text())
    assert record["sampling"]["partition"] == "supine" and record["count"] == 12
    assert sum(record["cell_counts"]["left_leg"]) == 12
    # the shape law: the box and each entry's power (Anny's weight drawn with a rising density)
    power = dict(zip(record["shape_names"], record["shape_power"]))
    assert power.pop("weight") == 2.0 and set(power.values()) == {1.0} and record["sampling_law"] >= 3
    for name in ("cells.png", "bodies.png"):
        assert (out / name).read_bytes()[:4] == b"\x89PNG"
    assert not list(out.glob(".*partial*"))  # no temporary files left behind
    # the same indices drawn in another batch size are the same samples
    again = tmp_path / "t"
    assert (
        main(
            [
                "sample",
                "--out",
                str(again),
                "--n",
                "12",
                "--partition",
                "supine",
                "--gender",
                "male",
                "--batch",
                "12",
                "--figures",
                "0",
            ]
        )
        == 0
    )
    other = load_poses(again / "poses.npz")
    for key in ("shape", "pose", "root_rotation", "root_translation", "cells"):
        np.testing.assert_array_equal(arrays[key], other[key])


def test_sample_bad_input_exits_2(tmp_path):
    r = run("sample", "--out", str(tmp_path / "x"), "--partition", "sideways")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "valid partitions: general, supine" in r.stderr
    r = run("sample", "--out", str(tmp_path / "x"), "--n", "0")
    assert r.returncode == 2 and "n must be >= 1" in r.stderr
    r = run("sample", "--out", str(tmp_path / "x"), "--partition", "hands_behind_head")
    assert r.returncode == 2 and "over_bed=True" in r.stderr


def test_load_poses_refuses_missing_and_corrupt_files(tmp_path):
    from pressurepose.commands.sample import load_poses

    with pytest.raises(ValueError, match="no poses file"):
        load_poses(tmp_path / "none.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a readable poses file"):
        load_poses(bad)


def test_simulate_writes_image_labels_and_figure(tmp_path):
    out = tmp_path / "sim"
    assert main(["simulate", "--out", str(out), "--partition", "supine", "--gender", "male", "--index", "1"]) == 0
    record = json.loads((out / "simulate.json").read_text())
    assert record["status"] == "ok" and record["reason"] == ""
    with np.load(out / "sample.npz", allow_pickle=False) as data:
        p, q, c = data["pressure_mmhg"], data["depth_mm"], data["contact"]
        assert p.shape == q.shape == c.shape == (64, 27)
        assert (p >= 0).all() and (p <= 100).all() and p.sum() > 0
        assert ((q < 0) == (c == 1)).all()
    assert (out / "simulate.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # Taxels reading >= 1 mmHg: the mat's membrane (the sponge preset's since session 42) reads a
    # faint halo around the body that the real mats' floor hides (the realism report compares at
    # the real floor, where the sponge areas agree within 5%): 0.64 m^2 for this body.
    assert 0.1 < record["contact_area_m2"] < 0.8
    # The default engine is the generator's: the articulated rest on the sponge bed, no MuJoCo.
    from pressurepose.sim.mattress import MattressParams

    assert record["timing_ms"]["sim1"] == 0 and record["mattress"] == MattressParams.preset("sponge").to_dict()
    # Its settling count is the articulated rest's re-posings (outer + 1: still moving at the cap).
    from pressurepose.sim.articulated import ArticulatedConfig

    assert 0 <= record["settle_steps"] <= ArticulatedConfig().outer + 1


def test_simulate_with_mujoco_runs_sim1_on_the_rigid_rests_bed(tmp_path):
    out = tmp_path / "sim"
    args = ["simulate", "--out", str(out), "--partition", "supine", "--gender", "male", "--index", "1"]
    assert main([*args, "--settle", "mujoco"]) == 0
    record = json.loads((out / "simulate.json").read_text())
    from pressurepose.sim.mattress import MattressParams

    assert record["status"] == "ok" and record["settle_steps"] > 0
    assert record["mattress"]["k1_pa_per_m"] == MattressParams().k1_pa_per_m


def test_simulate_bad_parameter_file_exits_2(tmp_path):
    bad = tmp_path / "bed.json"
    bad.write_text("not json")
    r = run("simulate", "--out", str(tmp_path / "s"), "--params", str(bad))
    assert r.returncode == 2 and "Traceback" not in r.stderr and "not readable JSON" in r.stderr


def test_simulate_half_sitting_uses_the_samples_bed_and_refuses_another(tmp_path):
    out = tmp_path / "sit"
    assert main(["simulate", "--out", str(out), "--partition", "half_sitting", "--gender", "male", "--index", "0"]) == 0
    record = json.loads((out / "simulate.json").read_text())
    angle = record["head_angle_deg"]
    assert record["status"] == "ok" and angle in (10.0, 20.0, 30.0, 40.0, 50.0, 60.0)
    other = 10.0 if angle != 10.0 else 20.0
    r = run(
        "simulate",
        "--out",
        str(tmp_path / "s2"),
        "--partition",
        "half_sitting",
        "--index",
        "0",
        "--gender",
        "male",
        "--head-angle-deg",
        str(other),
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr and "leave out --head-angle-deg" in r.stderr


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("pressurepose: error: "), lines
    assert "Traceback" not in err and "╭" not in err  # neither a traceback nor tyro's box
    return lines[0]


@pytest.mark.parametrize(
    "args, message",
    [
        # a config's __post_init__ (SamplingConfig, GenerateConfig), run while tyro builds it
        (["sample", "--seed", "-1"], "seed must be >= 0, got -1"),
        (["simulate", "--max-shapes", "0"], "max_shapes must be >= 1, got 0"),
        (["generate", "--workers", "0"], "workers must be >= 1, got 0"),
        (["generate", "--sim2", "rigid"], "--sim2 rigid needs --settle mujoco"),
        # a flag's text that is not of its type: the flag and the type are named
        (["sample", "--n", "abc"], "--n (expects INT): invalid literal for int()"),
        (["train", "--lr-gamma", "fast"], "--lr-gamma (expects FLOAT)"),
        # checked when the command runs (TrainConfig, NetConfig's range)
        (["train", "--dropout", "1.5", "--data", "tests/data"], "dropout must lie in [0, 1), got 1.5"),
    ],
)
def test_bad_config_values_are_one_line_exit_2(args, message, tmp_path, capsys):
    assert main([*args, "--out", str(tmp_path / "out")]) == 2
    assert message in one_line(capsys.readouterr().err)
    assert not (tmp_path / "out").exists()


def test_bad_config_value_in_a_real_process(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "pressurepose", "generate", "--out", str(tmp_path / "g"), "--workers", "0"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and r.stdout == ""
    assert one_line(r.stderr) == "pressurepose: error: workers must be >= 1, got 0"


@pytest.mark.parametrize("kind", [ValueError, TypeError])
def test_a_bug_while_building_a_config_keeps_its_traceback(kind, monkeypatch):
    # tyro catches ValueErrors raised while it builds the configs; one that is not a UserError
    # is a bug and must come out as itself, not as a one-line message. The command's module is
    # imported first (it builds a default SamplingConfig), so the bug meets tyro, not the import.
    import pressurepose.commands.sample  # noqa: F401
    from pressurepose.sampling.partitions import SamplingConfig

    def broken(self):
        raise kind("an internal bug in SamplingConfig")

    monkeypatch.setattr(SamplingConfig, "__post_init__", broken)
    with pytest.raises(kind, match="an internal bug in SamplingConfig") as caught:
        main(["sample", "--out", "unused", "--seed", "3"])
    assert type(caught.value) is kind


def test_a_bug_prints_its_traceback_in_a_real_process(tmp_path):
    script = (  # patched after the command's import, which builds the default configs
        "import sys\n"
        "from pressurepose.cli import main\n"
        "import pressurepose.commands.sample\n"
        "from pressurepose.sampling.partitions import SamplingConfig\n"
        "def broken(self):\n"
        "    raise ValueError('an internal bug in SamplingConfig')\n"
        "SamplingConfig.__post_init__ = broken\n"
        f"sys.exit(main(['sample', '--out', {str(tmp_path / 's')!r}, '--seed', '3']))\n"
    )
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert r.returncode == 1
    assert "Traceback (most recent call last)" in r.stderr and "in broken" in r.stderr
    assert r.stderr.strip().splitlines()[-1] == "ValueError: an internal bug in SamplingConfig"
    assert "pressurepose: error" not in r.stderr


def test_a_named_command_imports_only_its_own_module():
    """`pressurepose info` does not import the other commands (their dependencies cost seconds
    at start-up); help and unknown names see every command, so tyro can list and suggest them."""
    from pressurepose.cli import COMMANDS, commands_for

    assert list(commands_for(["evaluate-real", "--model", "x"])) == ["evaluate-real"]
    for argv in ([], ["--help"], ["evalute"], ["--model", "x"]):
        assert list(commands_for(argv)) == list(COMMANDS)
    code = (
        "import sys; from pressurepose.cli import commands_for; commands_for(['info']); "
        "print(sorted(m for m in sys.modules if m.startswith('pressurepose.commands.')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['pressurepose.commands.info']"


def test_predict_imports_mesh_and_figure_libraries_only_to_write_them(tmp_path):
    """`predict --no-figures --no-meshes` (a stream of frames) starts without matplotlib and
    trimesh (~1.6 s of imports): both load when a figure or a mesh is written."""
    code = (
        "import sys, numpy as np; from pressurepose.cli import main; "
        f"np.save({str(tmp_path / 'a.npy')!r}, np.random.default_rng(0).random((64, 27)) * 30); "
        f"args = ['predict', '--out', {str(tmp_path / 'p')!r}, {str(tmp_path / 'a.npy')!r}]; "
        "assert main([*args, '--no-figures', '--no-meshes']) == 0; "
        "print(sorted(m for m in ('matplotlib', 'trimesh') if m in sys.modules)); "
        "assert main(args) == 0; "
        "print(sorted(m for m in ('matplotlib', 'trimesh') if m in sys.modules))"
    )
    env = dict(os.environ, OMP_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env).stdout
    assert [line for line in out.splitlines() if line.startswith("[")] == ["[]", "['matplotlib', 'trimesh']"]
    assert (tmp_path / "p" / "a.png").is_file() and (tmp_path / "p" / "a.ply").is_file()
