"""Residual networks and `HybridFK`: shapes, parameter counts, gradients, model file."""

from __future__ import annotations

import pytest
import torch

from hybrid_pk import ModelFileError, Robot
from hybrid_pk.effects import Conditions, ExtendedModel, make_effect
from hybrid_pk.errors import HybridPKError
from hybrid_pk.evaluation.metrics import pose_error
from hybrid_pk.geometry import so3_exp, transform
from hybrid_pk.hybrid import (
    ARCHITECTURES,
    HybridFK,
    InputBox,
    build_net,
    count_parameters,
    residual_targets,
)
from hybrid_pk.hybrid.losses import corrected_orientation_errors_deg, corrected_position_errors_mm
from hybrid_pk.hybrid.nets import parse_arch
from hybrid_pk.io.hybrid_file import load_hybrid, predict_poses, save_hybrid
from hybrid_pk.io.model_file import load_model
from hybrid_pk.simulate import simulate_campaign
from tests.helpers import BATCH_SHAPES, assert_transforms_close, check_gradients

F64 = torch.float64
DOF = 6

# Trainable parameters from the appendix's layer widths, counted by hand (6 joint
# inputs, 3 outputs). Dense: sum of (n_in + 1) n_out. Chen et al. blocks of width u
# after width n: dense block 2 n u + 2 u² + 12 u, identity block 3 u² + 9 u (three
# Dense + BatchNorm, shortcut Dense + BatchNorm); head BatchNorm + Dense: 5 u + 3.
APPENDIX_PARAMETERS = {
    "D1": 7 * 5000 + 5001 * 3,  # 50,003
    "D4": 7 * 3500 + 3501 * 2500 + 2501 * 1500 + 1501 * 750 + 751 * 3,  # 13,656,503
    "D4w": 7 * 5000 + 5001 * 3000 + 3001 * 1000 + 1001 * 500 + 501 * 3,  # 18,541,003
    "D4W": 7 * 6000 + 6001 * 3000 + 3001 * 1500 + 1501 * 1000 + 1001 * 3,  # 24,050,503
    "Rw": 7_191_403,  # components 700, 500, 200
    "Rd": 2_737_753,  # components 500, 200, 100, 70, 30
    "B2": 8_883,  # Chen et al.'s optimal model: three components of width 16
}


def _resnet_count(widths: list[int], n_in: int = DOF) -> int:
    total, width = 0, n_in
    for u in widths:
        total += (2 * width * u + 2 * u * u + 12 * u) + 2 * (3 * u * u + 9 * u)
        width = u
    return total + 5 * width + 3


# ----------------------------------------------------------------------------- networks


@pytest.mark.parametrize("name", list(ARCHITECTURES))
def test_every_architecture_maps_joints_to_three_outputs(name):
    net = build_net(name, DOF).eval()
    for n in (1, 5):
        with torch.no_grad():
            out = net(torch.rand(n, DOF) * 2 - 1)
        assert out.shape == (n, 3)
        assert bool(torch.isfinite(out).all())


@pytest.mark.parametrize("name", list(APPENDIX_PARAMETERS))
def test_parameter_counts_match_the_appendix(name):
    assert count_parameters(build_net(name, DOF)) == APPENDIX_PARAMETERS[name]


def test_resnet_counts_follow_the_block_formula():
    assert _resnet_count([700, 500, 200]) == APPENDIX_PARAMETERS["Rw"]
    assert _resnet_count([500, 200, 100, 70, 30]) == APPENDIX_PARAMETERS["Rd"]
    assert _resnet_count([16, 16, 16]) == APPENDIX_PARAMETERS["B2"]


def test_resnet_components_are_one_dense_and_two_identity_blocks():
    net = build_net("Rd", DOF)
    kinds = [type(b).__name__ for b in net.blocks]
    assert kinds == ["DenseBlock", "IdentityBlock", "IdentityBlock"] * 5


def test_dense_nets_use_relu_and_a_linear_output():
    layers = list(build_net("D4", DOF).layers)
    assert [type(m).__name__ for m in layers[1::2]] == ["ReLU"] * 4
    assert isinstance(layers[-1], torch.nn.Linear)
    assert [m.out_features for m in layers[0::2]] == [3500, 2500, 1500, 750, 3]


