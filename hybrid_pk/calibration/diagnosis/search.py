"""Diagnosis: what the nominal model gets wrong, and which physical effects explain it.

1. Split rows into fit and hold-out sets; fit base and tool frames to the nominal
   robot (the ``nominal`` errors of the report are on the hold-out rows).
2. Forward selection (:mod:`.selection`): score every candidate from one Jacobian at
   the current model, refit the best one, keep it if the refit's F-test, BIC and
   hold-out error agree. Then the next step.
3. Backward elimination (:mod:`.elimination`) after each addition; after the search,
   a cause with a near-duplicate is swapped for it where the data then need fewer
   causes (:mod:`.swaps`).
4. Ambiguity (:mod:`.ambiguity`): candidates equivalent to a fitted frame, chosen
   causes whose correction another candidate could make, correlated estimates, and
   (:mod:`.stand_ins`) candidates not named that named causes together could mimic;
   such a candidate is named in place of one of them where the swap rule keeps it
   (:mod:`.group_swaps`); before that, a cause whose exchange (out, two forward steps
   in its place) gives a simpler model is exchanged (:mod:`.exchanges`).
5. Each cause's gain is measured by leaving it out (refit without it) on the
   hold-out rows (:mod:`.gains`). What remains is tested for structure: residuals of
   neighbouring configurations (in joint space) correlate when a smooth error is left
   unexplained.
"""

from __future__ import annotations

from collections.abc import Callable

from hybrid_pk.calibration.conventions import check_orientation_convention
from hybrid_pk.calibration.diagnosis.ambiguity import correlated_groups, near_duplicates
from hybrid_pk.calibration.diagnosis.budget import Budget
from hybrid_pk.calibration.diagnosis.carryover import Carry, weakest
from hybrid_pk.calibration.diagnosis.cyclic_screen import screen_cyclic
from hybrid_pk.calibration.diagnosis.elimination import eliminate
from hybrid_pk.calibration.diagnosis.entry import first_resolved, note_cap, untested, why_stop
from hybrid_pk.calibration.diagnosis.gains import (
    cap_warnings,
    measure_causes,
    range_warnings,
    stop_warnings,
)
from hybrid_pk.calibration.diagnosis.group_swaps import final_model
from hybrid_pk.calibration.diagnosis.leftovers import outliers_json, robust_json, unexplained_json
from hybrid_pk.calibration.diagnosis.noise import measurement_noise
from hybrid_pk.calibration.diagnosis.plausibility import (
    carried_finding,
    implausible_effect,
    plausibility_warnings,
    refusal_why,
)
from hybrid_pk.calibration.diagnosis.power import (
    check_determined,
    detectable_json,
    frame_parameters,
)
from hybrid_pk.calibration.diagnosis.regions import make_folds
from hybrid_pk.calibration.diagnosis.result import (
    Cause,
    Diagnosis,
    identifiability_json,
    stats_json,
)
from hybrid_pk.calibration.diagnosis.rivals import rival_stories
from hybrid_pk.calibration.diagnosis.selection import (
    candidate_labels,
    score_candidates,
    try_candidate,
)
from hybrid_pk.calibration.diagnosis.setup_moves import (
    mention_moves,
    setup_move_text,
    setup_moves,
)
from hybrid_pk.calibration.diagnosis.split import Split, split_campaign
from hybrid_pk.calibration.diagnosis.stand_ins import kept_stand_ins
from hybrid_pk.calibration.diagnosis.structural import structural_check
from hybrid_pk.calibration.diagnosis.swaps import prefer_fewer_causes
from hybrid_pk.calibration.diagnosis.variants import with_effects, without_effect
from hybrid_pk.calibration.fit import FitResult, fit, model_errors
from hybrid_pk.calibration.frames import FramePriors
from hybrid_pk.calibration.known_frames import initialise_with_priors
from hybrid_pk.calibration.settings import DiagnosisSettings
from hybrid_pk.calibration.setup_change import check_setup_change
from hybrid_pk.calibration.setups import FrameFit, check_one_setup
from hybrid_pk.calibration.tuning import DiagnosisTuning, diagnosis_tuning, tuned
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import ExtendedModel, Gravity, conditions_from_data, make_effect
from hybrid_pk.robot import Robot
from hybrid_pk.threads import fit_work

__all__ = ["Cause", "Diagnosis", "candidate_labels", "diagnose", "plausibility_warnings"]

_D = DiagnosisSettings()  # the keywords' defaults (one source of each default)


