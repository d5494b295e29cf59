"""Which cyclic order a joint's periodic error has: an order another one beats on the
blocked hold-out by the margin is resolved, as that one; orders within the margin of
each other are ambiguous (settle's rule, on given blocked advantages)."""

from __future__ import annotations

import pytest

from hybrid_pk.calibration.diagnosis import settle

MARGIN = 0.002  # mm
NAMED = "cyclic_error_17:joint_2"


def _decide(monkeypatch, advantages: dict[str, float]):
    """settle's decision for NAMED when it predicts the blocks ``advantages`` [mm]
    better than each other order."""
    monkeypatch.setattr(settle, "rival_advantages", lambda *a: dict(advantages))
    ambiguous: list[dict] = []
    drop, why, better = settle._unresolved(None, [NAMED], {NAMED: list(advantages)}, MARGIN,
                                           ambiguous)  # fmt: skip
    return drop, why, better, ambiguous


def test_an_order_beaten_by_the_margin_is_replaced_by_the_better_order(monkeypatch):
    drop, why, better, ambiguous = _decide(
        monkeypatch, {"cyclic_error_4:joint_2": -0.023, "cyclic_error_16:joint_2": 0.01}
    )
    assert (drop, better) == (NAMED, "cyclic_error_4:joint_2")
    assert "better by 0.023 mm" in why
    assert ambiguous == []  # resolved, as order 4


@pytest.mark.parametrize(
    "advantages",
    [
        {"cyclic_error_18:joint_2": 0.001},  # a tie within the margin
        {"cyclic_error_18:joint_2": -0.001},  # better, but by less than the margin
        # two orders better by the margin, within the margin of each other
        {"cyclic_error_4:joint_2": -0.0230, "cyclic_error_8:joint_2": -0.0225},
    ],
)
def test_orders_within_the_margin_of_each_other_are_ambiguous(monkeypatch, advantages):
    drop, why, better, ambiguous = _decide(monkeypatch, advantages)
    assert drop == NAMED
    assert better is None
    assert why.startswith("order not resolved")
    assert {a["effects"][1] for a in ambiguous} == set(advantages)


def test_a_resolved_order_stays(monkeypatch):
    assert _decide(monkeypatch, {"cyclic_error_18:joint_2": 0.01})[:3] == (None, "", None)
