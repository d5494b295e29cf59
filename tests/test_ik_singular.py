"""IK near singular configurations and joint limits, against EAIK's analytic branches.

Targets are the FK of joint values with a wrist axis 1e-5..1e-3 rad from alignment
(UR10 wrist_2 = 0, RX160 joint_5 = 0), or with each joint within 1e-4 rad of a limit
with probability 0.6 (on the UR10 a 2 pi limit of wrist_2 is also wrist_2 = 0, and an
elbow limit of pi a folded arm). There a solution within the tolerance is pinned to its
branch only to ``tol / sigma`` (``sigma`` the Jacobian's smallest singular value): before
solutions were polished onto their branch, a branch came back twice, several mrad
apart, or not at all (UR10 near limits: 492 of 709 branches; wrist_2 near 0: 350 of 684).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.ik import solve_ik

pytestmark = pytest.mark.usefixtures("one_thread")

N_TARGETS = 60
N_SEEDS = 64
# [m/rad] Branches with a smaller sigma are not asked for: a pose change within the
# tolerance (1e-3 mm) moves them by over a radian, so the solver returns samples of
# that family (UR10: elbow folded within 1e-4 rad of pi while wrist_2 is near 0).
SIGMA_ASKED = 1e-6
# [rad] A solution this far from a branch but not within the distinctness tolerance is
# that branch found only to within the tolerance: listed twice, or in its place.
NEAR_MISS = 0.05


def _sample(robot: hpk.Robot, seed: int) -> tuple[torch.Generator, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    return gen, robot.sample_q(N_TARGETS, gen)


def _near_limits(robot: hpk.Robot, seed: int) -> torch.Tensor:
    gen, q = _sample(robot, seed)
    lo, hi = robot.joint_limits
    pick, upper, depth = (torch.rand(q.shape, generator=gen, dtype=q.dtype) for _ in range(3))
    at = torch.where(upper < 0.5, lo + 1e-4 * depth, hi - 1e-4 * depth)
    return torch.where(pick < 0.6, at, q)


def _near_wrist_singularity(robot: hpk.Robot, seed: int, joint: int) -> torch.Tensor:
    gen, q = _sample(robot, seed)
    u, side = (torch.rand(N_TARGETS, generator=gen, dtype=q.dtype) for _ in range(2))
    q[:, joint] = torch.where(side < 0.5, -1.0, 1.0) * 10 ** (-5 + 2 * u)  # 1e-5..1e-3 rad
    return q


def _wrap(x: np.ndarray) -> np.ndarray:
    return (x + math.pi) % (2 * math.pi) - math.pi


def _compare(robot: hpk.Robot, q: torch.Tensor):
    """Solve the FK targets of ``q``; EAIK's branches within the limits (those with
    ``sigma >= SIGMA_ASKED``), how many a solution matches, and the near misses of
    those."""
    pytest.importorskip("eaik")
    from tests.oracles.eaik_oracle import branch_coverage, eaik_branches

    with torch.no_grad():
        T = robot.fk(q)
    result = solve_ik(robot, T, seeds=N_SEEDS)
    reference = eaik_branches(robot, T)
    asked = []
    for ref in reference:
        J = robot.jacobian(torch.as_tensor(ref)).reshape(-1, 6, robot.dof)
        J = torch.cat([J[:, :3], 0.5 * J[:, 3:]], 1)  # the solver's rotation weight
        asked.append(ref[torch.linalg.svdvals(J)[:, -1].numpy() >= SIGMA_ASKED])
    found = [result.solutions(i).numpy() for i in range(len(q))]
    matched, total, missed = branch_coverage(found, asked)
    near_misses = 0
    for sols, ref in zip(found, asked, strict=True):
        for s in sols:
            d = np.abs(_wrap(ref - s)).max(-1) if len(ref) else np.array([np.inf])
            near_misses += int(d.min() > 1e-3 and d.min() < NEAR_MISS)
    return result, matched, total, missed, near_misses


@pytest.mark.parametrize(
    ("name", "joint", "seed"), [("ur10", 4, 3), ("rx160", 4, 5)], ids=["ur10", "rx160"]
)
def test_every_branch_once_near_a_wrist_singularity(name, joint, seed):
    robot = hpk.Robot.from_urdf(name)
    robot.requires_grad_(False)
    q = _near_wrist_singularity(robot, seed, joint)
    result, matched, total, missed, near_misses = _compare(robot, q)
    assert total >= 3 * N_TARGETS  # the oracle is not trivially empty
    assert matched >= 0.98 * total, f"{name}: {matched}/{total} branches, missed {missed[:3]}"
    assert near_misses == 0, f"{name}: {near_misses} solutions a few mrad off a branch"
    assert result.n_failed == 0


@pytest.mark.parametrize(("name", "seed"), [("ur10", 1), ("rx160", 2)])
def test_every_branch_once_near_joint_limits(name, seed):
    robot = hpk.Robot.from_urdf(name)
    robot.requires_grad_(False)
    result, matched, total, missed, near_misses = _compare(robot, _near_limits(robot, seed))
    assert total >= 3 * N_TARGETS
    # RX160: a branch with three or four joints at their limits at once is rarely seeded
    # (8 of 474 on 100 such targets, found by no start at all): not the polish's part.
    assert matched >= 0.97 * total, f"{name}: {matched}/{total} branches, missed {missed[:3]}"
    assert near_misses == 0, f"{name}: {near_misses} solutions a few mrad off a branch"
    lo, hi = robot.joint_limits
    q = result.q[result.valid]
    assert bool(((q >= lo) & (q <= hi)).all())


def test_targets_at_singular_configurations_are_flagged_in_python():
    """``IKResult.near_singular`` says what the ``ik`` note says (before: only the CLI
    said it): the UR10 home pose (elbow stretched, wrist_2 = 0) and wrist_2 = 1e-4 are
    flagged, wrist_2 = 0.7 and an unreachable target (no solution) are not; the
    two-stage solver carries the flag too."""
    from hybrid_pk.effects import ExtendedModel, make_effect
    from hybrid_pk.ik import solve_ik_two_stage

    robot = hpk.Robot.from_urdf("ur10")
    robot.requires_grad_(False)
    q = torch.tensor(
        [
            [-math.pi, -math.pi / 2, 0.0, -math.pi / 2, 0.0, 0.0],
            [0.3, -1.0, 1.0, 0.5, 1e-4, 0.2],
            [0.3, -1.0, 1.0, 0.5, 0.7, 0.2],
        ],
        dtype=torch.float64,
    )
    with torch.no_grad():
        T = robot.fk(q)
    far = T[2].clone()
    far[:3, 3] = torch.tensor([5.0, 0.0, 0.0], dtype=torch.float64)  # beyond the reach
    T = torch.cat([T, far[None]])
    result = solve_ik(robot, T, seeds=32)
    assert result.near_singular.tolist() == [True, True, False, False]
    sigma = result.smallest_singular_value
    assert sigma.shape == (4,)
    assert bool(torch.isnan(sigma[3]))
    moved_m = sigma * 1e-3  # [m] pose change of a 1e-3 rad joint change along the weakest
    assert float(moved_m[2]) >= result.tol_mm * 1e-3 > float(moved_m[1])
    model = ExtendedModel(robot, [make_effect(robot, "joint_offset:elbow_joint", 2e-4)])
    model.requires_grad_(False)
    with torch.no_grad():
        T2 = model(q).reshape(3, 4, 4)
    two = solve_ik_two_stage(robot, model, T2.reshape(3, 1, 4, 4), seeds=32)
    assert two.near_singular.shape == (3, 1)
    assert two.near_singular[:, 0].tolist() == [True, True, False]
