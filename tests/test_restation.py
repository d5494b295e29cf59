"""A set-up transfer: the lifting-column arm calibrated standing upright, re-stationed on
an 8° tilted base (issue 27). Only the base frame is re-fitted, on rows of one flange
orientation (a total station's stationing); gravity comes from the levelled instrument
(``--gravity level-tracker``), so the calibrated compliance follows the tilt. The
campaign and the commands are ``experiments/restation.py``'s."""

from __future__ import annotations

import numpy as np
import pytest

from experiments.restation import restation
from tests.helpers import RUN_SEED, run_rng

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_thread")]

# The construction robot: nominal + frames 10.07 mm at a noise of 0.75 mm, some
# 13 sigma; the effects at scale 1 give 1-3 mm, so 0.1 mm keeps that regime (a ratio of
# 0.3 needs a noise floor well under 0.3x the nominal error).
NOISE_MM = 0.1
N_CALIBRATION = 600


def test_restationed_on_a_tilted_base(tmp_path):
    r = restation(lambda: run_rng("restation"), RUN_SEED % 1000, tmp_path, 1.0, NOISE_MM,
                  N_CALIBRATION)  # fmt: skip
    print(f"re-stationed at 8 deg: {r} (seed {RUN_SEED})")
    assert np.isfinite(r["ratio"])
    assert r["ratio"] <= 0.3, (r, RUN_SEED)


def test_a_soft_joint_carries_to_the_tilted_set_up_at_the_construction_robots_noise(tmp_path):
    """The issue's construction robot: 0.75 mm noise, 444 rows, nominal + frames some ten
    times the noise (the effects at 4x: 6-24 mm), the loaded joint as soft as a cobot's
    (1e-4 .. 2.6e-4 rad/Nm). Its compliance is named (within 10 %), so the model follows
    the tilt; with the old 1e-4 rad/Nm limit it was flagged, the search stopped, and the
    ratio was 0.56 (median of 15 seeds, up to 1.0; today 0.105, at most 0.40:
    ``python experiments/restation.py --scale 4 --noise 0.75 --rows 444 --seeds 1-15``)."""
    r = restation(lambda: run_rng("restation-x4"), RUN_SEED % 1000, tmp_path, 4.0, 0.75, 444)
    print(f"construction robot's regime: {r} (seed {RUN_SEED})")
    soft = next(label for label in r["hidden"] if label.startswith("joint_compliance"))
    assert soft in r["named"], (r, RUN_SEED)
    assert abs(r["named"][soft] / r["hidden"][soft] - 1) < 0.1, (r, RUN_SEED)
    assert r["ratio"] <= 0.5, (r, RUN_SEED)
