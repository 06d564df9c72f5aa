"""Proposals from a superset of a limb's reachable set (over the bed).

Over the bed most joint-angle draws miss their cell, their height or the mattress: a limb of
straight_limbs over the bed tests ~0.5% of its draws' capsules, and a limb whose cell is off
the mattress for this body and root burns its whole budget on draws that all miss. Instead of
drawing uniformly in the whole angle box, a limb draws uniformly in the union S of the boxes of
a fixed grid that may hold a draw meeting the cell, height, bed-outline and partition
conditions. Each box is kept unless a bound proves that no draw inside it meets them: the
chain's joints move by at most |v| |k - k_c| when a rotation vector k moves away from the
box centre k_c (the rotation vector to matrix map is 1-Lipschitz in the angle: the SO(3)
Jacobian has norm <= 1) and a hinge turns v by at most |v| |phi - phi_c|; every bound is
loosened by SUPPORT_MARGIN_M against round-off.

Same law as the uniform draws: among B uniform draws in the whole box, those in S are, in law,
N ~ Binomial(B, |S| / |box|) independent uniform draws in S, in order, and every draw outside
S fails the exact tests anyway. So a limb attempt draws N from its budget, then up to N draws
in S; the first that passes every test (exact tests, self-collisions) wins - the same winner,
failure and "no draw reached the cell" outcomes, in law, as before. S = {} gives N = 0: the
limb fails at once, unreachable for this shape and root.

Determinism: the grid's rotation matrices are computed once (fixed tables); a sample's boxes
come from its own numbers in fixed-shape numpy products, one sample at a time, so they never
depend on the batch. The draws in S come from a generator seeded from the sample's own stream
per limb attempt, which is then discarded (no winding back needed).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pressurepose.body.rotations import axis_angle_to_matrix
from pressurepose.sampling.attempt import ALONG, MAT_X, MAT_Y, UP
from pressurepose.sampling.limbs import Limb
from pressurepose.sampling.partitions import HEIGHT_TOLERANCE_M

# Boxes per rotation-vector component: 8 for bent limbs, 16 for straight ones (whose hinge is
# 0: one box along it). 8^3 x 8 boxes cost an eighth of 16^3 x 8 to bound; the looser boxes
# let more proposals through to the screen, which costs less (docs/benchmarks.md, issue 21).
GRID_ROTATION = 8
GRID_ROTATION_STRAIGHT = 16
GRID_HINGE = 8  # boxes along the knee / elbow angle (1 for straight limbs: the hinge is 0)
SUPPORT_MARGIN_M = 1e-5  # every bound loosened by this (the float32 tests round off by < 1e-6 m)
DIMS = 4  # drawn angles per limb: rotation vector (3) and hinge


def _component_major(R: np.ndarray) -> np.ndarray:
    """(3, 3 nk) from (nk, 3, 3) rotations: column c nk + i is row c of R_i^T (column c of R_i)."""
    return np.ascontiguousarray(R.transpose(1, 2, 0)).reshape(3, -1)


class LimbGrid:
    """A fixed grid over one limb's angle box and the rotation matrices of its box centres."""

    def __init__(self, limb: Limb, straight: bool) -> None:
        self.limb = limb
        self.leg = limb.name.endswith("leg")
        self.straight = straight
        n = GRID_ROTATION_STRAIGHT if straight else GRID_ROTATION
        self.n = np.array([n, n, n, 1 if straight else GRID_HINGE])
        low, span = limb.low, limb.high - limb.low
        centre = [low[d] + span[d] * (np.arange(self.n[d]) + 0.5) / self.n[d] for d in range(DIMS)]
        k = np.stack(np.meshgrid(*centre[:3], indexing="ij"), -1).reshape(-1, 3)
        # The box centres' rotations, component-major (3, n^3 * 3): F^T (f, 3) @ it gives R_i^T f
        # for every box.
        self.rt = _component_major(axis_angle_to_matrix(torch.from_numpy(k)).numpy())
        if not self.leg:  # the collar's third of the rotation
            self.rt3 = _component_major(axis_angle_to_matrix(torch.from_numpy(k / 3)).numpy())
        phi = np.zeros(1) if straight else centre[3]
        self.cos, self.sin = np.cos(phi), np.sin(phi)
        self.h_rot = 0.5 * math.sqrt(float(((span[:3] / n) ** 2).sum()))  # half diagonal of a box
        self.h_hinge = 0.0 if straight else 0.5 * float(span[3]) / GRID_HINGE
        self.boxes = int(np.prod(self.n))
        # Each box's grid indices (i, j, k, hinge) as floats, box b = ((i n + j) n + k) nphi + hinge.
        b, nphi = np.arange(self.boxes), int(self.n[3])
        self.corner = np.stack([b // nphi // (n * n), b // nphi // n % n, b // nphi % n, b % nphi], -1).astype(
            np.float64
        )

    def hinge(self, v: np.ndarray) -> np.ndarray:
        """(3, nphi): v turned by the hinge at each box centre (knee about x, elbow about y)."""
        c, s = self.cos, self.sin
        x, y, z = (np.full_like(c, v[i]) for i in range(3))
        if self.leg:
            return np.stack([x, c * y - s * z, s * y + c * z])
        return np.stack([c * x + s * z, y, c * z - s * x])

    def support(
        self,
        offsets: np.ndarray,
        root: np.ndarray,
        frame: np.ndarray,
        shift: np.ndarray,
        along: tuple[float, float],
        bed: tuple[float, float, float, float] | None,
        over_bed: list[int],
        below_shoulder: bool = False,
        left_of_midline: bool = False,
    ) -> np.ndarray:
        """Indices (ascending) of the boxes that may hold a draw meeting the conditions.

        offsets (n - 1, 3): the chain's rest offsets; root (3,): its first joint (body axes);
        frame (4, 3), shift (3,): as the exact tests; along: the cell's bounds on the distal
        joint's 'along' offset from the proximal joint; bed: mattress x_lo, x_hi, y_lo, y_hi
        (None: no outline); over_bed: chain indices of the joints that must lie over it;
        below_shoulder: 'up' <= 0 (hands behind the head); left_of_midline: the distal joint's
        body x < 0 (the crossing left leg)."""
        m = SUPPORT_MARGIN_M
        nk, nphi = self.rt.shape[1] // 3, self.cos.shape[0]
        f32 = np.float32
        hr, hh = self.h_rot, self.h_hinge
        norm = np.sqrt((offsets * offsets).sum(-1))
        # Steps of the chain from its root: (rotation table or None for R H, offset, slack).
        # Legs: hip R, knee and ankle R H; arms: collar R/3, shoulder R, elbow and wrist R H.
        if self.leg:
            steps = [(self.rt, offsets[0], norm[0] * hr)]
            bent = offsets[1:]
        else:
            steps = [(self.rt3, offsets[0], norm[0] * hr / 3), (self.rt, offsets[1], norm[1] * hr)]
            bent = offsets[2:]
        steps += [(None, v, n * (hr + hh)) for v, n in zip(bent, norm[len(steps) :])]
        slack = np.concatenate([[0.0], np.cumsum([st[2] for st in steps])]) + m
        # Projections onto the frame's up, along, mat x, mat y and the body's x axis.
        F = np.stack([frame[UP], frame[ALONG], frame[MAT_X], frame[MAT_Y], np.eye(3)[0]], 1)  # (3, 5)
        proj = {}  # table -> (5, 3, nk): R_i^T f for every f and box, component-major
        for tab in (self.rt, getattr(self, "rt3", None)):
            if tab is not None:  # F^T (5, 3) @ (3, 3 nk): already in (5, 3, nk) order
                proj[id(tab)] = (F.T @ tab).astype(f32).reshape(5, 3, nk)
        a = proj[id(self.rt)]
        hinged = [self.hinge(v).astype(f32) for v in bent]  # (3, nphi) each
        first_bent = len(steps) - len(bent)

        def rotated(tab, v, f):  # f . R_i v for every box (nk,)
            t = proj[id(tab)][f]
            v = v.astype(f32)
            return t[0] * v[0] + t[1] * v[1] + t[2] * v[2]

        # 1. The distal joint's up and along offsets from the proximal one on the whole grid.
        prox, dist = (0, 2) if self.leg else (1, 3)
        reach = [np.zeros((nk, 1), f32), np.zeros((nk, 1), f32)]
        for i in range(prox, dist):
            tab, v, _ = steps[i]
            for f in (0, 1):
                if tab is None:
                    reach[f] = reach[f] + a[f].T @ hinged[i - first_bent]
                else:
                    reach[f] = reach[f] + rotated(tab, v, f)[:, None]
        up, al = (np.broadcast_to(x, (nk, nphi)) for x in reach)
        r = f32(slack[dist] - slack[prox] + m)
        keep = np.abs(up) <= f32(HEIGHT_TOLERANCE_M) + r
        if below_shoulder:
            keep &= up <= r
        keep &= (al >= f32(along[0]) - r) & (al < f32(along[1]) + r)
        # 2. The joints' positions along the chain (mat x, mat y, body x), on the whole grid.
        if left_of_midline or bed is not None:
            base = (F.T @ root).astype(f32)
            pos = [[np.full((nk, 1), base[f], f32) for f in (2, 3, 4)]]
            for i, (tab, v, _) in enumerate(steps):
                if tab is None:
                    step = [a[f].T @ hinged[i - first_bent] for f in (2, 3, 4)]
                else:
                    step = [rotated(tab, v, f)[:, None] for f in (2, 3, 4)]
                pos.append([p + q for p, q in zip(pos[-1], step)])
            if left_of_midline:
                keep &= pos[dist][2] < f32(slack[dist] + m)  # body x
            if bed is not None:
                x_lo, x_hi, y_lo, y_hi = bed
                for j in over_bed:
                    r = f32(slack[j] + m)
                    x, y = pos[j][0] + f32(shift[0]), pos[j][1] + f32(shift[1])
                    keep &= (x > f32(x_lo) - r) & (x < f32(x_hi) + r) & (y > f32(y_lo) - r) & (y < f32(y_hi) + r)
        return np.flatnonzero(keep)

    def propose(self, boxes: np.ndarray, u: np.ndarray) -> np.ndarray:
        """(W, 5) uniform numbers -> (W, 4) uniform numbers of the whole angle box that lie in
        a box drawn uniformly among `boxes` (u[:, 0] picks the box, u[:, 1:] the point in it)."""
        pick = boxes[np.minimum((u[:, 0] * boxes.shape[0]).astype(np.int64), boxes.shape[0] - 1)]
        return (self.corner[pick] + u[:, 1:]) / self.n

    def propose_rows(self, boxes: list[np.ndarray], u: np.ndarray) -> np.ndarray:
        """`propose` for several rows at once: u (R, W, 5) with row r's boxes `boxes[r]` ->
        (R, W, 4); the same numbers as row by row (element-wise operations only)."""
        sizes = np.array([b.shape[0] for b in boxes], dtype=np.int64)
        first = np.cumsum(sizes) - sizes
        k = np.minimum((u[..., 0] * sizes[:, None]).astype(np.int64), sizes[:, None] - 1)
        pick = np.concatenate(boxes)[first[:, None] + k]
        return (self.corner[pick] + u[..., 1:]) / self.n
