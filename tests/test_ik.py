"""IK: branch coverage against EAIK, accuracy, limits, failures, singularities, shapes,
deduplication (contract section 6), and the two-stage solver on expensive models."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.effects import ExtendedModel, make_effect
from hybrid_pk.errors import HybridPKError, ShapeError
from hybrid_pk.evaluation.metrics import pose_error
from hybrid_pk.geometry import so3_exp, transform
from hybrid_pk.ik import (
    IKOptions,
    as_ik_model,
    distinct_mask,
    quasi_random_seeds,
    same_solution,
    solve_ik,
    solve_ik_two_stage,
    wang_baseline,
)
from hybrid_pk.ik.forward_model import autograd_pose_jacobian
from hybrid_pk.robot.kernel import ChainKernel
from tests.helpers import BATCH_SHAPES

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64
ROBOTS = ("ur10", "rx160")
ARM7 = Path(__file__).resolve().parent / "data" / "arm7_generic.urdf"
N_TARGETS = 200
N_SEEDS = 64
TOL_MM, TOL_DEG = 1e-3, 1e-3


@pytest.fixture(scope="module")
def robots() -> dict[str, hpk.Robot]:
    out = {name: hpk.Robot.from_urdf(name) for name in ROBOTS}
    out["arm7"] = hpk.Robot.from_urdf(ARM7, end_link="tool0")
    for r in out.values():
        r.requires_grad_(False)
    return out


def _vec(*v: float) -> torch.Tensor:
    return torch.tensor(v, dtype=F64)


def _targets(robot: hpk.Robot, n: int, seed: int) -> torch.Tensor:
    q = robot.sample_q(n, torch.Generator().manual_seed(seed))
    with torch.no_grad():
        return robot.fk(q)


def _assert_valid(robot: hpk.Robot, result, T: torch.Tensor) -> None:
    """Every returned solution: finite, within limits, and within tolerance by our FK."""
    q = result.q[result.valid]
    assert q.numel() > 0
    assert bool(torch.isfinite(q).all())
    lo, hi = robot.joint_limits
    assert bool(((q >= lo) & (q <= hi)).all()), "a solution violates the joint limits"
    target_of = T.expand(*result.valid.shape, 4, 4)[result.valid]
    with torch.no_grad():
        err = pose_error(target_of, robot.fk(q))
    assert float(err.position_mm.max()) <= TOL_MM
    assert float(err.orientation_deg.max()) <= TOL_DEG
    # The reported errors are the errors.
    assert torch.allclose(result.position_error_mm[result.valid], err.position_mm, atol=1e-9)


# ----------------------------------------------------------------------------- kernel


@pytest.mark.parametrize("name", [*ROBOTS, "arm7"])
def test_kernel_matches_robot_fk_and_jacobian(robots, name):
    robot = robots[name]
    q = robot.sample_q(64, torch.Generator().manual_seed(0))
    T, J = ChainKernel(robot)(q)
    with torch.no_grad():
        assert torch.allclose(T, robot.fk(q), atol=1e-12)
        assert torch.allclose(J, robot.jacobian(q), atol=1e-12)


def test_kernel_with_frames_matches_autograd_jacobian(robots):
    robot = robots["arm7"]  # has a prismatic joint
    base = transform(so3_exp(_vec(0.1, -0.2, 1.0)), _vec(1.0, 1.0, 1.0))
    tool = transform(so3_exp(_vec(0.3, 0.1, 0.0)), _vec(0.02, 0.0, 0.1))
    q = robot.sample_q(32, torch.Generator().manual_seed(1))
    T, J = ChainKernel(robot, base, tool)(q)
    T_ad, J_ad = autograd_pose_jacobian(lambda x, rows: base @ robot.fk(x) @ tool, q, None)
    assert torch.allclose(T, T_ad, atol=1e-12)
    assert torch.allclose(J, J_ad, atol=1e-12)


# ----------------------------------------------------------------------------- coverage


@pytest.mark.parametrize("name", ROBOTS)
def test_all_analytic_branches_found_within_limits_and_tolerance(robots, name):
    pytest.importorskip("eaik")
    from tests.oracles.eaik_oracle import branch_coverage, eaik_branches

    robot = robots[name]
    T = _targets(robot, N_TARGETS, seed=11)
    result = solve_ik(robot, T, seeds=N_SEEDS)  # its speed: bench/ik.py
    reference = eaik_branches(robot, T)
    found = [result.solutions(i).numpy() for i in range(N_TARGETS)]
    matched, total, missed = branch_coverage(found, reference)
    assert total >= 4 * N_TARGETS  # the oracle is not trivially empty
    assert matched >= 0.99 * total, f"{name}: {matched}/{total} branches, missed {missed[:3]}"
    assert result.n_failed == 0
    _assert_valid(robot, result, T[:, None])
    # Distinct as the contract defines: no two solutions of a target are the same.
    for sols in found:
        s = torch.as_tensor(sols)
        same = same_solution(s[:, None], s[None, :], robot.revolute)
        assert int(same.sum()) == len(sols)


def test_redundant_arm_with_prismatic_joint(robots):
    robot = robots["arm7"]
    T = _targets(robot, 20, seed=3)
    result = solve_ik(robot, T, seeds=32)
    assert result.n_failed == 0
    _assert_valid(robot, result, T[:, None])
    # 7 joints for 6 constraints: a self-motion manifold, so many distinct solutions.
    assert float(result.counts.double().mean()) > 4


# ----------------------------------------------------------------------------- failures


@pytest.mark.parametrize("name", ROBOTS)
def test_unreachable_targets_are_failures_never_wrong_solutions(robots, name):
    robot = robots[name]
    T = _targets(robot, 6, seed=5)
    far = T[:3].clone()
    far[:, :3, 3] *= 10.0  # ~10 m away: far outside the reach
    beyond = T[3:].clone()
    beyond[:, :3, 3] += torch.tensor([0.0, 0.0, 5.0], dtype=F64)
    result = solve_ik(robot, torch.cat([far, beyond, T[:2]]), seeds=16)
    assert result.failed.tolist() == [True] * 6 + [False] * 2
    assert result.counts[:6].sum() == 0
    assert bool(torch.isnan(result.q[:6]).all())  # empty slots are padding, not solutions
    _assert_valid(robot, result, torch.cat([far, beyond, T[:2]])[:, None])


def test_tolerance_below_float64_precision_gives_no_false_positives(robots):
    robot = robots["rx160"]
    T = _targets(robot, 4, seed=8)
    result = solve_ik(robot, T, seeds=16, options=IKOptions(tol_mm=1e-3, tol_deg=1e-3))
    assert result.n_failed == 0
    # Tighter than float64 round-off: whatever is returned meets it, the rest fails.
    strict = solve_ik(robot, T, seeds=16, options=IKOptions(tol_mm=1e-14, tol_deg=1e-14))
    assert bool((strict.position_error_mm[strict.valid] <= 1e-14).all())


# ----------------------------------------------------------------------------- singularities


def _ur10_shoulder_singular(robot: hpk.Robot) -> torch.Tensor:
    """A UR10 configuration with the shoulder singularity (wrist over the base axis):
    the root of det J in joint 2 with the elbow and wrist away from their singularities
    (det J = 0 there can only be the shoulder factor)."""

    def q_of(x: float) -> torch.Tensor:
        return torch.tensor([0.3, x, 1.5, -0.5, 1.0, 0.4], dtype=F64)

    def det(x: float) -> float:
        with torch.no_grad():
            return float(torch.linalg.det(robot.jacobian(q_of(x))))

    a, b = 0.0, 1.5  # det changes sign in between (checked below)
    assert det(a) * det(b) < 0
    for _ in range(60):
        m = (a + b) / 2
        a, b = (a, m) if det(a) * det(m) <= 0 else (m, b)
    q = q_of(a)
    assert float(torch.linalg.svdvals(robot.jacobian(q)).min()) < 1e-12
    return q


def test_singular_configurations_give_no_nan(robots):
    rx, ur = robots["rx160"], robots["ur10"]
    q_rx = rx.sample_q(8, torch.Generator().manual_seed(2))
    q_rx[:, 4] = 0.0  # RX160 wrist singular: axes 4 and 6 aligned
    q_ur = ur.sample_q(8, torch.Generator().manual_seed(3))
    q_ur[:4, 4] = 0.0  # UR10 wrist singularity
    q_ur[4:7, 2] = 0.0  # UR10 elbow stretched
    q_ur[7] = _ur10_shoulder_singular(ur)
    for robot, q in ((rx, q_rx), (ur, q_ur)):
        with torch.no_grad():
            T = robot.fk(q)
        # The singular configurations themselves as seeds too: J is singular there.
        result = solve_ik(robot, T, seeds=32, extra_seeds=q[:, None, :])
        assert result.n_failed == 0
        _assert_valid(robot, result, T[:, None])
        assert bool(torch.isfinite(result.position_error_mm[result.valid]).all())


def test_no_targets_and_all_unreachable_in_two_stages(robots):
    robot = robots["rx160"]
    empty = solve_ik(robot, torch.zeros(0, 4, 4, dtype=F64))
    assert empty.q.shape == (0, 0, 6)
    assert len(empty.to_frame()) == 0
    far = torch.eye(4, dtype=F64).repeat(2, 1, 1)
    far[:, :3, 3] = 9.0
    result = solve_ik_two_stage(robot, lambda q: robot.fk(q), far, robot=robot, seeds=4)
    assert result.failed.tolist() == [True, True]
    wang = wang_baseline(robot, lambda q: robot.fk(q), far, robot=robot, seeds=4)
    assert int(wang.valid.sum()) == 0


def test_degenerate_model_with_zero_jacobian_does_not_crash(robots):
    robot = robots["rx160"]
    fixed = robot.fk(torch.zeros(6, dtype=F64))

    def frozen(q):  # every configuration gives the same pose: J = 0, J^T J singular
        return fixed.expand(*q.shape[:-1], 4, 4) + 0 * q.sum(-1)[..., None, None]

    T = _targets(robot, 3, seed=4)
    result = solve_ik(frozen, T, robot=robot, seeds=8)
    assert result.n_failed == 3
    same = solve_ik(frozen, fixed, robot=robot, seeds=8)  # everything solves it
    assert not bool(same.failed)


def test_model_returning_nan_is_rejected_not_returned(robots):
    robot = robots["ur10"]

    def partly_nan(q):
        T = robot.fk(q)
        return torch.where((q[..., :1, None] > 0), T, torch.nan)

    T = _targets(robot, 4, seed=9)
    result = solve_ik(partly_nan, T, robot=robot, seeds=16)
    q = result.q[result.valid]
    assert bool(torch.isfinite(q).all())
    assert bool((q[:, 0] > 0).all())
    # the half of joint space where the model is finite still gives every target its
    # solutions there (joint 1 spans two turns: each target has some with q1 > 0)
    assert bool((result.valid.sum(-1) > 0).all()), result.valid.sum(-1)


# ----------------------------------------------------------------------------- shapes


@pytest.mark.parametrize("shape", BATCH_SHAPES, ids=str)
def test_batch_shapes(robots, shape):
    robot = robots["rx160"]
    n = math.prod(shape)
    T = _targets(robot, n, seed=6).reshape(*shape, 4, 4)
    result = solve_ik(robot, T, seeds=16)
    k = result.q.shape[-2]
    assert result.q.shape == (*shape, k, 6)
    assert result.valid.shape == result.position_error_mm.shape == (*shape, k)
    assert result.counts.shape == result.failed.shape == shape
    assert result.batch_shape == shape
    frame = result.to_frame()
    assert len(frame) == int(result.counts.sum())
    assert list(frame.columns) == [
        "target",
        "solution",
        *robot.joint_names,
        "position_error_mm",
        "orientation_error_deg",
    ]
    assert set(frame["target"]) == set(range(n))


def test_position_only_targets(robots):
    robot = robots["ur10"]
    T = _targets(robot, 5, seed=10)
    result = solve_ik(robot, T[:, :3, 3], seeds=16)
    assert result.position_only
    assert result.n_failed == 0
    assert bool(torch.isnan(result.orientation_error_deg).all())
    with torch.no_grad():
        p = robot.fk(result.q[result.valid])[:, :3, 3]
    target = T[:, None, :3, 3].expand(*result.valid.shape, 3)[result.valid]
    assert float((p - target).norm(dim=-1).max()) <= TOL_MM * 1e-3


def test_results_and_the_model_stay_usable_by_autograd(robots):
    """The chain kernel's iterations run in inference mode: nothing of it may leak into
    the result or into the model's caches (a fresh robot, its caches first filled by
    the solver, then used by autograd)."""
    T = _targets(robots["ur10"], 3, seed=13)
    robot = hpk.Robot.from_urdf("ur10")
    robot.requires_grad_(False)
    result = solve_ik(robot, T, seeds=8)
    fields = (result.q, result.valid, result.position_error_mm, result.orientation_error_deg)
    assert not any(t.is_inference() for t in fields)
    q = result.q[result.valid][:1].clone().requires_grad_(True)
    robot.fk(q)[..., :3, 3].sum().backward()  # cached chain constants saved for backward
    assert q.grad is not None
    assert bool(torch.isfinite(q.grad).all())


def test_extra_seeds_alone_find_the_seeded_branch(robots):
    robot = robots["rx160"]
    q = robot.sample_q(5, torch.Generator().manual_seed(12))
    with torch.no_grad():
        T = robot.fk(q)
    result = solve_ik(robot, T, seeds=0, extra_seeds=(q + 0.01)[:, None, :])
    assert result.n_failed == 0
    assert bool(same_solution(result.q[:, 0], q, robot.revolute).all())


def test_invalid_inputs_raise(robots):
    robot = robots["rx160"]
    with pytest.raises(ShapeError, match="4, 4"):
        solve_ik(robot, torch.zeros(3, 4, dtype=F64))
    with pytest.raises(ShapeError, match="not finite"):
        solve_ik(robot, torch.full((4, 4), torch.nan, dtype=F64))
    with pytest.raises(ShapeError, match="seeds"):
        solve_ik(robot, torch.eye(4, dtype=F64), seeds=torch.zeros(3, 5))
    with pytest.raises(HybridPKError, match="robot="):
        solve_ik(lambda q: robot.fk(q), torch.eye(4, dtype=F64))


def test_targets_that_are_not_poses_are_refused_in_one_line(robots):
    """A rotation scaled by 1.01 or a wrong last row was solved as if it were the
    nearest pose (before: 8 'solutions' with orientation errors 1e-8 deg from a matrix no
    pose has), a reflection failed without a word; now a one-line error names the
    target."""
    robot = robots["rx160"]
    with torch.no_grad():
        T = robot.fk(robot.sample_q(3, torch.Generator().manual_seed(3))).to(F64)
    assert solve_ik(robot, T.float(), seeds=4).q.shape[0] == 3  # float32 poses pass
    scaled, mirrored, bottom = T.clone(), T.clone(), T.clone()
    scaled[1, :3, :3] *= 1.01
    mirrored[2, :3, 0] *= -1
    bottom[0, 3, 0] = 1.0
    for bad, why in ((scaled, r"R\^T R - I"), (mirrored, "reflection"), (bottom, "last row")):
        with pytest.raises(ShapeError, match=f"is not a pose.*{why}") as info:
            solve_ik(robot, bad, seeds=4)
        assert "\n" not in str(info.value)


# ----------------------------------------------------------------------------- dedup / seeds


def test_same_solution_follows_the_contract():
    revolute = torch.tensor([True, True, False])
    q = torch.tensor([0.5, -3.0, 0.2], dtype=F64)
    two_pi = torch.tensor([2 * math.pi, -2 * math.pi, 0.0], dtype=F64)
    assert bool(same_solution(q, q + two_pi, revolute))  # modulo 2 pi
    assert bool(same_solution(q, q + torch.tensor([9e-4, -9e-4, 9e-7], dtype=F64), revolute))
    assert not bool(same_solution(q, q + torch.tensor([1.1e-3, 0, 0], dtype=F64), revolute))
    assert not bool(same_solution(q, q + torch.tensor([0, 0, 1.1e-6], dtype=F64), revolute))
    # The prismatic joint is not periodic.
    assert not bool(same_solution(q, q + torch.tensor([0, 0, 2 * math.pi], dtype=F64), revolute))
    # Across the +-pi seam.
    a = torch.tensor([math.pi - 2e-4, 0, 0], dtype=F64)
    b = torch.tensor([-math.pi + 2e-4, 0, 0], dtype=F64)
    assert bool(same_solution(a, b, revolute))


def test_distinct_mask_keeps_the_best_of_equal_solutions():
    revolute = torch.ones(2, dtype=torch.bool)
    q = torch.tensor(
        [[[0.0, 0.0], [2 * math.pi + 1e-4, 0.0], [1.0, 0.0], [1.0 + 5e-4, 0.0], [3.0, 3.0]]],
        dtype=F64,
    )
    candidate = torch.tensor([[True, True, True, True, False]])
    score = torch.tensor([[2.0, 1.0, 0.5, 0.7, 0.0]], dtype=F64)
    keep = distinct_mask(q, candidate, score, revolute)
    assert keep.tolist() == [[False, True, True, False, False]]


def test_seeds_lie_within_limits_and_repeat(robots):
    robot = robots["ur10"]
    for method in ("sobol", "halton", "uniform"):
        s = quasi_random_seeds(robot.lower, robot.upper, robot.revolute, 50, method=method)
        assert s.shape == (50, 6)
        assert bool(((s > robot.lower) & (s < robot.upper)).all())
        again = quasi_random_seeds(robot.lower, robot.upper, robot.revolute, 50, method=method)
        assert torch.equal(s, again)
    with pytest.raises(ShapeError):
        quasi_random_seeds(robot.lower, robot.upper, robot.revolute, 5, method="grid")


# ----------------------------------------------------------------------------- two stages


def _expensive_extended(robot: hpk.Robot) -> tuple[ExtendedModel, ExtendedModel]:
    """A calibrated-like model (frames + joint offset, link error, compliance) and the
    same frames without effects (the cheap model)."""
    base = transform(so3_exp(_vec(0.02, -0.01, 2.0)), _vec(2.5, 0.8, -0.4))
    tool = transform(so3_exp(_vec(0.1, 0.0, 0.3)), _vec(0.01, 0.02, 0.15))
    effects = [
        make_effect(robot, "joint_offset:joint_2", 2e-3),
        make_effect(robot, "link_length:joint_3", [1e-3, -5e-4, 2e-3]),
        make_effect(robot, "joint_compliance:joint_3", 2e-6),
    ]
    expensive = ExtendedModel(robot, effects, base=base, tool=tool)
    expensive.requires_grad_(False)
    return expensive, ExtendedModel(robot, [], base=base, tool=tool)


class _SmoothResidual(torch.nn.Module):
    """Nominal FK times a small, smooth, q-dependent twist from a fixed tiny MLP
    (mm / mrad scale, like a trained residual network)."""

    def __init__(self, robot: hpk.Robot) -> None:
        super().__init__()
        self._robot = (robot,)  # not a submodule: its parameters are not ours to set
        gen = torch.Generator().manual_seed(0)
        self.l1 = torch.nn.Linear(6, 16, dtype=F64)
        self.l2 = torch.nn.Linear(16, 6, dtype=F64)
        with torch.no_grad():
            for p in (*self.l1.parameters(), *self.l2.parameters()):
                p.copy_(0.5 * torch.randn(p.shape, generator=gen, dtype=F64))
        self.requires_grad_(False)

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        d = 1e-3 * self.l2(torch.tanh(self.l1(q)))
        return self._robot[0].fk(q) @ transform(so3_exp(d[..., 3:]), d[..., :3])


def _check_two_stage(model_fn, result, wang, T):
    # >= 99 % of the targets solved to 1e-3 mm / 1e-3 deg w.r.t. the expensive model.
    assert float((~result.failed).double().mean()) >= 0.99
    q = result.q[result.valid]
    with torch.no_grad():
        err = pose_error(T[:, None].expand(*result.valid.shape, 4, 4)[result.valid], model_fn(q))
    assert float(err.position_mm.max()) <= TOL_MM
    assert float(err.orientation_deg.max()) <= TOL_DEG
    # Table IV's shape: orders of magnitude below Wang et al.'s one-shot correction.
    ours, theirs = result.error_summary(), wang.error_summary()
    assert ours["position_mm"]["mean"] * 1e3 < theirs["position_mm"]["mean"]
    assert theirs["position_mm"]["mean"] > TOL_MM  # the baseline is not accurate
    assert int(wang.within_tolerance.sum()) < 0.5 * int(wang.valid.sum())


def test_two_stage_on_extended_model_beats_wang(robots):
    robot = robots["rx160"]
    expensive, cheap = _expensive_extended(robot)
    q = robot.sample_q(100, torch.Generator().manual_seed(21))
    with torch.no_grad():
        T = expensive(q)
    result = solve_ik_two_stage(cheap, expensive, T, seeds=32)
    assert result.info["autograd"]
    wang = wang_baseline(cheap, expensive, T, seeds=32)
    _check_two_stage(expensive, result, wang, T)


def test_two_stage_on_network_residual_beats_wang(robots):
    robot = robots["ur10"]
    net = _SmoothResidual(robot)
    q = robot.sample_q(100, torch.Generator().manual_seed(22))
    with torch.no_grad():
        T = net(q)
    result = solve_ik_two_stage(robot, net, T, seeds=32)
    wang = wang_baseline(robot, net, T, seeds=32)
    _check_two_stage(net, result, wang, T)


def test_as_ik_model_uses_analytic_jacobian_only_without_effects(robots):
    robot = robots["rx160"]
    expensive, cheap = _expensive_extended(robot)
    assert as_ik_model(robot).analytic
    assert as_ik_model(cheap).analytic
    assert not as_ik_model(expensive).analytic
    q = robot.sample_q(8, torch.Generator().manual_seed(0))
    T_a, J_a = as_ik_model(cheap).pose_and_jacobian(q, torch.arange(8))
    T_b, J_b = autograd_pose_jacobian(lambda x, rows: cheap(x), q, torch.arange(8))
    np.testing.assert_allclose(J_a.numpy(), J_b.numpy(), atol=1e-12)
    np.testing.assert_allclose(T_a.numpy(), T_b.numpy(), atol=1e-12)
