"""Python API misuse gives a one-line error naming what is wrong (third tour, API user)."""

import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.errors import DataError, HybridPKError
from tests.dh_reader import erd_root


@pytest.fixture(scope="module")
def ur10():
    return hpk.Robot.from_urdf("ur10")


@pytest.mark.parametrize(
    ("spec", "value", "said"),
    [
        ("link_length:elbow_joint", 5e-4, r"must be \(3,\) \[m\], got shape \(\)"),
        ("joint_offset:elbow_joint", [1e-3, 2e-3], r"must be a number \[rad\], got shape \(2,\)"),
        ("joint_offset:elbow_joint", "abc", r"must be a number \[rad\], got 'abc'"),
        ("joint_offset:elbow_joint", float("nan"), r"finite, got nan"),
    ],
)
def test_make_effect_value_checked(ur10, spec, value, said):
    with pytest.raises(HybridPKError, match=said):
        hpk.make_effect(ur10, spec, value)


def test_make_effect_value_kept(ur10):
    e = hpk.make_effect(ur10, "link_length:elbow_joint", [0.0, 0.0, 5e-4])
    assert e.value.tolist() == [0.0, 0.0, 5e-4]


@pytest.mark.parametrize("bad", ["joint_offset:elbow_joint", None])
def test_extended_model_refuses_non_effects(ur10, bad):
    with pytest.raises(HybridPKError, match="effects must be Effect objects"):
        hpk.ExtendedModel(ur10, [bad])


def test_extended_model_takes_lists_and_checks_joint_count(ur10):
    model = hpk.ExtendedModel(ur10, [hpk.make_effect(ur10, "joint_offset:elbow_joint", 1e-3)])
    q = [0.1, -0.5, 0.7, 0.0, 0.3, 0.2]
    assert torch.equal(model(q), model(torch.tensor(q, dtype=torch.float64)))
    with pytest.raises(hpk.ShapeError, match=r"shape \(\*B, 6\).*found \(2, 5\)"):
        model(torch.zeros(2, 5, dtype=torch.float64))


def test_diagnose_refuses_a_path(ur10):
    with pytest.raises(DataError, match=r"data must be a MeasuredData.*got str"):
        hpk.diagnose(ur10, "campaign.csv")


def test_pose_error_batches_must_match(ur10):
    T = ur10.fk(ur10.sample_q(4)).detach()
    with pytest.raises(hpk.ShapeError, match=r"T_measured batch \(4,\) and T_model batch \(3,\)"):
        hpk.pose_error(T, T[:3])
    assert hpk.pose_error(T, T[0]).position_mm.shape == (4,)  # one model pose broadcasts


def test_conditions_batch_and_direction_checked(ur10):
    q = ur10.sample_q(4)
    soft = hpk.ExtendedModel(ur10, [hpk.make_effect(ur10, "joint_compliance:elbow_joint", 1e-6)])
    with pytest.raises(hpk.ShapeError, match=r"Conditions.payload has batch \(3,\), q has \(4,\)"):
        soft(q, hpk.Conditions(payload=torch.full((3,), 5.0, dtype=torch.float64)))
    assert soft(q, hpk.Conditions(payload=torch.tensor(5.0))).shape == (4, 4, 4)
    play = hpk.ExtendedModel(ur10, [hpk.make_effect(ur10, "backlash:elbow_joint", 1e-3)])
    with pytest.raises(HybridPKError, match=r"direction must be \(\*B, 6\).*found \(4, 5\)"):
        play(q, hpk.Conditions(direction=torch.ones(4, 5)))


def test_several_leaves_name_the_python_argument():
    with pytest.raises(hpk.RobotModelError, match=r"end_link=.*"):
        hpk.Robot.from_urdf(erd_root() / "panda_description" / "urdf" / "panda.urdf")
    panda = hpk.Robot.from_urdf(
        erd_root() / "panda_description" / "urdf" / "panda.urdf", end_link="panda_hand_tcp"
    )
    assert panda.fk(panda.sample_q(2)).shape == (2, 4, 4)


def test_fit_names_an_unknown_free_label(ur10):
    data, _ = hpk.simulate_campaign(ur10, 30, "joint_offset:elbow_joint=1e-3", noise_mm=0.01)
    model = hpk.ExtendedModel(ur10, [hpk.make_effect(ur10, "joint_offset:elbow_joint")])
    with pytest.raises(HybridPKError, match="free: joint_ofset:elbow_joint not in this model"):
        hpk.fit(model, data, free=["joint_ofset:elbow_joint", "base_frame.rotation"])
    res = hpk.fit(model, data, free="base_frame.translation", covariance=False)  # one label
    assert [b.label for b in res.blocks] == ["base_frame.translation"]


def test_save_model_refuses_a_robot(ur10, tmp_path):
    with pytest.raises(HybridPKError, match="save_model needs an ExtendedModel, got Robot"):
        hpk.save_model(tmp_path / "m.pt", ur10)


def test_hybrid_takes_a_list_of_joints(ur10):
    from hybrid_pk.training import train_hybrid

    data, _ = hpk.simulate_campaign(ur10, 40, "joint_offset:elbow_joint=1e-3", noise_mm=0.01)
    base = hpk.ExtendedModel(ur10, [hpk.make_effect(ur10, "joint_offset:elbow_joint", 1e-3)])
    hybrid = train_hybrid(data, base, max_epochs=1, progress=False).hybrid
    q = [0.1, -0.5, 0.7, 0.0, 0.3, 0.2]
    assert torch.equal(hybrid(q), hybrid(torch.tensor(q, dtype=torch.float64)))


def test_data_of_another_robot_is_refused(ur10):
    rx160 = hpk.Robot.from_urdf("rx160")
    data, _ = hpk.simulate_campaign(rx160, 20, "joint_offset:joint_2=1e-3", noise_mm=0.01)
    with pytest.raises(DataError, match=r"data has joints joint_1.*robot ur10 has shoulder_pan"):
        hpk.diagnose(ur10, data)
    with pytest.raises(DataError, match="a table of another robot"):
        hpk.fit(hpk.ExtendedModel(ur10), data)


@pytest.mark.parametrize("grad", [False, True])
def test_gravity_torques_payload_batch_checked(ur10, grad):
    q = ur10.sample_q(4).requires_grad_(grad)  # plain (fast) path and autograd path
    with pytest.raises(hpk.ShapeError, match=r"payload must be .* found \(3,\)"):
        ur10.gravity_torques(q, payload=torch.ones(3, dtype=torch.float64))
    assert ur10.gravity_torques(q, payload=torch.ones(4, dtype=torch.float64)).shape == (4, 6)


@pytest.mark.parametrize("bad", [{"tol_mm": -1.0}, {"tol_deg": 0.0}, {"max_iterations": 0}])
def test_ik_options_refuse_non_positive_tolerances(bad):
    with pytest.raises(hpk.ShapeError, match=f"IKOptions: {next(iter(bad))} must be > 0"):
        hpk.IKOptions(**bad)
