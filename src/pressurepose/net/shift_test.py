"""The shift test (arch heatmap, eval only; `NetConfig.shift_test`, `--shift-test`): read each
pressure image as given and moved SHIFT_TEST_ROWS rows along the bed, move each read's localised
joints back and average them.

A body moved along a uniform flat bed presses the same image moved, so every copy estimates the
same joints; the mean has less of any one read's error. Simulated images read nearly the same
whichever way they are moved; real frames do not (their reads move 2-5 cm in height and turn 4-15%
of the postures when moved a few rows, docs/network.md "Where a real body lies changes its
reading"), and there the mean settles the read. A copy is moved as the training's shift
augmentation moves an image (`train.augment.shift_batch`): rows leaving the mat are lost, rows
entering read 0, the input channels made from the moved image. The moves are even so that the
heatmaps (stride 2 along the bed) move by whole cells.

Cost: the input channels and the encoder-decoder run once per copy (5x; the IK and the mesh once).
"""

from __future__ import annotations

import torch

from pressurepose.net.heatmap import Localisation

SHIFT_TEST_ROWS = (-4, -2, 2, 4)  # the copies besides the image as given (rows toward the foot)


def moved_rows(images: torch.Tensor, rows: int, fill: float = 0.0) -> torch.Tensor:
    """(..., R, C) images (or maps) moved `rows` rows toward higher row numbers (negative: lower);
    rows leaving are lost, rows entering read `fill`."""
    if rows == 0:
        return images
    out = torch.full_like(images, fill)
    R = images.shape[-2]
    if abs(rows) < R:
        out[..., max(rows, 0) : R + min(rows, 0), :] = images[..., max(-rows, 0) : R + min(-rows, 0), :]
    return out


def shift_stack(pressure: torch.Tensor, moves: tuple[int, ...] = SHIFT_TEST_ROWS) -> torch.Tensor:
    """(B, R, C) -> ((1 + len(moves)) B, R, C): the images as given, then each move's copies."""
    return torch.cat([pressure, *(moved_rows(pressure, k) for k in moves)])


def shift_merged(loc: Localisation, pitch_row_m: float, moves: tuple[int, ...] = SHIFT_TEST_ROWS) -> Localisation:
    """The shift test's localisation: `loc` holds (1 + len(moves)) B reads in `shift_stack`'s
    order. Each copy's joints (and heatmap means) are moved back along the bed by its move
    (x -= rows * pitch_row_m) and averaged with the rest, as are the heatmaps' variances, the
    heatmaps' logits (moved back by rows / 2 cells; cells a move brought in take the lowest
    logit) and the posture logits; the features are the image's own (for the parameter head)."""
    if any(k % 2 for k in moves):
        raise ValueError(f"the shift test's moves must be even (whole heatmap cells), got {moves}")
    n = 1 + len(moves)
    B = loc.joints.shape[0] // n
    if B * n != loc.joints.shape[0]:
        raise ValueError(f"a shift test's localisation holds {n} x B reads, got {loc.joints.shape[0]}")
    part = lambda a, i: a[i * B : (i + 1) * B]  # noqa: E731
    offsets = [0, *moves]

    def back(a: torch.Tensor, rows: int) -> torch.Tensor:
        step = torch.zeros(a.shape[-1], dtype=a.dtype, device=a.device)
        step[0] = rows * pitch_row_m
        return a - step

    mean = lambda parts: torch.stack(parts).mean(0)  # noqa: E731
    floor = float(loc.logits.amin()) if loc.logits.numel() else 0.0
    return Localisation(
        joints=mean([back(part(loc.joints, i), k) for i, k in enumerate(offsets)]),
        grid_joints=mean([back(part(loc.grid_joints, i), k) for i, k in enumerate(offsets)]),
        spread_m2=mean([part(loc.spread_m2, i) for i in range(n)]),
        logits=mean([moved_rows(part(loc.logits, i), -k // 2, floor) for i, k in enumerate(offsets)]),
        centres=loc.centres,
        posture_logits=None if loc.posture_logits is None else mean([part(loc.posture_logits, i) for i in range(n)]),
        features=None if loc.features is None else part(loc.features, 0),
    )


__all__ = ["SHIFT_TEST_ROWS", "moved_rows", "shift_merged", "shift_stack"]
