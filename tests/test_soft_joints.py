"""A joint as soft as a cobot's (1.5e-4 .. 5e-4 rad/Nm: a torque-sensed joint or a small
strain-wave gear) is a cause, not a wrong URDF: the diagnosis names it with its value,
and only a bend beyond what a joint can sag under the data's gravity is flagged."""

from __future__ import annotations

import math

import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.diagnosis.search import diagnose
from hybrid_pk.effects.limits import DRAWN_COMPLIANCE, MAX_COMPLIANCE, MAX_ROTATION_DEG
from hybrid_pk.simulate import simulate_campaign
from hybrid_pk.simulate.unmodelled import rms_gravity_torques
from tests.helpers import RUN_SEED, run_rng

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_thread")]

ROBOT = "column_arm"
# A joint is gravity-loaded when its RMS holding torque exceeds this [Nm] (as in
# test_restation): its sag is then millimetres at the flange.
LOADED_NM = 20.0


def test_a_soft_joint_is_named_not_flagged():
    rng = run_rng("soft-joint")
    robot = hpk.Robot.from_urdf(ROBOT, end_link="tool0")
    robot.requires_grad_(False)
    rms = rms_gravity_torques(robot, 0.0, torch.Generator().manual_seed(0))
    names, types = robot.joint_names, robot.joint_types
    loaded = [
        n for n, t, k in zip(names, rms, types, strict=True) if t > LOADED_NM and k == "revolute"
    ]
    joint = str(rng.choice(loaded))
    c = float(rng.uniform(1.5 * DRAWN_COMPLIANCE, 0.5 * MAX_COMPLIANCE))
    # a sag beyond what a joint can bend (MAX_ROTATION_DEG) under the poses' gravity is
    # drawn smaller, 20 % inside for what the fitted value may differ by
    q = robot.sample_q(2000, torch.Generator().manual_seed(1))
    tau = float(robot.gravity_torques(q)[:, robot.joint_names.index(joint)].abs().max())
    c = min(c, 0.8 * math.radians(MAX_ROTATION_DEG) / tau)
    label = f"joint_compliance:{joint}"
    data, _ = simulate_campaign(
        robot, 600, [hpk.make_effect(robot, label, c)], noise_mm=0.1, position_only=True,
        temperature_range=None, seed=RUN_SEED % 1000,
    )  # fmt: skip
    diag = diagnose(robot, data, seed=RUN_SEED % 1000)
    where = f"{label} = {c:.3g} rad/Nm (seed {RUN_SEED}); named {[c.effect for c in diag.causes]}"
    named = {f"{k.effect}:{k.joint}": k for k in diag.causes}
    assert label in named, where
    assert abs(named[label].value / c - 1) < 0.05, (named[label].value, where)
    assert diag.structural is None, (diag.structural, where)