def test_mlp_spec_and_case_sensitive_names():
    assert count_parameters(build_net("mlp:16x2", DOF)) == 7 * 16 + 17 * 16 + 17 * 3
    assert parse_arch("D4w").args != parse_arch("D4W").args
    with pytest.raises(HybridPKError, match=r"unknown network architecture 'd4w'.*D4w"):
        parse_arch("d4w")


# ----------------------------------------------------------------------------- HybridFK


def _base_model(robot: Robot, gen: torch.Generator) -> ExtendedModel:
    """Joint offset + unknown base and tool frames (no compliance: exact gradients)."""
    model = ExtendedModel(
        robot,
        [make_effect(robot, "joint_offset:joint_2", 1e-3)],
        base=transform(
            so3_exp(torch.tensor([0.1, -0.2, 1.5], dtype=F64)),
            torch.rand(3, generator=gen, dtype=F64),
        ),
        tool=transform(
            so3_exp(torch.tensor([0.3, 0.2, 0.1], dtype=F64)),
            torch.tensor([0.01, 0.02, 0.1], dtype=F64),
        ),
    )
    model.requires_grad_(False)
    return model


def _hybrid(robot: Robot, arch: str = "mlp:8x2", seed: int = 0) -> HybridFK:
    gen = torch.Generator().manual_seed(seed)
    base = _base_model(robot, gen)
    q = robot.sample_q(64, gen)
    box = InputBox.from_data(q, None, fade=0.2)
    torch.manual_seed(seed)
    hybrid = HybridFK.build(
        base, box, arch, arch, torch.full((3,), 1e-3, dtype=F64), torch.full((3,), 2e-3, dtype=F64)
    )
    return hybrid.eval()


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_hybrid_forward_keeps_batch_shapes(rx160, batch):
    hybrid = _hybrid(rx160)
    q = rx160.sample_q(max(1, int(torch.tensor(batch).prod())), torch.Generator().manual_seed(1))
    q = q.reshape(*batch, DOF)
    with torch.no_grad():
        T = hybrid(q)
        dp, dw = hybrid.corrections(q)
    assert T.shape == (*batch, 4, 4)
    assert dp.shape == dw.shape == (*batch, 3)
    assert T.dtype == F64


def test_gradient_flows_through_hybrid_to_q(rx160):
    hybrid = _hybrid(rx160, "mlp:6x2")
    hybrid.double()  # float64 networks for gradcheck
    q = rx160.sample_q(3, torch.Generator().manual_seed(2))
    # One row inside the training box, one in the fade zone, one outside it.
    box = hybrid.box
    size = box.trust_upper - box.trust_lower
    q[1, 1] = box.trust_upper[1] + 0.1 * size[1]
    q[2, 2] = box.trust_lower[2] - 0.5 * size[2]
    check_gradients(lambda x: hybrid(x), q)
    check_gradients(lambda x: torch.cat(hybrid.corrections(x), -1), q[:2])


def test_trust_is_one_inside_fades_and_is_zero_far_outside(rx160):
    hybrid = _hybrid(rx160)
    box = hybrid.box
    mid = (box.trust_lower + box.trust_upper) / 2
    size = box.trust_upper - box.trust_lower
    q = mid.repeat(4, 1)
    q[1, 0] = box.trust_upper[0]
    q[2, 0] = box.trust_upper[0] + 0.5 * box.fade * size[0]
    q[3, 0] = box.trust_upper[0] + 1.01 * box.fade * size[0]
    w = hybrid.trust(q)
    assert w[0] == 1
    assert w[1] == 1
    assert 0 < w[2] < 1
    assert w[3] == 0
    with torch.no_grad():
        dp, dw = hybrid.corrections(q[3:])
        T_far, T_base = hybrid(q[3:]), hybrid.base(q[3:])
    assert not dp.any()
    assert not dw.any()
    assert torch.equal(T_far, T_base)  # far outside: exactly the base model


