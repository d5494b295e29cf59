"""The fit's least-squares problem: its structured, chunked Jacobian against forward-mode
autodiff through the whole model, and the reductions (normal equations, R factor) and
linearised updates the diagnosis builds on it."""

from __future__ import annotations

import math

import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.diagnosis.selection import candidate_labels
from hybrid_pk.calibration.diagnosis.statistics import neighbour_structure
from hybrid_pk.calibration.diagnosis.variants import (
    linearised_removal,
    refit_without,
    without_effect,
)
from hybrid_pk.calibration.fit import fit, initialise_frames
from hybrid_pk.calibration.least_squares import jacobian
from hybrid_pk.calibration.problem import Problem, param_blocks
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.simulate import simulate_campaign


def _campaign(robot, n, *, position_only=False, files=1, seed=0):
    effects = [
        make_effect(robot, f"joint_compliance:{robot.joint_names[1]}", 2e-6),
        make_effect(robot, f"joint_offset:{robot.joint_names[2]}", 3e-4),
    ]
    parts = []
    for f in range(files):
        data, _ = simulate_campaign(
            robot,
            n,
            effects,
            noise_mm=0.02,
            noise_deg=0.0 if position_only else 0.002,
            position_only=position_only,
            payload=10.0 + 5 * f,
            temperature_range=(20.0 + f, 28.0),
            seed=seed + f,
        )
        parts.append(MeasuredData(**{**data.__dict__, "sources": (f"file{f}",)}))
    return parts[0] if files == 1 else MeasuredData.concat(parts)


def _perturbed_model(robot, data, sets):
    """One candidate of every effect kind (two compliances) at a random value, frames
    away from identity."""
    g = torch.Generator().manual_seed(1)
    labels, kinds = [], {}
    for c in candidate_labels(robot, data):
        kind = c.split(":")[0]
        kinds[kind] = kinds.get(kind, 0) + 1
        if kinds[kind] == 2 or (kind == "joint_compliance" and kinds[kind] == 3):
            labels.append(c)
        elif kind == "thermal_expansion":
            labels.append(c)
    model = ExtendedModel(robot, [make_effect(robot, c) for c in labels], frame_sets=sets)
    with torch.no_grad():
        for e in model.effects:
            e.value.copy_(0.5 * e.scale * torch.randn(e.value.shape, generator=g))
        R = hpk.geometry.so3_exp(torch.tensor([0.1, -0.2, 1.3], dtype=torch.float64))
        model.base.reset_to(hpk.geometry.transform(R, torch.tensor([1.0, 0.2, -0.3])))
        for p in (model.base.rotvec, model.tool.rotvec, model.tool.dp):
            p.copy_(0.02 * torch.randn(p.shape, generator=g, dtype=p.dtype))
    return model


def _stage(model, block) -> str | None:
    """The effect stage of a parameter block (None for the frames)."""
    if not block.name.startswith("effects."):
        return None
    return model.effects[int(block.name.split(".")[1])].stage


@pytest.mark.parametrize(
    ("robot_name", "position_only", "files"),
    [("rx160", False, 1), ("ur10", False, 2), ("ur10", True, 1)],
)
def test_structured_jacobian_matches_forward_mode_through_the_model(
    robot_name, position_only, files
):
    robot = hpk.Robot.from_urdf(robot_name)
    robot.requires_grad_(False)
    data = _campaign(robot, 60, position_only=position_only, files=files)
    model = _perturbed_model(robot, data, files)
    cond = conditions_from_data(data, files > 1)
    blocks = param_blocks(model, None, position_only)
    problem = Problem(model, data, cond, blocks, 0.03, 2e-4, chunk_rows=25)
    theta = 0.1 * torch.randn(problem.x0.numel(), generator=torch.Generator().manual_seed(2))
    theta = theta.to(torch.float64)
    r_ref, J_ref = jacobian(problem.residual, theta)
    r, J = problem.jacobian(theta)
    assert torch.allclose(r, r_ref, rtol=0, atol=1e-12 * float(r_ref.abs().max()))
    col_err = (J - J_ref).norm(dim=0) / J_ref.norm(dim=0).clamp_min(1e-12)
    # Frames and deflections: exact. Effects that move a joint (offsets, gear ratios,
    # compliances, ...) leave out how that joint changes the loads the compliances and
    # deflections see (c dtau/dq relative: 1e-6 to 2e-5 here, with 1e-7 to 5e-7 rad/Nm),
    # and the reference differentiates only the last two compliance fixed-point steps
    # (ExtendedModel.joint_values: ~(c dg/dq)^2 relative).
    stages = [_stage(model, b) for b in blocks for _ in range(b.size)]
    exact = torch.tensor([s in (None, "deflection") for s in stages])
    moves = torch.tensor([s in ("joint", "compliance") for s in stages])
    geometric = torch.tensor([s == "geometry" for s in stages])
    assert float(col_err[exact].max()) < 1e-9, float(col_err[exact].max())
    assert float(col_err[moves].max()) < 1e-4, float(col_err[moves].max())
    # Geometric effects ignore their second-order coupling through the gravity torques.
    assert float(col_err[geometric].max()) < 1e-3, float(col_err[geometric].max())
    # The chunked reductions are the same products of the same rows.
    A, g, cost = problem.normal_equations(theta)
    assert torch.allclose(A, J.T @ J, rtol=1e-10, atol=1e-10 * float(A.abs().max()))
    assert torch.allclose(g, J.T @ r, rtol=1e-10, atol=1e-10 * float(g.abs().max()))
    assert math.isclose(cost, float(r @ r), rel_tol=1e-12)
    R = problem.r_factor(theta)
    M = torch.cat([J, r[:, None]], 1)
    assert torch.allclose(R.T @ R, M.T @ M, rtol=1e-9, atol=1e-9 * float((M.T @ M).abs().max()))


