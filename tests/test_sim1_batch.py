"""Sim #1's batch independence, piece by piece: a body's numbers are the same bits whether it
is computed alone or among others, in any position (the whole settle is checked in
test_sim.py). Bitwise comparisons are right here: the code guarantees them by construction
(elementwise operations and sums in a fixed order, sim/fixed_order.py), and a batched
`sum`/`einsum`/`@` would break them on some CPUs (an AVX-512 Xeon did)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pressurepose.bed import BedShape
from pressurepose.body.rotations import axis_angle_to_matrix
from pressurepose.mat import MatSpec
from pressurepose.sim.capsule_foundation import CapsuleFoundation, hold_roll_torque
from pressurepose.sim.fixed_order import atan2_each, matvec3, sq_norm3, sum_last
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.settle_config import TRUNK, SettleConfig

MAT = MatSpec()
C = 20


def _misaligned(x: np.ndarray, shift: int) -> np.ndarray:
    """A copy of x starting `shift` float64s into a fresh buffer (other SIMD alignment)."""
    buf = np.empty(x.size + shift)
    out = buf[shift:].reshape(x.shape)
    out[...] = x
    return out


def test_fixed_order_helpers_match_numpy_and_are_row_independent():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(37, C, 3))
    R = rng.normal(size=(37, C, 3, 3))
    s = rng.normal(size=(37, C))
    np.testing.assert_allclose(sq_norm3(v), (v**2).sum(-1), rtol=1e-15, atol=0)
    np.testing.assert_allclose(matvec3(R, v), np.einsum("ncij,ncj->nci", R, v), rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(sum_last(s), s.sum(-1), rtol=1e-13, atol=1e-14)
    assert sum_last(np.zeros((3, 0))).shape == (3,)
    y, x = rng.normal(size=50), rng.normal(size=50)
    np.testing.assert_allclose(atan2_each(y, x), np.arctan2(y, x), rtol=2e-16, atol=0)
    for k in (0, 5, 36):
        for n in (1, 2, 7, 16):
            lo = max(0, min(k, 37 - n))
            sl = slice(lo, lo + n)
            for shift in (0, 1, 3):
                assert np.array_equal(sq_norm3(_misaligned(v[sl], shift))[k - lo], sq_norm3(v[k : k + 1])[0])
                assert np.array_equal(
                    matvec3(_misaligned(R[sl], shift), v[sl])[k - lo], matvec3(R[k : k + 1], v[k : k + 1])[0]
                )
                assert np.array_equal(sum_last(_misaligned(s[sl], shift))[k - lo], sum_last(s[k : k + 1])[0])


def _bodies(n: int, seed: int = 1):
    """n random capsule bodies (C capsules each) around the middle of the mat, partly below the top."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        centre = np.array([rng.uniform(0.6, 1.2), rng.uniform(0.25, 0.55), 0.0])
        u = rng.normal(size=(C, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        c = centre + np.stack([rng.uniform(-0.4, 0.4, C), rng.uniform(-0.2, 0.2, C), rng.uniform(-0.03, 0.06, C)], 1)
        half = rng.uniform(0.0, 0.15, C)[:, None]
        com = np.broadcast_to(centre + [0.0, 0.0, 0.1], (C, 3)).copy()
        out.append(
            dict(
                a=c - half * u,
                b=c + half * u,
                r=rng.uniform(0.03, 0.07, C),
                vel=rng.normal(scale=0.2, size=(C, 6)),
                com=com,
                xipos=c + rng.normal(scale=0.01, size=(C, 3)),
                mass=rng.uniform(0.5, 10.0, C),
                inertia=rng.uniform(0.005, 0.2, C),
            )
        )
    return out


def _forces(found: CapsuleFoundation, bodies: list[dict], stick: np.ndarray):
    n = len(bodies)
    cat = {k: np.concatenate([b[k] for b in bodies]) for k in bodies[0]}
    offset = np.repeat(np.arange(n) * found.nr * found.nc, C)
    return found.forces(
        cat["a"],
        cat["b"],
        cat["r"],
        cat["vel"],
        cat["com"],
        cat["xipos"],
        cat["mass"],
        cat["inertia"],
        offset,
        0.0103,
        stick,
    )


@pytest.mark.parametrize("head_angle", [0.0, 35.0])
def test_mattress_forces_of_a_body_do_not_depend_on_its_batch(head_angle):
    found = CapsuleFoundation(MAT, MattressParams(), bed=BedShape(head_angle_deg=head_angle))
    bodies = _bodies(5)
    S = len(found._sections)
    stick0 = np.random.default_rng(2).normal(scale=5.0, size=(S, 5, C, 2))  # anchors of earlier steps
    alone = []
    for k in range(5):
        st = stick0[:, k].copy()
        alone.append((_forces(found, [bodies[k]], st), st))
    touched = 0
    for order in ([0, 1, 2, 3, 4], [4, 2, 0], [1, 3], [3, 0, 4, 1, 2]):
        st = np.ascontiguousarray(stick0[:, order].reshape(S, -1, 2))
        out, cap, w, energy = _forces(found, [bodies[k] for k in order], st)
        for j, k in enumerate(order):
            (out1, cap1, w1, e1), st1 = alone[k]
            assert np.array_equal(out[j * C : (j + 1) * C], out1)
            mine = cap // C == j
            assert np.array_equal(cap[mine] - j * C, cap1) and np.array_equal(w[mine], w1)
            assert np.array_equal(energy[mine], e1)
            assert np.array_equal(st[:, j * C : (j + 1) * C], st1)
            touched += int((np.abs(out1[:, 2]) > 0).sum())
    assert touched > 50  # the bodies do press on the mattress
    # The forces are real: upward, and they hold the capsules' sunk parts (not all zero).
    assert all(r[0][0][:, 2].max() > 1.0 for r in alone)


def test_roll_hold_of_a_body_does_not_depend_on_its_batch():
    rng = np.random.default_rng(4)
    n = 6
    q = rng.normal(size=(2, n, 3))
    R, R0 = (axis_angle_to_matrix(torch.from_numpy(v)).numpy() for v in q)
    cv = rng.normal(size=(n, C, 6))
    mass = rng.uniform(0.5, 10.0, size=(n, C))
    weight = rng.uniform(400.0, 900.0, size=n)
    ft0 = rng.normal(size=(n, C, 6))
    cfg = SettleConfig(hold_roll_m=0.5)
    ft_all, e_all = hold_roll_torque(ft0.copy(), R, R0, cv, mass, weight, cfg)
    for k in range(n):
        for sl in (slice(k, k + 1), slice(0, k + 1), slice(k, n)):
            ft, e = hold_roll_torque(ft0[sl].copy(), R[sl], R0[sl], cv[sl], mass[sl], weight[sl], cfg)
            j = k - sl.start
            assert np.array_equal(ft[j], ft_all[k]) and e[j] == e_all[k]
    # And it is the roll: the torque on the trunk sums to -k (roll + t omega).
    E = R @ np.swapaxes(R0, 1, 2)
    roll = np.arctan2(E[:, 2, 1] - E[:, 1, 2], E[:, 1, 1] + E[:, 2, 2])
    share = mass[:, TRUNK] / mass[:, TRUNK].sum(1, keepdims=True)
    omega = (share * cv[:, TRUNK, 0]).sum(1)
    np.testing.assert_allclose((ft_all - ft0)[:, TRUNK, 3].sum(1), -0.5 * weight * (roll + 0.1 * omega), rtol=1e-12)
    assert math.isfinite(float(e_all.sum()))


def test_capsule_bodies_built_one_by_one_depend_on_their_own_shape_only(anny64):
    from pressurepose.body.capsules import build_capsule_body
    from pressurepose.sim.settle_config import SIM_VOLUME_POINTS

    g = torch.Generator().manual_seed(0)
    shape = torch.rand(3, anny64.shape_dim, generator=g, dtype=torch.float64)
    shape[:, 0] = torch.tensor([1.0, 0.0, 1.0])  # both genders
    together = build_capsule_body(anny64, shape, volume_points=SIM_VOLUME_POINTS, one_by_one=True)
    batched = build_capsule_body(anny64, shape, volume_points=SIM_VOLUME_POINTS)
    for i in (0, 2):
        alone = build_capsule_body(anny64, shape[i : i + 1], volume_points=SIM_VOLUME_POINTS, one_by_one=True)
        for name in ("volume_m3", "mass_kg", "inertia", "stiffness", "damping", "home_pose", "body_mass_kg"):
            assert torch.equal(getattr(together, name)[i], getattr(alone, name)[0]), name
            torch.testing.assert_close(getattr(together, name)[i], getattr(batched, name)[i], rtol=1e-12, atol=1e-15)
        for name in ("start", "end", "radius", "rest"):
            assert torch.equal(getattr(together.capsules, name)[i], getattr(alone.capsules, name)[0]), name
            torch.testing.assert_close(
                getattr(together.capsules, name)[i], getattr(batched.capsules, name)[i], rtol=1e-12, atol=1e-15
            )
