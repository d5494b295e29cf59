"""Measured orientations written in another convention than the table's.

The table's ``qw qx qy qz`` is the unit quaternion that turns the measurement frame into
the measured frame (contract section 1). Exports differ: some write the inverse (the
measurement frame seen from the target), some the order ``x y z w`` under the same
column names. Either is still a unit quaternion, so no column check sees it; after the
frame fit the orientations then miss by tens of degrees (30.7° inverted and 144.7° as
x y z w on 400 rows of the shared UR10's Series B, ``python experiments/row_checks.py``),
and the diagnosis said nothing of why: nothing named for the inverse, six causes named
for x y z w.

:func:`check_orientation_convention` tells that apart from a robot that is wrong: where
the frame fit leaves an orientation error beyond what a small correction can make
(:data:`~hybrid_pk.effects.limits.MAX_ROTATION_DEG`) and one of the other readings
leaves less, the quaternions are in that convention; it stops before any effect is
fitted, naming the reading and what to do.
"""

from __future__ import annotations

from dataclasses import replace

from torch import Tensor

from hybrid_pk.calibration.setups import SCREEN_FACTOR, FrameFit, Rows
from hybrid_pk.calibration.tuning import diagnosis_tuning
from hybrid_pk.effects.limits import MAX_ROTATION_DEG
from hybrid_pk.errors import DataError
from hybrid_pk.robot import Robot

__all__ = ["READINGS", "check_orientation_convention", "convention_text"]


def _inverse(q: Tensor) -> Tensor:
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def _xyzw(q: Tensor) -> Tensor:
    return q[:, [3, 0, 1, 2]]  # the columns qw qx qy qz hold x y z w


# The other readings of a table's quaternions: (what the table then holds, the quaternion
# of the contract from the columns as read).
READINGS = (
    ("their inverse (qw, -qx, -qy, -qz)", _inverse),
    ("the order x y z w under the columns qw qx qy qz", _xyzw),
    ("the inverse in the order x y z w", lambda q: _inverse(_xyzw(q))),
)


def check_orientation_convention(
    robot: Robot, rows: Rows, judged: Rows, given_deg: float, sets: int, how: FrameFit
) -> None:
    """Refuse quaternions written in another convention: a
    :class:`~hybrid_pk.errors.DataError` with :func:`convention_text`'s line where it
    has one (the arguments are its)."""
    text = convention_text(robot, rows, judged, given_deg, sets, how)
    if text is not None:
        raise DataError(text)


def convention_text(
    robot: Robot, rows: Rows, judged: Rows, given_deg: float, sets: int, how: FrameFit
) -> str | None:
    """The line that says the quaternions are in another convention, or None.

    Args:
        robot: the nominal robot.
        rows: the rows the nominal model's frames were fitted to, and their conditions.
        judged: the rows its errors are judged on (the hold-out, or the same rows).
        given_deg: its mean orientation error [deg] there, the quaternions as given.
        sets: base/tool frame sets of that fit; ``how``: how it was made.

    Returns:
        Where ``given_deg`` is beyond :data:`MAX_ROTATION_DEG` and the frames fitted to
        one of :data:`READINGS` leave less (the one whose closed-form registration
        leaves the least position error, fitted where that is within ``SCREEN_FACTOR``
        times ``gross_error_mm``): the line naming it with both errors. None otherwise
        and without orientations.
    """
    (data, cond), (test, cond_test) = rows, judged
    if data.quat is None or test.quat is None:
        return None
    if not given_deg > MAX_ROTATION_DEG:
        return None
    readings = []  # each reading's registered position error [mm] (closed form: cheap)
    for text, read in READINGS:
        read_rows = (replace(data, quat=read(data.quat)), cond)
        read_judged = (replace(test, quat=read(test.quat)), cond_test)
        registered = how.errors(robot, read_rows, read_judged, sets, refine=False)[0]
        readings.append((float(registered.mean()), text, read_rows, read_judged))
    # Registered, every reading matches the orientations (the relative rotations fix the
    # base's); a wrong one leaves the positions off by the tool's lever (480 mm on Series
    # B inverted, 1.0 mm read right), which the fit then trades for orientation.
    registered_mm, text, read_rows, read_judged = min(readings, key=lambda r: r[0])
    if registered_mm > SCREEN_FACTOR * diagnosis_tuning().gross_error_mm:
        return None  # not a convention: the robot or the rows are wrong (the gross warnings)
    other = float(how.errors(robot, read_rows, read_judged, sets)[1].mean())
    if other > MAX_ROTATION_DEG:
        return None
    return (
        f"the measured orientations miss by {given_deg:.4g}° (mean) after the frame fit, "
        f"beyond what a small correction makes ({MAX_ROTATION_DEG:g}°); read as "
        f"{text} they miss by {other:.3g}°: the table's qw qx qy qz must turn the "
        "measurement frame into the measured frame (contract section 1); convert them, "
        "or leave them out for a position-only diagnosis"
    )