def test_row_weights_scale_residuals_and_jacobian_rows():
    robot = hpk.Robot.from_urdf("rx160")
    robot.requires_grad_(False)
    data = _campaign(robot, 40)
    model = _perturbed_model(robot, data, 1)
    cond = conditions_from_data(data)
    blocks = param_blocks(model, None, False)
    w = torch.rand(data.n, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    plain = Problem(model, data, cond, blocks, 0.03, 2e-4)
    weighted = Problem(model, data, cond, blocks, 0.03, 2e-4, row_weights=w)
    theta = torch.zeros(plain.x0.numel(), dtype=torch.float64)
    r0, J0 = plain.jacobian(theta)
    r1, J1 = weighted.jacobian(theta)
    w_res = w.repeat_interleave(3).repeat(2)  # position rows then rotation rows
    assert torch.allclose(r1, w_res * r0)
    assert torch.allclose(J1, w_res[:, None] * J0)


def test_linearised_removal_predicts_the_refit():
    """The Wald statistic of removing an effect and the refit's sum of squares agree
    (the diagnosis keeps a clearly significant cause on the linearised one)."""
    robot = hpk.Robot.from_urdf("rx160")
    robot.requires_grad_(False)
    data = _campaign(robot, 400, seed=5)
    cond = conditions_from_data(data)
    model = ExtendedModel(
        robot,
        [
            make_effect(robot, "joint_compliance:joint_2"),
            make_effect(robot, "joint_offset:joint_3"),
        ],
    )
    initialise_frames(model, data, cond)
    res = fit(model, data, cond=cond)
    problem = Problem(model, data, cond, res.blocks, res.sigma_pos_mm, res.sigma_rot_rad)
    ssr_full = float(problem.residual(torch.zeros_like(problem.x0)).square().sum())
    for label in ("joint_compliance:joint_2", "joint_offset:joint_3"):
        increase, _ = linearised_removal(res, label)
        reduced = refit_without(model, label, data, cond, res)
        blocks = param_blocks(reduced, None, False)
        p = Problem(reduced, data, cond, blocks, res.sigma_pos_mm, res.sigma_rot_rad)
        ssr_red = float(p.residual(torch.zeros_like(p.x0)).square().sum())
        assert increase > 100.0  # both effects are strongly present
        assert abs(increase - (ssr_red - ssr_full)) < 0.01 * increase, (label, increase)
    assert len(without_effect(model, "joint_offset:joint_3").effects) == 1


def test_neighbour_structure_in_blocks_equals_full_distance_matrix():
    from hybrid_pk.calibration.diagnosis import statistics

    g = torch.Generator().manual_seed(4)
    q = torch.rand(700, 6, generator=g, dtype=torch.float64)
    residual = torch.randn(700, 3, generator=g, dtype=torch.float64)
    lower, upper = torch.zeros(6, dtype=torch.float64), torch.ones(6, dtype=torch.float64)
    block = statistics.NEIGHBOUR_BLOCK
    try:
        statistics.NEIGHBOUR_BLOCK = 64
        small = neighbour_structure(residual, q, lower, upper)
    finally:
        statistics.NEIGHBOUR_BLOCK = block
    assert small == neighbour_structure(residual, q, lower, upper)
    d = torch.cdist(q, q)
    d.fill_diagonal_(math.inf)
    b = residual - residual.mean(0)
    nn = b[d.argmin(1)]
    assert math.isclose(small[1], float((b * nn).sum() / (b.norm() * nn.norm())), rel_tol=1e-12)


def test_progress_reports_every_inner_step():
    """hybrid-pk shows the latest inner step: the selection step, the candidate under
    test, each LM iteration of its refit, each cause's gain (measured from its
    linearised removal: no LM iteration of its own).

    Both of the campaign's effects are candidates: since selection by what carries
    over, the offset alone (the larger compliance unmodelled) does not improve the
    blocked hold-out, so it is named only next to the compliance."""
    robot = hpk.Robot.from_urdf("rx160")
    robot.requires_grad_(False)
    data = _campaign(robot, 300, seed=7)
    messages: list[str] = []
    both = ["joint_compliance:joint_2", "joint_offset:joint_3"]
    diag = hpk.diagnose(robot, data, candidates=both, progress=messages.append)
    assert sorted(f"{c.effect}:{c.joint}" for c in diag.causes) == both
    assert "scoring 2 candidate effects (step 1)" in messages
    assert "scoring 1 candidate effects (step 2)" in messages
    assert "testing joint_offset:joint_3" in messages
    assert any(m.startswith("testing joint_offset:joint_3: LM iteration 1: cost") for m in messages)
    assert any(m.startswith("frames: LM iteration") for m in messages)
    assert "gain of joint_offset:joint_3" in messages
    fit_messages: list[str] = []
    model = ExtendedModel(robot)
    cond = conditions_from_data(data)
    initialise_frames(model, data, cond)
    fit(model, data, cond=cond, progress=fit_messages.append)
    assert fit_messages
    assert all(m.startswith("LM iteration") for m in fit_messages)
