"""The fast paths under IK and FK: the z-aligned chain (``Robot.fk`` without derivatives
from ``ALIGNED_MIN_BATCH`` configurations on, the IK kernel), the batched LM's
elimination, its two-precision run and the round-wise deduplication, each against a
plain reference."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.evaluation.metrics import pose_error
from hybrid_pk.geometry import so3_exp, so3_log
from hybrid_pk.ik import IKOptions, as_ik_model, batched_levenberg_marquardt
from hybrid_pk.ik.dedup import (
    cell_representatives,
    distinct_mask,
    joint_difference,
    same_solution,
)
from hybrid_pk.ik.lm_algebra import eliminate, normal_equations, pose_residual
from hybrid_pk.ik.two_precision import solve_two_precisions
from hybrid_pk.robot.aligned import ALIGNED_MIN_BATCH
from hybrid_pk.robot.chain import local_transforms, product
from tests.helpers import run_rng

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64
ARM7 = Path(__file__).resolve().parent / "data" / "arm7_generic.urdf"
ROBOTS = {
    "ur10": ("ur10", None),
    "rx160": ("rx160", None),
    "arm7 (prismatic joint)": (ARM7, "tool0"),
    "column_arm (mimic joints)": ("column_arm", "tool0"),
}


def _torch_rng(salt: str) -> torch.Generator:
    return torch.Generator().manual_seed(int(run_rng(salt).integers(2**31)))


def _starts_near(name: str, n: int, spread: float, salt: str, edit=None):
    """``(robot, ikm, q_true, q0, T)``: ``n`` random configurations of ``name`` (changed
    by ``edit(q_true, rng)`` if given), starts ``spread`` rad of noise from them inside
    the limits, and their poses."""
    robot = hpk.Robot.from_urdf(name)
    robot.requires_grad_(False)
    ikm = as_ik_model(robot)
    rng = _torch_rng(salt)
    q_true = robot.sample_q(n, rng)
    if edit is not None:
        edit(q_true, rng)
    q0 = q_true + spread * torch.randn(q_true.shape, generator=rng, dtype=F64)
    q0 = torch.clamp(q0, ikm.lower, ikm.upper)
    with torch.no_grad():
        T = robot.fk(q_true)
    return robot, ikm, q_true, q0, T


def _product_fk(robot: hpk.Robot, q: torch.Tensor) -> torch.Tensor:
    """The balanced product of ``Robot.fk``'s derivative path."""
    terms = robot._terms(None, q.dtype, fold_tip=True)
    return product(local_transforms(robot.chain_q(q), terms, robot.chain_revolute))


@pytest.mark.parametrize("name", ROBOTS)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_fk_without_gradients_equals_the_product(name, dtype):
    urdf, end = ROBOTS[name]
    robot = hpk.Robot.from_urdf(urdf, end_link=end)
    q = robot.sample_q(ALIGNED_MIN_BATCH + 7, torch.Generator().manual_seed(3)).to(dtype)
    q = q.reshape(1, -1, robot.dof)  # a leading batch shape too
    with torch.no_grad():
        T = robot.fk(q)
        T_ref = _product_fk(robot, q)
    assert T.dtype == dtype
    assert T.shape == (1, q.shape[1], 4, 4)
    tol = 1e-12 if dtype == F64 else 2e-6  # float32: its rounding over a ~1 m chain
    assert float((T - T_ref).abs().max()) <= tol
    T_grad = robot.fk(q)  # parameters require grad: the derivative path
    assert T_grad.requires_grad
    assert float((T_grad.detach() - T_ref).abs().max()) <= tol


def test_fk_follows_parameter_changes_and_keeps_gradients():
    robot = hpk.Robot.from_urdf("rx160")
    q = robot.sample_q(ALIGNED_MIN_BATCH, torch.Generator().manual_seed(4))
    with torch.no_grad():
        before = robot.fk(q)
        robot.origin_xyz[2, 0] += 0.01  # a link 10 mm longer
        after = robot.fk(q)
        assert float((after - _product_fk(robot, q)).abs().max()) <= 1e-12
    assert float((after - before).abs().max()) > 1e-3
    q.requires_grad_(True)
    robot.fk(q).sum().backward()  # q requires grad: the path with derivatives
    assert q.grad is not None
    assert bool(torch.isfinite(q.grad).all())


