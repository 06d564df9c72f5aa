"""The pillow augmentation (`train.augment.pillow_batch`) against a per-taxel reference on a
hand-built image."""

from __future__ import annotations

import math

import pytest
import torch

from pressurepose.mat import MatSpec
from pressurepose.net.model import NetInputs
from pressurepose.train import augment
from pressurepose.train.augment import REPRESS_THRESHOLD_MMHG, pillow_batch
from pressurepose.train.config import TrainConfig

MAT = MatSpec()


def _scene(head_row: float = 5.5, head_col: float = 13.5):
    """A trunk (rows 10-49, columns 8-18, 20 mmHg) and a head (rows 3-7, columns 11-15, 30
    mmHg); J24 joints at zero but the head's and the neck's."""
    p = torch.zeros(2, 64, 27, dtype=torch.float64)
    p[:, 10:50, 8:19] = 20.0
    p[:, 3:8, 11:16] = 30.0
    joints = torch.zeros(2, 24, 3, dtype=torch.float64)
    joints[:, augment.HEAD, 0] = head_row * MAT.pitch_row_m
    joints[:, augment.HEAD, 1] = head_col * MAT.pitch_col_m
    joints[:, augment.NECK, 0] = (head_row + 3) * MAT.pitch_row_m
    return p, joints


def _fixed(monkeypatch, beyond=0.2, past=0.02, width=0.4, share=0.08, moved=0.75):
    for name, v in (
        ("PILLOW_BEYOND_HEAD_M", beyond),
        ("PILLOW_PAST_NECK_M", past),
        ("PILLOW_WIDTH_M", width),
        ("PILLOW_SHARE", share),
        ("PILLOW_HEAD_MOVED", moved),
    ):
        monkeypatch.setattr(augment, name, (v, v))
    monkeypatch.setattr(augment, "PILLOW_TEXTURE", 0.0)


def _reference(p, head_x, head_y, neck_x, beyond, past, width, share, moved):
    """Per taxel, as the docstring says."""
    top, bottom, half = head_x - beyond, neck_x + past, width / 2
    sx, sy = max(bottom - top, MAT.pitch_row_m), width / 2
    spread = torch.zeros_like(p)
    inside = torch.zeros_like(p, dtype=torch.bool)
    for r in range(64):
        for c in range(27):
            x, y = (r + 0.5) * MAT.pitch_row_m, (c + 0.5) * MAT.pitch_col_m
            if top <= x < bottom and abs(y - head_y) < half:
                inside[r, c] = True
                spread[r, c] = math.exp(-0.5 * ((x - head_x) / sx) ** 2 - 0.5 * ((y - head_y) / sy) ** 2)
    q = torch.where(inside, p * (1 - moved), p) + spread / spread.sum() * share * p.sum()
    q = q * p.sum() / q.sum()
    return torch.where(q >= REPRESS_THRESHOLD_MMHG, q, torch.zeros_like(q)).clamp(max=100), inside


def test_pillow_against_a_per_taxel_reference(monkeypatch):
    _fixed(monkeypatch)
    p, joints = _scene()
    out = pillow_batch(NetInputs(pressure_mmhg=p), joints, 1.0, torch.Generator().manual_seed(0)).pressure_mmhg
    ref, inside = _reference(
        p[0], 5.5 * MAT.pitch_row_m, 13.5 * MAT.pitch_col_m, 8.5 * MAT.pitch_row_m, 0.2, 0.02, 0.4, 0.08, 0.75
    )
    assert torch.allclose(out[0], ref, rtol=1e-12, atol=1e-9)
    assert abs(float(out[0].sum()) / float(p[0].sum()) - 1) < 1e-9  # the force kept (nothing under 1 mmHg here)
    # The far edge, 0.2 m (7 rows) beyond the head joint, lies beyond the mat's first row: the
    # patch starts at row 0, where the bare head started at row 3.
    loaded = (out[0].sum(-1) > 0).nonzero()[:, 0]
    assert int(loaded.min()) == 0 and int((p[0].sum(-1) > 0).nonzero()[0, 0]) == 3
    # as wide as the footprint (0.4 m: 14-15 columns at the column pitch)
    assert 13 <= int((out[0, 0] > 0).sum()) <= 15
    # outside the footprint the image is only scaled, by the same factor everywhere
    ratio = out[0][~inside & (p[0] > 0)] / p[0][~inside & (p[0] > 0)]
    assert float(ratio.max() - ratio.min()) < 1e-12 and float(ratio[0]) < 1
    # highest under the head: the patch's peak column is the head's
    assert int(out[0, 0].argmax()) in (12, 13, 14)


def test_pillow_draws_share_and_misses(monkeypatch):
    p, joints = _scene()
    inputs = NetInputs(pressure_mmhg=p)
    assert torch.equal(pillow_batch(inputs, joints, 0.0, torch.Generator().manual_seed(0)).pressure_mmhg, p)
    a = pillow_batch(inputs, joints, 1.0, torch.Generator().manual_seed(3)).pressure_mmhg
    b = pillow_batch(inputs, joints, 1.0, torch.Generator().manual_seed(3)).pressure_mmhg
    assert torch.equal(a, b) and not torch.equal(a[0], p[0])
    # the two images draw their own pillows (texture and ranges)
    assert not torch.equal(a[0], a[1])
    # a share draws per image by the first uniform, as the docstring says
    on = torch.rand(6, 2, generator=torch.Generator().manual_seed(5))[0] < 0.5
    half = pillow_batch(inputs, joints, 0.5, torch.Generator().manual_seed(5)).pressure_mmhg
    for i in range(2):
        assert torch.equal(half[i], p[i]) != bool(on[i])
    # a head off the mat (beyond its foot end) gets no pillow on the mat: the image is unchanged
    far = joints.clone()
    far[:, augment.HEAD, 0] = far[:, augment.NECK, 0] = 3.0
    _fixed(monkeypatch, beyond=0.1)
    assert torch.equal(pillow_batch(inputs, far, 1.0, None).pressure_mmhg, p)


def test_pillow_share_is_validated():
    with pytest.raises(ValueError, match="pillow"):
        TrainConfig.smoke(pillow=1.5)
