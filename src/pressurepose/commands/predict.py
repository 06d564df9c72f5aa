"""`pressurepose predict`: pressure images in, body parameters, meshes and figures out.

Every input file is read and checked first (`net.inputs`), so a bad file stops the run
before anything is written. Images then go through the network in batches; per image
OUT/<name>.json (parameters by name, J24 joints, height and mass of the estimated shape; the
posture - supine, left, right or prone - read from the body's roll, as evaluate-real reads it; the
posture readout's probabilities for a network with one; for a heatmap network `joint_spread_m`, each
joint's heatmap spread on the mat (its RMS distance from its mean, m), which tells a joint the image
pins down from one it guesses
(docs/network.md "How far to trust a joint"); `load_ends`, whether the image's load
reaches the mat's head row, its foot row, both or neither - a body the mat cuts shows less of its
length, and its height is then read from its proportions: docs/network.md; `inference`, how the
network was read: its IK steps, flip test and shift test),
OUT/<name>.ply (the mesh, mat frame, metres; or .obj / .glb with --mesh-format, written by
trimesh) and OUT/<name>.png (the pressure image with the
projected skeleton, each joint marked by its heatmap spread's band for a heatmap network, top and
side views of the mesh). <name> is the file's stem, with
_<index> for files holding several images. Last, OUT/predictions.csv: one row per image in input
order (posture, roll, height, mass, where the load lies; the head and torso joints' median heatmap
spread and the readout's posture when the network has them) - a recording at a glance; a run that
stops early leaves none.

`--head-end last-row` reads files whose head end is their last row (turned end for end first);
`auto` reads each file both ways and keeps, for all its images, the way the heatmaps pin the head
and torso more sharply (`eval.real.head_end_spreads`; docs/real_data.md "Which end is the head").
The outputs are then in the mat frame with the head end at row 0, and each JSON and row says which
end of the file was the head. Left and right cannot be told apart so (a mirrored body presses the
mirrored image): the columns stay as given.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import time
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import tyro

from pressurepose.body.joints import J24_NAMES, TRUNK_JOINTS
from pressurepose.commands.netopts import with_inference_options
from pressurepose.errors import UserError
from pressurepose.eval.real import head_end_spreads, load_ends, posture_of, roll_deg
from pressurepose.files import atomic_write, write_text
from pressurepose.net.inputs import read_pressure_file
from pressurepose.net.model import GENDER_UNKNOWN, NetInputs
from pressurepose.net.posture import POSTURES
from pressurepose.train.checkpoint import load_network
from pressurepose.train.loop import pick_device

GENDERS = {"female": 1.0, "male": 0.0, "unknown": GENDER_UNKNOWN}


@dataclasses.dataclass(frozen=True)
class PredictConfig:
    """`pressurepose predict --model RUN FILES...`.

    Args:
        files: pressure images: .npy / .npz (mmHg, (64, 27) or (N, 64, 27)), .parquet dataset
            shards, .csv / .txt PmatData-like frames (64 lines of 27, row 0 at the foot end).
        model: a `pressurepose train` run folder (model.safetensors); "default" = the packaged model.
        out: output folder.
        gender: the subject's gender, if the network takes it (unknown = 0.5 on Anny's scale).
        height_m: the subject's height, for networks trained with height and mass inputs.
        mass_kg: the subject's mass: input of such networks, and the scale of raw text frames.
        text_units: raw (PmatData's uncalibrated units, scaled to mass_kg) or mmhg.
        batch_size: images per network pass.
        figures: write one PNG per image.
        meshes: write one mesh per image (with neither meshes nor figures the body is not
            skinned: ~20% less network time, the same joints and numbers).
        mesh_format: the meshes' file format: ply (binary), obj or glb.
        ik_steps: arch heatmap: IK steps fitting the body to the localised joints, instead of
            the model's own (3 by default; more fit closer, ~1 ms per image and step at batch 1).
        flip_test: arch heatmap: also localise the joints on the mirror image and average
            (MPJPE ~2 mm lower for the default model; twice the network's work per image).
        shift_test: arch heatmap: also read the image moved +-2 and +-4 rows along the bed and
            average the joints moved back (real frames' reads settle: docs/network.md "The shift
            test"; 5x the encoder-decoder's work per image).
        device: auto (CUDA when present), cpu or cuda.
        force: use images reading more than 1000 mmHg (the plausibility bound, net.inputs), clipped there.
        head_end: which row of the files lies at the head end: first-row (the project's
            convention), last-row (the images are turned end for end before reading), or auto (per
            file, the way a heatmap network pins the head and torso more sharply).
    """

    files: tyro.conf.Positional[tuple[Path, ...]] = ()
    model: Path = Path("default")
    out: Path = Path("out/predict")
    gender: Literal["female", "male", "unknown"] = "unknown"
    height_m: float | None = None
    mass_kg: float | None = None
    text_units: Literal["raw", "mmhg"] = "raw"
    batch_size: int = 32
    figures: bool = True
    meshes: bool = True
    mesh_format: Literal["ply", "obj", "glb"] = "ply"
    ik_steps: int | None = None
    flip_test: bool = False
    shift_test: bool = False
    device: Literal["auto", "cpu", "cuda"] = "auto"
    force: bool = False
    head_end: Literal["first-row", "last-row", "auto"] = "first-row"


def read_inputs(cfg: PredictConfig) -> list[tuple[str, np.ndarray, int]]:
    """[(name, (64, 27) image, index of its file in cfg.files)] of every file, all checked
    (ValueError on the first bad one)."""
    if not cfg.files:
        raise UserError("no input files; give pressure images after the options")
    items = []
    for f, path in enumerate(cfg.files):
        images = read_pressure_file(path, cfg.text_units, cfg.mass_kg or 70.0, cfg.force)
        for k, image in enumerate(images):
            items.append((path.stem if len(images) == 1 else f"{path.stem}_{k:04d}", image, f))
    names = [n for n, _, _ in items]
    if len(set(names)) != len(names):
        raise UserError("two inputs would write the same output name; give files with different names")
    return items


def run_predict(cfg: PredictConfig) -> dict:
    """Predict every image; returns a summary (counts, timings, output folder)."""
    if cfg.batch_size < 1:
        raise UserError(f"batch_size must be >= 1, got {cfg.batch_size}")
    out = Path(cfg.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file; give a folder for the outputs")
    items = read_inputs(cfg)
    device = pick_device(cfg.device)
    net, _ = load_network(cfg.model, device)
    net = with_inference_options(net, cfg.ik_steps, cfg.flip_test, cfg.shift_test)
    if net.config.height_weight and (cfg.height_m is None or cfg.mass_kg is None):
        raise UserError("this network takes height and mass as inputs: give --height-m and --mass-kg")
    if cfg.head_end == "auto" and net.config.arch != "heatmap":
        raise UserError("--head-end auto reads the head end from heatmaps: it needs a heatmap network (--arch heatmap)")
    items, ends = _orient(items, cfg, net, device)
    out.mkdir(parents=True, exist_ok=True)
    (out / "predictions.csv").unlink(missing_ok=True)  # an earlier run's table would not match this run's files
    t_net = 0.0
    mesh = cfg.meshes or cfg.figures  # the posed mesh only for a file or a figure: ~1/5 of the network's time
    table = []  # one row per image: OUT/predictions.csv, written last (a run that stops leaves none)
    for start in range(0, len(items), cfg.batch_size):
        chunk = items[start : start + cfg.batch_size]
        B = len(chunk)
        pressure = torch.from_numpy(np.stack([im for _, im, _ in chunk])).to(device)
        full = lambda v: None if v is None else torch.full((B,), float(v), device=device)  # noqa: E731
        inputs = NetInputs(
            pressure, gender=full(GENDERS[cfg.gender]), height_m=full(cfg.height_m), mass_kg=full(cfg.mass_kg)
        )
        t0 = time.perf_counter()
        with torch.inference_mode():
            est = net(inputs, mesh=mesh, maps=False)[-1]
            t_net += time.perf_counter() - t0
            measured = net.body.measure(est.params.shape)
        rolls = roll_deg(est.params.root_rotation.detach().double().cpu())
        for i, (name, image, f) in enumerate(chunk):
            table.append(_write_one(out, name, image, est, measured, i, net, cfg, float(rolls[i]), ends.get(f)))
    _write_table(out / "predictions.csv", table)
    return {"images": len(items), "out": str(out), "network_ms_per_image": 1000 * t_net / len(items)}


def _orient(items: list, cfg: PredictConfig, net, device) -> tuple[list, dict[int, dict]]:
    """The items with each file's images turned end for end where its head end is its last row
    (`--head-end`), and per file index what was found: {"head_end": "first row" | "last row"}, with
    auto the two trunk spreads; empty for the default (first-row)."""
    if cfg.head_end == "first-row":
        return items, {}
    ends = {}
    for f in sorted({f for _, _, f in items}):
        if cfg.head_end == "last-row":
            ends[f] = {"head_end": "last row"}
            continue
        mine = [im for _, im, g in items if g == f]
        images = torch.from_numpy(np.stack(mine)).to(device)  # head_end_spreads reads up to 64 of them
        given, turned = head_end_spreads(
            net, images, height_m=cfg.height_m, mass_kg=cfg.mass_kg, gender=GENDERS[cfg.gender]
        )
        ends[f] = {
            "head_end": "last row" if turned < given else "first row",
            "head_end_trunk_spread_m": {"first row": given, "last row": turned},
        }
    flip = {f for f, e in ends.items() if e["head_end"] == "last row"}
    return [(n, np.ascontiguousarray(im[::-1]) if f in flip else im, f) for n, im, f in items], ends


def _write_table(path: Path, rows: list[dict]) -> Path:
    """The images' summaries as CSV, one row each, in input order (a night's recording at a glance)."""
    columns = list(dict.fromkeys(k for row in rows for k in row))
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")  # quotes a name holding a comma
    writer.writerow(columns)
    for row in rows:
        writer.writerow([f"{c:.4f}" if isinstance(c, float) else c for c in (row.get(k, "") for k in columns)])
    return write_text(path, text.getvalue())


def _write_one(
    out: Path, name: str, image: np.ndarray, est, measured, i: int, net, cfg: PredictConfig, roll: float, end=None
) -> dict:
    """OUT/<name>.json (and the mesh and figure when asked); returns the image's row of predictions.csv."""
    p = est.params
    joints = est.joints[i].detach().cpu().numpy()
    record = {
        "model": str(cfg.model),
        "backend": net.config.backend,
        # how the network was read (its own settings or predict's options)
        "inference": {k: getattr(net.config, k) for k in ("ik_steps", "flip_test", "shift_test")},
        "shape": dict(zip(net.body.shape_names, p.shape[i].tolist())),
        "root_rotation_axis_angle": p.root_rotation[i].tolist(),
        "root_translation_m": p.root_translation[i].tolist(),
        "pose_axis_angle": {n: v for n, v in zip(J24_NAMES[1:], p.pose[i].tolist())},
        "joints_m": {n: v for n, v in zip(J24_NAMES, joints.tolist())},
        "height_m": float(measured.height_m[i]),
        "mass_kg": float(measured.mass_kg[i]),
        "load_ends": load_ends(image[None])[0],
        "posture": posture_of(torch.tensor([roll], dtype=torch.float64))[
            0
        ],  # from the body's roll, as evaluate-real reads it
        "roll_deg": roll,
        **(end or {}),  # which end of the file was the head (--head-end)
    }
    loc = est.localisation
    spread = None
    if loc is not None:  # how sharply each joint's heatmap pins it: large where the image shows it not
        spread = loc.spread_m[i].detach().double().cpu().numpy()
        record["joint_spread_m"] = dict(zip(J24_NAMES, spread.tolist()))
    row = {k: record[k] for k in ("posture", "roll_deg", "height_m", "mass_kg", "load_ends", "head_end") if k in record}
    if spread is not None:  # the head and torso joints' median spread, as evaluate-real reports it
        row["trunk_spread_m"] = float(torch.from_numpy(spread[list(TRUNK_JOINTS)]).median())  # the lower middle
    if loc is not None and loc.posture_logits is not None:  # the network's posture readout
        prob = torch.softmax(loc.posture_logits[i].detach().double(), -1).tolist()
        record["posture_readout"] = dict(zip(POSTURES, prob))
        row["readout_posture"] = POSTURES[int(np.argmax(prob))]
    write_text(out / f"{name}.json", json.dumps(record, indent=1))
    if est.vertices is None:  # neither meshes nor figures asked for: the body was not skinned
        return {"image": name, **row}
    vertices, faces = est.vertices[i].detach().cpu().numpy(), net.faces.cpu().numpy()
    if cfg.meshes:
        atomic_write(out / f"{name}.{cfg.mesh_format}", lambda tmp: write_mesh(tmp, vertices, faces))
    if cfg.figures:
        from pressurepose.viz.prediction import plot_prediction  # matplotlib (~0.7 s) only when drawing

        atomic_write(
            out / f"{name}.png", lambda tmp: plot_prediction(tmp, image, vertices, joints, net.mat, name, spread)
        )
    return {"image": name, **row}


def write_mesh(path: str | Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """A triangle mesh, vertices (V, 3) m and faces (F, 3), in the format of the file's suffix
    (.ply binary, .obj, .glb), every vertex kept in order."""
    import trimesh  # ~0.9 s to import: only when meshes are written

    trimesh.Trimesh(np.asarray(vertices, dtype=np.float32), np.asarray(faces), process=False).export(path)
    return Path(path)


def read_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The (vertices (V, 3), faces (F, 3)) of a mesh file `write_mesh` wrote."""
    import trimesh

    mesh = trimesh.load(path, process=False, force="mesh")
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def predict(cfg: PredictConfig) -> None:
    """Estimate the body from pressure images with a trained network: JSON parameters, meshes
    (.ply) and one figure per image in --out."""
    summary = run_predict(cfg)
    print(
        f"{summary['images']} images -> {summary['out']} "
        f"({summary['network_ms_per_image']:.1f} ms per image for the network and body model)"
    )


__all__ = ["PredictConfig", "predict", "read_inputs", "read_mesh", "run_predict", "write_mesh"]
