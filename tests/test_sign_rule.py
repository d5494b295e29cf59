"""An effect whose physics fixes its sign (a play, a joint or tilt compliance) fitted
below zero is not a cause, whatever its size
(hybrid_pk.calibration.diagnosis.plausibility.implausibility).

Before, a negative value was only warned about and still named: on Series B of the
shared UR10 without the cause limit the search named a wrist-1 tilt compliance of
(-3.8e-5, 1.3e-4) rad/Nm. Now such a candidate is refused at its refit, and an effect a
later refit carries below zero is taken out (settle), each listed as a finding."""

from __future__ import annotations

import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.diagnosis.plausibility import implausibility
from tests.helpers import run_rng


def test_a_negative_play_or_compliance_is_a_finding_a_positive_one_is_not(ur10):
    rng = run_rng("sign-rule")
    small = float(rng.uniform(1e-6, 1e-4))  # far inside every size limit
    for label in ("joint_compliance:elbow_joint", "backlash:wrist_3_joint"):
        assert implausibility(hpk.make_effect(ur10, label, small), ur10) is None, label
        why = implausibility(hpk.make_effect(ur10, label, -small), ur10)
        assert why is not None, label
        assert why["cause"] == label
        assert "negative" in why["why"]
    tilt = torch.tensor([small, -small / 3])  # one component below zero is enough
    why = implausibility(hpk.make_effect(ur10, "tilt_compliance:wrist_1_joint", tilt), ur10)
    assert why is not None
    assert why["value"] < 0


def test_effects_without_a_sign_rule_keep_both_signs(ur10):
    rng = run_rng("sign-rule-2")
    small = float(rng.uniform(1e-5, 1e-4))
    for label in ("joint_offset:elbow_joint", "gear_ratio:wrist_2_joint"):
        assert implausibility(hpk.make_effect(ur10, label, -small), ur10) is None, label


def test_a_robot_that_shrinks_as_it_warms_beyond_any_structure_is_a_finding(ur10):
    """A thermal expansion keeps a carbon-fibre laminate's slightly negative coefficient
    (floor -2e-6 1/K) and a value within three std of that floor; below, it is refused
    like a negative play. Before, 300 position-only rows of the shared UR10's Series A
    (0.75 K of temperature span) named ``thermal_expansion = -1.8e-4 +- 2.9e-5 1/K`` as
    a cause, with a warning only (``python experiments/row_checks.py``, case drift)."""
    rng = run_rng("sign-rule-thermal")
    floor = type(hpk.make_effect(ur10, "thermal_expansion")).floor
    assert -1e-5 < floor < 0  # slightly negative: a laminate, not a shrinking robot
    laminate = float(rng.uniform(floor, 0.0))
    assert implausibility(hpk.make_effect(ur10, "thermal_expansion", laminate), ur10) is None
    sd = float(rng.uniform(1e-6, 3e-5))
    for k, refused in ((1.0, False), (2.9, False), (3.1, True), (9.0, True)):
        alpha = floor - k * sd
        why = implausibility(hpk.make_effect(ur10, "thermal_expansion", alpha), ur10, std=[sd])
        assert (why is not None) == refused, (k, why)
        if refused:
            assert why["cause"] == "thermal_expansion"
            assert why["limit"] == floor
            assert "shrinks as it warms" in why["why"]
    big = float(rng.uniform(1e-4, 4e-4))  # positive, beyond any metal: warned, not refused
    assert implausibility(hpk.make_effect(ur10, "thermal_expansion", big), ur10) is None


def test_a_component_within_three_std_of_zero_is_zero_not_a_negative_finding(ur10):
    """The sign rule reads a component's standard deviation where the fit gave one: a
    tilt compliance of (-3.7e-10 +- 7.8e-9, 1.08e-6 +- 2e-9) rad/Nm (a component the rows
    barely determine, beside one they do) is zero within 0.05 std, not a negative
    compliance. Refused as negative, it stopped a joint-3 offset from entering a
    pinocchio-generated campaign (sweep seed 737373): the search kept the tilt
    compliance alone in place of the true joint-2 compliance and joint-3 offset."""
    rng = run_rng("sign-rule-std")
    sd = float(rng.uniform(1e-9, 1e-8))
    big = float(rng.uniform(5e-7, 5e-6))
    label = "tilt_compliance:wrist_1_joint"
    for k, refused in ((0.05, False), (2.9, False), (3.1, True), (30.0, True)):
        tilt = hpk.make_effect(ur10, label, torch.tensor([-k * sd, big]))
        why = implausibility(tilt, ur10, std=[sd, sd / 5])
        assert (why is not None) == refused, (k, why)
        if refused:
            assert f"{k:.3g} std below zero" in why["why"], why
    # without a standard deviation (a fit without covariance: NaN) any value below zero
    tilt = hpk.make_effect(ur10, label, torch.tensor([-0.05 * sd, big]))
    assert implausibility(tilt, ur10) is not None
    assert implausibility(tilt, ur10, std=[float("nan"), float("nan")]) is not None
    # one component: a compliance or a play
    for name in ("joint_compliance:elbow_joint", "backlash:wrist_3_joint"):
        effect = hpk.make_effect(ur10, name, -sd)
        assert implausibility(effect, ur10, std=[sd]) is None, name
        assert implausibility(effect, ur10, std=[sd / 10]) is not None, name
