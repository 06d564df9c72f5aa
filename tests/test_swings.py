"""The articulated rest's swing damping (`sim.rest_state.damp_swings`): a secant share of each
unknown's re-posing motion, by hand and on scalar fixed-point iterations."""

import pytest
import torch

from pressurepose.sim.rest_state import damp_swings

CAP = torch.tensor([0.05, 0.25], dtype=torch.float64)  # the vertical shift (m), one rotation (rad)
TOL = torch.tensor([3e-4, 5e-3], dtype=torch.float64)


def _state(n=2):
    z = torch.zeros(1, n, dtype=torch.float64)
    return z.clone(), torch.ones_like(z), z.clone()


def test_by_hand():
    """A reversal takes the secant share |last| / (|last| + |q|); a shrinking motion the same
    way grows it to share / (1 - rho); a motion at the cap resets it to 1; motions within the
    tolerance change nothing."""
    last, share, streak = _state()
    q = torch.tensor([[0.0, -0.1]], dtype=torch.float64)
    step, share, streak = damp_swings(q, torch.tensor([[0.0, 0.1]], dtype=torch.float64), share, streak, CAP, TOL)
    assert share[0, 1] == pytest.approx(0.5) and step[0, 1] == pytest.approx(-0.05)
    assert share[0, 0] == 1.0 and step[0, 0] == 0.0
    # Asymmetric reversal: +0.09 after -0.03 -> share 0.5 * 0.03 / 0.12.
    step, share2, _ = damp_swings(
        torch.tensor([[0.0, 0.09]]).double(), q.new_tensor([[0.0, -0.03]]), share, streak, CAP, TOL
    )
    assert share2[0, 1] == pytest.approx(0.125) and step[0, 1] == pytest.approx(0.09 * 0.125)
    # The same way, shrinking by rho = 0.5: the share doubles (secant extrapolation), at most 1.
    step, share3, _ = damp_swings(q.new_tensor([[0.0, 0.02]]), q.new_tensor([[0.0, 0.04]]), share2, streak, CAP, TOL)
    assert share3[0, 1] == pytest.approx(0.25)
    _, share4, _ = damp_swings(q.new_tensor([[0.0, 0.02]]), q.new_tensor([[0.0, 0.04]]), share, streak, CAP, TOL)
    assert share4[0, 1] == pytest.approx(1.0)
    # At the cap: the whole motion.
    step, share5, _ = damp_swings(q.new_tensor([[0.0, -0.25]]), q.new_tensor([[0.0, 0.1]]), share2, streak, CAP, TOL)
    assert share5[0, 1] == 1.0 and step[0, 1] == pytest.approx(-0.25)
    # Within the tolerance: unchanged.
    _, share6, _ = damp_swings(q.new_tensor([[1e-4, -1e-3]]), q.new_tensor([[-1e-4, 1e-3]]), share2, streak, CAP, TOL)
    assert torch.equal(share6, share2)


def _iterate(residual, x0, steps, damp=True):
    """x_{t+1} = x_t + share * r(x_t) on one rotation unknown; returns the positions."""
    last, share, streak = _state()
    x, xs = x0, [x0]
    for _ in range(steps):
        q = torch.tensor([[0.0, residual(x)]], dtype=torch.float64)
        if damp:
            step, share, streak = damp_swings(q, last, share, streak, CAP, TOL)
            last = q
        else:
            step = q
        x += float(step[0, 1])
        xs.append(x)
    return xs


def test_a_swing_about_a_smooth_rest_ends_in_one_step():
    """A linearisation that overshoots its rest by as much as it moves (r = -2 (x - x*)):
    undamped it alternates for ever; damped, the first reversal lands on the rest."""
    rest = 0.03

    def residual(x):
        return -2.0 * (x - rest)

    undamped = _iterate(residual, 0.0, 10, damp=False)
    assert abs(undamped[-1] - undamped[-3]) < 1e-12 and abs(undamped[-1] - rest) > 0.02
    damped = _iterate(residual, 0.0, 10)
    assert damped[2] == pytest.approx(rest, abs=1e-12)


def test_a_swing_about_a_kink_narrows_onto_it():
    """A motion of the same size either side of a contact's onset (r = -0.1 sign(x - x*)):
    undamped it swings +-0.1 to the cap; damped, it bisects onto the onset, and the steps it
    takes fall below the settled tolerance."""
    onset = 0.037

    def residual(x):
        return -0.1 if x > onset else 0.1

    undamped = _iterate(residual, 0.0, 20, damp=False)
    assert max(abs(a - b) for a, b in zip(undamped[-4:], undamped[-5:-1])) == pytest.approx(0.1)
    damped = _iterate(residual, 0.0, 20)
    assert abs(damped[-1] - onset) < 5e-3
    assert abs(damped[-1] - damped[-2]) < float(TOL[1])


def test_a_slide_after_a_swing_regains_its_reach():
    """A motion that keeps its direction and size (a leg sliding against friction) gets its
    whole motion back within a few re-posings after a swing halved it."""
    last, share, streak = _state()
    q = torch.tensor([[0.0, 0.1]], dtype=torch.float64)
    _, share, streak = damp_swings(-q, q, share, streak, CAP, TOL)  # a reversal: share 0.5
    last = -q
    for _ in range(3):
        _, share, streak = damp_swings(-q, last, share, streak, CAP, TOL)
        last = -q
    assert share[0, 1] == pytest.approx(1.0)


def test_mirrored_motions_are_damped_alike():
    """The rule sees magnitudes and signs' agreement only: a mirrored motion (signs flipped)
    takes the mirrored step."""
    g = torch.Generator().manual_seed(0)
    q, last = (0.3 * torch.rand(4, 2, generator=g, dtype=torch.float64) - 0.15 for _ in range(2))
    share = 0.2 + 0.8 * torch.rand(4, 2, generator=g, dtype=torch.float64)
    streak = torch.randint(0, 3, (4, 2), generator=g).double()
    a = damp_swings(q, last, share, streak, CAP, TOL)
    b = damp_swings(-q, -last, share, streak, CAP, TOL)
    assert torch.equal(a[0], -b[0]) and torch.equal(a[1], b[1]) and torch.equal(a[2], b[2])
