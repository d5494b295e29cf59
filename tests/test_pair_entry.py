"""Two hidden effects that mask each other enter as a pair (:mod:`hybrid_pk.calibration.
diagnosis.pair_entry`): neither alone carries over on the blocked hold-out, together
they do. The campaign is the pinocchio-generated one of ``test_diagnose`` at the draw of
sweep seed 242424 (offset and compliance sizes), where the search named nothing before."""

from __future__ import annotations

import numpy as np
import pytest

from hybrid_pk.calibration import diagnose
from tests.test_diagnose import _check, pinocchio_campaign

pytestmark = pytest.mark.usefixtures("one_thread")

# the stream run_rng("pinocchio") gives at HYBRID_PK_TEST_SEED=242424
MASKING_DRAW = np.random.default_rng([242424, sum(map(ord, "pinocchio"))])


def test_two_effects_that_carry_over_only_together_are_named(pin):
    robot, data, truth = pinocchio_campaign(pin, MASKING_DRAW)
    diag = diagnose(robot, data, seed=5)
    steps = diag.steps
    # no candidate carried over alone at the first step: a pair entered
    assert "entered_with" in steps[0], steps[0]
    pair = steps[0]["entered_with"]
    assert {pair["lead"], pair["partner"]} == set(truth), pair
    assert pair["gain_mm"] >= max(pair["se_mm"], steps[0]["min_gain_mm"])
    assert steps[0]["blocked_gain_mm"] < steps[0]["blocked_gain_se_mm"]  # alone: no
    _check(diag, truth, "pinocchio-generated, the masking draw (seed 242424)")
