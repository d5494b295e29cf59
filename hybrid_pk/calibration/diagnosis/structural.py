"""A cause is a small correction of the URDF; a large one says the URDF is wrong.

Statistically supported is not physically credible. A fitted effect is *implausible*
(:func:`~hybrid_pk.calibration.diagnosis.plausibility.implausibility`) when its value
is beyond what the physics it names can be:

- a rotation (joint offset, axis misalignment, eccentricity amplitude) beyond
  ``MAX_ROTATION_DEG``, a backlash beyond ``MAX_BACKLASH_DEG``;
- a translation (link length; the offset of a prismatic joint) beyond
  ``MAX_TRANSLATION_M``;
- a gear ratio error beyond ``MAX_GEAR_RATIO``;
- a compliance beyond ``MAX_COMPLIANCE`` (metal joints and gearboxes), or one that
  bends or tilts its joint by more than ``MAX_ROTATION_DEG`` under the gravity of the
  data;
- any other effect with a value of unit rad / m beyond the rotation / translation
  limit;

or when its *signature is mostly the frames'*: more than the tuning's ``max_frame_share`` of the
displacement it makes is what a change of the base and tool frames makes too, so its
value measures a trade-off with the frames, not a physical error.

Such a cause is never listed as a plain cause. The diagnosis instead looks for the
place where the URDF is wrong (:func:`locate_structural_error`): at each joint a full
origin correction (translation, rotation about the joint axis and perpendicular to it)
is fitted without limits, and the joint whose correction explains the errors best is
named with the size of the correction and the error it would leave.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from hybrid_pk.calibration.diagnosis.budget import Budget
from hybrid_pk.calibration.diagnosis.frame_share import (
    determined_part,
    displacement,
    even_subset,
    frame_share,
    off_frames,
)
from hybrid_pk.calibration.diagnosis.plausibility import effect_std, finding_entry, implausibility
from hybrid_pk.calibration.fit import fit, model_errors
from hybrid_pk.calibration.frames import FramePriors
from hybrid_pk.calibration.tuning import diagnosis_tuning
from hybrid_pk.calibration.work import done as work_done
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import (
    ExtendedModel,
    effect_joint_names,
    make_effect,
)
from hybrid_pk.effects.geometric import AxisMisalignment, LinkLength
from hybrid_pk.effects.joint import JointOffset
from hybrid_pk.effects.limits import (
    MAX_ROTATION_DEG,
    MAX_TRANSLATION_M,
)
from hybrid_pk.geometry import so3_exp, so3_log, twist_swing

__all__ = [
    "MAX_ROTATION_DEG",
    "MAX_TRANSLATION_M",
    "locate_structural_error",
    "structural_check",
]


def _origin_correction(model: ExtendedModel, joint: str, data: MeasuredData, cond) -> dict:
    """Rotation [deg] (and axis in the joint frame) and translation [mm] of the origin
    correction held by the joint's offset, misalignment and link-length effects; the
    translation without the part a change of the frames makes as well
    (:func:`_frame_free_move`, on ``data``)."""
    robot = model.robot
    misalignment = model.effect(f"{AxisMisalignment.kind}:{joint}")
    axis = torch.as_tensor(robot.spec.axes[misalignment.joint_index], dtype=torch.float64)
    R = so3_exp(misalignment.rotation_vector().detach().double())
    offset, prismatic = 0.0, False
    if f"{JointOffset.kind}:{joint}" in [e.label for e in model.effects]:
        j = robot.joint_names.index(joint)
        prismatic = robot.joint_types[j] == "prismatic"
        offset = float(model.effect(f"{JointOffset.kind}:{joint}").value.detach())
        if not prismatic:
            R = R @ so3_exp(axis * offset)
    rotvec = so3_log(R)
    dp = _frame_free_move(model, f"{LinkLength.kind}:{joint}", data, cond)
    angle = math.degrees(float(rotvec.norm()))
    unit = rotvec / rotvec.norm().clamp_min(1e-300)
    mm = 1e3 * float(dp.norm()) + (1e3 * abs(offset) if prismatic else 0.0)
    twist, swing = (math.degrees(float(a)) for a in twist_swing(R, axis / axis.norm()))
    # a turn about the joint's own axis beyond a small correction, the rest within one:
    # the joint's zero, not its origin (a controller counting from another zero); only
    # a joint with a column of its own (a mimic segment's zero is its driver's)
    revolute = robot.chain_joint_types[misalignment.joint_index] != "prismatic"
    own = revolute and joint in robot.joint_names
    zero = own and abs(twist) > MAX_ROTATION_DEG and swing <= MAX_ROTATION_DEG
    return {
        "rotation_deg": angle,
        "rotation_axis": [float(x) for x in unit],
        "translation_mm": mm,
        "joint_zero_deg": twist if zero else None,
    }


# A direction of a link length whose frame-free displacement is below this fraction of
# the largest direction's is a frame change (selection.RANK_TOLERANCE: 1e-4 of the
# norm, a motion no tracker resolves).
FRAME_MOVE_FRACTION = 1e-4


def _frame_free_move(model: ExtendedModel, label: str, data: MeasuredData, cond) -> Tensor:
    """``(3,)`` [m] link length ``label``'s value without its directions whose
    displacement a change of the base and tool frames makes exactly (the origin after
    the first joint moved along that joint's axis is a base translation): the fits of the
    structural search hold no frame prior, so such a direction goes wherever the fit's
    path leaves it and measures no error of the URDF."""
    value = model.effect(label).value.detach().double().reshape(-1)
    data, cond = even_subset(data, cond)
    unit = torch.eye(3, dtype=value.dtype) * 1e-3  # 1 mm along each axis: exactly linear
    fields = [displacement(model, label, data, cond, u) for u in unit]
    free = off_frames(model, data, cond, *fields)
    _, S, Vh = torch.linalg.svd(torch.stack([f.reshape(-1) for f in free], 1), full_matrices=False)
    kept = Vh[S > FRAME_MOVE_FRACTION * S[0]]
    return kept.T @ (kept @ value)


# The structural search fits without limits: no frame prior, so nothing held either
# (its start is the nominal fit's frames, fitted to a structure that may be wrong).
_PLAIN = FramePriors(tool_std_m=math.inf, base_std_m=math.inf, rotation_std_rad=math.inf)


def _fit_correction(nominal: ExtendedModel, joint: str, split, sigmas, start: Tensor | None):
    """The nominal model plus a full origin correction of ``joint``, fitted (frames too)
    on the fit rows from ``start`` (a misalignment on its basis, or zero). Returns the
    model and its mean hold-out position error [mm]."""
    robot = nominal.robot
    labels = [f"{AxisMisalignment.kind}:{joint}", f"{LinkLength.kind}:{joint}"]
    if joint in robot.joint_names:  # an independent joint (not a mimic) has an offset
        labels.append(f"{JointOffset.kind}:{joint}")
    effects = [make_effect(robot, lb) for lb in labels]
    if start is not None:
        with torch.no_grad():
            effects[0].value.copy_(start)
    model = ExtendedModel(robot, effects, frame_sets=nominal.base.sets, gravity=nominal.gravity)
    model.base.reset_to(nominal.base.matrix().detach())
    model.tool.reset_to(nominal.tool.matrix().detach())
    # 40 LM steps: a cap for a fit that does not settle (one that converges from the
    # nominal start takes a handful)
    fit(model, split.train, cond=split.cond_fit, covariance=False, max_iter=40,
        sigma_pos_mm=sigmas[0], sigma_rot_rad=sigmas[1],
        frames=_PLAIN)  # fmt: skip
    return model, float(model_errors(model, split.test, split.cond_hold)[0].mean())


def locate_structural_error(
    nominal: ExtendedModel,
    split,
    sigmas: tuple[float, float | None],
    hint: list[str] = (),
    say: Callable[[str], None] | None = None,
    budget: Budget | None = None,
) -> dict | None:
    """Where the URDF looks wrong: the joint whose full origin correction (fitted without
    limits on the fit rows) leaves the smallest mean hold-out error.

    Joints named in ``hint`` (those of implausible causes) are tried first; the search
    stops at the first correction that explains the error (leaves less than the
    tuning's ``structural_fraction`` of it). Only when none does, each joint is refitted
    from quarter and half turns about its perpendicular axes (a large rotation is out of
    reach of a fit that starts at zero), the joints whose plain correction left the
    least first. With a ``budget`` the search stops before a fit that would overrun it
    (one as large as the largest so far; the plain fits of the hinted joints, or of the
    first joint without hints, are always made) and records what it left undone.

    Returns:
        ``{"joint", "rotation_deg", "rotation_axis", "translation_mm",
        "holdout_mean_mm_before", "holdout_mean_mm_after"}``, or None if no joint can
        take geometric corrections.
    """
    say = say or (lambda _m: None)
    robot = nominal.robot
    before = float(model_errors(nominal, split.test, split.cond_hold)[0].mean())
    chain = effect_joint_names(robot, LinkLength)[1:]  # origin 0: the base's
    joints = [j for j in chain if j in hint]
    joints += [j for j in chain if j not in joints]
    tasks = [(j, None) for j in joints]  # (joint, start) fits, in order
    floor = [j for j in joints if j in hint] or joints[:1]  # fitted whatever the budget
    best, plain, k, largest = None, {}, 0, 0  # largest: the most work of a fit so far
    while k < len(tasks):
        joint, start = tasks[k]
        spent = budget is not None and budget.spent(largest)
        if spent and (start is not None or joint not in floor):
            left = sorted({j for j, s in tasks[k:] if s is None})
            turns = sorted({j for j, s in tasks[k:] if s is not None})
            budget.cut("structural search", [*left, *(f"{j} (turned starts)" for j in turns)])
            break
        if start is None or start is _TURNS[0]:
            say(f"looking for a structural error at {joint}")
        w0 = work_done()
        model, after = _fit_correction(nominal, joint, split, sigmas, start)
        largest = max(largest, work_done() - w0)
        plain.setdefault(joint, after)
        if best is None or after < best[1]:
            best = (joint, after, model)
        k += 1
        joint_done = k == len(tasks) or tasks[k][0] != joint or tasks[k][1] is None
        explained = best[1] < diagnosis_tuning().structural_fraction * before
        if joint_done and explained:  # the best of a joint's starts
            break
        if k == len(joints):  # no plain correction explains it: the turned starts
            tasks += [(j, t) for j in sorted(joints, key=plain.get) for t in _TURNS]
    if best is None:
        return None
    if best[1] < diagnosis_tuning().structural_fraction * before and best[0] != chain[0]:
        best = _joint_before(nominal, split, sigmas, (chain, best, plain), (budget, largest))
    joint, after, model = best
    return {
        "joint": joint,
        **_origin_correction(model, joint, split.train, split.cond_fit),
        "holdout_mean_mm_before": before,
        "holdout_mean_mm_after": after,
    }


def _joint_before(nominal, split, sigmas, found, work) -> tuple:
    """``best`` (``found``: the chain, ``(joint, hold-out mm, model)``, the joints fitted)
    or the joint before it in the chain, when that one's correction predicts the
    hold-out as well (within a hold-out mean's standard error, ``sigma / sqrt(rows)``)
    with a smaller move: an offset ``d`` at joint k is exactly a full origin correction
    of the next joint, ``R_k(d) T_next`` (a turn, and a move of the next origin's lever),
    and the offset alone is the simpler story. ``work``: ``(budget, largest fit's work)``."""
    chain, best, plain = found
    budget, largest = work
    before = chain[chain.index(best[0]) - 1]
    if before in plain:  # fitted already: it did not explain the error
        return best
    if budget is not None and budget.spent(largest):
        budget.cut("structural search", [f"{before} (the joint before {best[0]})"])
        return best
    model, after = _fit_correction(nominal, before, split, sigmas, None)
    tolerance = sigmas[0] / math.sqrt(split.test.n)  # [mm]
    rows = (split.train, split.cond_fit)
    moved = _origin_correction(model, before, *rows)["translation_mm"]
    next_move = _origin_correction(best[2], best[0], *rows)["translation_mm"]
    if after <= best[1] + tolerance and moved < next_move:
        return before, after, model
    return best


# Starting misalignments of the second search: quarter and half turns on the basis.
_TURNS = tuple(
    torch.tensor([a, 0.0] if k == 0 else [0.0, a], dtype=torch.float64)
    for k in range(2)
    for a in (math.pi / 2, -math.pi / 2, math.pi)
)


def _located_words(loc: dict) -> str:
    axis = ", ".join(f"{x:+.2f}" for x in loc["rotation_axis"])
    zero = loc["joint_zero_deg"]
    own = (
        ""
        if zero is None
        else f"; that turn is about the joint's own axis but for less than {MAX_ROTATION_DEG:g}°: "
        f"its zero is off by {zero:+.4g}° (joint values counted from another zero than the "
        f"URDF's, as a controller's can be, do this: then add {zero:+.4g}° to the "
        f"{loc['joint']} column)"
    )
    return (
        f"the URDF looks structurally wrong at {loc['joint']}: its origin would have to "
        f"turn by {loc['rotation_deg']:.3g}° about ({axis}) of the joint frame and move by "
        f"{loc['translation_mm']:.3g} mm, which takes the hold-out mean position error "
        f"from {loc['holdout_mean_mm_before']:.4g} to {loc['holdout_mean_mm_after']:.4g} mm{own}"
    )


def _left_mm(model: ExtendedModel, split) -> float:
    """The hold-out mean position error [mm] the diagnosed model leaves."""
    return float(model_errors(model, split.test, split.cond_hold)[0].mean())


def structural_check(
    model: ExtendedModel,
    causes: list,
    flagged: list[dict],
    split,
    nominal: ExtendedModel,
    sigmas: tuple[float, float | None],
    say: Callable[[str], None] | None = None,
    budget: Budget | None = None,
    res=None,
) -> tuple[list, dict | None]:
    """Keep only plausible causes; say where the URDF looks wrong when it does.

    Args:
        model: the diagnosed model (holds the causes' effects).
        causes: the causes found, largest gain first.
        flagged: implausible candidates the selection set aside (``implausibility``
            entries).
        split: the diagnosis's fit / hold-out rows.
        nominal: the nominal model with frames fitted to the fit rows.
        sigmas: noise levels ``(position mm, rotation rad)`` of the structural fits.
        budget: the optional stages' work budget (:mod:`.budget`); the structural
            search stops when it is spent (``budget_cut`` says what it left undone).
        res: the fit of ``model``: its standard deviations say which parameters the
            frame share judges (:func:`frame_share`).

    Returns:
        ``(causes, structural)``: the causes that stay plain causes, and the
        ``"structural"`` section (None when every cause is a small correction and the
        nominal error is not gross). When a structural correction explains the errors
        (it leaves less than the tuning's ``structural_fraction`` of the hold-out
        error), no cause is listed: those found were fitted on a wrong structure and are withheld.
    """
    robot = model.robot
    findings, keep = list(flagged), []
    for c in causes:
        label = f"{c.effect}:{c.joint}" if c.joint else c.effect
        why = implausibility(model.effect(label), robot, split.train, c.std)
        if why is None:
            std = effect_std(res, label)
            share, _, _ = frame_share(model, label, split.train, split.cond_fit, std)
            if share > diagnosis_tuning().max_frame_share:
                part = "it makes" if determined_part(model.effect(label), std) is None else (
                    "the components the rows determine make")  # fmt: skip
                why = finding_entry(
                    label,
                    c.value,
                    None,
                    c.unit,
                    f"{100 * share:.1f} % of the displacement {part} is what a "
                    "change of the base and tool frames makes: its value measures a "
                    "trade-off with the frames, not a physical error",
                )
        (keep if why is None else findings).append(c if why is None else why)
    before = float(model_errors(nominal, split.test, split.cond_hold)[0].mean())
    tuning = diagnosis_tuning()
    if not findings and before < tuning.gross_error_mm:
        return causes, None
    if not findings and _left_mm(model, split) < tuning.structural_fraction * before:
        return causes, None  # gross, but small corrections explain it (a soft joint's sag)
    hint = [f["cause"].partition(":")[2] for f in findings]
    cuts = len(budget.cuts) if budget is not None else 0
    location = locate_structural_error(nominal, split, sigmas, hint, say, budget)
    cut = budget.cuts[-1] if budget is not None and len(budget.cuts) > cuts else None
    explained = (
        location is not None
        and location["holdout_mean_mm_after"] < tuning.structural_fraction * before
        and (location["rotation_deg"] > MAX_ROTATION_DEG
             or location["translation_mm"] > 1e3 * MAX_TRANSLATION_M)
    )  # fmt: skip
    structural = {
        "findings": findings,
        "location": location,
        "structurally_wrong": explained,
        "withheld_causes": [c.to_json() for c in keep] if explained else [],
        "budget_cut": cut,
    }
    if explained:
        structural["message"] = (
            _located_words(location) + ". Correct the URDF there (the joint's <origin>) "
            "and diagnose again; causes fitted on this structure are withheld"
        )
        return [], structural
    names = ", ".join(f["cause"] for f in findings) or "no single cause"
    searched = "" if cut is None else " of those searched before its work budget ran out"
    # a gross nominal error no single correction explains: the URDF may be another robot's
    other = " (or the rows are not this URDF's robot)" if before >= tuning.gross_error_mm else ""
    structural["message"] = (
        f"{names}: not a small correction of the URDF (see findings); no origin "
        f"correction at one joint{searched} explains the errors either, so the URDF may "
        f"be wrong in more than one place{other} or an unmodelled effect is at work"
    )
    return keep, structural
