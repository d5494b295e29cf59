"""What a cause must carry over in (diagnosis.blocked.position_channel).

By default a cause is judged on the blocked hold-out error of every measured component
(rotation at the noise ratio); with the tuning's ``carry_over_channel: position`` on the
position error of the measured point alone (the refit of every block still uses
rotation).
"""

from __future__ import annotations

import pytest
import torch

from hybrid_pk.calibration.diagnosis.blocked import Blocked, Folds
from hybrid_pk.calibration.problem import ParamBlock
from hybrid_pk.calibration.tuning import ACTIVE, DiagnosisTuning
from hybrid_pk.errors import HybridPKError
from tests.helpers import run_rng


def _grams(rng, rows: int, cells: int):
    """Cell Grams of ``[J r]`` for one effect column that explains a rotation residual
    and does not move the point: position residual noise only, rotation residual
    ``a x column + noise``."""
    cell = torch.as_tensor(rng.integers(0, cells, rows))
    col = torch.as_tensor(rng.standard_normal(3 * rows))
    a = float(rng.uniform(2.0, 5.0))
    r_pos = torch.as_tensor(rng.standard_normal(3 * rows))
    r_rot = a * col + torch.as_tensor(rng.standard_normal(3 * rows))
    pos = torch.zeros(cells, 2, 2, dtype=torch.float64)
    rot = torch.zeros(cells, 2, 2, dtype=torch.float64)
    for c in range(cells):
        m = cell.repeat_interleave(3) == c
        P = torch.stack([torch.zeros(int(m.sum()), dtype=torch.float64), r_pos[m]], 1)
        R = torch.stack([col[m], r_rot[m]], 1)
        pos[c], rot[c] = P.T @ P, R.T @ R
    folds = Folds(cell, cells, tuple((c,) for c in range(cells)), {})
    blocks = (ParamBlock("e", "cyclic_error_3:wrist_3_joint", 1, 1.0, "rad"),)
    return Blocked(pos, rot, folds, blocks, torch.zeros(1, dtype=torch.float64), (0.01, 1e-5))


def test_a_rotation_only_gain_counts_only_when_rotation_counts():
    rng = run_rng("carry-over-channel")
    blocked = _grams(rng, int(rng.integers(200, 600)), int(rng.integers(3, 7)))
    label = "cyclic_error_3:wrist_3_joint"
    with_it, without = blocked.of([label]), blocked.of([], [label])
    parts = blocked.parts(without, with_it)
    assert parts["orientation_deg"] > 0
    assert abs(parts["position_mm"]) < 1e-12
    assert blocked.gain_mm(without, with_it) > 0.5 * 0.01  # the default: a of 2-5 noise units
    with ACTIVE.using(DiagnosisTuning(carry_over_channel="position")):
        assert abs(blocked.gain_mm(without, with_it)) < 1e-12


def test_an_unknown_channel_is_one_clear_error():
    rng = run_rng("carry-over-channel-bad")
    blocked = _grams(rng, 100, 3)
    score = blocked.of([])
    with ACTIVE.using(DiagnosisTuning(carry_over_channel="rotation")):  # type: ignore[arg-type]
        with pytest.raises(HybridPKError, match="carry_over_channel 'rotation'"):
            blocked.gain_mm(score, score)
