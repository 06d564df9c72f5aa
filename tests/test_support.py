"""The reachable boxes of a limb (sampling.support) hold every draw that meets the conditions."""

import numpy as np
import pytest
import torch

from pressurepose.body.limits import JointLimits
from pressurepose.body.rotations import axis_angle_to_matrix
from pressurepose.sampling.limbs import limb_table
from pressurepose.sampling.partitions import HEIGHT_TOLERANCE_M
from pressurepose.sampling.support import LimbGrid

LIMBS = limb_table(JointLimits.default(torch.float64))
# A supine body: body x -> mat -y, body y (toward the head) -> mat -x; rows: along (toward the
# foot), up, mat x, mat y in body axes.
FRAME = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]])
BED = (0.0, 1.9, 0.0, 0.9)


def chain_positions(name, offsets, root, angles):
    """(N, n, 3) joint positions of the chain for (N, 4) angles, as the exact tests build them."""
    a = torch.from_numpy(angles)
    R = axis_angle_to_matrix(a[:, :3])
    c, s = torch.cos(a[:, 3]), torch.sin(a[:, 3])
    one, zero = torch.ones_like(c), torch.zeros_like(c)
    if name.endswith("leg"):
        H = torch.stack([one, zero, zero, zero, c, -s, zero, s, c], -1).view(-1, 3, 3)
        rots = [R, R @ H, R @ H]
    else:
        H = torch.stack([c, zero, s, zero, one, zero, -s, zero, c], -1).view(-1, 3, 3)
        rots = [axis_angle_to_matrix(a[:, :3] / 3), R, R @ H, R @ H]
    pos = [torch.from_numpy(root).expand(len(a), 3)]
    for rot, v in zip(rots, torch.from_numpy(offsets)):
        pos.append(pos[-1] + rot @ v)
    return torch.stack(pos, 1).numpy()


@pytest.mark.parametrize(
    "name, straight, cell",
    [
        ("left_leg", False, 2),
        ("left_leg", True, 3),
        ("right_arm", False, 1),
        ("left_arm", True, 6),
        ("left_arm", False, 4),
    ],
)
def test_the_boxes_hold_every_valid_draw(name, straight, cell):
    limb = LIMBS[name]
    grid = LimbGrid(limb, straight)
    leg = name.endswith("leg")
    side = 1.0 if limb.side == "left" else -1.0
    if leg:
        offsets = np.array([[0.01 * side, -0.40, 0.0], [0.0, -0.42, -0.02], [0.0, -0.05, 0.13]])
        root = np.array([0.09 * side, -0.08, 0.0])
        L = 0.82
        lo, hi = cell * L / 4, (np.inf if cell == 3 else (cell + 1) * L / 4)
    else:
        offsets = np.array(
            [[0.12 * side, 0.02, -0.01], [0.27 * side, 0.0, 0.0], [0.25 * side, 0.0, 0.0], [0.08 * side, 0, 0]]
        )
        root = np.array([0.07 * side, 0.35, 0.0])
        A = 0.52
        lo = -np.inf if cell == 0 else (cell - 4) * A / 4
        hi = np.inf if cell == 7 else (cell - 3) * A / 4
    shift = np.array([1.0, 0.3, 0.0])  # near the bed's edge: some draws leave it
    over_bed = [1, 2, 3] if leg else [2, 3, 4]
    boxes = grid.support(offsets, root, FRAME, shift, (lo, hi), BED, over_bed)
    assert 0 < boxes.size < grid.boxes  # some boxes dropped, some kept
    rng = np.random.default_rng(0)
    u = rng.random((200_000, 4))
    angles = limb.low + (limb.high - limb.low) * u
    if straight:
        angles[:, 3] = 0.0
    pos = chain_positions(name, offsets, root, angles)
    prox, dist = (0, 2) if leg else (1, 3)
    reach = pos[:, dist] - pos[:, prox]
    up, along = reach @ FRAME[1], reach @ FRAME[0]
    ok = (np.abs(up) <= HEIGHT_TOLERANCE_M) & (along >= lo) & (along < hi)
    x = pos[:, over_bed] @ FRAME[2] + shift[0]
    y = pos[:, over_bed] @ FRAME[3] + shift[1]
    ok &= ((x > BED[0]) & (x < BED[1]) & (y > BED[2]) & (y < BED[3])).all(-1)
    assert ok.sum() > 20  # the test sees valid draws
    idx = np.minimum((u * grid.n).astype(np.int64), grid.n - 1)
    n = int(grid.n[0])
    box = ((idx[:, 0] * n + idx[:, 1]) * n + idx[:, 2]) * int(grid.n[3]) + idx[:, 3]
    assert np.isin(box[ok], boxes).all()
    # and the boxes are tight enough to pay: far fewer than the whole grid
    assert boxes.size < 0.6 * grid.boxes


def test_proposals_are_uniform_in_the_kept_boxes():
    grid = LimbGrid(LIMBS["left_arm"], False)
    boxes = np.array([3, 70, grid.boxes - 1])
    u = grid.propose(boxes, np.random.default_rng(1).random((30_000, 5)))
    assert ((u >= 0) & (u < 1)).all()
    idx = (u * grid.n).astype(np.int64)
    n = int(grid.n[0])
    box = ((idx[:, 0] * n + idx[:, 1]) * n + idx[:, 2]) * int(grid.n[3]) + idx[:, 3]
    counts = np.array([(box == b).sum() for b in boxes])
    assert counts.sum() == 30_000
    assert (np.abs(counts - 10_000) < 400).all()


