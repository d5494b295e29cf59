"""The calibration workflow, one place for the CLI, the demo and the experiments:
(diagnose ->) fit the frames of the nominal robot -> fit frames and effects.

    result = calibrate(robot, data)                      # diagnose, then fit the causes
    result = calibrate(robot, data, labels)              # fit these kind:joint effects
    result = calibrate(robot, data, settings=DiagnosisSettings(robust="cauchy"))
    refit_frames(model, data, cond, "tool")              # re-fit one frame, effects kept

``calibrate`` returns a :class:`CalibrationResult` (the fitted model, the nominal model
with its frames fitted, both fits, the diagnosis when one ran); writing the model file
and the URDF is the caller's (``hybrid-pk calibrate`` does both).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from hybrid_pk.calibration.conventions import check_orientation_convention
from hybrid_pk.calibration.diagnosis import Diagnosis, diagnose
from hybrid_pk.calibration.diagnosis.result import cause_labels
from hybrid_pk.calibration.fit import FitResult, fit, model_errors
from hybrid_pk.calibration.frames import FramePriors
from hybrid_pk.calibration.known_frames import initialise_with_priors
from hybrid_pk.calibration.settings import DiagnosisSettings
from hybrid_pk.calibration.setup_change import check_setup_change
from hybrid_pk.calibration.setups import FrameFit, check_one_setup
from hybrid_pk.data import MeasuredData
from hybrid_pk.effects import (
    Conditions,
    Effect,
    ExtendedModel,
    conditions_from_data,
    make_effect,
    unloaded_reason,
)
from hybrid_pk.errors import HybridPKError
from hybrid_pk.robot import Robot

__all__ = [
    "FRAME_LABELS",
    "CalibrationResult",
    "calibrate",
    "cause_labels",
    "diagnose_and_calibrate",
    "refit_frames",
]

# Parameter blocks of the frames, by --refit choice (labels of calibration.fit).
FRAME_LABELS = {
    "base": ("base_frame.translation", "base_frame.rotation"),
    "tool": ("tool_frame.translation", "tool_frame.rotation"),
}
FRAME_LABELS["frames"] = FRAME_LABELS["base"] + FRAME_LABELS["tool"]


@dataclass(frozen=True)
class CalibrationResult:
    """What :func:`calibrate` returns.

    Attributes:
        model: frames and effects fitted on all rows.
        nominal: the nominal robot with its frames fitted (the baseline).
        fit: the fit of ``model``; ``nominal_fit`` that of ``nominal``.
        labels: the fitted effects (``kind:joint``).
        diagnosis: the diagnosis that chose them, or None when they were given.
        conditions: the rows' operating conditions the fits used.
    """

    model: ExtendedModel
    nominal: ExtendedModel
    fit: FitResult
    nominal_fit: FitResult
    labels: list[str]
    diagnosis: Diagnosis | None
    conditions: Conditions


def refit_frames(
    model: ExtendedModel,
    data: MeasuredData,
    cond: Conditions,
    which: str = "frames",
    priors: FramePriors | None = None,
    robust: str | None = None,
) -> FitResult:
    """Register then least-squares fit only the ``which`` frame(s); effects stay fixed.

    Args:
        which: ``"base"``, ``"tool"`` or ``"frames"`` (both).
        priors: known frames (``--tool``, ``--base``) and the prior of the fit.
        robust: robust loss (``--robust``), or None.
    """
    initialise_with_priors(model, data, cond, priors, which=which)
    return fit(model, data, free=list(FRAME_LABELS[which]), cond=cond, frames=priors, robust=robust)


def calibrate(
    robot: Robot,
    data: MeasuredData,
    labels: Sequence[str] | None = None,
    *,
    settings: DiagnosisSettings | None = None,
    frames_per_file: bool = False,
    stage: Callable[[str], None] | None = None,
    progress: Callable[[str], None] | None = None,
) -> CalibrationResult:
    """Fit base/tool frames and physical effects to ``data``.

    Args:
        labels: the effects to fit; None diagnoses them first (``--effects auto``), the
            fit then starts at the diagnosed values.
        settings: the fits' known frames, robust loss and mounting and the diagnosis'
            settings (hold-out, seed, candidates, margin, tuning): what ``hybrid-pk
            calibrate``'s flags and ``--config`` give (default: ``DiagnosisSettings()``).
        frames_per_file: each file of ``data`` gets its own base and tool frames.
        stage: told the name of each step; ``progress``: the diagnosis' messages.
    """
    settings = settings or DiagnosisSettings()
    priors, robust, gravity = settings.priors(), settings.loss(), settings.mounting()
    stage = stage or (lambda _m: None)
    sets = len(data.sources) if frames_per_file else 1
    cond = conditions_from_data(data, frames_per_file)
    diag = None
    if labels is None:
        stage("diagnosing effects")
        keywords = settings.keywords() | {"frames": priors, "gravity": gravity}
        diag = diagnose(robot, data, frames_per_file=frames_per_file, progress=progress, **keywords)
        labels = cause_labels(diag)
    start = _start_effects(robot, list(labels), diag.model if diag else None)
    model = ExtendedModel(robot, start, frame_sets=sets, gravity=gravity)
    unloaded = unloaded_reason(robot, data.payload)
    if unloaded and model.loaded_effects():
        loaded = ", ".join(e.label for e in model.loaded_effects())
        raise HybridPKError(f"{loaded} cannot be sized: {unloaded}")
    stage("fitting frames to the nominal robot")
    nominal = ExtendedModel(robot, frame_sets=sets, gravity=gravity)
    res0 = refit_frames(nominal, data, cond, priors=priors, robust=robust)
    _check_rows(nominal, data, cond, FrameFit(priors, robust, gravity))
    stage("fitting frames and effects")
    initialise_with_priors(model, data, cond, priors)
    res = fit(model, data, cond=cond, frames=priors, robust=robust, weights=res0.weights)
    return CalibrationResult(model, nominal, res, res0, list(labels), diag, cond)


def _check_rows(nominal: ExtendedModel, data: MeasuredData, cond, how: FrameFit) -> None:
    """Refuse files of separate set-ups given one frame set, a set-up that changed
    within the rows and quaternions in another convention
    (:func:`~hybrid_pk.calibration.setups.check_one_setup`,
    :func:`~hybrid_pk.calibration.setup_change.check_setup_change`,
    :func:`~hybrid_pk.calibration.conventions.check_orientation_convention`), judged
    on the rows ``nominal``'s frames were fitted to, as ``how`` says."""
    position, orientation = model_errors(nominal, data, cond)
    rows, sets = (data, cond), nominal.base.sets
    if sets == 1:
        check_one_setup(nominal.robot, rows, rows, float(position.mean()), how)
    check_setup_change(nominal, data, cond, how)
    if orientation is not None:
        given = float(orientation.mean())
        check_orientation_convention(nominal.robot, rows, rows, given, sets, how)


def diagnose_and_calibrate(robot: Robot, data: MeasuredData, **options) -> CalibrationResult:
    """:func:`calibrate` of the effects the diagnosis names (``--effects auto``)."""
    return calibrate(robot, data, None, **options)


def _start_effects(robot, labels: list[str], diag_model: ExtendedModel | None) -> list[Effect]:
    effects = []
    for label in labels:
        value = None
        if diag_model is not None:
            value = diag_model.effect(label).value.detach().clone()
        effects.append(make_effect(robot, label, value))
    return effects
