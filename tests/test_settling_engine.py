"""The articulated settling engine (`simulate_poses(settle="articulated")`): every partition
rests without NaN, a sample does not depend on its batch beyond the engine's tolerance, runs
repeat exactly."""

import numpy as np
import pytest
import torch

from pressurepose.sampling.partitions import PARTITIONS, SamplingConfig
from pressurepose.sampling.sampler import PoseSampler
from pressurepose.sim.articulated import ArticulatedConfig, rest_articulated
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.run import settle_config_for, simulate_poses

FLAT = [p for p in PARTITIONS if p != "half_sitting"]


def _drawn(model, partition, n, seed=0):
    over_bed = PARTITIONS[partition].over_bed_choices[0]
    cfg = SamplingConfig(partition=partition, gender="male", seed=seed, over_bed=over_bed)
    return PoseSampler(model, cfg).sample(range(n)).params


@pytest.mark.slow
@pytest.mark.parametrize("partition", FLAT)
def test_every_partition_rests_without_nan(anny64, partition):
    params = _drawn(anny64, partition, 2)
    hold = settle_config_for(partition).hold_roll_m
    sim = simulate_poses(
        anny64,
        params,
        MattressParams.preset("sponge"),
        settle="articulated",
        articulated=ArticulatedConfig(hold_roll_m=hold),
    )
    for name in ("pressure_mmhg", "depth_mm", "joints", "vertices"):
        assert torch.isfinite(getattr(sim, name)).all(), name
    kept = [i for i, r in enumerate(sim.reason) if not r]
    assert all(r.startswith("sim #2: ") for r in sim.reason if r)  # no MuJoCo on a flat bed
    # The settling count is the articulated rest's re-posings (outer + 1: still moving at the cap).
    assert ((sim.settle_steps >= 0) & (sim.settle_steps <= ArticulatedConfig().outer + 1)).all()
    for i in kept:
        assert float(sim.pressure_mmhg[i].max()) > 5.0


def test_a_sample_does_not_depend_on_its_batch(anny64):
    """Alone or with others, a body rests the same: a body that has settled leaves its batch
    and finishes its solve on its own, and a solve steps each body on its own
    (`test_articulated_batch`), so what differs is round-off (batched solves and products
    are not bitwise the same for every batch size; here ~1e-10 m). The bound is the old one,
    the re-posing stop criterion (5 mrad: ~2 mm at a hand), because round-off can still
    tip a body at a bifurcation (a raised knee falling out or in). Without friction: with it
    the rest depends on the path, and round-off can send a limb along another one
    (docs/physics.md); a dataset fixes its batches, so it still repeats exactly."""
    params = _drawn(anny64, "supine", 3)
    mp = MattressParams.preset("sponge")
    cfg = ArticulatedConfig(friction=False)
    together = rest_articulated(anny64, params, mattress=mp, config=cfg)
    for i in range(3):
        alone = rest_articulated(anny64, params.index(torch.tensor([i])), mattress=mp, config=cfg)
        assert alone.failure[0] == together.failure[i]
        d = (alone.joints[0] - together.joints[i]).norm(dim=-1)
        assert float(d.max()) < 2e-3, float(d.max())
        a, b = alone.foundation_pa[0], together.foundation_pa[i]
        assert float((a - b).abs().sum() / a.abs().sum()) < 0.02


def test_runs_repeat_exactly(anny64):
    params = _drawn(anny64, "general", 2)
    a = rest_articulated(anny64, params)
    b = rest_articulated(anny64, params)
    assert a.failure == b.failure
    assert torch.equal(a.joints, b.joints) and torch.equal(a.foundation_pa, b.foundation_pa)
    np.testing.assert_array_equal(a.iterations.numpy(), b.iterations.numpy())
