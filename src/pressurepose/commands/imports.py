"""`pressurepose import-*`: other datasets converted into ours (the converters: `data.importer`,
`data.pmatdata`, `data.pressurepose_real`, `data.slp`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import tyro

from pressurepose.data.importer import import_original as import_original_files
from pressurepose.data.pmatdata import import_pmatdata as convert_pmatdata
from pressurepose.data.pressurepose_real import CloudFrame
from pressurepose.data.pressurepose_real import import_pressurepose_real as convert_pressurepose_real
from pressurepose.data.slp import import_slp as convert_slp


def import_original(
    files: tyro.conf.Positional[list[Path]],
    out: Path = Path("out/imported"),
    split: Literal["train", "test"] | None = None,
    gender: Literal["female", "male"] | None = None,
    partition: str | None = None,
) -> None:
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
    path = import_original_files(files, out, split=split, gender=gender, partition=partition)
    print(f"{json.loads(path.read_text())['total']} samples from {len(files)} files -> {out}")


def import_pmatdata(
    pmatdata: Path = Path("pmatdata"),
    out: Path = Path("out/pmatdata.npz"),
    groups: str | None = None,
    mattress: str | None = None,
    threshold: float = 20.0,
) -> None:
    """Convert PmatData (PhysioNet) frames into one .npz of 64 x 27 mmHg images (row 0 at the
    head) with their subject, posture and mattress, ready for `predict`.

    Args:
        pmatdata: PmatData folder (index.csv, experiment-ii/); "pmatdata" = the packaged copy of experiment II.
        out: .npz file to write.
        groups: posture groups to keep, e.g. BCD (default: all).
        mattress: air or sponge (default: both).
        threshold: raw noise threshold of the normalisation (data README).
    """
    res = convert_pmatdata(pmatdata, out, groups, mattress, threshold)
    print(f"{res['frames']} frames of {res['subjects']} subjects -> {res['out']}")


def import_pressurepose_real(
    src: tyro.conf.Positional[Path],
    out: Path = Path("out/pressurepose_real.npz"),
    pose_sets: tuple[Literal["prescribed", "p_select"], ...] = ("prescribed", "p_select"),
    pressure: Literal["release", "weight", "stored"] = "release",
    bed_angle_deg: float = 0.0,
    frame: CloudFrame = CloudFrame(),
) -> None:
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
        frame: Where the release's cloud frame sits in the mat frame.
    """
    res = convert_pressurepose_real(src, out, tuple(pose_sets), pressure, bed_angle_deg, frame)
    print(
        f"{res['frames']} frames of {res['participants']} participants ({res['points']} cloud points) -> {res['out']}"
    )


def import_slp(
    slp: tyro.conf.Positional[Path],
    out: Path = Path("out/slp.npz"),
    covers: tuple[Literal["uncover", "cover1", "cover2"], ...] = ("uncover", "cover1", "cover2"),
    subjects: list[int] | None = None,
    calibration: Literal["weight", "pmcali"] = "weight",
    pitch_m: float = 0.01,
    head_row: Literal["first", "last"] = "first",
    flip_columns: bool = False,
) -> None:
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
    res = convert_slp(slp, out, tuple(covers), subjects, calibration, pitch_m, head_row, flip_columns)
    print(f"{res['frames']} frames of {res['subjects']} subjects -> {res['out']}")


__all__ = ["import_original", "import_pmatdata", "import_pressurepose_real", "import_slp"]
