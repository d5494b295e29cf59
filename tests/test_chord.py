"""A refit that steps with a nearby Jacobian (the diagnosis' score of the effect it
adds, :mod:`hybrid_pk.calibration.chord`) ends where the plain refit ends, with the
same covariance, and builds fewer Jacobians; a Jacobian that lacks a block of the
refit is not used."""

from __future__ import annotations

import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.chord import Linearisation
from hybrid_pk.calibration.diagnosis.variants import with_effects
from hybrid_pk.calibration.fit import fit, initialise_frames
from hybrid_pk.calibration.problem import Problem, param_blocks
from hybrid_pk.effects import ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.simulate import simulate_campaign


def _setup():
    robot = hpk.Robot.from_urdf("rx160")
    robot.requires_grad_(False)
    truth = "joint_compliance:joint_2=2e-6; joint_offset:joint_3=3e-4"
    data, _ = simulate_campaign(
        robot, 400, truth, noise_mm=0.02, noise_deg=0.002, payload=15.0, seed=5
    )
    cond = conditions_from_data(data)
    model = ExtendedModel(robot, [make_effect(robot, "joint_offset:joint_3")])
    initialise_frames(model, data, cond)
    res = fit(model, data, cond=cond)
    return robot, data, cond, model, res


def _near(trial, data, cond, res) -> Linearisation:
    """``[J r]`` chunks of ``trial`` at its values, as the diagnosis' scoring keeps them."""
    blocks = param_blocks(trial, None, False)
    problem = Problem(trial, data, cond, blocks, res.sigma_pos_mm, res.sigma_rot_rad)
    problem.kept = []
    for _ in problem.augmented_chunks(torch.zeros_like(problem.x0)):
        pass
    return Linearisation(problem.kept, blocks, (res.sigma_pos_mm, res.sigma_rot_rad))


def _counted_fit(model, data, cond, res, near):
    calls = []
    original = Problem.augmented_chunks

    def counting(self, theta):
        calls.append(1)
        return original(self, theta)

    Problem.augmented_chunks = counting
    try:
        out = fit(
            model, data, cond=cond, near=near,
            initial_sigma=(res.sigma_pos_mm, res.sigma_rot_rad),
        )  # fmt: skip
    finally:
        Problem.augmented_chunks = original
    return out, len(calls)


def test_refit_stepping_with_the_score_jacobian_ends_where_the_plain_refit_ends():
    robot, data, cond, model, res = _setup()
    label = "joint_compliance:joint_2"
    # the scoring's linearisation: the current model and the candidate at zero
    near = _near(with_effects(model, [make_effect(robot, label)]), data, cond, res)
    plain = with_effects(model, [make_effect(robot, label)])
    chord = with_effects(model, [make_effect(robot, label)])
    res_plain, jac_plain = _counted_fit(plain, data, cond, res, None)
    res_chord, jac_chord = _counted_fit(chord, data, cond, res, near)
    assert res_chord.converged
    assert jac_chord < jac_plain, (jac_chord, jac_plain)
    # the stopping rule's 0.01 std, against the plain refit's own (also within 0.01)
    diff = (res_chord.x - res_plain.x) / res_plain.std
    assert float(diff.abs().max()) < 0.02, diff
    assert torch.allclose(res_chord.std, res_plain.std, rtol=1e-3)
    assert abs(res_chord.sigma_pos_mm / res_plain.sigma_pos_mm - 1) < 1e-3


def test_a_linearisation_without_a_block_of_the_refit_is_not_used():
    robot, data, cond, model, res = _setup()
    near = _near(model, data, cond, res)  # lacks the compliance's column
    new = with_effects(model, [make_effect(robot, "joint_compliance:joint_2")])
    out = fit(new, data, cond=cond, near=near)
    assert near.pass_sigmas is None  # no pass stepped with it
    plain = fit(
        with_effects(model, [make_effect(robot, "joint_compliance:joint_2")]), data, cond=cond
    )
    assert torch.allclose(out.x, plain.x)
