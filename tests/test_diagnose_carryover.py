"""Selection by what carries over: the blocked hold-out and its practical margin.

A cause is named only if it lowers the error of rows held out in blocks (regions of
joint space, whole files) by the practical margin; a cyclic order another order
predicts as well is never named. Campaigns drawn at random per run
(``tests.helpers.run_rng``).
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.diagnosis.blocked import Blocked, BlockedScore, Folds, practical_margin
from hybrid_pk.calibration.diagnosis.search import diagnose
from hybrid_pk.calibration.problem import ParamBlock
from hybrid_pk.simulate import simulate_campaign
from tests.helpers import RUN_SEED, banded_poses, cyclic_campaign, run_rng, smooth_field

pytestmark = pytest.mark.slow


def _ur10() -> hpk.Robot:
    robot = hpk.Robot.from_urdf("ur10")
    robot.requires_grad_(False)
    return robot


def test_linearised_blocked_score_matches_refits_per_block():
    """The blocked score of a linear least-squares problem, from cell Grams, equals the
    direct refit on each block's training rows and its prediction of the block."""
    rng = run_rng("blocked-linear")
    n, p = int(rng.integers(200, 400)), int(rng.integers(2, 6))
    J = torch.as_tensor(rng.normal(size=(n, p)))
    r = torch.as_tensor(rng.normal(size=n))
    cell = torch.as_tensor(rng.integers(0, 4, n))
    grams = torch.zeros(4, p + 1, p + 1, dtype=J.dtype)
    for c in range(4):
        M = torch.cat([J, r[:, None]], 1)[cell == c]
        grams[c] = M.T @ M
    folds = Folds(cell, 4, ((0,), (1,), (2,), (3,)), {})
    blocks = (ParamBlock("x", "x", p, 1.0, "m"),)
    b = Blocked(grams, None, folds, blocks, torch.zeros(p, dtype=J.dtype), (1.0, None))
    score = b.score(torch.ones(p, dtype=torch.bool))
    per_block = []
    for c in range(4):
        train, test = cell != c, cell == c
        theta = -torch.linalg.lstsq(J[train], r[train, None]).solution[:, 0]
        per_block.append(float((r[test] + J[test] @ theta).pow(2).sum()))
    want = sum(per_block)
    assert abs(score.total - want) <= 1e-9 * want
    for (total, _, rows), direct, c in zip(score.per_fold, per_block, range(4), strict=True):
        assert abs(total - direct) <= 1e-9 * want
        assert rows == int((cell == c).sum())
    # against the model at the linearisation point (nothing re-fitted): the drop per
    # block is that block's RMS before minus after, and blocks_gained counts them
    nothing = b.score(torch.zeros(p, dtype=torch.bool))
    drops = b.block_drops(nothing, score)
    pairs = zip(drops, nothing.per_fold, score.per_fold, strict=True)
    for d, (before, _, n_c), (after, _, _) in pairs:
        assert d == pytest.approx(math.sqrt(before / n_c) - math.sqrt(after / n_c), rel=1e-12)
    assert b.parts(nothing, score)["blocks_gained"] == sum(d > 0 for d in drops)
    assert b.parts(nothing, score)["blocks"] == 4
    # no block held out (the whole campaign as one cell): nothing to score
    whole = dataclasses.replace(b, folds=Folds(cell, 4, (), {}))
    assert whole.score(torch.ones(p, dtype=torch.bool)) == BlockedScore(0.0, 0.0, None, 0)


def test_an_unresolved_cyclic_order_is_never_named():
    """A cyclic error of the UR10's shoulder lift or elbow, measured over 1 rad of the
    joint, moving the point by about the noise: neighbouring orders predict the
    held-out regions as well, so no cyclic error is named (it is listed as ambiguous
    or gains too little to be one)."""
    rng = run_rng("unresolved-cyclic")
    robot = _ur10()
    j, order, noise, q = banded_poses(robot, rng, (6, 30), 1.0)
    data, label, amp = cyclic_campaign(robot, q, j, order, (0.7, 1.5), noise, rng)
    diag = diagnose(robot, data, seed=RUN_SEED % 1000)
    where = f"seed {RUN_SEED}: {label}, {amp * 1e6:.1f} µrad, noise {noise:.3f} mm"
    named = [f"{c.effect}:{c.joint}" for c in diag.causes]
    assert not [c for c in named if c.startswith("cyclic_error_")], (where, named, diag.steps)


