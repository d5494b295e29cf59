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
    for label in ("joint_offset:elbow_joint", "gear_ratio:wrist_2_joint", "thermal_expansion"):
        assert implausibility(hpk.make_effect(ur10, label, -small), ur10) is None, label
