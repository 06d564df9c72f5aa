"""`pressurepose` command line: one subcommand per pipeline stage.

User errors (`pressurepose.errors.UserError`: bad input, bad files; OSError: missing,
unreadable or unwritable files) print one line and exit with status 2; anything else is a bug
and keeps its traceback.
"""

from __future__ import annotations

import contextlib
import json
import logging
import sys
from pathlib import Path
from typing import Literal

import tyro

from pressurepose.calib.run import CalibrateConfig
from pressurepose.commands.realism import RealismConfig
from pressurepose.data.coregister import CoregisterConfig
from pressurepose.demo import DemoConfig
from pressurepose.errors import UserError
from pressurepose.eval.real import RealEvalConfig
from pressurepose.eval.report import EvaluateConfig
from pressurepose.generate.plan import GenerateConfig
from pressurepose.net.predict import PredictConfig
from pressurepose.pose_figure import PoseConfig
from pressurepose.sampling.run import SampleConfig
from pressurepose.sim.run import SimulateConfig
from pressurepose.train.config import TrainConfig


def demo(cfg: DemoConfig) -> None:
    """The whole system on embedded defaults: simulate fresh samples, estimate their bodies with
    the packaged network, run it on real PmatData recordings; report.md in --out."""
    from pressurepose.demo import run_demo

    paths = run_demo(cfg)
    print(Path(paths["markdown"]).read_text())
    print(f"demo report: {paths['markdown']}")


def realism(cfg: RealismConfig) -> None:
    """Simulated pressure images against real ones of known posture, height and weight (PmatData
    by default): area, pressure, coverage, profiles, load per region, the real-vs-real ceiling."""
    from pressurepose.commands.realism import run_realism

    paths = run_realism(cfg)
    print(Path(paths["markdown"]).read_text())
    print(f"realism report: {paths['markdown']}")


def pose(cfg: PoseConfig) -> None:
    """Pose the body model's default adult supine on the mat and draw it (body.png, body.json)."""
    from pressurepose.pose_figure import run_pose

    paths = run_pose(cfg)
    print(f"wrote {paths['png']} and {paths['json']}")


def cache(build: bool = True) -> None:
    """Show the cache directory and build the Anny body-model cache if missing.

    Args:
        build: Build the Anny cache now (about a minute, once).
    """
    from pressurepose.cache import cache_dir

    root = cache_dir()
    if build:
        from pressurepose.body.anny_backend import load_anny

        load_anny()
    size = sum(p.stat().st_size for p in Path(root).rglob("*") if p.is_file())
    print(f"{root} ({size / 1e6:.0f} MB)")


def sample(cfg: SampleConfig) -> None:
    """Draw initial poses for one partition (seed A.1) and write poses.npz, cells.png and
    bodies.png."""
    from pressurepose.sampling.run import run_sample

    paths = run_sample(cfg)
    record = json.loads(paths["config"].read_text())
    print(f"{record['count']} poses ({record['samples_per_second']:.0f}/s) -> {cfg.out}: "
          + ", ".join(p.name for p in paths.values()))


def simulate(cfg: SimulateConfig) -> None:
    """Simulate one sample: initial pose, settling (sim #1), pressure (sim #2), sensor and
    label maps; writes sample.npz, simulate.json and simulate.png."""
    from pressurepose.sim.run import run_simulate

    paths = run_simulate(cfg)
    record = json.loads(paths["record"].read_text())
    print(f"{record['mass_kg']} kg: contact {record['contact_area_m2']} m^2, mean "
          f"{record['mean_contact_pressure_mmhg']} mmHg, peak {record['peak_pressure_mmhg']} mmHg, "
          f"sim #1 {record['timing_ms']['sim1']} ms ({record['settle_steps']} steps), "
          f"sim #2 {record['timing_ms']['sim2']} ms -> {cfg.out}")


