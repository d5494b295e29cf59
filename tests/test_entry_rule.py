"""A candidate enters only on a blocked gain above its own standard error over the
blocks (the delete-one-block jackknife, the one-standard-error rule); the margin alone
holds only the noise. Campaign drawn per run (``tests.helpers.run_rng``)."""

from __future__ import annotations

import dataclasses
import math

import pytest

from hybrid_pk.calibration.diagnosis.selection import Scores
from tests.helpers import run_rng
from tests.test_blocked_each import _blocked


def test_standard_error_is_the_jackknife_of_the_pooled_gain_over_the_blocks():
    b, labels = _blocked(run_rng("entry-rule"))
    current, extra = labels[:3], labels[3]
    without, with_it = b.of(current), b.of([*current, extra])
    # independently: each block dropped from the folds, the pooled gain of the others
    k = len(b.folds.folds)
    rest = []
    for j in range(k):
        folds = dataclasses.replace(b.folds, folds=b.folds.folds[:j] + b.folds.folds[j + 1 :])
        bj = dataclasses.replace(b, folds=folds)
        rest.append(bj.gain_mm(bj.of(current), bj.of([*current, extra])))
    mean = sum(rest) / k
    expected = math.sqrt((k - 1) / k * sum((g - mean) ** 2 for g in rest))
    assert expected > 0
    assert b.gain_se_mm(without, with_it) == pytest.approx(expected, rel=1e-9)
    one = dataclasses.replace(b, folds=dataclasses.replace(b.folds, folds=b.folds.folds[:1]))
    assert one.gain_se_mm(one.of(current), one.of([*current, extra])) == 0.0


def test_entry_needs_the_margin_and_the_standard_error():
    s = Scores(scored=[], m=100, n_current=3, margin=0.002)
    s.carry = {"a": 0.010, "b": 0.010, "c": 0.001, "d": 0.010}
    s.carry_se = {"a": 0.004, "b": 0.012, "c": 0.0, "d": 0.010}
    assert s.carries("a")  # above both
    assert not s.carries("b")  # above the margin, within its standard error
    assert not s.carries("c")  # consistent, below the margin
    assert s.carries("d")  # at its standard error
    assert s.carries("no blocks")  # not scored on blocks: the F-test alone decides


def test_every_entry_and_cause_carries_its_standard_error():
    """A simulated RX160 campaign (the sizes of ``bench/diagnose.py --case rx160``, on
    fewer rows): each accepted step entered above its standard error over the blocks,
    each cause reports its own (JSON and the printed line)."""
    import hybrid_pk as hpk
    from hybrid_pk.calibration.diagnosis.search import diagnose
    from hybrid_pk.cli.diagnose_cmd import summary_lines
    from hybrid_pk.simulate import simulate_campaign

    robot = hpk.Robot.from_urdf("rx160")
    robot.requires_grad_(False)
    effects = "joint_offset:joint_3=4e-4; joint_compliance:joint_2=1.5e-6"
    data, _ = simulate_campaign(robot, 800, effects, noise_mm=0.02, payload=20.0, seed=1)
    diag = diagnose(robot, data, seed=0)
    named = {f"{c.effect}:{c.joint}" for c in diag.causes}
    assert {"joint_offset:joint_3", "joint_compliance:joint_2"} <= named, named
    for step in diag.to_json()["selection"]:
        if step.get("accepted") and "blocked_gain_mm" in step:
            assert step["blocked_gain_mm"] >= step["blocked_gain_se_mm"] >= 0.0, step
    for c in diag.causes:
        assert c.to_json()["blocked_holdout_gain_se_mm"] >= 0.0
    text = "\n".join(summary_lines(diag))
    assert f"blocked hold-out {diag.causes[0].blocked_holdout_gain_mm:.3g} ± " in text
