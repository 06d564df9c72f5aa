"""The height from the localised skeleton (net.stature): the bone chain by hand, its pose
invariance, the shape update, the optimal share, and the network option."""

import dataclasses

import pytest
import torch

from pressurepose.body.joints import J24_NAMES
from pressurepose.body.kinematics import forward_kinematics
from pressurepose.errors import UserError
from pressurepose.net import NetConfig, NetInputs, PressureNet
from pressurepose.net.stature import HEIGHT_PARAMETER, chain_length, optimal_weight, stature_from_joints
from pressurepose.train.checkpoint import net_config_from_record


def test_chain_length_by_hand():
    """The trunk chain 1 + 2 + 3 + 4 + 5 and the legs 1 + 2 + 3 (left) and 2 + 2 + 2 (right):
    15 + (6 + 6) / 2 = 21."""
    j = torch.zeros(1, 24, 3)
    put = lambda name, xyz: j[0, J24_NAMES.index(name)].copy_(torch.tensor(xyz))  # noqa: E731
    put("pelvis", [0.0, 0.0, 0.0])
    put("spine1", [0.0, 5.0, 0.0])
    put("spine2", [0.0, 9.0, 0.0])
    put("spine3", [0.0, 12.0, 0.0])
    put("neck", [0.0, 14.0, 0.0])
    put("head", [0.0, 15.0, 0.0])
    put("left_hip", [1.0, 0.0, 0.0])
    put("left_knee", [1.0, -2.0, 0.0])
    put("left_ankle", [1.0, -5.0, 0.0])
    put("right_hip", [0.0, 0.0, 2.0])
    put("right_knee", [0.0, -2.0, 2.0])
    put("right_ankle", [0.0, -4.0, 2.0])
    assert float(chain_length(j)) == pytest.approx(21.0)
    # From the neck down the head - neck link (1) is left out: 14 + 6 = 20; moving the head
    # changes only the full chain.
    assert float(chain_length(j, head=False)) == pytest.approx(20.0)
    put("head", [0.0, 25.0, 0.0])
    assert float(chain_length(j)) == pytest.approx(31.0)
    assert float(chain_length(j, head=False)) == pytest.approx(20.0)


def test_chain_length_does_not_depend_on_the_pose(anny64):
    """Every link of the chain is a bone (parent and child): posing the skeleton keeps it."""
    g = torch.Generator().manual_seed(0)
    shape = torch.rand(4, 6, generator=g, dtype=torch.float64)
    rest = anny64.rest_joints(shape)
    pose = 0.6 * torch.randn(4, 23, 3, generator=g, dtype=torch.float64)
    _, posed = forward_kinematics(rest, pose)
    torch.testing.assert_close(chain_length(posed), chain_length(rest), rtol=0, atol=1e-12)


def test_stature_from_joints_recovers_the_height_parameter(anny64):
    """Joints of a body whose height parameter is 0.7 instead of 0.4 (the rest alike): weight 1
    recovers 0.7, weight 0.5 goes half way, weight 0 returns the shape; the other parameters stay."""
    k = anny64.shape_names.index(HEIGHT_PARAMETER)
    shape = torch.tensor([[0.3, 0.5, 0.5, 0.4, 0.4, 0.5], [0.7, 0.3, 0.6, 0.5, 0.4, 0.4]], dtype=torch.float64)
    true = shape.clone()
    true[:, k] = 0.7
    _, joints = forward_kinematics(anny64.rest_joints(true), 0.3 * torch.ones(2, 23, 3, dtype=torch.float64))
    assert torch.equal(stature_from_joints(anny64, shape, joints, 0.0), shape)
    full = stature_from_joints(anny64, shape, joints, 1.0, iterations=4)
    torch.testing.assert_close(full[:, k], true[:, k], rtol=0, atol=2e-3)
    half = stature_from_joints(anny64, shape, joints, 0.5, iterations=4)
    torch.testing.assert_close(half[:, k], (shape[:, k] + true[:, k]) / 2, rtol=0, atol=1e-3)
    others = [i for i in range(6) if i != k]
    assert torch.equal(full[:, others], shape[:, others])
    # A skeleton twice as long is out of the model's reach: the parameter stops at its bound.
    assert torch.equal(stature_from_joints(anny64, shape, 2 * joints, 1.0)[:, k], torch.ones(2, dtype=torch.float64))
    # From the neck down: the same answer for these joints, and one the head's place does not move.
    neck_down = stature_from_joints(anny64, shape, joints, 1.0, iterations=4, head=False)
    torch.testing.assert_close(neck_down[:, k], true[:, k], rtol=0, atol=2e-3)
    far_head = joints.clone()
    far_head[:, J24_NAMES.index("head")] += torch.tensor([0.0, 0.0, 0.15], dtype=torch.float64)
    torch.testing.assert_close(
        stature_from_joints(anny64, shape, far_head, 1.0, iterations=4, head=False), neck_down, rtol=0, atol=1e-12
    )
    assert float(stature_from_joints(anny64, shape, far_head, 1.0, iterations=4)[0, k]) > float(full[0, k]) + 0.01


