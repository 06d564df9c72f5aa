"""Drawing the limbs of a pose attempt (`PoseSampler`'s limb rounds): windows of rounds, a
float32 screen looser than the exact tests, the exact float64 tests, self-collisions in draw
order (module docstring of `sampling.sampler`)."""

from __future__ import annotations

import numpy as np
import torch

from pressurepose.body.capsule_geometry import dot
from pressurepose.body.capsules import capsule_clearance
from pressurepose.body.rotations import axis_angle_to_matrix
from pressurepose.sampling.attempt import ALONG, MAT_X, MAT_Y, UP, Attempt, SampleState
from pressurepose.sampling.limb_context import PREFILTER_MARGIN_M, LimbContext, limb_context
from pressurepose.sampling.limbs import (
    LIMBS,
    Limb,
    apply_hinge,
    arm_cell,
    cols,
    leg_cell,
    rodrigues,
    rotate,
    split_xyz,
    vadd,
    vdot,
)
from pressurepose.sampling.partitions import (
    HEIGHT_TOLERANCE_M,
)

# Elements per temporary of the screen: samples x draws chunks that stay in the CPU cache.
_SCREEN_ELEMENTS = 1 << 16
# Draws tested at once (pending samples x rounds of a window): ~4 ms of work, so that the fixed
# cost of a window (~3 ms of small tensor operations) stays a small share.
_WINDOW_DRAWS = 1 << 16
# Over the bed, rounds drawn uniformly in the whole angle box before the rest of the budget
# comes from the reachable boxes (sampling.support): limbs that find a draw early never pay
# for the boxes.
PLAIN_ROUNDS = 3


