"""The posture a body lies in, read from its root rotation (PmatData's labels: supine, left,
right lateral; `pressurepose evaluate-real`).

Posture from the root: the heights of the body's left and front axes in the mat frame give
the roll about the bed's long axis, roll = atan2(left_z, front_z) whatever the yaw (0 supine,
-90 deg on the left side, +90 deg on the right, +-180 prone; the convention of `sampling` and
`benchmarks/sim_realism.py`, which put PmatData's group D "left" at roll -90 deg).
|roll| <= 45 deg: supine; >= 135: prone; otherwise left or right by its sign.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np
import torch

from pressurepose.body.joints import TRUNK_JOINTS
from pressurepose.eval.realism import EXTENT_SHARE, load_span
from pressurepose.net.model import GENDER_UNKNOWN, NetInputs
from pressurepose.net.posture import POSTURES, posture_index
from pressurepose.net.posture import roll_from_root as roll_deg

GROUP_POSTURE = {"B": "supine", "C": "right", "D": "left"}  # PmatData's flat groups (README)
# PmatData's group E: lateral on one or two wedges or a pillow, rolled 20 or 40 deg toward the
# side its posture names - between the flat groups' supine and full side, so judged by its roll
# (`tilt_summary`), not by a posture class.
TILTED_GROUPS = "E"
# PmatData's group F: supine with the head of the bed raised 0-60 deg (F1 flat ... F7 60 deg), the
# network's flat-bed scope left; reported apart (posture and height per angle), not in the flat table.
RAISED_GROUPS = "F"
RAISED_POSTURE = "supine"
TURN_DEG = 10.0  # a read roll this far toward a side is turned to it (`tilt_summary`)
# Where a frame's load lies on the mat (`load_ends`).
LOAD_ENDS = ("neither", "head only", "foot only", "both", "empty")


def posture_of(roll: torch.Tensor) -> list[str]:
    return [POSTURES[i] for i in posture_index(roll).tolist()]


@dataclasses.dataclass(frozen=True)
class BodyReadings:
    """What a network says about each of N images: height (N,) m, mass (N,) kg (`body.measure`
    of the estimated shape), roll (N,) deg (`roll_deg` of the estimated root); for a network
    with a posture readout, the posture it reads; for a heatmap network, each joint's heatmap
    spread (N, 24) m (docs/network.md "How far to trust a joint")."""

    height_m: torch.Tensor
    mass_kg: torch.Tensor
    roll_deg: torch.Tensor
    readout: list[str] | None = None  # the network's posture readout (net.posture), if it has one
    spread_m: torch.Tensor | None = None

    @property
    def postures(self) -> list[str]:
        return posture_of(self.roll_deg)


def read_bodies(
    net, pressure_mmhg: torch.Tensor, height_m=None, mass_kg=None, batch: int = 32, gender=None
) -> BodyReadings:
    """Run a network on (N, 64, 27) mmHg images in batches; height_m and mass_kg (N,) are passed
    as inputs for networks that take them (ignored otherwise), and gender (N,) on Anny's scale
    (default unknown, as PmatData's)."""
    heights, masses, rolls, readout, spreads = [], [], [], [], []
    with torch.no_grad():
        for lo in range(0, pressure_mmhg.shape[0], batch):
            p = pressure_mmhg[lo : lo + batch]
            inputs = NetInputs(
                pressure_mmhg=p,
                gender=torch.full((p.shape[0],), GENDER_UNKNOWN) if gender is None else gender[lo : lo + batch],
                height_m=None if height_m is None else torch.as_tensor(height_m[lo : lo + batch]),
                mass_kg=None if mass_kg is None else torch.as_tensor(mass_kg[lo : lo + batch]),
            )
            est = net(inputs, mesh=False)[-1]
            meas = net.body.measure(est.params.shape)
            heights.append(meas.height_m)
            masses.append(meas.mass_kg)
            rolls.append(roll_deg(est.params.root_rotation.to(torch.float64)))
            if net.config.posture_head:
                readout += [POSTURES[i] for i in est.localisation.posture_logits.argmax(-1).tolist()]
            if est.localisation is not None:
                spreads.append(est.localisation.spread_m)
    return BodyReadings(
        torch.cat(heights),
        torch.cat(masses),
        torch.cat(rolls),
        readout if net.config.posture_head else None,
        torch.cat(spreads) if spreads else None,
    )


def load_ends(images: np.ndarray, share: float = EXTENT_SHARE) -> list[str]:
    """Per (N, rows, cols) image (row 0 at the head end): whether its load - the rows from the
    first to the last holding >= `share` of its force (`eval.realism.load_span`) - reaches the
    mat's first row only, its last only, both or neither (`LOAD_ENDS`; "empty": no force). A load
    that reaches an end may run on beyond the mat, so its length says less of the body's."""
    images = np.asarray(images)
    if images.ndim != 3:
        raise ValueError(f"images must have shape (N, rows, cols), got {images.shape}")
    out = []
    for image in images:
        span = load_span(image, share)
        if span is None:
            out.append("empty")
            continue
        head, foot = span[0] == 0, span[1] == image.shape[0] - 1
        out.append(LOAD_ENDS[int(head) + 2 * int(foot)])
    return out


def height_by_load_ends(height_error: Sequence[float], ends: Sequence[str]) -> dict[str, dict]:
    """The median signed height error (m) and the count ("frames") per `load_ends` class present
    among the images (`ends[i]` the class of image i, `height_error[i]` its estimated minus
    true height): whether a reading is the body or where it lies (docs/network.md "Where a real
    body lies changes its reading"). `evaluate` and `evaluate-real` report it alike."""
    err = np.asarray(height_error, dtype=np.float64)
    labels = np.asarray(ends)
    if err.shape != labels.shape:
        raise ValueError(f"one class per height error: {labels.shape} against {err.shape}")
    return {
        where: {"frames": int(mask.sum()), "height_median_signed_m": float(np.median(err[mask]))}
        for where in LOAD_ENDS
        if (mask := labels == where).any()
    }


def load_ends_cells(groups: dict[str, dict]) -> list[str]:
    """`height_by_load_ends`'s result as report cells, one per LOAD_ENDS class: "+1.2 (34)"
    (median signed cm, count), "-" for a class with no image."""
    return [
        "-" if (g := groups.get(w)) is None else f"{g['height_median_signed_m'] * 100:+.1f} ({g['frames']})"
        for w in LOAD_ENDS
    ]


def load_ends_table(rows: dict[str, dict[str, dict]], first: str) -> list[str]:
    """A markdown table of `height_by_load_ends` results, one row per entry of `rows` (its key in
    the column named `first`: a mattress, a split), a column per LOAD_ENDS class."""
    return [
        f"| {first} | " + " | ".join(LOAD_ENDS) + " |",
        "| --- |" + " --- |" * len(LOAD_ENDS),
        *(f"| {name} | " + " | ".join(load_ends_cells(groups)) + " |" for name, groups in rows.items()),
    ]


def subject_interval(
    values: Sequence[float],
    subjects: Sequence[int],
    statistic: Callable[[np.ndarray], float],
    level: float = 0.95,
    draws: int = 4000,
    seed: int = 0,
) -> tuple[float, float]:
    """A `level` confidence interval of `statistic` over per-frame `values`, resampling whole
    subjects with replacement (a cluster bootstrap: a subject's frames are not independent -
    PmatData has 8 subjects and ~16 frames of each per mattress). Percentile interval over
    `draws` resamples; deterministic for a given seed."""
    values = np.asarray(values, dtype=float)
    subjects = np.asarray(subjects)
    if values.shape != subjects.shape or values.size == 0:
        raise ValueError(
            f"values and subjects must be non-empty and of one length, got {values.shape} / {subjects.shape}"
        )
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must lie in (0, 1), got {level}")
    ids = np.unique(subjects)
    groups = [values[subjects == s] for s in ids]
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(ids), size=(draws, len(ids)))
    stats = np.array([statistic(np.concatenate([groups[i] for i in row])) for row in picks])
    tail = (1.0 - level) / 2
    return float(np.quantile(stats, tail)), float(np.quantile(stats, 1.0 - tail))


