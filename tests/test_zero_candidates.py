"""Candidates at zero change nothing: the model and the Jacobian skip their work and give
the same values, bit for bit (a diagnosis scores ~80 of them at every step)."""

import torch

from hybrid_pk.calibration.least_squares import jacobian
from hybrid_pk.calibration.loaded_jacobian import loaded_state
from hybrid_pk.calibration.problem import Problem, param_blocks
from hybrid_pk.effects import Conditions, ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.simulate import simulate_campaign

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


def test_columns_of_zero_candidates_match_forward_mode(ur10):
    """The shortcuts taken at zero (a deflection's left Jacobian of exp(0) = I, a thermal
    expansion's origins that do not turn, its one direction pushed forward without
    batching) give the columns forward mode through the whole model gives."""
    zero = ["tilt_compliance:elbow_joint", "tilt_compliance:wrist_1_joint", "thermal_expansion"]
    fitted = [make_effect(ur10, k, v) for k, v in CAUSES.items() if "compliance" not in k]
    model = ExtendedModel(ur10, fitted + [make_effect(ur10, c) for c in CANDIDATES + zero])
    data, _ = simulate_campaign(
        ur10, 40, [], noise_mm=0.0, payload=8.0, temperature_range=(18.0, 27.0), seed=5
    )
    cond = conditions_from_data(data, False)
    problem = Problem(
        model, data, cond, param_blocks(model, None, False), 0.03, 2e-4, chunk_rows=16
    )
    theta = torch.zeros_like(problem.x0)
    r_ref, J_ref = jacobian(problem.residual, theta)
    r, J = problem.jacobian(theta)
    assert torch.equal(r, r_ref)
    err = (J - J_ref).norm(dim=0) / J_ref.norm(dim=0).clamp_min(1e-12)
    assert float(err.max()) < 1e-9, float(err.max())  # no compliance: every column exact
