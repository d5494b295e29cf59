"""A refit that adds (or swaps in) one cause is judged on every effect it moved, not
only on the new one (hybrid_pk.calibration.diagnosis.plausibility.implausible_effect).

Before, the search, the swaps and the exchanges checked only the effect they added. On
the shared UR10 series without the cause limit, a group swap's refit carried two named
link lengths along the parallel elbow / wrist-2 axes to -2455 and +2455 mm (they
cancel); the structural check then listed them as findings, but the diagnosed model
kept them and a 6.3 mrad shoulder-lift offset with a -6.6 mrad wrist-2 tilt stood in
the causes. Measured with the check on every effect: 13 causes, every link length
below 0.7 mm and every rotation below 1.5 mrad, no structural finding.
"""

from __future__ import annotations

import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.diagnosis.plausibility import (
    carried_finding,
    implausibility,
    implausible_effect,
)
from hybrid_pk.effects import ExtendedModel
from tests.helpers import run_rng


def _model(ur10, far_m: float, tilt_rad: float) -> ExtendedModel:
    return ExtendedModel(
        ur10,
        [
            hpk.make_effect(ur10, "link_length:elbow_joint", torch.tensor([0.0, -far_m, 0.0])),
            hpk.make_effect(ur10, "link_length:wrist_2_joint", torch.tensor([0.0, far_m, 0.0])),
            hpk.make_effect(
                ur10, "axis_misalignment:wrist_2_joint", torch.tensor([tilt_rad, 0.0, 0.0])
            ),
        ],
    )


def test_an_earlier_cause_carried_to_metres_is_caught_with_the_new_one_small(ur10):
    rng = run_rng("plausible-every-effect")
    far = float(rng.uniform(0.1, 3.0))  # [m]: beyond the 50 mm of a URDF correction
    model = _model(ur10, far, float(rng.uniform(1e-4, 1e-3)))
    new = "axis_misalignment:wrist_2_joint"
    assert implausibility(model.effect(new), ur10) is None  # the old check: only the new one
    why = implausible_effect(model, None, first=new)
    assert why is not None
    assert why["cause"] == "link_length:elbow_joint"  # the first of the others, in order
    assert abs(why["value"] - far) < 1e-6 * far  # (float32 values)


def test_the_new_effect_is_named_first_and_a_plausible_model_passes(ur10):
    rng = run_rng("plausible-every-effect-2")
    tilt = float(rng.uniform(0.2, 0.5))  # [rad]: beyond any axis misalignment
    model = _model(ur10, 0.0, tilt)
    why = implausible_effect(model, None, first="axis_misalignment:wrist_2_joint")
    assert why is not None
    assert why["cause"] == "axis_misalignment:wrist_2_joint"
    assert implausible_effect(_model(ur10, 2e-4, 2e-4), None) is None


def test_a_candidate_whose_refit_carried_another_effect_off_is_the_finding(ur10):
    rng = run_rng("plausible-every-effect-3")
    far = float(rng.uniform(0.1, 3.0))
    model = _model(ur10, far, 2e-4)
    why = implausible_effect(model, None, first="thermal_expansion")
    finding = carried_finding(why, "thermal_expansion")
    assert finding["cause"] == "thermal_expansion"  # the candidate, not a named cause
    assert finding["moved"] == "link_length:elbow_joint"
    assert "its refit carries link_length:elbow_joint off" in finding["why"]
    assert carried_finding(why, "link_length:elbow_joint") is why  # its own value: as is