@pytest.mark.parametrize("robot_name", ["rx160", "ur10"])
def test_null_campaign_with_coloured_residuals_names_at_most_one_cause(robot_name):
    """No effect of the vocabulary, a smooth unmodelled field of 0.05 mm and white
    noise: at most one cause, and none below the practical margin on the blocked
    hold-out."""
    rng = run_rng(f"coloured-null-{robot_name}")
    robot = hpk.Robot.from_urdf(robot_name)
    robot.requires_grad_(False)
    n = int(rng.integers(1500, 3001))
    noise = float(rng.uniform(0.01, 0.03))
    data, _ = simulate_campaign(
        robot, n, [], noise_mm=noise, noise_deg=noise / 10, trajectory="random",
        seed=int(rng.integers(1 << 30)),
    )  # fmt: skip
    data = dataclasses.replace(data, position=data.position + smooth_field(data.q, 0.05, rng))
    diag = diagnose(robot, data, seed=RUN_SEED % 1000)
    js = diag.to_json()
    margin = js["carry_over"]["min_gain_mm"]
    where = f"seed {RUN_SEED}, {robot_name}, n={n}, noise {noise:.3f} mm"
    assert len(diag.causes) <= 1, (where, [c.to_json() for c in diag.causes])
    for c in diag.causes:
        assert c.blocked_holdout_gain_mm >= margin, (where, c.to_json(), margin)


@pytest.mark.parametrize("robot_name", ["rx160", "ur10"])
def test_repeated_poses_lower_the_margin_to_the_noise_and_no_cause_appears(robot_name):
    """The coloured null campaign with a tenth of its poses measured twice: the
    model-free noise (close pairs) sees the white noise, not the 0.05 mm field the fit's
    sigma holds, so the margin is the noise / 10; still at most one cause, and none
    below that margin."""
    rng = run_rng(f"coloured-null-repeats-{robot_name}")
    robot = hpk.Robot.from_urdf(robot_name)
    robot.requires_grad_(False)
    n = int(rng.integers(1500, 3001))
    noise = float(rng.uniform(0.005, 0.015))
    g = torch.Generator().manual_seed(int(rng.integers(1 << 30)))
    q = robot.sample_q(n, g)
    q = torch.cat([q, q[torch.randperm(n, generator=g)[: n // 10]]])
    data, _ = simulate_campaign(
        robot, None, [], poses=q, noise_mm=noise, noise_deg=noise / 10,
        seed=int(rng.integers(1 << 30)),
    )  # fmt: skip
    data = dataclasses.replace(data, position=data.position + smooth_field(data.q, 0.05, rng))
    diag = diagnose(robot, data, seed=RUN_SEED % 1000)
    carry = diag.to_json()["carry_over"]
    where = f"seed {RUN_SEED}, {robot_name}, n={n}, noise {noise:.4f} mm, {carry['noise']}"
    assert abs(carry["noise"]["sigma_mm"] / noise - 1) <= 0.3, where
    assert carry["fit_sigma_mm"] > 1.3 * noise, where  # the field is in the fit's sigma
    assert carry["min_gain_mm"] == pytest.approx(carry["noise"]["sigma_mm"] / 10), where
    assert len(diag.causes) <= 1, (where, [c.to_json() for c in diag.causes])
    for c in diag.causes:
        assert c.blocked_holdout_gain_mm >= carry["min_gain_mm"], (where, c.to_json())


def test_default_margin_is_the_standard_error_of_a_50_pose_check():
    rng = run_rng("margin")
    sigma = float(rng.uniform(0.005, 1.0))
    assert practical_margin(sigma) == pytest.approx(sigma / 10)
    assert practical_margin(sigma, 0.25) == 0.25


def test_unresolved_orders_are_printed_per_joint():
    """Entries of orders that predict as well as each other, as the search and settle
    write them, print as one line per joint with the orders ascending; other
    ambiguities stay one line each."""
    from hybrid_pk.calibration.diagnosis.settle import order_groups, unresolved_entry
    from hybrid_pk.cli.diagnose_cmd import ambiguous_lines

    rng = run_rng("order-groups")
    joints = ["elbow_joint", "wrist_3_joint"]
    want: dict[str, set[int]] = {}
    ambiguous = [{"effects": ["joint_offset:shoulder_pan_joint", "base_frame"], "why": "."}]
    for joint in joints:
        orders = [int(o) for o in rng.choice(range(2, 37), int(rng.integers(2, 6)), False)]
        rivals = {f"cyclic_error_{o}:{joint}": float(rng.normal(0, 1e-3)) for o in orders[1:]}
        ambiguous += unresolved_entry(f"cyclic_error_{orders[0]}:{joint}", rivals, 1e-3)
        want[joint] = set(orders)
    groups, others = order_groups(ambiguous)
    assert groups == {j: sorted(o) for j, o in want.items()}
    assert others == ambiguous[:1]
    lines = ambiguous_lines(ambiguous)
    assert lines[:2] == ["ambiguous (1):", "  joint_offset:shoulder_pan_joint ~ base_frame"]
    for joint in joints:
        assert f"  {joint}: {', '.join(map(str, sorted(want[joint])))} per turn" in lines
    assert ambiguous_lines([]) == []