def _moved_params(robot: hpk.Robot, rng: torch.Generator, turn: float):
    """The robot's kinematic parameters with every origin moved by ~1 mm and every axis
    turned by ~``turn`` rad (shared parameters, as an extended model's)."""
    p = robot.kinematic_params()
    return type(p)(
        p.origin_xyz + 1e-3 * torch.randn(p.origin_xyz.shape, generator=rng, dtype=F64),
        p.origin_rot,
        p.axis + turn * torch.randn(p.axis.shape, generator=rng, dtype=F64),
    )


@pytest.mark.parametrize("name", ROBOTS)
def test_fk_with_other_parameters_without_gradients_equals_the_product(name):
    """An extended model's parameters (origins moved, axes turned: shared, not the
    robot's own) take the z-aligned path too, with the same poses; per-sample
    parameters and parameters carrying derivatives keep the product."""
    urdf, end = ROBOTS[name]
    robot = hpk.Robot.from_urdf(urdf, end_link=end)
    rng = _torch_rng(f"fk params {name}")
    q = robot.sample_q(ALIGNED_MIN_BATCH + 3, rng)
    moved = _moved_params(robot, rng, turn=1e-3)
    terms = robot._terms(moved, F64, fold_tip=True)
    ref = product(local_transforms(robot.chain_q(q), terms, robot.chain_revolute)).detach()
    aligned = robot._no_grad_fk.with_params
    with torch.no_grad():
        T = robot.fk(q, params=moved)
        assert aligned(robot._terms(moved, F64), robot.chain_q(q)) is not None
        assert float((T - robot.fk(q)).abs().max()) > 1e-4  # the moved parameters were used
    assert float((T - ref).abs().max()) <= 1e-12
    per_sample = type(moved)(*(t.expand(len(q), *t.shape) for t in moved))
    with torch.no_grad():
        assert aligned(robot._terms(per_sample, F64), robot.chain_q(q)) is None
        assert float((robot.fk(q, params=per_sample) - ref).abs().max()) <= 1e-12
    grad = type(moved)(*(t.clone().requires_grad_(True) for t in moved))
    T_grad = robot.fk(q, params=grad)  # derivatives wanted: the product, differentiable
    assert T_grad.requires_grad
    assert float((T_grad.detach() - ref).abs().max()) <= 1e-12


def _product_link_frames(robot: hpk.Robot, q: torch.Tensor, params) -> torch.Tensor:
    """The frames after each joint as the chain's running product (the derivative path)."""
    terms = robot._terms(params, q.dtype)
    local = local_transforms(robot.chain_q(q), terms, robot.chain_revolute)
    frames = [local[..., 0, :, :]]
    for i in range(1, robot.chain_dof):
        frames.append(frames[-1] @ local[..., i, :, :])
    frames.append(frames[-1] @ terms.tip)
    return torch.stack(frames, -3).detach()


@pytest.mark.parametrize("name", ROBOTS)
def test_link_frames_without_gradients_equal_the_product(name):
    """The frames after each joint from the z-aligned chain (no derivatives, shared
    parameters, the robot's own or moved) are the running product's; per-sample
    parameters and a few configurations keep the product."""
    urdf, end = ROBOTS[name]
    robot = hpk.Robot.from_urdf(urdf, end_link=end)
    rng = _torch_rng(f"link frames {name}")
    q = robot.sample_q(ALIGNED_MIN_BATCH + 5, rng)
    moved = _moved_params(robot, rng, turn=1e-2)
    fast = robot._no_grad_fk.link_frames
    for params in (None, moved):
        ref = _product_link_frames(robot, q, params)
        with torch.no_grad():
            assert fast(robot._terms(params, F64), robot.chain_q(q)) is not None
            F = robot.link_frames(q, params)
        assert F.shape == ref.shape
        assert float((F - ref).abs().max()) <= 1e-12
    per_sample = type(moved)(*(t.expand(len(q), *t.shape) for t in moved))
    with torch.no_grad():
        assert fast(robot._terms(per_sample, F64), robot.chain_q(q)) is None
        assert fast(robot._terms(moved, F64), robot.chain_q(q[:10])) is None


