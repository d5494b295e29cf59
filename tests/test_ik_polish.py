"""The polish and its one fresh check (:func:`hybrid_pk.ik.polish.polish`), on the RX160's
own kernel: ends within the tolerances, ends near a solution, ends far from any, and a
polished value that fails the check falling back to the end as the solver left it."""

from __future__ import annotations

import math

import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.evaluation.metrics import pose_error
from hybrid_pk.ik import IKOptions, as_ik_model
from hybrid_pk.ik.batched_lm import LMOutput
from hybrid_pk.ik.polish import NEAR_FACTOR, polish, within
from hybrid_pk.ik.solver import check_solutions
from tests.helpers import run_rng

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64
N = 24  # 8 ends within the tolerances, 8 near a solution, 8 far from any


def _ends():
    """``(robot, ikm, q_true, out, T)``: the RX160 at random configurations and an
    ``LMOutput`` of ends 2e-8 rad, 2e-5 rad and 0.3 rad from them, with their errors."""
    robot = hpk.Robot.from_urdf("rx160")
    robot.requires_grad_(False)
    ikm = as_ik_model(robot)
    gen = torch.Generator().manual_seed(int(run_rng("polish check").integers(2**31)))
    q_true = robot.sample_q(N, gen)
    q_true = torch.clamp(q_true, ikm.lower + 0.5, ikm.upper - 0.5)  # room for the offsets
    size = torch.tensor([2e-8] * 8 + [2e-5] * 8 + [0.3] * 8, dtype=F64)[:, None]
    sign = torch.where(torch.rand(N, 6, generator=gen) < 0.5, -1.0, 1.0).to(F64)
    q = q_true + size * sign
    with torch.no_grad():
        T = robot.fk(q_true)
        err = pose_error(T, robot.fk(q))
    out = LMOutput(
        q=q,
        position_error=err.position_mm * 1e-3,
        rotation_error=err.orientation_deg.deg2rad(),
        iterations=torch.zeros(N, dtype=torch.long),
        damping=torch.zeros(N, 2, dtype=F64),
        evaluations=0,
    )
    return robot, ikm, q_true, out, T


def _run(ikm, out, T, check):
    options = IKOptions()
    s = options.lm_settings(position_only=False)
    near = within(out, 2e-3 * options.tol_mm, 2 * math.radians(options.tol_deg), False)
    inside = within(out, 1e-3 * options.tol_mm, math.radians(options.tol_deg), False)
    stalled = within(out, NEAR_FACTOR * s.accept_position, NEAR_FACTOR * s.accept_rotation, False)
    rows = torch.arange(N)
    with torch.no_grad():
        return near, polish(
            ikm, out, near, inside, stalled, rows, T, (ikm.lower, ikm.upper), s, check
        )


def test_one_check_after_the_polish():
    robot, ikm, q_true, out, T = _ends()
    options = IKOptions()

    def check(q, candidate):
        return check_solutions(ikm, q, torch.arange(N), T, False, options, candidate)

    near, (polished, ok, pos, _) = _run(ikm, out, T, check)
    assert near[:8].all()  # the case is the one described
    assert not near[8:].any()
    assert ok[:16].all()  # near ones polished onto their solution
    assert not ok[16:].any()
    moved = (polished.q - q_true).abs().amax(-1)
    assert (moved[:16] < 1e-9).all()  # at the exact branch, not just within the tolerance
    assert torch.equal(polished.q[16:], out.q[16:])  # far ends: not touched
    with torch.no_grad():
        fresh = pose_error(T[:16], robot.fk(polished.q[:16]))
    torch.testing.assert_close(pos[:16], fresh.position_mm, rtol=0, atol=1e-12)
    assert polished.evaluations > 0


def test_a_polished_value_failing_the_check_falls_back_to_the_end():
    """A lower cost need not lower both errors: where the check refuses a polished value,
    the end as the solver left it is checked instead, and kept if it passes."""
    _, ikm, _, out, T = _ends()
    options = IKOptions()
    refuse = torch.zeros(N, dtype=torch.bool)
    refuse[:4] = True  # four of the ends within the tolerances
    calls = []

    def check(q, candidate):
        ok, pos, ori = check_solutions(ikm, q, torch.arange(N), T, False, options, candidate)
        polished_value = (q != out.q).any(-1)
        calls.append(candidate.clone())
        return ok & ~(refuse & polished_value), pos, ori

    _, (polished, ok, _, _) = _run(ikm, out, T, check)
    assert len(calls) == 2
    assert torch.equal(calls[1], refuse)  # the fallback: those four only
    assert torch.equal(polished.q[:4], out.q[:4])  # the ends as they were ...
    assert ok[:4].all()  # ... which pass
    assert (polished.q[4:16] != out.q[4:16]).any(-1).all()  # the others polished
    assert ok[4:16].all()