def test_optimal_weight_by_hand_and_against_a_grid():
    g = torch.Generator().manual_seed(1)
    a, b = torch.randn(20000, generator=g), torch.randn(20000, generator=g)
    assert optimal_weight(a, b) == pytest.approx(0.5, abs=0.02)  # equal, independent errors
    assert optimal_weight(a, torch.zeros(20000)) == pytest.approx(1.0)  # a perfect second reading
    assert optimal_weight(torch.zeros(20000), b) == pytest.approx(0.0)
    x = 3 * a
    y = 0.8 * x + 2 * b  # correlated, unequal
    grid = torch.linspace(0, 1, 1001)
    mse = torch.stack([(((1 - w) * x + w * y) - ((1 - w) * x + w * y).mean()).square().mean() for w in grid])
    assert optimal_weight(x, y) == pytest.approx(float(grid[mse.argmin()]), abs=2e-3)


def test_network_option_moves_only_the_height_parameter(anny32):
    torch.manual_seed(0)
    net = PressureNet(NetConfig(arch="heatmap", gender_input=False), body=anny32).eval()
    p = torch.rand(2, 64, 27) * 40 * (torch.rand(2, 64, 27) > 0.5)
    with torch.no_grad():
        before = net(NetInputs(p), mesh=False, maps=False)[-1].params.shape
        net.config = dataclasses.replace(net.config, stature_weight=1.0)
        after = net(NetInputs(p), mesh=False, maps=False)[-1].params.shape
    k = anny32.shape_names.index(HEIGHT_PARAMETER)
    others = [i for i in range(6) if i != k]
    assert torch.equal(after[:, others], before[:, others])
    assert not torch.equal(after[:, k], before[:, k])


def test_stature_weight_bad_settings():
    with pytest.raises(UserError, match="stature_weight must lie in"):
        NetConfig(arch="heatmap", stature_weight=1.5)
    with pytest.raises(UserError, match="heatmap"):
        NetConfig(arch="fast", stature_weight=0.2)
    with pytest.raises(UserError, match="Anny"):
        NetConfig(arch="heatmap", backend="smpl", stature_weight=0.2)
    with pytest.raises(UserError, match="stature_weight"):
        net_config_from_record({"net": {"arch": "heatmap", "stature_weight": "high"}}, "m.safetensors")
    assert net_config_from_record({"net": {"arch": "heatmap", "stature_weight": 0.2}}).stature_weight == 0.2
    assert net_config_from_record({"net": {"arch": "heatmap", "stature_weight": 0.2}}).stature_head
    rec = {"net": {"arch": "heatmap", "stature_weight": 0.2, "stature_head": False}}
    assert not net_config_from_record(rec).stature_head
    with pytest.raises(UserError, match="stature_head"):
        net_config_from_record({"net": {"arch": "heatmap", "stature_head": "no"}}, "m.safetensors")


def test_rest_pose_joints_keep_the_chain(anny64):
    """Anny's rest bone heads give the T-pose skeleton's chain within millimetres (the bones'
    lengths; only the orientations differ)."""
    g = torch.Generator().manual_seed(2)
    shape = torch.rand(64, 6, generator=g, dtype=torch.float64)
    diff = (chain_length(anny64.rest_pose_joints(shape)) - chain_length(anny64.rest_joints(shape))).abs()
    assert float(diff.median()) < 0.005
    assert float(diff.median()) > 0  # a different skeleton (not the same call)


def test_rest_pose_joints_default_is_the_t_pose(smpl64):
    """A backend without a cheaper skeleton answers with its T-pose joints."""
    shape = torch.zeros(2, 10, dtype=torch.float64)
    shape[1, 0] = 1.0
    assert torch.equal(smpl64.rest_pose_joints(shape), smpl64.rest_joints(shape))