def test_networks_do_not_depend_on_base_and_tool_frames(rx160):
    hybrid = _hybrid(rx160)
    q = rx160.sample_q(20, torch.Generator().manual_seed(3))
    with torch.no_grad():
        T_before = hybrid(q)
        B0 = hybrid.base.base.matrix()[0]
        B1 = transform(so3_exp(torch.tensor([0.0, 0.0, 0.7], dtype=F64)), torch.ones(3, dtype=F64))
        hybrid.base.base.reset_to(B1)
        T_after = hybrid(q)
    # A moved tracker moves every predicted pose rigidly; the corrections stay.
    expected = B1 @ torch.linalg.inv(B0) @ T_before
    assert_transforms_close(T_after, expected, atol_pos=1e-12, atol_rot=1e-12)


def test_training_errors_equal_the_contract_metrics_of_the_forward_pass(rx160):
    """The losses on residual targets are the distance / angle of the full forward pass."""
    hybrid = _hybrid(rx160)
    data, _ = simulate_campaign(rx160, 50, "paper", noise_mm=0.0, payload=20.0, seed=4)
    cond = Conditions(payload=data.payload)
    targets = residual_targets(hybrid.base, data, cond)
    with torch.no_grad():
        dp, dw = hybrid.corrections(targets.q)
        pos = corrected_position_errors_mm(targets.position, targets.lever, dp, dw)
        ori = corrected_orientation_errors_deg(targets.rotation, dw)
        expected = pose_error(data.T_measured(), hybrid(data.q, cond))
    torch.testing.assert_close(pos, expected.position_mm, rtol=0, atol=1e-9)
    torch.testing.assert_close(ori, expected.orientation_deg, rtol=0, atol=1e-9)
    assert float(pos.mean()) > 0.1  # the campaign's errors are real, not all zero


# ----------------------------------------------------------------------------- model file


@pytest.mark.parametrize("arch", ["mlp:8x2", "B2"])
def test_save_load_round_trip_gives_identical_outputs(rx160, tmp_path, arch):
    hybrid = _hybrid(rx160, arch)
    path = save_hybrid(tmp_path / "hybrid.pt", hybrid, training={"note": "test"})
    loaded = load_model(path)  # torch.load(weights_only=True) inside
    assert loaded.has_networks
    restored = load_hybrid(loaded)
    assert not restored.training
    data, _ = simulate_campaign(rx160, 30, "none", noise_mm=0.0, seed=5)
    cond = Conditions()
    with torch.no_grad():
        expected = hybrid(data.q, cond)
        assert torch.equal(restored(data.q, cond), expected)
        assert torch.equal(predict_poses(loaded, data, cond), expected)
    assert loaded.networks["training"] == {"note": "test"}
    assert loaded.networks["position"]["arch"] == arch


def test_loading_refuses_a_model_for_another_robot(rx160, tmp_path):
    path = save_hybrid(tmp_path / "hybrid.pt", _hybrid(rx160))
    with pytest.raises(ModelFileError, match=r"made for robot 'rx160'.*not 'ur10'"):
        load_model(path, robot_check="ur10")


def test_networks_for_other_joints_are_refused(rx160, tmp_path):
    hybrid = _hybrid(rx160)
    state = hybrid.state()
    state["joint_names"] = ["a", "b", "c", "d", "e", "f"]
    with pytest.raises(ModelFileError, match=r"trained for joints \['a'.*'rx160' has"):
        HybridFK.from_state(hybrid.base, state)
    with pytest.raises(ModelFileError, match="not hybrid_pk residual networks"):
        HybridFK.from_state(hybrid.base, {"w": torch.ones(1)})


def test_zero_fade_is_the_base_model_right_outside_the_box(rx160):
    hybrid = _hybrid(rx160)
    hybrid.box.fade = 0.0
    box = hybrid.box
    q = ((box.trust_lower + box.trust_upper) / 2).repeat(2, 1)
    q[0, 1] = box.trust_upper[1]  # on the edge: full correction
    q[1, 1] = box.trust_upper[1] + 1e-6  # just outside: none
    assert hybrid.trust(q).tolist() == [1.0, 0.0]
    with torch.no_grad():
        assert torch.equal(hybrid(q[1:]), hybrid.base(q[1:]))