@pytest.mark.parametrize("A", [500, 40])  # the elimination, then LAPACK's Cholesky
def test_elimination_solves_damped_normal_equations(A):
    rng = _torch_rng(f"elimination {A}")
    n = 6
    J = torch.randn(6, n, A, generator=rng, dtype=F64)
    e = torch.randn(6, A, generator=rng, dtype=F64)
    G = normal_equations(J, e)
    H = torch.einsum("rja,rka->ajk", J, J) + 1e-3 * torch.eye(n, dtype=F64)
    G.view(-1, A)[:: n + 2] += 1e-3
    x, ok = eliminate(G)
    x_ref = torch.linalg.solve(H, torch.einsum("rja,ra->aj", J, e))
    assert bool(ok.all())
    assert float((x.T - x_ref).abs().max()) <= 1e-8 * float(x_ref.abs().max())
    G = normal_equations(J, e)
    G[2, 2] = -1.0  # not positive definite
    assert not bool(eliminate(G)[1].any())
    G = normal_equations(J, e)
    G.view(-1, A)[:: n + 2] += 1e-3
    G[:, :, 3] = torch.nan  # one problem's system is NaN: only its step fails
    ok = eliminate(G)[1]
    assert not bool(ok[3])
    assert int(ok.sum()) == A - 1


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_pose_residual_is_the_weighted_rotation_vector_also_near_pi(dtype):
    """The IK's residual against ``so3_log`` of ``R_t R^T`` (float64 reference), for
    rotations about random axes by angles within 1e-9 .. 1e-2 rad of pi (the residual
    takes the axis from the symmetric part there) and by angles from 3e-7 rad to pi."""
    rng = _torch_rng(f"residual near pi {dtype}")
    A, w = 64, 0.7
    axis = torch.nn.functional.normalize(torch.randn(A, 3, generator=rng, dtype=F64), dim=-1)
    gap = 10 ** (-9 + 7 * torch.rand(A, 1, generator=rng, dtype=F64))
    angle = torch.where(torch.arange(A)[:, None] < A // 2, math.pi - gap, math.pi * gap / 1e-2)
    R = so3_exp(torch.randn(A, 3, generator=rng, dtype=F64))
    R_t = so3_exp(axis * angle) @ R  # R_t R^T: that rotation
    p, p_t = (
        torch.randn(3, A, generator=rng, dtype=F64),
        torch.randn(3, A, generator=rng, dtype=F64),
    )
    cast = [x.to(dtype) for x in (R.permute(1, 2, 0), p, R_t.permute(1, 2, 0), p_t)]
    dp, wr, cost, pos, rot = pose_residual(*cast, w, False)
    dp_ref = p_t - p
    E = R_t @ R.transpose(-1, -2)
    tol = 1e-12 if dtype == F64 else 1e-5
    if dtype == F64:
        assert float((wr.T - w * so3_log(E)).abs().max()) <= tol
    else:  # within float32's resolution of pi the axis' sign is either: as rotations
        off = so3_log(so3_exp(wr.T.to(F64) / w).transpose(-1, -2) @ E)
        assert float(off.norm(dim=-1).max()) <= tol
    assert float((rot[0].to(F64) - angle[:, 0]).abs().max()) <= tol
    assert float((dp.to(F64) - dp_ref).abs().max()) <= tol
    assert float((pos[0].to(F64) - dp_ref.norm(dim=0)).abs().max()) <= tol
    cost_ref = dp_ref.square().sum(0) + (w * angle[:, 0]) ** 2
    assert float((cost[0].to(F64) - cost_ref).abs().max()) <= 10 * tol


def _greedy(q, candidate, score, revolute):
    """The contract's definition, one candidate at a time (the reference)."""
    keep = torch.zeros_like(candidate)
    for i in range(q.shape[0]):
        kept = []
        for j in torch.argsort(torch.where(candidate[i], score[i], math.inf), stable=True):
            if candidate[i, j] and not any(
                bool(same_solution(q[i, j], q[i, k], revolute)) for k in kept
            ):
                kept.append(int(j))
        keep[i, kept] = True
    return keep


@pytest.mark.parametrize("spread", [1e-9, 1e-3])
def test_round_wise_dedup_equals_the_greedy_definition(spread):
    rng = _torch_rng(f"dedup {spread}")
    N, K, dof = 6, 40, 6
    revolute = torch.tensor([True] * 5 + [False])
    roots = 3 * torch.randn(N, 5, dof, generator=rng, dtype=F64)
    pick = torch.randint(0, 5, (N, K), generator=rng)
    q = torch.take_along_dim(roots, pick[..., None], 1)
    q = q + spread * torch.randn(N, K, dof, generator=rng, dtype=F64)  # chains at 1e-3
    q[..., :5] += 2 * math.pi * torch.randint(-1, 2, (N, K, 5), generator=rng)
    candidate = torch.rand(N, K, generator=rng) > 0.2
    score = torch.rand(N, K, generator=rng, dtype=F64)
    keep = distinct_mask(q, candidate, score, revolute)
    assert torch.equal(keep, _greedy(q, candidate, score, revolute))


def test_same_cell_merge_keeps_the_best_of_each_cell():
    """Clusters at float32 accuracy (1e-5 rad, 1e-8 m) around a few roots per target: every dropped
    candidate has a kept one of its own target within a cell, with a score no worse;
    targets never merge; most of each cluster merges."""
    rng = _torch_rng("same cell")
    N, K, dof = 5, 64, 6
    revolute = torch.tensor([True] * 5 + [False])
    roots = 3 * torch.randn(N, 4, dof, generator=rng, dtype=F64)
    roots[1:] = roots[0]  # every target the same roots: only the group keeps them apart
    pick = torch.randint(0, 4, (N, K), generator=rng)
    q = torch.take_along_dim(roots, pick[..., None], 1)
    noise = torch.tensor([1e-5] * 5 + [1e-8], dtype=F64)  # [rad], [m]
    q = q + noise * torch.randn(N, K, dof, generator=rng, dtype=F64)
    q[..., :5] += 2 * math.pi * torch.randint(-1, 2, (N, K, 5), generator=rng)
    q, group = q.reshape(-1, dof), torch.arange(N).repeat_interleave(K)
    candidate = torch.rand(N * K, generator=rng) > 0.2
    score = torch.rand(N * K, generator=rng, dtype=F64)
    cell_r, cell_p = 5e-4, 5e-7
    rep = cell_representatives(q, group, candidate, score, revolute, cell_r, cell_p)
    keep = rep == torch.arange(N * K)
    assert bool((rep[~candidate] == -1).all())
    assert not bool((keep & ~candidate).any())
    # every merged candidate names a kept one of its target, in its cell, scoring no worse
    gone = (candidate & ~keep).nonzero()[:, 0]
    assert bool(keep[rep[gone]].all())
    assert bool((group[rep[gone]] == group[gone]).all())
    d = joint_difference(q[rep[gone]], q[gone], revolute).abs()
    assert bool(((d[:, :5] < cell_r).all(-1) & (d[:, 5] < cell_p)).all())
    assert bool((score[rep[gone]] <= score[gone]).all())
    for i in (candidate & ~keep).nonzero()[:, 0]:
        d = joint_difference(q[keep], q[i], revolute).abs()
        near = (d[:, :5] < cell_r).all(-1) & (d[:, 5] < cell_p) & (group[keep] == group[i])
        assert bool((near & (score[keep] <= score[i])).any())
    assert int(keep.sum()) <= N * 4 * 4  # a cluster straddles few cell borders
    assert int(keep.sum()) >= len(torch.unique(group[candidate] * 4 + pick.view(-1)[candidate]))


def test_two_precisions_finish_in_float64():
    """float32 to the handover, float64 to the caller's tolerances: as many problems
    arrive as with float64 throughout, and each within tolerance by a fresh FK."""
    robot, ikm, _, q0, T = _starts_near("rx160", 256, 0.5, "two precisions")
    s = IKOptions().lm_settings(position_only=False)
    args = (ikm.evaluate, q0, torch.arange(256), T, ikm.lower, ikm.upper, s, ikm.revolute)
    with torch.no_grad():
        (out, _), ref = solve_two_precisions(*args), batched_levenberg_marquardt(*args)
        err = pose_error(T, robot.fk(out.q))
    assert out.q.dtype == F64
    arrived = (err.position_mm <= 1e-3) & (err.orientation_deg <= 1e-3)
    ref_arrived = (ref.position_error <= s.keep_position) & (ref.rotation_error <= s.keep_rotation)
    assert int(arrived.sum()) >= int(ref_arrived.sum()) - 3  # a different path may miss a few
    assert int(arrived.sum()) >= 200  # started within 0.5 rad: most arrive
    assert torch.allclose(out.position_error[arrived] * 1e3, err.position_mm[arrived], atol=1e-9)


def test_the_second_phase_goes_on_with_the_damping_it_had():
    """``LMOutput.damping`` is where each problem stopped, and a call given it starts
    there (a call of no iteration hands it back unchanged)."""
    _, ikm, _, q0, T = _starts_near("ur10", 64, 0.3, "damping carried")
    s = IKOptions().lm_settings(position_only=False)
    args = (ikm.evaluate, q0, torch.arange(64), T, ikm.lower, ikm.upper)
    with torch.no_grad():
        out = batched_levenberg_marquardt(*args, replace(s, max_iterations=3), ikm.revolute)
        assert out.damping.shape == (64, 2)
        assert bool((out.damping > 0).all())
        assert bool(torch.isfinite(out.damping).all())
        assert not torch.allclose(out.damping[:, 0], torch.full((64,), s.damping_init, dtype=F64))
        again = batched_levenberg_marquardt(
            ikm.evaluate, out.q, torch.arange(64), T, ikm.lower, ikm.upper,
            replace(s, max_iterations=0), ikm.revolute, damping=out.damping,
        )  # fmt: skip
    assert torch.equal(again.damping, out.damping)


def test_a_problem_too_slow_for_its_budget_is_given_up():
    """A Jacobian twenty times too large makes every step a twentieth of the way: the
    cost falls at a steady rate that passes the stall check but would need far more
    than the budget. ``reach_factor`` gives such problems up at the second progress
    check; it leaves problems that converge as they were, and spares slow ones whose
    budget is large enough."""
    _, ikm, _, q0, T = _starts_near("ur10", 64, 0.3, "too slow")
    s = IKOptions().lm_settings(position_only=False)

    def stiff(qt, rows):
        R, p, J = ikm.evaluate(qt, rows)
        return R, p, 20 * J

    def run(evaluate, settings):
        with torch.no_grad():
            return batched_levenberg_marquardt(
                evaluate, q0, torch.arange(64), T, ikm.lower, ikm.upper, settings, ikm.revolute
            )

    off = replace(s, reach_factor=math.inf)
    good, good_off = run(ikm.evaluate, s), run(ikm.evaluate, off)
    assert torch.equal(good.q, good_off.q)
    assert torch.equal(good.iterations, good_off.iterations)
    slow, slow_off = run(stiff, s), run(stiff, off)
    assert bool((slow.iterations == 2 * s.stall_window).all())
    assert bool((slow_off.iterations > 2 * s.stall_window).all())
    roomy = run(stiff, replace(s, max_iterations=2000))
    assert torch.equal(roomy.iterations, slow_off.iterations)


def test_near_singular_crawl_is_handed_to_the_polish():
    """Near a singular configuration (UR10 wrist_2 ~1e-5 rad) the damped iteration
    crawls within the polish's reach; with ``handoff_position`` such problems leave after
    two progress checks in the band (fewer evaluations), and Gauss-Newton finishes each
    of them within the tolerances."""
    from hybrid_pk.ik.polish import NEAR_FACTOR, gauss_newton

    def wrist_near_zero(q, rng):  # wrist_2 within 1e-5..1e-4 rad of 0, either sign
        size = 10 ** (-5 + torch.rand(128, generator=rng, dtype=F64))
        q[:, 4] = size * torch.where(torch.rand(128, generator=rng) < 0.5, -1.0, 1.0).to(F64)

    robot, ikm, _, q0, T = _starts_near("ur10", 128, 0.05, "hand-off", wrist_near_zero)
    s = IKOptions().lm_settings(position_only=False)
    args = (ikm.evaluate, q0, torch.arange(128), T, ikm.lower, ikm.upper)
    with torch.no_grad():
        plain_run = batched_levenberg_marquardt(*args, s, ikm.revolute)
        near = NEAR_FACTOR * s.accept_position, NEAR_FACTOR * s.accept_rotation
        s_h = replace(s, handoff_position=near[0], handoff_rotation=near[1])
        handed = batched_levenberg_marquardt(*args, s_h, ikm.revolute)
    assert handed.evaluations < plain_run.evaluations
    band = (handed.position_error <= NEAR_FACTOR * s.accept_position) & (
        handed.rotation_error <= NEAR_FACTOR * s.accept_rotation
    )
    kept = (handed.position_error <= s.keep_position) & (handed.rotation_error <= s.keep_rotation)
    left = band & ~kept
    assert int(left.sum()) > 0  # some did leave unfinished: the case is one where it matters
    sel = left.nonzero()[:, 0]
    with torch.no_grad():
        q_pol, _, _, settled, _ = gauss_newton(
            ikm, handed.q[sel], sel, T[sel], ikm.lower, ikm.upper, s
        )
        err = pose_error(T[sel], robot.fk(q_pol))
    assert bool(settled.all())
    assert bool(((err.position_mm <= 1e-3) & (err.orientation_deg <= 1e-3)).all())


def test_polish_steps_only_the_problems_not_yet_settled():
    """Gauss-Newton polish: a problem at its solution settles at once and stops (one
    evaluation); those ~1e-2 rad off step on to float64's floor."""
    from hybrid_pk.ik.polish import gauss_newton

    robot = hpk.Robot.from_urdf("rx160")
    robot.requires_grad_(False)
    ikm = as_ik_model(robot)
    rng = _torch_rng("polish compaction")
    q_true = robot.sample_q(64, rng)
    with torch.no_grad():
        T = robot.fk(q_true)
    off = torch.zeros(64, dtype=torch.bool)
    off[::4] = True  # 16 of 64 start off their solution
    q0 = q_true + off[:, None] * 1e-2 * torch.randn(q_true.shape, generator=rng, dtype=F64)
    s = IKOptions().lm_settings(position_only=False)
    with torch.no_grad():
        q, _, _, settled, evaluations = gauss_newton(
            ikm, q0, torch.arange(64), T, ikm.lower, ikm.upper, s
        )
        err = pose_error(T, robot.fk(q))
    assert bool(settled[~off].all())
    assert bool((err.position_mm < 1e-6).all())  # the off ones too, to float64's floor
    assert torch.equal(q[~off], q0[~off])  # nothing to gain: the start is kept
    assert 64 < evaluations <= 48 + 16 * 7  # the settled 48 were evaluated once
    one = q0[:1].clone()  # one problem: its (dof, 1) transpose is already contiguous
    with torch.no_grad():
        gauss_newton(ikm, one, torch.arange(1), T[:1], ikm.lower, ikm.upper, s)
    assert torch.equal(one, q0[:1])  # the caller's start is never written into


def test_the_kernel_of_a_robot_is_kept_until_its_parameters_change():
    from hybrid_pk.robot.kernel import ChainKernel

    robot = hpk.Robot.from_urdf("ur10")
    kernel = ChainKernel.of(robot)
    assert ChainKernel.of(robot) is kernel  # requires_grad or not: the terms are cached
    q = robot.sample_q(4, _torch_rng("kernel memo"))
    with torch.no_grad():
        robot.origin_xyz[2, 0] += 0.01  # in place: a new version of the parameter
        T_new = robot.fk(q)
    changed = ChainKernel.of(robot)
    assert changed is not kernel
    torch.testing.assert_close(changed(q)[0], T_new, rtol=0, atol=1e-12)
    assert (kernel(q)[0] - T_new).abs().max() > 1e-3  # the old one had the old link
