"""A cyclic order enters the search only if it is resolved among *every* order of its
joint, the comparison that takes an unresolved order out after the search, not only
among the orders the cyclic screen let into the step's scoring. On the shared UR10
series (``--max-causes 40``) that kept 7 unresolved orders from taking a step each (21
steps -> 14, the same 11 causes). Campaign drawn per run (``tests.helpers.run_rng``)."""

from __future__ import annotations

from hybrid_pk.calibration.diagnosis.blocked import Folds
from hybrid_pk.calibration.diagnosis.carryover import Carry
from hybrid_pk.calibration.diagnosis.entry import first_resolved
from hybrid_pk.calibration.diagnosis.regions import make_folds
from hybrid_pk.calibration.diagnosis.selection import score_candidates
from hybrid_pk.calibration.diagnosis.settle import entry_rivals, order_rivals
from hybrid_pk.calibration.diagnosis.split import split_campaign
from hybrid_pk.calibration.fit import fit
from hybrid_pk.calibration.known_frames import initialise_with_priors
from hybrid_pk.effects import ExtendedModel, conditions_from_data
from tests.helpers import RUN_SEED, banded_poses, cyclic_campaign, run_rng
from tests.test_diagnose_carryover import _ur10


def _unresolved_campaign(rng):
    """A UR10 with a cyclic error of its shoulder lift or elbow of 4-11 per turn,
    measured over 0.6 rad of that joint (at most one period: a neighbouring order fits
    the same rows), moving the point by 1.5-3 noise levels (significant)."""
    robot = _ur10()
    j, order, noise, q = banded_poses(robot, rng, (4, 12), 0.6)
    data, label, amp = cyclic_campaign(robot, q, j, order, (1.5, 3.0), noise, rng)
    return robot, data, label, f"seed {RUN_SEED}: {label}, {amp * 1e6:.1f} µrad"


def test_an_order_the_screen_scored_alone_is_compared_with_every_order():
    robot, data, label, where = _unresolved_campaign(run_rng("order-entry"))
    split = split_campaign(data, conditions_from_data(data), 0.2, 0)
    model = ExtendedModel(robot, effects=[])
    initialise_with_priors(model, split.train, split.cond_fit, None)
    res = fit(model, split.train, cond=split.cond_fit)
    folds = make_folds(model, split, 0)
    assert isinstance(folds, Folds)
    carry = Carry(folds)

    def say(_text):
        return None

    # this step's scoring holds the true order alone: no scored order is its rival
    scores = score_candidates(model, res, [label], split, 1e-3, True, carry=carry)
    (sc,) = scores.scored
    assert scores.eligible(sc), (where, scores.carry, scores.carry_se)
    assert entry_rivals(scores, [], label) == {}
    assert first_resolved(scores, model, [])[0] is sc  # the screened comparison: enters
    # every order of the joint: its neighbours predict the held-out blocks as well
    rivals = order_rivals(model, res, split, carry, label, say, {})
    assert rivals, where
    ambiguous: list[dict] = []
    best, aside = first_resolved(scores, model, ambiguous, (model, res, split, carry, say))
    assert best is None, (where, rivals)
    assert label in aside
    assert {e["order_not_resolved"] for e in ambiguous} == {label.partition(":")[2]}
