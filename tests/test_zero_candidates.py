"""Candidates at zero change nothing: the model and the Jacobian skip their work and give
the same values, bit for bit (a diagnosis scores ~80 of them at every step)."""

import torch

from hybrid_pk.calibration.loaded_jacobian import loaded_state
from hybrid_pk.effects import Conditions, ExtendedModel, make_effect

# fitted causes (non-zero) and candidates of every built-in joint and geometric law
CAUSES = {
    "link_length:wrist_1_joint": [1e-4, 0.0, -2e-4],
    "cyclic_error_4:shoulder_lift_joint": [1e-4, -2e-4],
    "axis_misalignment:elbow_joint": [3e-4, -1e-4],
    "joint_compliance:shoulder_lift_joint": 2e-6,
}
CANDIDATES = [
    "joint_offset:elbow_joint",
    "gear_ratio:wrist_1_joint",
    "joint_eccentricity:shoulder_lift_joint",
    "cyclic_error_17:shoulder_lift_joint",
    "link_length:elbow_joint",
    "axis_misalignment:wrist_1_joint",
]


def _model(robot, candidates=()):
    effects = [make_effect(robot, k, v) for k, v in CAUSES.items()]
    return ExtendedModel(robot, effects + [make_effect(robot, c) for c in candidates])


def test_inert_is_a_built_in_law_at_exactly_zero_with_plain_values(ur10):
    e = make_effect(ur10, "cyclic_error_17:shoulder_lift_joint")
    assert not e.inert()  # its value may carry a derivative (grad mode, requires_grad)
    with torch.no_grad():
        assert e.inert()
        assert not make_effect(ur10, "backlash:elbow_joint").inert()  # reads the direction
        assert not make_effect(ur10, "thermal_expansion").inert()  # reads the temperature
        e.value.fill_(1e-9)
        assert not e.inert()


def test_candidates_at_zero_leave_joint_values_and_parameters_bit_for_bit(ur10):
    q = ur10.sample_q(64, torch.Generator().manual_seed(3))
    cond = Conditions(payload=torch.full((64,), 2.0, dtype=torch.float64))
    plain, scored = _model(ur10), _model(ur10, CANDIDATES)
    with torch.no_grad():
        q_kin = plain.kinematic_joint_values(q, cond)
        assert torch.equal(q_kin, scored.kinematic_joint_values(q, cond))
        for a, b in zip(plain.kinematic_params(cond), scored.kinematic_params(cond), strict=True):
            assert torch.equal(a, b)
        assert torch.equal(plain(q, cond), scored(q, cond))


def test_loaded_state_hands_on_the_wrench_frames_where_nothing_bends(ur10):
    q = ur10.sample_q(32, torch.Generator().manual_seed(4))
    cond = Conditions(payload=torch.full((32,), 5.0, dtype=torch.float64))
    model = ExtendedModel(ur10, [make_effect(ur10, "tilt_compliance:elbow_joint")])
    with torch.no_grad():
        params, gravity, q_star, wrenches, bent, frames = loaded_state(model, q, cond)
        assert bent is params  # the tilt at zero bends nothing
        assert torch.equal(frames, ur10.link_frames(q_star, params))
        load = (q_star, cond.payload, gravity, params, "joint")
        assert torch.equal(ur10.static_wrenches(*load, frames), wrenches)
        assert torch.equal(ur10.static_wrenches(*load), wrenches)
        model.effects[0].value.fill_(1e-6)
        *_, bent, frames = loaded_state(model, q, cond)
        assert bent is not params
        assert frames is None  # bent: the pose needs frames of its own