def coregister(cfg: CoregisterConfig) -> None:
    """Co-register a camera with the mat from clicked corner markers (seed A.6): camera.json
    (pose), coregister.png and, with --cloud, the point cloud in the mat frame."""
    from pressurepose.data.coregister import run_coregister

    paths = run_coregister(cfg)
    record = json.loads(paths["camera"].read_text())
    print(f"camera at {[round(v, 3) for v in record['camera_position_in_mat_m']]} m in the mat frame, "
          f"reprojection RMS {record['rms_px']:.2f} px -> {cfg.out}")


def calibrate(cfg: CalibrateConfig) -> None:
    """Calibrate mattress, mat and sensor parameters to measurements of rigid objects with
    CMA-ES (seed A.4); resumable; writes params.json for `simulate --params`."""
    from pressurepose.calib.run import run_calibrate

    paths = run_calibrate(cfg)
    record = json.loads(paths["record"].read_text())
    state = "finished" if record["finished"] else "stopped (resume with the same command)"
    print(f"{state} after {record['iterations']} generations, {record['evaluations']} evaluations: loss "
          f"{record['start_loss']:.4g} -> {record['best_loss']:.4g}; parameters -> {paths['params']}")


def train(cfg: TrainConfig) -> None:
    """Train PressureNet's Mod1 (--module 1) or Mod2 on a trained Mod1 (--module 2 --mod1 RUN);
    writes checkpoints, metrics and a plot to --out and resumes a run found there."""
    from pressurepose.train.loop import train as run_training

    run = run_training(cfg)
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines() if line.strip()]
    last = rows[-1] if rows else {}
    val = f", val MPJPE {last['val_mpjpe_mm']:.1f} mm" if "val_mpjpe_mm" in last else ""
    print(f"{len(rows)} epochs -> {run}: loss {last.get('loss', float('nan')):.4f}, train MPJPE "
          f"{last.get('train_mpjpe_mm', float('nan')):.1f} mm{val}")


def predict(cfg: PredictConfig) -> None:
    """Estimate the body from pressure images with a trained network: JSON parameters, .ply
    meshes and one figure per image in --out."""
    from pressurepose.net.predict import run_predict

    summary = run_predict(cfg)
    print(f"{summary['images']} images -> {summary['out']} "
          f"({summary['network_ms_per_image']:.1f} ms per image for the network and body model)")


def evaluate(cfg: EvaluateConfig) -> None:
    """Evaluate a trained network on a dataset (seed Table 5): tables per partition and gender
    with the seed's numbers and two baselines, per-region errors, best/median/worst cases and
    failures; report.md, report.json and PNGs in --out."""
    from pressurepose.eval.report import run_evaluate

    paths = run_evaluate(cfg)
    record = json.loads(paths["json"].read_text())
    o = record["overall"]
    print(f"{record['count']} samples: 3DVPE {o['vpe_m']['mean'] * 100:.2f} cm, MPJPE {o['mpjpe_m']['mean'] * 100:.2f} cm "
          f"-> {paths['markdown']}")


def evaluate_real(cfg: RealEvalConfig) -> None:
    """Run a trained network on PmatData's real recordings: posture accuracy from the estimated
    root, estimated height and mass against the subjects', per mattress (real.md, real.png);
    with --data FILE.npz (import-pressurepose-real), 3DVPE against its point clouds per
    participant."""
    from pressurepose.eval.real import run_evaluate_real

    paths = run_evaluate_real(cfg)
    record = json.loads(paths["json"].read_text())
    if record.get("kind") == "point-cloud":
        o = record["overall"]
        extra = (f", height MAE {o['height_mae_m'] * 100:.1f} cm, mass MAE {o['mass_mae_kg']:.1f} kg"
                 if "height_mae_m" in o else "")
        print(f"{record['frames']} frames of {o['participants']} participants: 3DVPE {o['vpe_m'] * 100:.2f} cm"
              f"{extra} -> {paths['markdown']}")
        return
    parts = [f"{k}: posture {v['posture_accuracy'] * 100:.0f}%, height MAE {v['height_mae_m'] * 100:.1f} cm, "
             f"mass MAE {v['mass_mae_kg']:.1f} kg" for k, v in record["by_mattress"].items()]
    print(f"{record['frames']} frames; " + "; ".join(parts) + f" -> {paths['markdown']}")