@pytest.mark.parametrize("straight", [False, True])
def test_proposals_are_the_box_index_plus_the_offset_in_it(straight):
    # (i + u) / n per component, i the picked box's grid index: the table of box corners gives
    # the same numbers, bit for bit, as the index arithmetic it replaced.
    grid = LimbGrid(LIMBS["left_leg"], straight)
    rng = np.random.default_rng(2)
    boxes = np.sort(rng.choice(grid.boxes, 300, replace=False))
    u = rng.random((5_000, 5))
    pick = boxes[np.minimum((u[:, 0] * boxes.shape[0]).astype(np.int64), boxes.shape[0] - 1)]
    n, nphi = int(grid.n[0]), int(grid.n[3])
    idx = np.stack([pick // nphi // (n * n), pick // nphi // n % n, pick // nphi % n, pick % nphi], -1)
    assert grid.propose(boxes, u).tobytes() == ((idx + u[:, 1:]) / grid.n).tobytes()


@pytest.mark.parametrize("name, flag", [("left_arm", "below_shoulder"), ("left_leg", "left_of_midline")])
def test_the_boxes_hold_every_valid_draw_of_the_partition_conditions(name, flag):
    """Hands behind the head (wrist no higher than the shoulder) and the crossing left leg
    (ankle left of the midline) on the bent limbs' grid: every valid draw lies in a kept box."""
    limb = LIMBS[name]
    grid = LimbGrid(limb, False)
    assert tuple(grid.n) == (8, 8, 8, 8)  # bent limbs: the coarser rotation grid
    leg = name.endswith("leg")
    if leg:
        offsets = np.array([[0.01, -0.40, 0.0], [0.0, -0.42, -0.02], [0.0, -0.05, 0.13]])
        root, L = np.array([0.09, -0.08, 0.0]), 0.82
        lo, hi = L / 4, 2 * L / 4
        over_bed, prox, dist = [1, 2, 3], 0, 2
    else:
        offsets = np.array([[0.12, 0.02, -0.01], [0.27, 0.0, 0.0], [0.25, 0.0, 0.0], [0.08, 0, 0]])
        root, A = np.array([0.07, 0.35, 0.0]), 0.52
        lo, hi = -np.inf, -3 * A / 4  # arm cell 0: the wrist over the head
        over_bed, prox, dist = [2, 3, 4], 1, 3
    shift = np.array([0.95, 0.45, 0.0])
    kw = {flag: True}
    boxes = grid.support(offsets, root, FRAME, shift, (lo, hi), BED, over_bed, **kw)
    assert 0 < boxes.size < 0.6 * grid.boxes
    rng = np.random.default_rng(2)
    u = rng.random((200_000, 4))
    angles = limb.low + (limb.high - limb.low) * u
    pos = chain_positions(name, offsets, root, angles)
    reach = pos[:, dist] - pos[:, prox]
    up, along = reach @ FRAME[1], reach @ FRAME[0]
    ok = (np.abs(up) <= HEIGHT_TOLERANCE_M) & (along >= lo) & (along < hi)
    ok &= (up <= 0) if flag == "below_shoulder" else (pos[:, dist, 0] < 0)
    x = pos[:, over_bed] @ FRAME[2] + shift[0]
    y = pos[:, over_bed] @ FRAME[3] + shift[1]
    ok &= ((x > BED[0]) & (x < BED[1]) & (y > BED[2]) & (y < BED[3])).all(-1)
    assert ok.sum() > 20
    idx = np.minimum((u * grid.n).astype(np.int64), grid.n - 1)
    n = int(grid.n[0])
    box = ((idx[:, 0] * n + idx[:, 1]) * n + idx[:, 2]) * int(grid.n[3]) + idx[:, 3]
    assert np.isin(box[ok], boxes).all()
    # the condition itself drops boxes: without it more are kept
    assert boxes.size < grid.support(offsets, root, FRAME, shift, (lo, hi), BED, over_bed).size


@pytest.mark.parametrize("name, straight", [("left_leg", True), ("right_arm", False)])
def test_the_component_major_tables_give_the_projections_bit_for_bit(name, straight):
    # F^T @ (3, 3 nk) table: the same three-term sums as the (nk 3, 3) table @ F it replaced,
    # already in (5, 3, nk) order.
    grid = LimbGrid(LIMBS[name], straight)
    rng = np.random.default_rng(4)
    nk = grid.rt.shape[1] // 3
    for cols in (grid.rt, getattr(grid, "rt3", None)):
        if cols is None:
            continue
        # The row-major table: rows of R_i^T stacked (row 3 i + c is column c of R_i).
        tab = np.ascontiguousarray(cols.reshape(3, 3, nk).transpose(2, 1, 0)).reshape(-1, 3)
        for _ in range(5):
            F = rng.normal(size=(3, 5))
            old = np.ascontiguousarray((tab @ F).reshape(nk, 3, 5).transpose(2, 1, 0)).astype(np.float32)
            assert (F.T @ cols).astype(np.float32).reshape(5, 3, nk).tobytes() == old.tobytes()


def test_proposals_of_several_rows_at_once_are_those_row_by_row():
    grid = LimbGrid(LIMBS["left_arm"], False)
    rng = np.random.default_rng(5)
    boxes = [np.sort(rng.choice(grid.boxes, size, replace=False)) for size in (1, 7, 300, grid.boxes)]
    u = rng.random((len(boxes), 257, 5))
    want = np.stack([grid.propose(b, row) for b, row in zip(boxes, u)])
    assert grid.propose_rows(boxes, u).tobytes() == want.tobytes()