@fit_work
@tuned
def diagnose(
    robot: Robot,
    data: MeasuredData,
    *,
    holdout: float = _D.holdout,
    seed: int = _D.seed,
    candidates: list[str] | None = None,
    alpha: float = _D.alpha,
    max_causes: int = _D.max_causes,
    frames_per_file: bool = False,
    progress: Callable[[str], None] | None = None,
    frames: FramePriors | None = None,
    robust: str | None = None,
    gravity: Gravity | None = None,
    min_gain_mm: float | None = None,
    tuning: DiagnosisTuning | None = None,
) -> Diagnosis:
    """Name the physical causes of the nominal model's errors on ``data``.

    Args:
        robot: nominal robot (not modified).
        data: measured rows, in acquisition order (backlash reads the order).
        holdout: fraction of rows kept out of every fit and used to compare models.
        seed: seed of the hold-out split and of the blocked hold-out's k-means starts.
        candidates: effect labels to consider (default :func:`candidate_labels`).
        alpha: family-wise false-positive rate of the F-tests per step.
        max_causes: stop after this many causes.
        frames_per_file: give each input file its own base and tool frames.
        progress: called with a short text at each stage.
        frames: known frames (``--tool``, ``--base``) and the frame prior of every fit.
        robust: ``"huber"`` or ``"cauchy"``: every fit down-weights rows with gross
            errors (listed in ``robust``); None: least squares. Outliers beyond
            ``OUTLIER_K`` sigma are listed either way.
        gravity: the mounting (root-frame vector or levelled tracker); default upright.
        min_gain_mm: the practical margin [mm] every cause must gain on the blocked
            hold-out (:mod:`.blocked`); None: from the noise estimate
            (:func:`.blocked.practical_margin`).
        tuning: the diagnosis' tuning constants (default :class:`DiagnosisTuning`()).
    """
    say = progress or (lambda _msg: None)
    robot.requires_grad_(False)
    budget = Budget()  # the optional stages' share of the main search's work
    cond = conditions_from_data(data, frames_per_file, robot)
    split = split_campaign(data, cond, holdout, seed)

    say("fitting base and tool frames to the nominal model")
    model = ExtendedModel(
        robot, frame_sets=len(data.sources) if frames_per_file else 1, gravity=gravity
    )
    res = _fit_frames(model, split, frames, robust, say)
    frame_json = None if res.frame_report is None else res.frame_report.to_json()
    nominal_model = with_effects(model)
    with budget.aside():  # the checks of the rows: no work of the search
        nominal = _nominal_errors(model, split, (data, cond, frames_per_file), (frames, robust))

    pool = _pool(robot, data, candidates)
    flagged: list[dict] = []
    carry = Carry(make_folds(model, split, seed), min_gain_mm, measurement_noise(model, data, cond))
    model, res, steps, ambiguous, unobservable = _select(
        model, res, pool, split, (alpha, carry, budget), max_causes, say, flagged
    )
    final = final_model(model, res, pool, split, (alpha, carry, budget), steps, say)
    model, res, flagged = final.model, final.res, flagged + final.flagged
    say("measuring each cause's gain")
    errors = model_errors(model, split.test, split.cond_hold)
    causes = measure_causes(
        model, res, split, steps, alpha, errors, progress=say, blocked=final.gains
    )
    causes, structural, stories, moves = _later_findings(
        model, res, (causes, flagged, pool), split, (carry, nominal_model), say, budget
    )
    ambiguous += correlated_groups(res) + final.unresolved
    ambiguous += kept_stand_ins(final.stand_ins, causes)
    return Diagnosis(
        outliers=outliers_json(model, data, frames_per_file, res),
        robust=robust_json(res, data, split),
        structural=structural,
        frames=frame_json,
        warnings=_warnings(causes, data, steps, robot, budget, moves),
        setup_moves=moves,
        carry_over=carry.rule(res),
        budget=budget.to_json(),
        detectable=detectable_json(model, final.detectable, res.sigma_pos_mm, carry.margin(res)),
        robot=robot.name,
        n_samples=data.n,
        n_holdout=split.test.n,
        nominal=nominal,
        extended=stats_json(*errors),
        causes=causes,
        ambiguous=ambiguous,
        unexplained=unexplained_json(model, split, errors, carry.noise),
        identifiability=identifiability_json(res, unobservable),
        model=model,
        nominal_model=nominal_model,
        fit_rows=split.fit_rows,
        holdout_rows=split.holdout_rows,
        steps=steps,
        rival_stories=stories,
    )