def generate(cfg: GenerateConfig) -> None:
    """Generate a dataset (sampling, sim #1, sim #2, sensor) into Parquet shards and
    manifest.json; re-running the same command resumes an interrupted run."""
    from pressurepose.generate.run import run_generate

    s = run_generate(cfg)
    print(f"{s['total']} samples in {s['shards']} shards -> {cfg.out} ({s['made']} made now, {s['resumed']} "
          f"already there; {s['rejected']} rejected and replaced)"
          + (f", {s['made'] / s['seconds']:.2f} samples/s" if s["made"] else ""))


def info(dataset: tyro.conf.Positional[Path], sheet: int = 24, seed: int = 0) -> None:
    """Describe a dataset: counts per partition and gender, rejections, pressure statistics;
    verifies every shard's sha256 and writes DATASET/contact_sheet.png.

    Args:
        dataset: Dataset folder (with manifest.json).
        sheet: Random samples drawn in the contact sheet (0: none).
        seed: Which random samples.
    """
    from pressurepose.data.info import dataset_info, format_info

    print(format_info(dataset_info(dataset, sheet=sheet, seed=seed)))


def import_original(files: tyro.conf.Positional[list[Path]], out: Path = Path("out/imported"),
                    split: Literal["train", "test"] | None = None, gender: Literal["female", "male"] | None = None,
                    partition: str | None = None) -> None:
    """Convert original PressurePose synthetic files (Python 2 pickles of dicts of lists) into a
    dataset folder (Parquet shards + manifest.json). Only numpy arrays and plain containers are
    accepted from the pickles; anything else is refused.

    Args:
        files: Original .p files.
        out: Dataset folder to write.
        split: train or test (default: from the file name, else train).
        gender: female or male (default: from the file name, e.g. train_roll0_f_lay_...).
        partition: Partition label (default: from the file name, else "unknown").
    """
    from pressurepose.data.importer import import_original as run

    path = run(files, out, split=split, gender=gender, partition=partition)
    print(f"{json.loads(path.read_text())['total']} samples from {len(files)} files -> {out}")


def import_pmatdata(pmatdata: Path = Path("pmatdata"), out: Path = Path("out/pmatdata.npz"),
                    groups: str | None = None, mattress: str | None = None, threshold: float = 20.0) -> None:
    """Convert PmatData (PhysioNet) frames into one .npz of 64 x 27 mmHg images (row 0 at the
    head) with their subject, posture and mattress, ready for `predict`.

    Args:
        pmatdata: PmatData folder (index.csv, experiment-ii/); "pmatdata" = the packaged copy of experiment II.
        out: .npz file to write.
        groups: posture groups to keep, e.g. BCD (default: all).
        mattress: air or sponge (default: both).
        threshold: raw noise threshold of the normalisation (data README).
    """
    from pressurepose.data.pmatdata import import_pmatdata as run

    res = run(pmatdata, out, groups, mattress, threshold)
    print(f"{res['frames']} frames of {res['subjects']} subjects -> {res['out']}")


