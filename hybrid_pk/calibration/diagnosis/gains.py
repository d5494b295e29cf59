"""Each chosen cause's gains (left out and refitted) and its evidence line.

Three gains per cause, each the drop of the RMS error [mm] in the carry-over channel
(:func:`.blocked.position_channel`; by default rotation counted at the noise ratio
``sigma_pos / sigma_rot``, with the tuning's ``carry_over_channel = "position"`` the
position error alone) that leaving it out costs: on the fit rows (in-sample), on the
random hold-out rows, and on the blocked hold-out (regions of joint space, whole
files). The first two are measured with the model refitted without the cause, the last
one linearised per block. A periodic cause
also gives its own-range gain (:mod:`.own_range`: the two ends of its joint's range).
"""

from __future__ import annotations

from collections.abc import Callable

from torch import Tensor

from hybrid_pk.calibration.covariance import MAX_CONDITION
from hybrid_pk.calibration.diagnosis.blocked import position_channel
from hybrid_pk.calibration.diagnosis.result import Cause, report_value
from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.calibration.diagnosis.statistics import weighted_ssr
from hybrid_pk.calibration.diagnosis.variants import refit_without
from hybrid_pk.calibration.fit import FitResult, model_errors
from hybrid_pk.effects import Effect, ExtendedModel
from hybrid_pk.effects.joint import CYCLIC_PREFIX
from hybrid_pk.robot import Robot

__all__ = ["GAIN_REFIT_STEPS", "cap_warnings", "measure_causes", "range_warnings", "stop_warnings"]

# LM steps of the refit without a cause, after its linearised removal: none. The
# linearised start is within ~1e-6 of the refit's cost (a step gains 1e-7 - 3e-6 of it
# on the UR10 series): its parameters within ~0.5 std of the refit's, which moves a
# gain by <= 1e-5 mm there, 1/200 of the practical margin; a step costs a Jacobian.
GAIN_REFIT_STEPS = 0


def measure_causes(
    model: ExtendedModel,
    res: FitResult,
    split: Split,
    steps: list[dict],
    alpha: float,
    errors: tuple[Tensor, Tensor | None],
    progress: Callable[[str], None] | None = None,
    blocked: dict[str, dict] | None = None,
) -> list[Cause]:
    """The causes of ``model``, largest hold-out position gain first.

    A cause's gain is the hold-out mean error of the model refitted without it (its
    linearised removal, :data:`GAIN_REFIT_STEPS` LM steps) minus the full model's
    (``errors``: its per-row hold-out position [mm] and orientation [deg] errors); its
    evidence quotes the step that accepted it. ``blocked``: each cause's blocked gains
    (:func:`.carryover.removal_gains`).
    """
    pos1, ori1 = errors
    causes = []
    full = _full_ssr(model, res, split)  # the full model's, the same for every cause
    exact = [g for g in res.undetermined(MAX_CONDITION) if len(g) > 1]  # likewise
    for e in model.effects:
        say = None
        if progress is not None:
            progress(f"gain of {e.label}")
            say = lambda text, lbl=e.label: progress(f"gain of {lbl}: {text}")  # noqa: E731
        reduced = refit_without(
            model, e.label, split.train, split.cond_fit, res, say, max_iter=GAIN_REFIT_STEPS
        )
        pos_r, ori_r = model_errors(reduced, split.test, split.cond_hold)
        step = next(s for s in steps if s["candidate"] == e.label and s.get("accepted"))
        cause = _cause(e, res, step, alpha, (pos1, ori1), (pos_r, ori_r))
        cause.undetermined = _undetermined(e, exact, cause.value)
        _add_gains(cause, (full, reduced), res, split, (blocked or {}).get(e.label))
        if e.kind.startswith(CYCLIC_PREFIX):
            q = split.train.q[:, e.joint_index]
            cause.fitted_range_rad = [float(q.min()), float(q.max())]
        causes.append(cause)
    causes.sort(key=lambda c: c.position_gain_mm, reverse=True)
    return causes


def _cause(
    e: Effect,
    res: FitResult,
    step: dict,
    alpha: float,
    with_it: tuple[Tensor, Tensor | None],
    without: tuple[Tensor, Tensor | None],
) -> Cause:
    (pos1, ori1), (pos_r, ori_r) = with_it, without
    value, std, components = report_value(e, res.std[res.block_slice(e.label)])
    gain_p = float(pos_r.mean() - pos1.mean())
    gain_o = None if ori1 is None else float(ori_r.mean() - ori1.mean())
    evidence = (
        f"F-test of the refit F = {step['fit_F']:.3g} on {e.value.numel()} dof, "
        f"p = {step['fit_p']:.2g} < {step['threshold']:.1g} (Bonferroni over "
        f"{round(alpha / step['threshold'])} candidates); BIC change "
        f"{step['delta_bic']:.1f}; hold-out mean position error without it "
        f"{float(pos_r.mean()):.4f} mm, with it {float(pos1.mean()):.4f} mm"
    )
    return Cause(
        effect=e.kind,
        joint=e.joint,
        value=value,
        unit=e.unit,
        std=std,
        position_gain_mm=gain_p,
        orientation_gain_deg=gain_o,
        evidence=evidence,
        components=components,
    )