def documented_roll(posture: str, roll_deg: float) -> float:
    """A tilted frame's roll in `roll_deg`'s convention (+ right, - left) from PmatData's posture
    label ("right" / "left") and its unsigned documented roll."""
    if posture not in ("right", "left"):
        raise ValueError(f"a tilted frame lies to the right or the left, got {posture!r}")
    if not 0.0 < roll_deg < 90.0:
        raise ValueError(f"a tilt's documented roll lies in (0, 90) deg, got {roll_deg}")
    return roll_deg if posture == "right" else -roll_deg


def roll_error(documented_deg, read_deg) -> np.ndarray:
    """|read - documented| per frame (deg), wrapped to [0, 180]."""
    doc, read = np.asarray(documented_deg, dtype=np.float64), np.asarray(read_deg, dtype=np.float64)
    return np.abs((read - doc + 180.0) % 360.0 - 180.0)


def turned_toward(documented_deg, read_deg) -> np.ndarray:
    """Per frame: read TURN_DEG to 135 deg toward the documented roll's side (beyond 135 the read
    is face down, `posture_of`)."""
    toward = np.sign(np.asarray(documented_deg, dtype=np.float64)) * np.asarray(read_deg, dtype=np.float64)
    return (toward >= TURN_DEG) & (toward <= 135.0)


def tilt_summary(documented_deg: Sequence[float], read_deg: Sequence[float], subjects=None) -> dict:
    """How a network reads tilted bodies (PmatData group E) against their documented rolls (deg,
    + right, `documented_roll`): the median roll read toward the documented side (s x read roll,
    s its sign; negative: turned the other way), the median absolute roll error (wrapped to
    [0, 180]), the shares turned TURN_DEG to 135 deg toward the documented side (beyond, the read
    is face down) and at least TURN_DEG toward the other, and with `subjects` a 95% interval of the
    first share resampling whole subjects."""
    doc = np.asarray(documented_deg, dtype=np.float64)
    read = np.asarray(read_deg, dtype=np.float64)
    if doc.shape != read.shape or doc.ndim != 1 or doc.size == 0:
        raise ValueError(f"one read roll per documented roll, non-empty: {read.shape} against {doc.shape}")
    if (doc == 0).any():
        raise ValueError("a documented tilt has a side: no roll may be 0")
    toward = np.sign(doc) * read
    error = roll_error(doc, read)
    turned = turned_toward(doc, read).astype(np.float64)
    out = {
        "frames": int(doc.size),
        "read_toward_median_deg": float(np.median(toward)),
        "abs_error_median_deg": float(np.median(error)),
        "share_turned": float(turned.mean()),
        "share_other_way": float((toward <= -TURN_DEG).mean()),
    }
    if subjects is not None:
        out["share_turned_ci"] = subject_interval(turned, subjects, np.mean)
    return out


