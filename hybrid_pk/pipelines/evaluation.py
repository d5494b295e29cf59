"""The evaluation workflow: a model (its frames re-fitted to the data where asked) ->
predicted poses -> position [mm] / orientation [deg] errors (contract 5) -> an
optional report beside the nominal URDF with frames fitted to the same rows.

    res = evaluate_model(load_model("model.pt"), data, model_label="model.pt")
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from hybrid_pk.calibration.conventions import convention_text
from hybrid_pk.calibration.fit import FitResult
from hybrid_pk.calibration.frames import FramePriors
from hybrid_pk.calibration.setup_change import setup_change_error
from hybrid_pk.calibration.setups import FrameFit, separate_setups, setups_text
from hybrid_pk.data import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel, conditions_from_data
from hybrid_pk.evaluation.metrics import evaluate_json, row_errors
from hybrid_pk.io.hybrid_file import predict_poses
from hybrid_pk.io.model_file import NOMINAL_PREFIX, LoadedModel, model_robot
from hybrid_pk.pipelines.calibration import refit_frames
from hybrid_pk.pipelines.refit import refit, with_frame_sets

__all__ = ["AS_TRAINED", "EvaluationResult", "evaluate_model", "networks_summary"]

# The rule of networks no re-fit on a new set-up has judged.
AS_TRAINED = "as trained: no frame re-fit on a new set-up has judged them (calibrate --refit)"


@dataclass(frozen=True)
class EvaluationResult:
    """What :func:`evaluate_model` returns.

    Attributes:
        loaded: the model evaluated (its frames re-fitted with ``fit_frames``).
        poses: predicted flange poses ``(n, 4, 4)``.
        position, orientation: per-row errors [mm], [deg] (orientation None for
            position-only data).
        summary: the contract's JSON document (n, position_mm, orientation_deg; and
            ``networks`` for a file with residual networks: :func:`networks_summary`).
        frame_fit: the frames' fit (None without ``fit_frames``).
        report: the report written (None without ``report``).
        gross_cause: with ``fit_frames``, where the rows are files of separate set-ups
            given one frame set or a set-up changed within them
            (:mod:`hybrid_pk.calibration.setups`, :mod:`~hybrid_pk.calibration.setup_change`):
            the line that says so (the cause of the gross-error warning); else None.
        warnings: with ``fit_frames``, quaternions in another convention
            (:mod:`hybrid_pk.calibration.conventions`).
    """

    loaded: LoadedModel
    poses: Tensor
    position: Tensor
    orientation: Tensor | None
    summary: dict
    frame_fit: FitResult | None = None
    report: Path | None = None
    gross_cause: str | None = None
    warnings: list[str] = dataclasses.field(default_factory=list)


def evaluate_model(
    loaded: LoadedModel,
    data: MeasuredData,
    *,
    model_label: str,
    sets: int | None = None,
    fit_frames: bool = False,
    priors: FramePriors | None = None,
    robust: str | None = None,
    report: str | os.PathLike | None = None,
    stage: Callable[[str], None] | None = None,
) -> EvaluationResult:
    """Errors of MODEL (``loaded``, named ``model_label``) on ``data``.

    Args:
        sets: base/tool frame sets (default: the model's).
        fit_frames: first fit only the base and tool frames to ``data`` (``priors``,
            ``robust`` as in :func:`~hybrid_pk.pipelines.calibration.refit_frames`); a
            file with residual networks is re-fitted as by ``calibrate --refit frames``
            (:func:`~hybrid_pk.pipelines.refit.refit`): the networks are used only if
            they beat the physics on these rows, held out.
        report: directory of the report (None: none).
        stage: told the name of each step.
    """
    stage = stage or (lambda _m: None)
    sets = loaded.model.base.sets if sets is None else sets
    cond = conditions_from_data(data, sets > 1)
    frame_fit = None
    if fit_frames:
        stage("fitting base and tool frames")
        if loaded.has_networks:
            # the rows are a new set-up: its networks are judged on them as on re-fit rows
            moved = refit(
                loaded, data, "frames", frames_per_file=sets > 1, priors=priors, robust=robust
            )
            frame_fit, model, networks = moved.fit, moved.model, moved.networks
        else:
            model, networks = with_frame_sets(loaded.model, sets), loaded.networks
            frame_fit = refit_frames(model, data, cond, priors=priors, robust=robust)
        loaded = dataclasses.replace(loaded, model=model, frames_fitted=True, networks=networks)
    stage("predicting")
    T = predict_poses(loaded, data, cond)
    position, orientation = row_errors(T, data)
    checks = (None, [])
    if fit_frames:  # what the frames fitted to DATA say of its rows
        how = FrameFit(priors, robust, loaded.model.gravity)
        checks = _row_checks(loaded.model, (data, cond), (position, orientation), sets, how)
    summary = evaluate_json(data.n, position, orientation)
    if loaded.has_networks:
        summary["networks"] = networks_summary(loaded)
    written = None
    if report:
        stage("writing the report")
        nominal = model_label.startswith(NOMINAL_PREFIX) and fit_frames
        written = _report(report, model_label, loaded, data, cond, sets, T, nominal)
    return EvaluationResult(loaded, T, position, orientation, summary, frame_fit, written, *checks)


def _row_checks(model: ExtendedModel, rows, errors, sets: int, how: FrameFit):
    """``(gross_cause, warnings)`` of rows evaluated with frames fitted to them: files
    of separate set-ups given one frame set or a set-up that changed within the rows
    (the cause of a gross error), quaternions in another convention (a warning); what
    ``diagnose`` and ``calibrate`` refuse (:mod:`hybrid_pk.calibration.setups`)."""
    (data, cond), (position, orientation) = rows, errors
    cause = None
    if sets == 1:
        own = separate_setups(model.robot, rows, rows, float(position.mean()), how)
        cause = None if own is None else setups_text(len(data.sources), own)
    if cause is None:
        changed = setup_change_error(model, data, cond, how)
        cause = None if changed is None else str(changed)
    warnings = []
    if orientation is not None:
        given = float(orientation.mean())
        text = convention_text(model.robot, rows, rows, given, sets, how)
        warnings += [] if text is None else [text]
    return cause, warnings


def networks_summary(loaded: LoadedModel) -> dict:
    """Whether a file's residual networks were used, and by which rule: the verdict of
    its last re-fit on a new set-up (:mod:`~hybrid_pk.pipelines.network_rule`), else
    used as trained."""
    verdict = loaded.networks.get("transfer")
    return dict(verdict) if verdict else {"used": True, "rule": AS_TRAINED}


def _report(path, label: str, loaded, data, cond: Conditions, sets: int, T, nominal: bool) -> Path:
    """The report of MODEL on DATA beside the nominal URDF with frames fitted to DATA
    (that column left out where MODEL is that model: ``nominal``)."""
    from hybrid_pk.report.evaluation_report import write_evaluation_report

    robot = model_robot(loaded)
    predictions = {}
    if not nominal:
        baseline = ExtendedModel(robot, frame_sets=sets)
        refit_frames(baseline, data, cond)
        with torch.no_grad():
            predictions["nominal + frames fitted to DATA"] = baseline(data.q, cond)
    predictions[Path(label).name] = T
    files = ", ".join(Path(s).name for s in data.sources)
    intro = (
        f"{label} ({robot.name}) on {data.n} rows of {files}. The baseline column is "
        "the nominal URDF whose base and tool frames were fitted to these same rows: "
        "what a user gets without calibration."
    )
    return write_evaluation_report(
        path, data, predictions, intro=intro, joint_types=robot.joint_types
    )[0]
