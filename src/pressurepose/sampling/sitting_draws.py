"""Sitting a drawn pose up on its raised bed (the half_sitting partition; docs/sampling.md):
the pitch and the limbs' frames per new shape (`_pitch`), and the check of each drawn pose
once turned up (`_sit_up`). A mixin of `PoseSampler`: it uses its mat, config, limbs and poses.
One sample at a time, so a sample's numbers never depend on its batch."""

from __future__ import annotations

import torch

from pressurepose.bed import BedShape
from pressurepose.body.capsules import Capsules
from pressurepose.body.joints import NUM_POSE_JOINTS
from pressurepose.body.kinematics import pose_in_mat
from pressurepose.body.params import BodyParams
from pressurepose.sampling.attempt import MAT_X, SampleState
from pressurepose.sampling.partitions import HEIGHT_TOLERANCE_M
from pressurepose.sampling.sitting import sit_up, sit_up_frame

# Sitting up on a raised bed: the trunk must rest on the bed, not be propped up by a hand or a
# heel by more than a lying body may be (its distal joints lie up to HEIGHT_TOLERANCE_M below
# their proximal joints); sim #1 lets it down.
SEAT_TOLERANCE_M = HEIGHT_TOLERANCE_M


class SittingDraws:
    """The raised-bed steps of `PoseSampler` (a mixin)."""

    def _pitch(self, st: SampleState, root_aa: torch.Tensor) -> None:
        """The pitch this trunk sits up by on its bed, and the limbs' frames for it (one sample
        at a time: never batch-dependent)."""
        caps, lying = _lying(st, root_aa, torch.zeros(1, NUM_POSE_JOINTS, 3, dtype=torch.float64))
        up = sit_up_frame(caps, lying, BedShape(st.head_angle), self.mat)
        st.pitch = up.pitch
        # The legs are measured in the bed's frame turned back by the pitch: a body-axes vector
        # v of the turned body points along Q v in the lying frame, so the bed axes f seen from
        # the lying frame are Q^T f: rows f^T Q.
        st.leg_frame, st.leg_shift = st.frame @ up.turn[0], up.pelvis[0]
        if self.config.over_bed:
            # The arms turn up with the trunk: their over-bed rule is measured on the head
            # section as they will lie there (their cells and heights stay the trunk's, which
            # turning keeps; sampling law 5).
            st.arm_frame, st.arm_shift = st.frame.clone(), st.shift.clone()
            st.arm_frame[MAT_X], st.arm_shift[0] = up.head_row[0], up.head_offset[0]

    def _sit_up(self, states: list[SampleState]) -> None:
        """Turn each fully drawn pose up onto its raised bed and check what turning changes; a
        pose that fails loses its limbs (a failed attempt). One sample at a time: its numbers
        then never depend on the batch."""
        (x_lo, x_hi), (y_lo, y_hi) = self.mat.mattress_bounds_m
        over_bed = sorted({j for lb in self.limbs.values() for j in lb.over_bed})
        for st in states:
            bed = BedShape(st.head_angle)
            caps, lying = _lying(st, st.root_aa[None], self._pose([st]))
            sat, seat = sit_up(caps, lying, bed, self.mat, pitch=st.pitch, keep_thighs=False)
            ok = float(seat[0]) <= SEAT_TOLERANCE_M
            if ok and self.config.over_bed:
                _, joints = pose_in_mat(caps.rest, sat)
                s_y = bed.to_surface(joints[0, over_bed], self.mat)
                ok = bool(((s_y[:, 0] > x_lo) & (s_y[:, 0] < x_hi) & (s_y[:, 1] > y_lo) & (s_y[:, 1] < y_hi)).all())
            if ok:
                st.sat = sat
            else:
                st.angles = {}
                st.sat = None
                st.failed_limb = None
                st.counts["sit_up_rejections"] += 1


def _lying(st: SampleState, root_aa: torch.Tensor, pose: torch.Tensor) -> tuple[Capsules, BodyParams]:
    """A sample's capsules and its pose lying flat (pelvis over the bed, height 0), batch of 1."""
    caps = Capsules(st.caps[0][None], st.caps[1][None], st.caps[2][None], st.rest[None])
    return caps, BodyParams(
        shape=torch.from_numpy(st.shape)[None],
        root_rotation=root_aa,
        root_translation=st.shift[None].clone(),
        pose=pose,
    )


__all__ = ["SEAT_TOLERANCE_M", "SittingDraws"]