def _undetermined(e: Effect, exact: list[list[str]], value) -> list[dict] | None:
    """The components of ``e`` in one of the ``exact`` groups (parameters the data do not
    separate at all: :meth:`FitResult.undetermined` at :data:`MAX_CONDITION`), where each
    reported component is one parameter; else None."""
    if not isinstance(value, list) or len(value) != e.value.numel():
        return None
    out = []
    for group in exact:
        for k in range(len(value)):
            name = f"{e.label}[{k}]"
            if name in group:
                out.append({"component": k, "with": [n for n in group if n != name]})
    return sorted(out, key=lambda u: u["component"]) or None


def _full_ssr(model: ExtendedModel, res: FitResult, split: Split) -> tuple[float, float]:
    """The full model's weighted sums of squares on the fit and the hold-out rows, in
    the carry-over channel."""
    position = position_channel()
    return (
        weighted_ssr(model, split.train, split.cond_fit, res, position),
        weighted_ssr(model, split.test, split.cond_hold, res, position),
    )


def _add_gains(cause: Cause, models, res: FitResult, split: Split, blocked: dict | None):
    """The cause's in-sample, random and blocked hold-out RMS gains [mm]. ``models``:
    the full model's :func:`_full_ssr` and the model without the cause."""
    (full_fit, full_hold), reduced = models
    sig = res.sigma_pos_mm

    position = position_channel()

    def rms_drop(data, cond, full: float) -> float:
        without = weighted_ssr(reduced, data, cond, res, position) / max(data.n, 1)
        with_it = full / max(data.n, 1)
        return sig * (max(without, 0.0) ** 0.5 - max(with_it, 0.0) ** 0.5)

    cause.in_sample_gain_mm = rms_drop(split.train, split.cond_fit, full_fit)
    cause.random_holdout_gain_mm = rms_drop(split.test, split.cond_hold, full_hold)
    if blocked is not None:
        cause.blocked_holdout_gain_mm = blocked["gain_mm"]
        cause.blocked_holdout_gain_se_mm = blocked.get("se_mm")
        cause.blocked_position_gain_mm = blocked["position_mm"]
        cause.blocked_orientation_gain_deg = blocked.get("orientation_deg")
        cause.blocked_blocks = {"gained": blocked["blocks_gained"], "of": blocked["blocks"]}
        own = blocked.get("own_range")  # a periodic cause: the ends of its joint's range
        if own is not None:
            cause.own_range_gain_mm = own["gain_mm"]
            cause.own_range = own


def range_warnings(causes: list[Cause], robot: Robot) -> list[dict]:
    """A warning per cyclic cause whose joint can move beyond the range it was fitted
    on: there the model extrapolates the periodic law."""
    lower, upper = robot.joint_limits
    out = []
    for c in causes:
        if c.fitted_range_rad is None:
            continue
        j = robot.joint_names.index(c.joint)
        lo, hi = c.fitted_range_rad
        if float(lower[j]) < lo or float(upper[j]) > hi:
            inside = ""
            if c.own_range_gain_mm is not None:  # checked on the ends of the fitted range
                inside = (
                    f" (inside it, the end quarters predicted from the rest gain "
                    f"{c.own_range_gain_mm:.3g} mm with it)"
                )
            out.append(
                {
                    "cause": f"{c.effect}:{c.joint}",
                    "why": f"fitted on {c.joint} in [{lo:.3g}, {hi:.3g}] rad of its range "
                    f"[{float(lower[j]):.3g}, {float(upper[j]):.3g}] rad: beyond the "
                    f"fitted range the model extrapolates the periodic law, unchecked{inside}",
                }
            )
    return out


def stop_warnings(steps: list[dict]) -> list[dict]:
    """A warning for a search that stopped on candidates rejected in a row: which, why,
    and that the candidates after them were not tested."""
    out = []
    for i, s in enumerate(steps):
        stop = s.get("stopped_search")
        if not stop:
            continue
        last = steps[i + 1 - stop["in_a_row"] : i + 1]
        why = "; ".join(f"{t['candidate']}: {t.get('why', 'rejected')}" for t in last)
        out.append(
            {
                "cause": ", ".join(t["candidate"] for t in last),
                "why": f"the search stopped after {stop['in_a_row']} candidates in a row were "
                f"rejected ({why}): the model rather than one candidate looks wrong, and "
                f"the {stop['untested']} candidates after them were not tested",
            }
        )
    return out


def cap_warnings(steps: list[dict]) -> list[dict]:
    """A warning for a search that stopped at its limit with a significant candidate;
    causes taken out after it (settle, swaps) are counted, so the limit and the number
    of named causes agree."""
    out = []
    for i, s in enumerate(steps):
        if not s.get("capped"):
            continue
        taken = sum(1 for t in steps[i + 1 :] if t.get("removed"))
        after = f" ({taken} of them taken out after it: {s['capped'] - taken} named)" * bool(taken)
        gain = "the practical margin"
        if "blocked_gain_mm" in s:  # what it would have entered on: gain ± its standard error
            se = s.get("blocked_gain_se_mm")
            gain = f"{s['blocked_gain_mm']:.3g}" + (f" ± {se:.2g}" if se is not None else "")
            gain += f" mm (margin {s['min_gain_mm']:.3g} mm)"
        out.append(
            {
                "cause": s["candidate"],
                "why": f"still significant (score F {s['score_F']:.3g}, p {s['score_p']:.2g}) "
                f"and gaining {gain} on the blocked hold-out "
                f"when the search stopped at its limit of {s['capped']} "
                f"cause{'s' if s['capped'] != 1 else ''}{after}: the "
                "data carry more causes than were named; --max-causes N names more",
            }
        )
    return out