SURE_SPREAD_M = 0.10  # a joint whose heatmap spread is below this is pinned by the image


def spread_summary(spread_m: torch.Tensor) -> dict[str, float]:
    """(N, J) heatmap spreads (m) of some joints of N frames -> the median over the frames of each
    frame's median spread (torch's median: the lower middle of an even count), and the share of the
    joints under SURE_SPREAD_M. For the head and torso joints the shipped model reads simulated test
    images at ~7.8 cm and 93%, PmatData's frames at 11.7-12.8 cm and 23-27% (docs/network.md "How far
    to trust a joint"): how sure the network is where a body lies."""
    return {
        "median_m": float(spread_m.median(1).values.median()),
        "share_sure": float((spread_m < SURE_SPREAD_M).double().mean()),
    }


def trunk_spread(net, images: torch.Tensor, **inputs) -> dict[str, float] | None:
    """`spread_summary` of the head and torso joints of a heatmap network reading (N, 64, 27) mmHg
    images (`inputs`: read_bodies' height_m, mass_kg, gender); None for a network without
    heatmaps or no images."""
    if len(images) == 0:
        return None
    spread = read_bodies(net, images, **inputs).spread_m
    return None if spread is None else spread_summary(spread[:, list(TRUNK_JOINTS)])


HEAD_END_FRAMES = 64  # frames of a recording `head_end_spreads` reads (evenly spaced)


def head_end_picks(n: int, frames: int = HEAD_END_FRAMES) -> torch.Tensor:
    """The indices of up to `frames` evenly spaced images of n (all of them when n <= frames)."""
    return torch.linspace(0, n - 1, min(frames, n)).round().long().unique()


def head_end_spreads(
    net, images: torch.Tensor, frames: int = HEAD_END_FRAMES, height_m=None, mass_kg=None, gender=None
) -> tuple[float, float]:
    """How sharply a heatmap network pins the head and torso of a recording's (N, 64, 27) mmHg
    images as given and turned end for end (rows reversed): the median over up to `frames` evenly
    spaced images of each image's median trunk spread (m), as given and reversed. The way with
    the smaller one has the head at row 0: for the shipped model the right way on 94.6% of PmatData's
    frames one by one, 99.6-100% of its recordings of 4 or more frames (docs/real_data.md "Which end is
    the head"). `height_m`, `mass_kg`, `gender`: the subject's, as numbers, for networks that take
    them. ValueError for a network without heatmaps or no images."""
    if len(images) == 0:
        raise ValueError("no images to read the head end from")
    sub = images[head_end_picks(len(images), frames)]
    full = lambda v: None if v is None else torch.full((len(sub),), float(v), device=sub.device)  # noqa: E731
    inputs = {"height_m": full(height_m), "mass_kg": full(mass_kg), "gender": full(gender)}
    given, reversed_ = trunk_spread(net, sub, **inputs), trunk_spread(net, sub.flip(1), **inputs)
    if given is None or reversed_ is None:
        raise ValueError("the head end is read from heatmaps: this network has none")
    return given["median_m"], reversed_["median_m"]


def spread_lines(summaries: dict[str, dict]) -> list[str]:
    """Markdown lines of `spread_summary` per set (e.g. per mattress); none without summaries."""
    if not summaries:
        return []
    cells = [
        f"{k} {s['median_m'] * 100:.1f} cm, {s['share_sure'] * 100:.0f}% under 10 cm" for k, s in summaries.items()
    ]
    return [
        "",
        "Heatmap spread of the head and torso joints, median per image (how sure the network is where the "
        "body lies; the shipped model on simulated test images: ~7.8 cm, 93% of them under 10 cm): " + "; ".join(cells),
    ]


__all__ = [
    "GROUP_POSTURE",
    "LOAD_ENDS",
    "POSTURES",
    "TILTED_GROUPS",
    "RAISED_GROUPS",
    "RAISED_POSTURE",
    "HEAD_END_FRAMES",
    "TURN_DEG",
    "BodyReadings",
    "documented_roll",
    "head_end_picks",
    "head_end_spreads",
    "height_by_load_ends",
    "load_ends",
    "load_ends_cells",
    "load_ends_table",
    "posture_of",
    "read_bodies",
    "roll_deg",
    "roll_error",
    "spread_lines",
    "spread_summary",
    "subject_interval",
    "tilt_summary",
    "trunk_spread",
    "turned_toward",
]
