"""Every output file is written atomically: a grep over src/ for writes that bypass
`pressurepose.files` (atomic_write and the helpers built on it), and `pose` as an example."""

import re
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "pressurepose"

# A call that writes a file.
WRITE = re.compile(
    r"\.write_text\(|\.write_bytes\(|\.savefig\(|\bnp\.save[z_]*\w*\(|\bsave_file\(|"
    r"\bopen\([^)]*['\"][wax]b?\+?['\"]|\.to_csv\(|\bpq\.write_table\("
)
# Allowed: inside an atomic_write on the same line, or writing to `tmp` (the temporary name
# atomic_write hands its writer), or to an in-memory buffer.
ALLOWED = re.compile(r"atomic_write\(|\((?:Path\()?tmp\b|\(fh\b|[(, ]buf\b|open\(tmp\b")
# Writes that are not outputs, each with its reason.
EXCEPTIONS = {
    ("cache.py", 'with open(path, "a") as handle:'): "the cache's lock file (flock), never holds data",
    ("generate/run.py", 'fh = open(out / ".lock", "a")'): "the dataset folder's lock file (flock)",
}


def bare_writes() -> list[str]:
    found = []
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(SRC).as_posix()
        if rel == "files.py":
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            code = line.split("#", 1)[0]
            if not WRITE.search(code) or ALLOWED.search(code):
                continue
            if (rel, code.strip()) in EXCEPTIONS:
                continue
            found.append(f"{rel}:{number}: {line.strip()}")
    return found


def test_no_output_bypasses_the_atomic_helpers():
    assert bare_writes() == []


def test_the_grep_catches_a_bare_write(tmp_path, monkeypatch):
    import test_atomic_outputs as me

    (tmp_path / "bad.py").write_text(
        'def f(p, fig):\n    p.write_text("x")\n    fig.savefig(p)\n    with open(p, "w") as fh:\n        pass\n'
    )
    monkeypatch.setattr(me, "SRC", tmp_path)
    assert len(me.bare_writes()) == 3


def test_write_mesh_is_only_called_inside_atomic_write():
    calls = [
        line
        for path in SRC.rglob("*.py")
        for line in path.read_text().splitlines()
        if "write_mesh(" in line and "def write_mesh" not in line
    ]
    assert calls and all("atomic_write(" in line for line in calls)


def test_pose_writes_nothing_under_its_final_names_when_drawing_fails(tmp_path, monkeypatch):
    """A crash while drawing leaves neither body.png nor body.json behind (the old pose
    wrote body.png in place, then body.json)."""
    import pressurepose.viz.body_on_mat as fig_module
    from pressurepose.commands.pose import PoseConfig, run_pose

    real = fig_module.plt.Figure.savefig

    def half_then_crash(self, fname, *args, **kwargs):
        Path(fname).write_bytes(b"\x89PNG half")
        raise RuntimeError("disk full while drawing")

    monkeypatch.setattr(fig_module.plt.Figure, "savefig", half_then_crash)
    with pytest.raises(RuntimeError, match="disk full"):
        run_pose(PoseConfig(out=tmp_path / "pose"))
    assert sorted(p.name for p in (tmp_path / "pose").iterdir()) == []
    monkeypatch.setattr(fig_module.plt.Figure, "savefig", real)
    paths = run_pose(PoseConfig(out=tmp_path / "pose"))
    assert paths["png"].read_bytes()[:4] == b"\x89PNG" and paths["json"].is_file()
