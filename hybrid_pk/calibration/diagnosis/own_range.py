"""Periodic errors carry over along their own joint.

The region blocks of :mod:`.blocked` cut joint space along the joints that move the
measured point most: a wrist joint's range is never held out there, and a periodic
law fitted on part of a wrist's range is extrapolated beyond it unchecked. So a cause
whose law repeats within a turn of one joint (an effect class with ``order >= 2``
cycles per turn: the cyclic errors) must also predict the two ends of its own joint's
measured range: the fit rows with the lowest and with the highest angles of that joint
(:data:`END_SHARE` of them each) are held out in turn and predicted by the linearised
refit on the others (the frames of a file seen only there re-fitted on it, as in the
blocked hold-out). Its own-range gain (the drop of the two ends' RMS error when it is
kept, rotation at the noise ratio, as :func:`.carryover.removal_gains`) must reach the
practical margin too; otherwise the cause is not resolved over its joint's range and
is not named (listed beside the ambiguous orders, with the numbers). Both ends are
pooled, as the region blocks are: requiring each end alone took out a 17-per-turn
error of the UR10's elbow (Series A: low end 0.0009 mm, high end 0.020 mm, margin
0.0024 mm) whose model transfers better to Series B (0.451 mm with it, 0.465 without).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import torch

from hybrid_pk.calibration.diagnosis.blocked import Folds
from hybrid_pk.calibration.diagnosis.carryover import linearise
from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.calibration.fit import FitResult
from hybrid_pk.calibration.tuning import diagnosis_tuning
from hybrid_pk.effects import ExtendedModel

__all__ = ["END_SHARE", "end_folds", "off_range", "own_range_gains", "periodic_causes"]

# Each end a quarter of the fit rows: half of them held out in all, as in a two-fold
# check, while every refit keeps three quarters of the rows and of the joint's range.
END_SHARE = 0.25


def periodic_causes(model: ExtendedModel) -> dict[int, list[str]]:
    """``{joint index: labels}`` of the causes whose law repeats within a turn of that
    joint's angle (the classes' ``stage``, ``evidence`` and ``order`` say so)."""
    out: dict[int, list[str]] = {}
    for e in model.effects:
        cls = type(e)
        joint = getattr(e, "joint_index", None)
        if cls.stage == "joint" and cls.evidence == "joint_angle" and cls.order >= 2:
            if joint is not None:
                out.setdefault(joint, []).append(e.label)
    return out


def end_folds(model: ExtendedModel, split: Split, joint: int) -> Folds | None:
    """The two ends of joint ``joint``'s measured range as folds (cells: file x part,
    part 0 the low end, 1 the middle, 2 the high end); None when an end would hold
    fewer rows than a block needs (the tuning's ``min_block_rows``)."""
    data = split.train
    n_end = int(END_SHARE * data.n)
    if n_end < max(diagnosis_tuning().min_block_rows, 1):
        return None
    q = data.q[:, joint]
    order = torch.argsort(q, stable=True)
    part = torch.ones(data.n, dtype=torch.long)
    part[order[:n_end]] = 0
    part[order[-n_end:]] = 2
    several = len(data.sources) > 1
    files = data.file_index if several else torch.zeros(data.n, dtype=torch.long)
    n_files = int(files.max()) + 1
    description = {
        "joint": model.robot.joint_names[joint],
        "end_share": END_SHARE,
        "low_end_below_rad": float(q[order[n_end - 1]]),
        "high_end_above_rad": float(q[order[-n_end]]),
        "range_rad": [float(q.min()), float(q.max())],
        "files": n_files if several else 0,
        "linearised": True,
    }
    folds = (tuple(3 * f for f in range(n_files)), tuple(3 * f + 2 for f in range(n_files)))
    return Folds(files * 3 + part, 3 * n_files, folds, description)


def own_range_gains(
    model: ExtendedModel,
    res: FitResult,
    split: Split,
    progress: Callable[[str], None] | None = None,
) -> dict[str, dict]:
    """Per periodic cause of ``model`` (:func:`periodic_causes`): its own-range gain
    [mm] (``gain_mm``, both ends pooled), its position [mm] and orientation [deg] parts
    (``position_mm``, ``orientation_deg``), each end's (``ends_mm``: low, high) and the
    ends (:func:`end_folds`' description). Causes whose ends would be too small are
    absent."""
    labels = [e.label for e in model.effects]
    out: dict[str, dict] = {}
    for joint, periodic in periodic_causes(model).items():
        folds = end_folds(model, split, joint)
        if folds is None:
            continue
        blocked = linearise(model, res, split, folds, progress, factor=False, share=False)[3]
        ends = [replace(blocked, folds=replace(folds, folds=(f,))) for f in folds.folds]
        for label in periodic:
            rest = [x for x in labels if x != label]
            gain = [b.gain_mm(b.of(rest, [label]), b.of(labels)) for b in [blocked, *ends]]
            parts = blocked.parts(blocked.of(rest, [label]), blocked.of(labels))
            out[label] = {"gain_mm": gain[0], "ends_mm": gain[1:], **parts, **folds.description}
    return out


def off_range(own: dict[str, dict], margin: float, ambiguous: list[dict]):
    """``(label, why)`` of the periodic cause with the smallest own-range gain below
    ``margin`` (its entry appended to ``ambiguous``), or ``(None, "")``."""
    short = {k: v for k, v in own.items() if v["gain_mm"] < margin}
    if not short:
        return None, ""
    label = min(short, key=lambda k: short[k]["gain_mm"])
    r = short[label]
    low, high = r["ends_mm"]
    why = (
        f"not resolved over its joint's range: the rows with {r['joint']} below "
        f"{r['low_end_below_rad']:.3g} rad and above {r['high_end_above_rad']:.3g} rad "
        f"(a quarter of the fit rows each, of {r['range_rad'][0]:.3g} .. "
        f"{r['range_rad'][1]:.3g} rad), each predicted by the refit on the others, gain "
        f"{r['gain_mm']:.3g} mm with it (low end {low:.3g}, high end {high:.3g} mm), less "
        f"than the practical margin {margin:.3g} mm: the law fitted on part of the range "
        "does not hold beyond it, so it is not named"
    )
    ambiguous.append(
        {"effects": [label], "not_resolved_over_range": True, "own_range": r, "why": why}
    )
    return label, why