def import_pressurepose_real(src: tyro.conf.Positional[Path], out: Path = Path("out/pressurepose_real.npz"),
                             pose_sets: tuple[Literal["prescribed", "p_select"], ...] = ("prescribed", "p_select"),
                             pressure: Literal["release", "weight", "stored"] = "release", bed_angle_deg: float = 0.0,
                             head_x_m: float = 64 * 0.0286 * 1.04, col0_y_m: float = 0.0,
                             mattress_z_m: float = 0.075) -> None:
    """Convert the original PressurePose real dataset (participant folders S103 ... of Python 2
    pickles) into one .npz: 64 x 27 mmHg images (row 0 at the head), participant, gender,
    height, mass, bed angle, and the Kinect point clouds in the mat frame, for `predict` and
    `evaluate-real --data`. Only numpy arrays and plain containers are accepted from the pickles.

    Args:
        src: The release's real/ folder (or one participant's folder).
        out: .npz file to write.
        pose_sets: prescribed (48 poses) and/or p_select (5 participant-selected poses).
        pressure: release (x4, the release's bed-sheet factor), weight (summed force = the
            participant's weight) or stored; all clipped at 100 mmHg.
        bed_angle_deg: Head-of-bed angle to record (the release evaluates its real frames flat).
        head_x_m: Cloud frame: the head edge of the sensing area along the cloud's axis 0 (m).
        col0_y_m: Cloud frame: the column-0 edge along the cloud's axis 1 (m).
        mattress_z_m: Cloud frame: the mattress top along the cloud's (downward) axis 2 (m).
    """
    from pressurepose.data.pressurepose_real import CloudFrame
    from pressurepose.data.pressurepose_real import import_pressurepose_real as run

    res = run(src, out, tuple(pose_sets), pressure, bed_angle_deg, CloudFrame(head_x_m, col0_y_m, mattress_z_m))
    print(f"{res['frames']} frames of {res['participants']} participants ({res['points']} cloud points) -> {res['out']}")


def import_slp(slp: tyro.conf.Positional[Path], out: Path = Path("out/slp.npz"),
               covers: tuple[Literal["uncover", "cover1", "cover2"], ...] = ("uncover", "cover1", "cover2"),
               subjects: list[int] | None = None, calibration: Literal["weight", "pmcali"] = "weight",
               pitch_m: float = 0.01, head_row: Literal["first", "last"] = "first", flip_columns: bool = False) -> None:
    """Convert SLP pressure maps (danaLab/NNNNN/PMarray/COVER/NNNNNN.npy, 192 x 84 at 1 cm)
    into one .npz of 64 x 27 mmHg images on the BT3510 grid (area resampling, row 0 at the
    head) with subject, cover, frame, gender, height and mass, ready for `predict`.

    Args:
        slp: SLP's danaLab folder (physiqueData.npy and the subject folders).
        out: .npz file to write.
        covers: Cover conditions to import.
        subjects: Subject numbers (default: all found).
        calibration: weight (summed force on our grid = the subject's weight) or pmcali
            (PMarray x PMcali.npy, taken as kPa).
        pitch_m: SLP taxel pitch (m).
        head_row: Which stored row is at the head end.
        flip_columns: Mirror the columns.
    """
    from pressurepose.data.slp import import_slp as run

    res = run(slp, out, tuple(covers), subjects, calibration, pitch_m, head_row, flip_columns)
    print(f"{res['frames']} frames of {res['subjects']} subjects -> {res['out']}")


def view(path: tyro.conf.Positional[Path], port: int = 8765, open: bool = True, data: Path | None = None,
         model: Path | None = None, backend: Literal["anny", "smpl"] | None = None, smpl_dir: Path | None = None) -> None:
    """Browse samples and predictions in a local web page on 127.0.0.1: pressure images, true
    and estimated 3D bodies, joint errors, training curves (docs/viewer.md). Ctrl-C stops it.

    Args:
        path: Dataset folder (manifest.json), `evaluate` report folder, training run folder, or a
            .npz of pressure images (import-pmatdata).
        port: Port on 127.0.0.1 (0: any free port).
        open: Open the page in the default web browser.
        data: Dataset of a report or run, when the path recorded in it is not found.
        model: Training run whose network estimates the bodies shown (datasets, .npz images).
        backend: Body model (default: the dataset's or run's, else anny).
        smpl_dir: Folder with the SMPL files for --backend smpl.
    """
    from pressurepose.viz.viewer import ViewConfig, serve

    cfg = ViewConfig(path=path, port=port, open=open, data=data, model=model, backend=backend, smpl_dir=smpl_dir)
    serve(cfg, ready=lambda url: print(f"viewing {path} at {url} (Ctrl-C stops)", flush=True))
    print("viewer stopped")