def _later_findings(model, res, named, split, refs, say, budget):
    """The structural search and the rival stories, each under the optional stages'
    ``budget``, and the set-up moves (:mod:`.setup_moves`, named in the structural
    verdict too). ``named``: ``(causes, flagged, pool)``; ``refs``: ``(carry, nominal)``."""
    (causes, flagged, pool), (carry, nominal_model) = named, refs
    with budget.stage("structural search"):
        sigmas = (res.sigma_pos_mm, res.sigma_rot_rad)
        causes, structural = structural_check(
            model, causes, flagged, split, nominal_model, sigmas, say, budget, res
        )
    with budget.stage("rival stories"):
        stories = rival_stories(model, res, pool, split, carry, say, budget)
    moves = setup_moves(model, res, split, carry, say)
    return causes, mention_moves(structural, moves), stories, moves


def _fit_frames(model: ExtendedModel, split, frames, robust, say) -> FitResult:
    """The frames of the nominal model, after refusing a campaign too small for them."""
    check_determined(split, frame_parameters(model, split, frames))
    initialise_with_priors(model, split.train, split.cond_fit, frames)
    return fit(
        model, split.train, cond=split.cond_fit, progress=_prefixed(say, "frames"),
        frames=frames, robust=robust,
    )  # fmt: skip


def _nominal_errors(model: ExtendedModel, split, campaign, fitted) -> dict:
    """The nominal model's hold-out errors (JSON), after refusing files of separate
    set-ups fitted with one frame set, a set-up that changed within the rows, and
    quaternions in another convention (:func:`~hybrid_pk.calibration.setups.check_one_setup`,
    :func:`~hybrid_pk.calibration.setup_change.check_setup_change`,
    :func:`~hybrid_pk.calibration.conventions.check_orientation_convention`).
    ``campaign``: ``(data, cond, frames_per_file)`` (a change of set-up is searched
    on all rows, in their order); ``fitted``: the frame fit's ``(priors, robust)``."""
    data, cond, frames_per_file = campaign
    nominal = stats_json(*model_errors(model, split.test, split.cond_hold))
    rows, judged = (split.train, split.cond_fit), (split.test, split.cond_hold)
    how = FrameFit(*fitted, model.gravity)
    if not frames_per_file:
        check_one_setup(model.robot, rows, judged, nominal["position_mm"]["mean"], how)
    check_setup_change(model, data, cond, how)
    if nominal["orientation_deg"] is not None:
        given, sets = nominal["orientation_deg"]["mean"], model.base.sets
        check_orientation_convention(model.robot, rows, judged, given, sets, how)
    return nominal


def _warnings(causes, data: MeasuredData, steps, robot: Robot, budget: Budget, moves) -> list:
    """Every warning of the diagnosis: plausibility, the cap, ranges, budget cuts, set-up
    moves (:mod:`.setup_moves`)."""
    return (
        plausibility_warnings(causes, data)
        + cap_warnings(steps)
        + stop_warnings(steps)
        + range_warnings(causes, robot)
        + budget.warnings()
        + [{"cause": "set-up", "why": setup_move_text(m)} for m in moves]
    )


def _pool(robot: Robot, data: MeasuredData, candidates: list[str] | None) -> list[str]:
    """The candidates to consider (default :func:`candidate_labels`), those needing a
    temperature only when the data have one."""
    pool = candidates if candidates is not None else candidate_labels(robot, data)
    return [
        c
        for c in pool
        if make_effect(robot, c).needs != "temperature" or data.temperature is not None
    ]


