"""Poses kept per (model point, rows) (hybrid_pk.calibration.kept_poses): a question
at a point and rows already evaluated reads them; any change of the point (a frame, an
effect's value) or of the rows (in place, too) computes them anew."""

from __future__ import annotations

import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.fit import predicted_poses
from hybrid_pk.effects import Conditions, ExtendedModel
from tests.helpers import run_rng


def _fresh(model, q, cond):
    with torch.no_grad():
        return model(q, cond)


def test_kept_poses_follow_every_change_of_the_point_and_the_rows():
    rng = run_rng("kept-poses")
    robot = hpk.Robot.from_urdf("ur10")
    robot.requires_grad_(False)
    model = ExtendedModel(robot, [hpk.make_effect(robot, "joint_offset:elbow_joint", 1e-3)])
    q = robot.sample_q(50, torch.Generator().manual_seed(int(rng.integers(1 << 20))))
    cond = Conditions()
    first = predicted_poses(model, q, cond)
    torch.testing.assert_close(first, _fresh(model, q, cond), rtol=0, atol=0)
    first.zero_()  # the caller's copy: what is kept stays
    torch.testing.assert_close(predicted_poses(model, q, cond), _fresh(model, q, cond))
    q[:, 2] += float(rng.uniform(0.1, 0.5))  # rows changed in place
    torch.testing.assert_close(predicted_poses(model, q, cond), _fresh(model, q, cond))
    with torch.no_grad():
        model.effects[0].value.fill_(float(rng.uniform(2e-3, 5e-3)))  # another point
    torch.testing.assert_close(predicted_poses(model, q, cond), _fresh(model, q, cond))
    with torch.no_grad():
        model.base.dp.add_(1e-3)  # a frame moved
    torch.testing.assert_close(predicted_poses(model, q, cond), _fresh(model, q, cond))