class LimbDraws:
    """The limb rounds of `PoseSampler` (a mixin: they use its model, config, limits and limbs)."""

    def _draw_limbs(self, states: list[SampleState]) -> None:
        """One pose attempt: limbs in a fixed order, each drawn until it reaches its cell
        without touching what is already placed (torso, head, earlier limbs)."""
        for st in states:
            st.angles = {}
        batch = Attempt(states)
        rows = torch.arange(len(states))
        for name in LIMBS:
            rows = self._rounds(batch, rows, self.limbs[name])
        for r in rows.tolist():
            batch.states[r].placed = (batch.a[r], batch.b[r])

    def _rounds(self, batch: Attempt, rows: torch.Tensor, limb: Limb) -> torch.Tensor:
        """Draw angles for `limb` until each sample (attempt rows `rows`) has a draw that meets
        every condition; returns the rows that got one (the others have failed this attempt).

        Draws come in rounds of growing size (64, 128, ... 4096) up to `max_limb_draws`, so
        common cells cost one small round and rare ones (a foot near the buttocks) still get
        thousands of tries; the first draw that passes everything wins, and the sample's
        generator has then used up exactly the rounds up to the winner's. For speed, several
        rounds are drawn and tested at once (a window: few pending samples, many rounds) and
        the generator is wound back to the end of the winner's round: the outcome is the same
        as drawing round by round. Each draw is first screened by a cheap float32 test that
        is looser than the real conditions by PREFILTER_MARGIN_M (so it never drops a draw
        they accept); survivors are tested exactly (float64), then for self-collisions."""
        done = []
        reachable = torch.zeros(len(batch.states), dtype=torch.bool)
        ctx = limb_context(batch, limb, self._limb_capsules[limb.name])
        ends = self._round_ends
        grid = self._grids.get(limb.name)
        # Over the bed: the first PLAIN_ROUNDS rounds as above; the rest of the budget, for the
        # samples still without a draw, from the boxes that may reach the cell (same law).
        plain = ends if grid is None else ends[:PLAIN_ROUNDS]
        ctx.budget = torch.full((len(batch.states),), int(plain[-1]), dtype=torch.long)
        pending = self._phase(batch, ctx, rows, limb, plain, reachable, done)
        if pending.numel() and len(plain) < len(ends):
            self._proposals(batch, ctx, pending, limb, grid, int(ends[-1] - plain[-1]))
            self._phase(batch, ctx, pending, limb, ends, reachable, done)
        won = torch.cat(done) if done else rows[:0]
        for r in rows[~torch.isin(rows, won)].tolist():  # budget exhausted: this attempt fails
            st = batch.states[r]
            st.counts["limb_failures"] += 1
            st.failed_limb = limb.name
            # No draw met even the cell and bed conditions: other limbs cannot help (unless
            # the condition depends on them, as crossing does), only a new shape and root.
            if not reachable[r] and not (self.part.crossed_legs and limb.name == "right_leg"):
                st.unreachable = limb.name
        return won.sort().values

    def _phase(self, batch, ctx, pending, limb, ends, reachable, done) -> torch.Tensor:
        """Rounds ending at `ends` (each row up to its budget, ctx.budget) in windows;
        returns the rows left without a winner."""
        budget = ctx.budget
        start, j = 0, 0
        while j < len(ends):
            pending = pending[budget[pending] > start]
            if not pending.numel():
                break
            # A window: the rounds from `start` on that keep pending x draws within
            # _WINDOW_DRAWS (at least one round), so few pending samples take few windows.
            P = pending.numel()
            cap = int(budget[pending].max())
            while j + 1 < len(ends) and P * (ends[j + 1] - start) <= _WINDOW_DRAWS and ends[j] < cap:
                j += 1
            stop = int(ends[j])
            W = stop - start
            step = max(1, _WINDOW_DRAWS // W)
            won = [
                self._window(batch, ctx, pending[lo : lo + step], limb, ends, start, W, reachable, done)
                for lo in range(0, P, step)
            ]
            pending = pending[~torch.cat(won)]
            start, j = stop, j + 1
        return pending

    def _proposals(self, batch: Attempt, ctx: LimbContext, rows: torch.Tensor, limb: Limb, grid, left: int) -> None:
        """The rest of each row's budget for this limb attempt (`left` uniform draws) as
        N ~ Binomial(left, |S| / |box|) draws uniform in the boxes S that may reach the cell
        (`sampling.support`: the same law), from a generator seeded from the sample's stream."""
        bed = (self.x_lo, self.x_hi, self.y_lo, self.y_hi)
        for r in rows.tolist():
            st = batch.states[r]
            key = (limb.name, int(ctx.cell[r]))
            if key not in st.support:
                st.support[key] = grid.support(
                    ctx.offsets[r].numpy(),
                    ctx.root[r].numpy(),
                    ctx.frame[r].numpy(),
                    ctx.shift[r].numpy(),
                    (float(ctx.lo[r]), float(ctx.hi[r])),
                    bed,
                    ctx.over_bed,
                    below_shoulder=self.part.hands_behind_head and not grid.leg,
                    left_of_midline=self.part.crossed_legs and limb.name == "left_leg",
                )
            boxes = st.support[key]
            ctx.budget[r] = int(st.rng.binomial(left, boxes.size / grid.boxes))
            ctx.children[r] = (np.random.Generator(np.random.PCG64(int(st.rng.integers(2**63)))), boxes)

    def _window(self, batch, ctx, pending, limb, ends, start, W, reachable, done) -> torch.Tensor:
        """Draws start .. start + W (whole rounds ending at `ends`) of each pending row;
        returns which rows found a winner."""
        P = pending.numel()
        states = [batch.states[r] for r in pending.tolist()]
        one_round = int(np.searchsorted(ends, start, side="right")) == int(
            np.searchsorted(ends, start + W - 1, side="right")
        )
        children = [ctx.children.get(r) for r in pending.tolist()]
        saved = [None if (one_round or ch) else st.rng.bit_generator.state for st, ch in zip(states, children)]
        u = np.empty((P, W, limb.low.shape[0]))
        boxed = [p for p, ch in enumerate(children) if ch is not None]
        for st, ch, row in zip(states, children, u):
            if ch is None:
                st.rng.random(out=row)
        if boxed:  # uniform in the reachable boxes (sampling.support), the rows' numbers at once
            v = np.empty((len(boxed), W, 5))
            for p, row in zip(boxed, v):
                children[p][0].random(out=row)
            u[boxed] = self._grids[limb.name].propose_rows([children[p][1] for p in boxed], v)
        u = torch.from_numpy(u)
        avail = (ctx.budget[pending] - start).clamp(0, W)  # draws of the budget in this window
        # 1. Screen every draw (float32, conservative).
        p_idx, k_idx = self._screen(ctx, pending, limb, u)
        inside = (k_idx < avail.index_select(0, p_idx)).nonzero()[:, 0]
        p_idx, k_idx = p_idx.index_select(0, inside), k_idx.index_select(0, inside)
        # 2. The survivors exactly: cell, height, partition conditions, bed outline. Their
        # angles low + span * random = rng.uniform(low, high), bit for bit.
        drawn = u.view(P * W, -1).index_select(0, p_idx * W + k_idx)  # u[p_idx, k_idx]
        angles = torch.from_numpy(limb.low) + torch.from_numpy(limb.high - limb.low) * drawn
        if self.part.straight_limbs:
            angles[:, 3] = 0.0
        rows_s = pending.index_select(0, p_idx)
        geo, pos, caps_ab = self._limb_survivors(ctx, rows_s, limb, angles)  # caps_ab: of the draws in geo
        geo = geo.nonzero()[:, 0]
        p_idx, k_idx, rows_s, pos, angles = (x.index_select(0, geo) for x in (p_idx, k_idx, rows_s, pos, angles))
        # 3. Self-collision, in draw order: each sample's first 4 geometric draws, then (for
        # the samples without a free one yet) the next 32, 256, ... until one is free.
        reachable[rows_s] = True
        first = avail.clone()
        if p_idx.numel():
            count = torch.bincount(p_idx, minlength=P)
            rank = torch.arange(p_idx.numel()) - (count.cumsum(0) - count)[p_idx]  # within its sample
            lo, width, top = 0, 4, int(rank.max())
            avail_p = avail.index_select(0, p_idx)
            while lo <= top:
                open_ = first.index_select(0, p_idx) == avail_p  # its sample has no free draw yet
                sel = ((rank >= lo) & (rank < lo + width) & open_).nonzero()[:, 0]
                if sel.numel():
                    ab = (caps_ab[0].index_select(0, sel), caps_ab[1].index_select(0, sel))
                    free = self._collision_free(batch, rows_s.index_select(0, sel), limb, ab).nonzero()[:, 0]
                    sel = sel.index_select(0, free)
                    first.scatter_reduce_(0, p_idx.index_select(0, sel), k_idx.index_select(0, sel), "amin")
                lo, width = lo + width, 8 * width
        before = k_idx < first.index_select(0, p_idx)  # geometric draws before the winner: all collided
        collided = torch.bincount(p_idx[before], minlength=P)
        rejected = first - collided
        for st, rej, col in zip(states, rejected.tolist(), collided.tolist()):
            st.counts["limb_draws_rejected"] += rej
            st.counts["collisions"] += col
        won = first < avail
        if won.any():
            win = (k_idx == first[p_idx]).nonzero()[:, 0]  # one survivor per winning sample
            r = rows_s[win]
            caps = self._limb_capsules[limb.name]
            batch.a[r[:, None], caps] = caps_ab[0][win]
            batch.b[r[:, None], caps] = caps_ab[1][win]
            if limb.name == "left_leg":
                batch.left_ankle_x[r] = pos[win, -2, 0]
            for rr, pp, kk, ang in zip(r.tolist(), p_idx[win].tolist(), k_idx[win].tolist(), angles[win]):
                st = batch.states[rr]
                st.angles[limb.name] = ang
                # Wind the generator back to the end of the winner's round.
                used = int(ends[np.searchsorted(ends, start + kk, side="right")]) - start
                if used < W and saved[pp] is not None:  # (never in a one-round window)
                    st.rng.bit_generator.state = saved[pp]
                    st.rng.random(used * limb.low.shape[0])
            done.append(r)
        return won

    def _screen(self, ctx: LimbContext, pending: torch.Tensor, limb: Limb, u: torch.Tensor):
        """(p, k) of the draws that may meet the conditions, from the uniform numbers u (P, M, 4)
        the angles are made of: first the distal joint's cell and height above the bed (bed
        axes after the roll) for every draw, then for those left crossing and, over the bed,
        the distal joint's position - all loosened by PREFILTER_MARGIN_M (float32 round-off is
        < 1e-6 m), and for arms by how far the collar's third of the rotation can move the
        shoulder (at most |angle| / 3 x the collar-shoulder distance)."""
        P, M = u.shape[:2]
        leg = limb.name.endswith("leg")
        m = PREFILTER_MARGIN_M
        f32 = torch.float32
        low = torch.from_numpy(limb.low).to(f32)
        span = torch.from_numpy(limb.high - limb.low).to(f32)
        ps, ks = [], []
        step = max(1, _SCREEN_ELEMENTS // M)
        for lo in range(0, P, step):
            rows = pending[lo : lo + step]
            x = u[lo : lo + step].permute(2, 0, 1).to(f32, memory_format=torch.contiguous_format)  # (4, p, M)
            rot = rodrigues(tuple(low[i] + span[i] * x[i] for i in range(3)))
            o2 = cols(ctx.o2[rows])
            if not self.part.straight_limbs:
                o2 = apply_hinge(limb, low[3] + span[3] * x[3], o2)
            reach = rotate(rot, vadd(cols(ctx.o1[rows]), o2))
            frame = ctx.frame32[rows]
            up = vdot(reach, cols(frame[:, UP]))
            along = vdot(reach, cols(frame[:, ALONG]))
            ok = up.abs() <= HEIGHT_TOLERANCE_M + m
            ok &= (along >= ctx.lo32[rows, None]) & (along < ctx.hi32[rows, None])
            if not leg and self.part.hands_behind_head:
                ok &= up <= m  # no higher than the shoulder
            flat = ok.view(-1).nonzero()[:, 0]  # draws left, row-major: p * M + k
            p, k = flat.div(M, rounding_mode="floor"), flat.remainder(M)
            crossed = leg and self.part.crossed_legs
            if crossed or self.config.over_bed:
                # The same draws' distal joint, for those left.
                r = rows.index_select(0, p)
                picked = tuple(c.expand(ok.shape).reshape(-1).index_select(0, flat) for c in reach)
                dist = vadd(split_xyz(ctx.prox32.index_select(0, r)), picked)
                keep = torch.ones_like(p, dtype=torch.bool)
                if crossed:
                    if limb.side == "left":
                        keep &= dist[0] < m
                    else:
                        keep &= dist[0] > ctx.left_ankle32[r]
                if self.config.over_bed:
                    slack = ctx.slack32[r]
                    if not leg:
                        slack = slack * rot[1].reshape(-1).index_select(0, flat).sqrt() + m
                    fr, shift = ctx.frame32.index_select(0, r), ctx.shift32.index_select(0, r)
                    wx = vdot(split_xyz(fr[:, MAT_X]), dist) + shift[:, 0]
                    wy = vdot(split_xyz(fr[:, MAT_Y]), dist) + shift[:, 1]
                    keep &= (wx > self.x_lo - slack) & (wx < self.x_hi + slack)
                    keep &= (wy > self.y_lo - slack) & (wy < self.y_hi + slack)
                p, k = p[keep], k[keep]
            ps.append(p + lo)
            ks.append(k)
        return torch.cat(ps), torch.cat(ks)

    def _limb_survivors(self, ctx: LimbContext, rows: torch.Tensor, limb: Limb, angles: torch.Tensor):
        """For N draws (rows (N,), angles (N, 4)) that passed the screen: whether they meet
        every condition (N,) - cell, height, the partition's conditions, the bed outline - the
        chain joints' positions (N, n, 3) in body axes and the limb's capsule end points
        ((M, c, 3), (M, c, 3)) of the M draws that meet them, in order."""
        leg = limb.name.endswith("leg")
        c, s = torch.cos(angles[:, 3]), torch.sin(angles[:, 3])
        one, zero = torch.ones_like(c), torch.zeros_like(c)
        if leg:  # knee about x
            hinge = torch.stack([one, zero, zero, zero, c, -s, zero, s, c], -1).view(-1, 3, 3)
        else:  # elbow about y
            hinge = torch.stack([c, zero, s, zero, one, zero, -s, zero, c], -1).view(-1, 3, 3)
        R = axis_angle_to_matrix(angles[:, :3])
        lower = R @ hinge
        # World rotation of each chain joint (and the capsule riding it).
        if leg:  # hip, knee, ankle, foot
            rots = torch.stack([R, lower, lower, lower], 1)
        else:  # collar (1/3 of the rotation), shoulder, elbow, wrist, hand
            rots = torch.stack([axis_angle_to_matrix(angles[:, :3] / 3), R, lower, lower, lower], 1)
        # (Row gathers by index_select: several times faster than indexing with a tensor or list.)
        steps = (rots[:, :-1] @ ctx.offsets.index_select(0, rows)[..., None])[..., 0]
        pos = torch.cat([ctx.root.index_select(0, rows)[:, None], steps], 1).cumsum(1)  # (N, n, 3)
        # Cell and height in the bed's axes after the roll only: 'along' is the body's long
        # axis and 'up' the height above the bed, whatever the yaw (a yawed body keeps its cells).
        frame = ctx.frame.index_select(0, rows)
        dist, prox = pos[:, ctx.distal], pos[:, ctx.proximal]
        reach = dist - prox
        up = dot(reach, frame[:, UP])
        along = dot(reach, frame[:, ALONG])  # toward the foot
        ok = up.abs() <= HEIGHT_TOLERANCE_M
        # The knee or elbow no lower than that below its hip or shoulder: lower, it would be
        # pressed into the bed and prop the trunk up (a face-down body kneeling on the bed).
        ok &= dot(pos[:, ctx.distal - 1] - prox, frame[:, UP]) >= -HEIGHT_TOLERANCE_M
        cell, length = ctx.cell.index_select(0, rows), ctx.length.index_select(0, rows)
        if leg:
            ok &= (along >= 0) & (leg_cell(along, length) == cell)
            if self.part.crossed_legs:
                # Feet crossed: the left ankle lies on the right of the right ankle (body x =
                # the subject's left). The left leg, drawn first, crosses the midline; the
                # right ankle must then stay on its left.
                ok &= (dist[:, 0] < 0) if limb.side == "left" else (ctx.left_ankle[rows] < dist[:, 0])
        else:
            ok &= arm_cell(-along, length) == cell
            if self.part.hands_behind_head:
                # Behind the head: the wrist between the midline and its shoulder, no higher
                # than the shoulder (it lies under the head).
                ok &= (dist[:, 0].abs() < prox[:, 0].abs()) & (up <= 0)
        if self.config.over_bed:
            bed = pos.index_select(1, torch.tensor(ctx.over_bed))  # (N, k, 3)
            shift = ctx.shift.index_select(0, rows)
            x = dot(bed, frame[:, None, MAT_X]) + shift[:, None, 0]
            y = dot(bed, frame[:, None, MAT_Y]) + shift[:, None, 1]
            ok &= ((x > self.x_lo) & (x < self.x_hi) & (y > self.y_lo) & (y < self.y_hi)).all(-1)
        # Capsule end points of the draws that pass: joint position + the joint's rotation of
        # the rest offset.
        sel = ok.nonzero()[:, 0]
        cj = torch.tensor(ctx.cap_joints)
        local = ctx.local.index_select(0, rows.index_select(0, sel))[..., None]
        joint_rot = rots.index_select(0, sel).index_select(1, cj)
        ab = (joint_rot @ local)[..., 0] + pos.index_select(0, sel).index_select(1, cj)
        c2 = len(ctx.cap_joints) // 2
        return ok, pos, (ab[:, :c2], ab[:, c2:])

    def _collision_free(self, batch: Attempt, rows: torch.Tensor, limb: Limb, ends) -> torch.Tensor:
        """(N,) whether each draw's capsules clear the capsules already placed (checked pairs)."""
        pairs = self._limb_pairs[limb.name]
        if rows.numel() == 0 or pairs.numel() == 0:
            return torch.ones(rows.shape[0], dtype=torch.bool)
        caps = self._limb_capsules[limb.name]
        a, b = batch.a.index_select(0, rows), batch.b.index_select(0, rows)
        a[:, caps], b[:, caps] = ends
        return (capsule_clearance(a, b, batch.radius.index_select(0, rows), pairs) >= 0).all(-1)
