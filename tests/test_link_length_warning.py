"""A named link-length correction beyond what machining and assembly leave is warned
about (it trades off with another cause), as an expansion coefficient no structure has
is: measured on the UR10 pan split's rows, a search path named the elbow and wrist-2
link lengths at +45 and -45 mm along their parallel axes, below the 50 mm structural
limit and without a word."""

from __future__ import annotations

import hybrid_pk as hpk
from hybrid_pk.calibration.diagnosis.plausibility import plausibility_warnings
from hybrid_pk.calibration.diagnosis.result import Cause
from hybrid_pk.effects.limits import MAX_TRANSLATION_M, WARNED_TRANSLATION_M
from hybrid_pk.simulate import simulate_campaign


def _cause(value: list[float]) -> Cause:
    return Cause("link_length", "elbow_joint", value, "m", [1e-6] * 3, 0.1, None, "pose")


def test_a_link_length_beyond_assembly_tolerances_is_warned_about():
    robot = hpk.Robot.from_urdf("ur10")
    data, _ = simulate_campaign(robot, 20, [], noise_mm=0.02, seed=0)
    assert WARNED_TRANSLATION_M < MAX_TRANSLATION_M  # warned before it is structural
    (warning,) = plausibility_warnings([_cause([-1.8e-4, 0.04497, 1.1e-3])], data)
    assert warning["cause"] == "link_length:elbow_joint"
    assert "45 mm is beyond what machining and assembly leave" in warning["why"]
    # the shared UR10's named link lengths (below 1 mm) and a 4 mm one: no word
    assert plausibility_warnings([_cause([-1.2e-4, 4.0e-4, 7.3e-4])], data) == []
    assert plausibility_warnings([_cause([0.0, 0.0, 0.004])], data) == []