def _select(
    model: ExtendedModel,
    res: FitResult,
    pool: list[str],
    split: Split,
    tests: tuple[float, Carry, Budget],
    max_causes: int,
    say: Callable[[str], None],
    flagged: list[dict],
) -> tuple[ExtendedModel, FitResult, list[dict], list[dict], list[str]]:
    """Forward selection with backward elimination after each accepted cause.

    ``tests``: ``(alpha, carry, budget)``, the F-tests' level, the blocked hold-out's
    blocks and margin, and the work budget of the optional stages (the capped-search
    check and the swaps, after the loop). A candidate whose refit value is not a small physical
    correction is set aside and appended to ``flagged`` (its :func:`implausibility`
    entry).

    Returns the final model and fit, the step records, the ambiguity entries found
    on the way and the candidates without any signature in this data.
    """
    alpha, carry, budget = tests
    ambiguous: list[dict] = []
    steps: list[dict] = []
    unobservable: list[str] = []
    first_step = True
    rejected_in_a_row = 0
    pairs: list[tuple[str, str]] = []  # (chosen, near-duplicate) for the swaps after
    remaining = list(pool)  # every candidate still open, all cyclic orders included
    while remaining and len(model.effects) < max_causes:
        # cyclic orders ranked anew each step: an error an earlier cause explains hides them
        pool, screened = screen_cyclic(
            model, split, remaining, res.weights, carry.folds, carry.margin(res)
        )
        say(f"scoring {len(pool)} candidate effects (step {len(steps) + 1})")
        scores = score_candidates(
            model, res, pool, split, alpha, first_step, progress=say, screened=screened,
            carry=carry,
        )  # fmt: skip
        unobservable += scores.unobservable
        ambiguous += scores.equivalent
        first_step = False
        kept = {s.label for s in scores.scored}
        remaining = [c for c in remaining if c in kept or c not in pool]
        if not scores.scored:
            break
        every_order = (model, res, split, carry, say)
        best, aside = first_resolved(scores, model, ambiguous, every_order)
        remaining = [c for c in remaining if c not in aside]
        if best is None:
            steps.append(untested(scores.ranked[0], scores, why_stop(scores, aside)))
            break
        say(f"testing {best.label}")
        new, new_res, step = try_candidate(
            model, res, best, scores, split, progress=_prefixed(say, f"testing {best.label}")
        )
        steps.append(step)
        remaining = [c for c in remaining if c != best.label]
        implausible = implausible_effect(new, split.train, first=best.label, res=new_res)
        if step["accepted"] and implausible is not None:
            step["accepted"] = False
            implausible = carried_finding(implausible, best.label)
            step["why"] = refusal_why(implausible)
            flagged.append(implausible)
        if not step["accepted"]:
            rejected_in_a_row += 1
            if rejected_in_a_row >= diagnosis_tuning().max_rejected_in_a_row:
                step["stopped_search"] = {"in_a_row": rejected_in_a_row, "untested": len(remaining)}
                break
            continue
        rejected_in_a_row = 0
        # Near-duplicates among the remaining candidates make this choice ambiguous.
        duplicates = near_duplicates(best.label, best.fitted, scores.signatures)
        ambiguous += duplicates
        pairs += [(best.label, d["effects"][1]) for d in duplicates]
        before = [e.label for e in model.effects] + [best.label]
        model, res = new, new_res
        model, res, removed = eliminate(model, res, split, alpha, best.label, steps, say)
        model, res, dropped = _eliminate_blocked(model, res, scores, before, split, steps, say)
        remaining = [c for c in remaining if c not in removed | dropped]
    budget.main_done()
    if remaining and len(model.effects) >= max_causes:
        with budget.stage("capped-search check"):  # one scoring step: done whatever the budget
            pool, screened = screen_cyclic(
                model, split, remaining, res.weights, carry.folds, carry.margin(res)
            )
            limits = (max_causes, screened)
            note_cap(model, res, pool, split, (alpha, carry), limits, steps, say)
    with budget.stage("swaps"):
        model, res = prefer_fewer_causes(
            model, res, pairs, split, (alpha, carry), steps, say, budget
        )
    return model, res, steps, ambiguous, unobservable


def _eliminate_blocked(model, res, scores, before, split, steps, say):
    """Take out, one at a time, causes whose blocked gain (linearised at this step's
    scoring point, ``before`` its effects and the newest) fell below the margin; the
    newest (just measured) stays. Returns the model, its fit and the removed labels."""
    dropped: set[str] = set()
    if scores.blocked is None:
        return model, res, dropped
    newest = before[-1]
    while len(model.effects) > 1:
        labels = [e.label for e in model.effects]
        gone = [x for x in before if x not in labels]
        worst = weakest(scores.blocked, labels, scores.margin, newest, gone)
        if worst is None:
            break
        label, gain = worst
        say(f"removing {label}: it no longer carries over")
        steps.append(
            {
                "candidate": label,
                "removed": True,
                "blocked_gain_mm": gain,
                "min_gain_mm": scores.margin,
                "accepted": False,
                "why": "gains less than the practical margin on the blocked hold-out "
                "once later causes were added",
            }
        )
        model = without_effect(model, label)
        sigmas = (res.sigma_pos_mm, res.sigma_rot_rad)
        res = fit(
            model, split.train, cond=split.cond_fit, initial_sigma=sigmas, progress=say,
            **res.settings(),
        )  # fmt: skip
        dropped.add(label)
    return model, res, dropped


def _prefixed(say: Callable[[str], None], prefix: str) -> Callable[[str], None]:
    """``say`` with ``prefix: `` in front of every message."""
    return lambda text: say(f"{prefix}: {text}")