def click(image: tyro.conf.Positional[Path], out: Path = Path("markers.json"), fx: float | None = None,
          fy: float | None = None, cx: float | None = None, cy: float | None = None, intrinsics: Path | None = None,
          depth_unit: Literal["auto", "m", "mm"] = "auto", port: int = 8765, open: bool = True) -> None:
    """Click the mat's corner markers in a camera image on a local web page (127.0.0.1) and
    save the marker file `coregister --markers` reads (docs/real_data.md). Ctrl-C stops it.

    Args:
        image: RGB image (.png, .jpg) or depth image (.npy, (H, W), metres or millimetres;
            clicks then record the marker's depth).
        out: Marker file to write; an existing one is loaded for editing.
        fx: Focal length along u (pixels).
        fy: Focal length along v (pixels).
        cx: Principal point u (pixels; pixel centres at integers).
        cy: Principal point v (pixels).
        intrinsics: JSON with fx, fy, cx, cy (top level or under "intrinsics"); flags override it.
        depth_unit: Unit of a depth .npy (auto: integers or values over 20 are millimetres).
        port: Port on 127.0.0.1 (0: any free port).
        open: Open the page in the default web browser.
    """
    from pressurepose.viz.clicker import ClickConfig, make_click_server
    from pressurepose.viz.viewer import run_local

    cfg = ClickConfig(image=image, out=out, fx=fx, fy=fy, cx=cx, cy=cy, intrinsics=intrinsics,
                      depth_unit=depth_unit, port=port, open=open)
    server = make_click_server(cfg)
    run_local(server, open, ready=lambda url: print(f"clicking {image} at {url} -> {out} (Ctrl-C stops)", flush=True))
    print("click page stopped")


COMMANDS = {
    "demo": demo, "pose": pose, "sample": sample, "simulate": simulate, "generate": generate, "info": info,
    "import-original": import_original, "import-pmatdata": import_pmatdata,
    "import-pressurepose-real": import_pressurepose_real, "import-slp": import_slp, "calibrate": calibrate,
    "coregister": coregister, "click": click, "cache": cache, "realism": realism,
    "train": train, "predict": predict, "evaluate": evaluate, "evaluate-real": evaluate_real, "view": view,
}


def _argument_error(event) -> None:
    """tyro's parse-error hook: a config's own check (a UserError from __post_init__) is one
    line, like any other user error, not a box naming tyro's internal field names."""
    if type(event).__name__ == "InstantiationFailure":
        raise UserError(str(event.message).strip())


def _parse_and_run(argv: list[str] | None) -> None:
    hook = getattr(getattr(tyro, "_errors", None), "on_parse_error", None)
    context = hook(_argument_error) if hook is not None else contextlib.nullcontext()
    with context:
        run = tyro.extras.subcommand_cli_from_dict(
            COMMANDS, prog="pressurepose", args=argv, config=(tyro.conf.OmitArgPrefixes,)
        )
    return run


def describe_os_error(exc: OSError) -> str:
    """One line for a missing, unreadable or unwritable file, naming it."""
    if exc.filename is None or exc.strerror is None:
        return str(exc)
    where = f"{exc.filename}" + (f" -> {exc.filename2}" if exc.filename2 else "")
    return f"{where}: {exc.strerror.lower()}"


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        _parse_and_run(argv)
    except UserError as exc:
        # Our input checks raise UserError naming the file, the field and what was expected.
        print(f"pressurepose: error: {' '.join(str(exc).split())}", file=sys.stderr)  # one line
        return 2
    except OSError as exc:
        # Unreadable, unwritable or missing files: not a bug either.
        print(f"pressurepose: error: {describe_os_error(exc)}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
