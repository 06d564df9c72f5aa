import math

import pytest
import torch

from pressurepose.body.joints import J24_MIRROR, J24_NAMES
from pressurepose.body.limits import ALPHA, JointLimits


def test_table_is_well_formed_and_mirrored():
    lim = JointLimits.default(torch.float64)
    assert lim.lower.shape == (23, 3)
    assert (lim.lower < lim.upper).all()  # no empty range (the original's right-hip typo)
    for j in range(1, 24):
        m = J24_MIRROR[j]
        lo, hi = lim.lower[j - 1], lim.upper[j - 1]
        mlo, mhi = lim.lower[m - 1], lim.upper[m - 1]
        assert torch.allclose(lo[0], mlo[0]) and torch.allclose(hi[0], mhi[0])
        assert torch.allclose(lo[1:], -mhi[1:]) and torch.allclose(hi[1:], -mlo[1:])


def test_reference_values():
    lim = JointLimits.default(torch.float64)
    assert lim.bounds_of("left_knee")[0].tolist() == pytest.approx([-0.0227, 2.4417])
    assert lim.bounds_of("right_elbow")[1].tolist() == pytest.approx([-0.048, 2.5709])
    assert lim.bounds_of("right_hip")[1].tolist() == pytest.approx([-0.5690, 0.5882])
    assert lim.bounds_of("neck")[0].tolist() == pytest.approx([-math.pi / 3, math.pi / 3])
    # Collar + shoulder together span the seed's shoulder pitch range.
    total = lim.bounds_of("left_collar")[2] + lim.bounds_of("left_shoulder")[2]
    assert [math.degrees(v) for v in total.tolist()] == pytest.approx([-90.0, 80.4])
    with pytest.raises(ValueError, match="unknown joint name 'pelvis'"):
        lim.bounds_of("pelvis")


def test_squash_inside_inflated_bounds_monotone_and_invertible():
    lim = JointLimits.default(torch.float64)
    a = torch.linspace(-20, 20, 2001, dtype=torch.float64)[:, None, None].expand(-1, 23, 3)
    s = lim.squash(a)
    mid, half = (lim.lower + lim.upper) / 2, ALPHA * (lim.upper - lim.lower) / 2
    assert ((s >= mid - half) & (s <= mid + half)).all()  # closed: tanh saturates in float
    assert (s.diff(dim=0) >= 0).all()
    # Strictly increasing where it has not saturated (within the inflated range).
    u = torch.linspace(-0.99, 0.99, 101, dtype=torch.float64)[:, None, None]
    a = mid + u * half
    assert (lim.squash(a).diff(dim=0) > 0).all()
    # Slope 1 at the midpoint; identity there.
    assert torch.allclose(lim.squash(mid[None]), mid[None])
    x = (torch.rand(5, 23, 3, dtype=torch.float64) - 0.5) * 2 * half + mid
    assert torch.allclose(lim.squash(lim.unsquash(x)), x)
    # The uninflated bounds are reachable: a straight knee is not squeezed away.
    assert lim.contains(lim.squash(lim.unsquash(lim.lower[None] + 1e-9))).all()


def test_squash_bad_input():
    lim = JointLimits.default()
    with pytest.raises(ValueError, match=r"pose must have shape \(B, 23, 3\)"):
        lim.squash(torch.zeros(2, 24, 3))
    with pytest.raises(ValueError, match="outside the inflated joint limits"):
        lim.unsquash(torch.full((1, 23, 3), 100.0))
    with pytest.raises(ValueError, match="alpha must be > 0"):
        lim.squash(torch.zeros(1, 23, 3), alpha=0.0)
    assert J24_NAMES[0] == "pelvis"
