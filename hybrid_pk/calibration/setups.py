"""Files measured from separate set-ups but fitted with one base and tool frame.

A laser tracker moved between two files of a campaign (or a tool re-mounted) gives each
file its own base and tool frame (``--frames-per-file``). Fitted with one shared set,
the nominal model misses the rows by about the distance between the set-ups: 618 mm
(mean) on the two shared UR10 series, where each file's own frames leave 0.8 mm. No small
cause explains that: the diagnosis named nothing, listed every row of one file as an
outlier and spent its search on it, and a calibration fits effects to it.

:func:`separate_setups` tells the two apart by the diagnosis' own line between small
corrections and gross errors (``gross_error_mm``): where one frame set misses the rows
by more, and each file's own frames by less, the files are separate set-ups. The
diagnosis, the calibration and ``train --fit-frames`` then stop before any effect is
fitted or network trained, naming the flag (:func:`check_one_setup`); ``evaluate
--fit-frames`` says so in its gross-error warning (before: "the rows are not this
robot's").
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from hybrid_pk.calibration.fit import fit
from hybrid_pk.calibration.frames import FramePriors
from hybrid_pk.calibration.known_frames import initialise_with_priors
from hybrid_pk.calibration.poses import model_errors
from hybrid_pk.calibration.tuning import diagnosis_tuning
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel, Gravity
from hybrid_pk.errors import DataError
from hybrid_pk.robot import Robot

__all__ = ["FrameFit", "check_one_setup", "own_frame_rows", "separate_setups", "setups_text"]

# Residuals per frame parameter a file must give before its own frames are trusted to
# say "small": two, so that as many residuals are left to judge the fit as it used.
RESIDUALS_PER_PARAMETER = 2
# A check fits frames only where their closed-form registration leaves less than this
# many times the line it tests: on rows a model explains the registration is within the
# noise of the fit, and twice the line leaves room for one thrown by the model's errors.
SCREEN_FACTOR = 2.0


Rows = tuple[MeasuredData, Conditions]  # rows and their conditions


@dataclass(frozen=True)
class FrameFit:
    """How a nominal model's frames were fitted, so that the checks of this module and
    of :mod:`.setup_change`, :mod:`.conventions` fit others the same way: the known
    frames (``--tool``, ``--base``) and frame prior, the robust loss, the mounting."""

    priors: FramePriors | None = None
    robust: str | None = None
    gravity: Gravity | None = None

    def errors(self, robot: Robot, rows: Rows, judged: Rows, sets: int = 1, refine=True):
        """Per-row position [mm] and orientation [deg] errors (None without
        orientations) on ``judged`` of the nominal model with ``sets`` frame sets (the
        groups of the conditions) fitted to ``rows``; without ``refine``, registered
        only (closed form, the fit's start)."""
        (data, cond), (test, cond_test) = rows, judged
        model = ExtendedModel(robot, frame_sets=sets, gravity=self.gravity)
        initialise_with_priors(model, data, cond, self.priors)
        if refine:
            fit(model, data, cond=cond, frames=self.priors, robust=self.robust)
        return model_errors(model, test, cond_test)


def check_one_setup(
    robot: Robot, rows: Rows, judged: Rows, shared_mm: float, how: FrameFit
) -> None:
    """Refuse files of separate set-ups fitted with one frame set: where
    :func:`separate_setups` finds them, a :class:`~hybrid_pk.errors.DataError` naming
    both errors and ``--frames-per-file``, before any effect is fitted (the arguments
    are its)."""
    own_mm = separate_setups(robot, rows, judged, shared_mm, how)
    if own_mm is None:
        return
    gross = diagnosis_tuning().gross_error_mm
    raise DataError(
        f"one base/tool frame set misses the rows by {shared_mm:.4g} mm (mean), beyond "
        f"what small corrections make ({gross:g} mm): "
        f"{setups_text(len(rows[0].sources), own_mm)}"
    )


def setups_text(files: int, own_mm: float) -> str:
    """What :func:`separate_setups`' answer means, and the flag that follows from it."""
    return (
        f"the {files} files look like separate set-ups (each file's own frames miss them "
        f"by {own_mm:.3g} mm: the tracker moved or the tool was re-mounted between them); "
        "rerun with --frames-per-file (Python: frames_per_file=True)"
    )


def separate_setups(
    robot: Robot, rows: Rows, judged: Rows, shared_mm: float, how: FrameFit
) -> float | None:
    """Each file's own frames' mean position error [mm] where it shows the files to be
    separate set-ups, else None.

    Args:
        robot: the nominal robot (the frames of its nominal model are compared).
        rows: the rows the frames were fitted to and their conditions (one frame set).
        judged: the rows ``shared_mm`` was measured on (the hold-out, or the same rows)
            and their conditions.
        shared_mm: mean position error [mm] there of a model with one frame set fitted
            to ``rows``.
        how: how that fit was made.

    Returns:
        The error of each file's own frames, fitted the same way, where ``shared_mm`` is
        beyond ``gross_error_mm`` and that error is not; None otherwise, and with one
        file or a file with too few rows for frames of its own (:func:`own_frame_rows`).
    """
    (data, cond), (test, cond_test) = rows, judged
    files = len(data.sources)
    gross = diagnosis_tuning().gross_error_mm
    counts = data.file_index.bincount(minlength=files)
    if files < 2 or not shared_mm > gross or not bool((counts >= own_frame_rows(data)).all()):
        return None
    own = (data, replace(cond, group=data.file_index))
    position, _ = how.errors(robot, own, (test, replace(cond_test, group=test.file_index)), files)
    own_mm = float(position.mean())
    return own_mm if own_mm <= gross else None  # else the frames are not what is wrong


def own_frame_rows(data: MeasuredData) -> int:
    """Rows a file (or a part of one) of ``data`` needs before frames of its own are
    trusted: :data:`RESIDUALS_PER_PARAMETER` residuals per parameter of them (12; 9
    position-only: the tool's rotation is unseen)."""
    per_row, params = (3, 9) if data.quat is None else (6, 12)
    return -(-RESIDUALS_PER_PARAMETER * params // per_row)
