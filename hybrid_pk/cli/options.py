"""The flags that several sub-commands share, declared once with one wording.

Each ``add_*`` function adds one flag (or one group of flags that belong together) to
an ``argparse`` parser. A command module calls them in its ``register`` and keeps only
its own flags. A new flag that more than one command takes belongs here; one that
only a single command takes stays in that command's module.

Groups:
    the command itself: :func:`command_parser` (with :func:`add_threads`, every command)
    robot and model: :func:`add_robot`, :func:`add_end_link`, :func:`add_model`
    data: :func:`add_data` (DATA..., --frames-per-file, --skip-bad-rows)
    fits: :func:`add_fit_options` (every command that diagnoses or calibrates: the
        hold-out fraction, :func:`add_frame_options` and :func:`add_robust`),
        :func:`add_fit_frames`
    outputs: :func:`add_out`, :func:`add_json`, :func:`add_report`
    runs: :func:`add_seed`, :func:`add_epochs`, :func:`add_noise`, :func:`add_progress`
    solving for targets (ik, compensate): :func:`add_approach`, :func:`add_frame_set`
"""

from __future__ import annotations

import argparse

from hybrid_pk.calibration.frames import MAX_TOOL_TRANSLATION_M
from hybrid_pk.calibration.robust import ROBUST_LOSSES
from hybrid_pk.robot import shipped_robots
from hybrid_pk.threads import ENV as THREADS_ENV
from hybrid_pk.threads import parse_threads

__all__ = [
    "APPROACH_HELP",
    "END_LINK_HELP",
    "ROBOT_HELP",
    "add_approach",
    "add_data",
    "add_end_link",
    "add_epochs",
    "add_fit_frames",
    "add_fit_options",
    "add_frame_options",
    "add_frame_set",
    "add_gravity",
    "add_json",
    "add_model",
    "add_noise",
    "add_out",
    "add_progress",
    "add_report",
    "add_robot",
    "add_robust",
    "add_seed",
    "add_threads",
    "command_parser",
    "fraction",
]

ROBOT_HELP = f"shipped robot name ({', '.join(shipped_robots())}) or URDF path"
END_LINK_HELP = "end link of the chain, e.g. a tool link (default: the URDF's leaf link)"
_ROBOT_CHECK_HELP = "refuse a MODEL made for another robot than ROBOT"
APPROACH_HELP = (
    "backlash: the side each joint approaches the target from, + (moving in the joint's "
    "positive direction), - or mid, for every backlash joint or per joint as "
    "joint_3=+,joint_4=- (default: the mid-play model, half-way between both; a note "
    "says so)"
)


def command_parser(subparsers, name: str, *, help: str, description: str):
    """The parser of sub-command ``name``: ``help`` in the command list, ``description``
    (units, formats) kept as written in ``NAME --help``; every command takes
    ``--threads`` (:func:`add_threads`)."""
    parser = subparsers.add_parser(
        name,
        help=help,
        description=description,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_threads(parser)
    return parser


def _threads(text: str) -> int | str | None:
    """``argparse`` type of ``--threads``."""
    try:
        return parse_threads(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_threads(parser: argparse.ArgumentParser) -> None:
    """``--threads N|auto|torch``: torch's threads (:mod:`hybrid_pk.threads`)."""
    parser.add_argument(
        "--threads",
        type=_threads,
        default=None,
        metavar="N",
        help="torch threads: N, auto (the cores this process may use, one per 2,048 rows "
        "of the work, at most OMP_NUM_THREADS) or torch (torch's own default); waiting "
        f"threads sleep instead of spinning (default: ${THREADS_ENV}, else auto)",
    )


def non_negative_mm(text: str) -> float:
    """``argparse`` type: a length [mm], zero or more."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a length in mm, got {text!r}") from None
    if not value >= 0.0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a finite length >= 0 mm, got {value:g}")
    return value


def fraction(text: str) -> float:
    """``argparse`` type: a fraction of the rows, strictly between 0 and 1."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1), got {text!r}") from None
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(
            f"expected a fraction of the rows in (0, 1), got {value:g} (e.g. 0.2 for 20 %)"
        )
    return value


# ----------------------------------------------------------------------------- robot, model


def add_robot(
    parser: argparse.ArgumentParser,
    *,
    required: bool = False,
    default: str | None = None,
    positional: bool = False,
    help: str | None = None,
) -> None:
    """``--robot ROBOT`` (or the positional ``ROBOT``): a shipped name or a URDF path.

    Args:
        required: the command cannot run without it.
        default: robot used when the flag is not given.
        positional: ``ROBOT`` is the first positional argument (``simulate``).
        help: what the command does with the robot, when more than naming it.
    """
    text = help or ROBOT_HELP
    if default is not None:
        text += " (default: %(default)s)"
    if positional:
        parser.add_argument("robot", metavar="ROBOT", help=text)
    else:
        parser.add_argument(
            "--robot", metavar="ROBOT", required=required, default=default, help=text
        )


def add_end_link(parser: argparse.ArgumentParser) -> None:
    """``--end-link NAME``: the link whose pose is measured or solved for."""
    parser.add_argument("--end-link", metavar="NAME", help=END_LINK_HELP)


def add_model(parser: argparse.ArgumentParser, *, flag: bool = False, help: str | None = None):
    """MODEL (a model file or ``nominal:ROBOT``), ``--robot`` as a check, ``--end-link``.

    Args:
        flag: ``--model MODEL`` (required) instead of the positional ``MODEL``.
        help: what MODEL is for this command.
    """
    text = help or "model file, or nominal:ROBOT (the URDF, identity frames)"
    if flag:
        parser.add_argument("--model", required=True, metavar="MODEL", help=text)
    else:
        parser.add_argument("model", metavar="MODEL", help=text)
    add_robot(parser, help=_ROBOT_CHECK_HELP)
    add_end_link(parser)


# ----------------------------------------------------------------------------- data


def add_data(parser: argparse.ArgumentParser) -> None:
    """``DATA...``, ``--frames-per-file`` and ``--skip-bad-rows``."""
    parser.add_argument(
        "data",
        nargs="+",
        metavar="DATA",
        help="measured pose table(s), .csv or .parquet: one column per joint [rad, m for "
        "prismatic], x y z [m], optional qw qx qy qz, temperature [degC], payload [kg]; "
        "several files are one campaign measured in series",
    )
    parser.add_argument(
        "--frames-per-file",
        action="store_true",
        help="give each DATA file its own base and tool frame (tracker moved, tool "
        "re-mounted); effects are shared",
    )
    parser.add_argument(
        "--skip-bad-rows",
        action="store_true",
        help="leave out rows with NaN/inf, text, out-of-limit joints or non-unit "
        "quaternions (each reported by file and row) instead of stopping at the first",
    )


# ----------------------------------------------------------------------------- fits


def add_fit_options(parser: argparse.ArgumentParser, *, holdout_help: str) -> None:
    """Options of every command that diagnoses effects (``diagnose``, ``calibrate``).

    ``--holdout F``: the fraction of rows the diagnosis keeps out of every fit to
    compare models; ``--min-gain-mm``: the practical margin on the blocked hold-out;
    the known frames (:func:`add_frame_options`), the robust loss
    (:func:`add_robust`) and the mounting (:func:`add_gravity`) of its fits.
    """
    parser.add_argument("--holdout", type=fraction, default=0.2, metavar="F", help=holdout_help)
    parser.add_argument(
        "--min-gain-mm",
        type=non_negative_mm,
        metavar="MM",
        help="practical margin: a cause is named only if it lowers the RMS error on "
        "blocked hold-out rows (regions of joint space, whole files) by at least MM "
        "(default: the measurement noise / 10, the standard error of an RMS error "
        "measured on 50 check poses; the noise from residual differences of the closest "
        "pairs of poses per file, capped by the fit's sigma)",
    )
    add_frame_options(parser)
    add_robust(parser)
    add_gravity(parser)


def add_gravity(parser: argparse.ArgumentParser) -> None:
    """``--gravity X,Y,Z|level-tracker``: the mounting, which compliance and deflection
    follow."""
    parser.add_argument(
        "--gravity",
        metavar="X,Y,Z|level-tracker",
        help="how the robot is mounted, for compliance and deflection: gravity in the "
        "robot's root frame [m/s^2] (ceiling: 0,0,9.81), or level-tracker: the "
        "measurement frame is levelled (laser tracker, total station), so gravity is -z "
        "there and its direction in the robot frame follows from the fitted base frame "
        "(default: upright, 0,0,-9.81)",
    )


_FRAME_HELP = (
    "{what} known from outside the data, X,Y,Z[,RX,RY,RZ] in metres and roll-pitch-yaw "
    "radians ({frame}): fixed as given (only the translation with three values), or "
    "after 'seed:' a start and prior that the data refine where they determine it"
)


def add_frame_options(parser: argparse.ArgumentParser) -> None:
    """``--tool``, ``--base`` and ``--max-tool-offset``: frames known from outside the
    data (fixed, or ``seed:`` values), and the plausibility limit of a fitted tool (every
    command that fits frames: with :func:`add_fit_options`, and ``evaluate --fit-frames``)."""
    parser.add_argument(
        "--tool",
        metavar="X,Y,Z[,RX,RY,RZ]",
        help=_FRAME_HELP.format(
            what="tool frame (the measured point on the flange, e.g. from the target's "
            "mount drawing)",
            frame="flange frame",
        ),
    )
    parser.add_argument(
        "--base",
        metavar="X,Y,Z[,RX,RY,RZ]",
        help=_FRAME_HELP.format(
            what="base frame (the robot root in the measurement frame)",
            frame="measurement frame",
        ),
    )
    parser.add_argument(
        "--max-tool-offset",
        type=float,
        default=MAX_TOOL_TRANSLATION_M,
        metavar="M",
        help="a fitted tool translation beyond M metres from the flange is reported as "
        f"implausible (default: {MAX_TOOL_TRANSLATION_M:g})",
    )


def add_robust(parser: argparse.ArgumentParser) -> None:
    """``--robust none|huber|cauchy``."""
    parser.add_argument(
        "--robust",
        choices=("none", *ROBUST_LOSSES),
        default="none",
        help="down-weight rows with gross errors (a broken beam, a bad visit): huber "
        "(bounded influence) or cauchy (a wild row has no pull); every down-weighted row "
        "is reported (default: none, plain least squares)",
    )


def add_fit_frames(parser: argparse.ArgumentParser, *, help: str) -> None:
    """``--fit-frames``: fit only the base and tool frames of MODEL to DATA first."""
    parser.add_argument("--fit-frames", action="store_true", help=help)


# ----------------------------------------------------------------------------- outputs


def add_out(
    parser: argparse.ArgumentParser,
    *,
    metavar: str,
    help: str,
    required: bool = True,
    default: str | None = None,
) -> None:
    """``--out PATH``: the file or folder the command writes."""
    if default is not None:
        required = False
        help += " (default: %(default)s)"
    parser.add_argument("--out", required=required, default=default, metavar=metavar, help=help)


def add_json(parser: argparse.ArgumentParser, *, help: str, required: bool = False) -> None:
    """``--json OUT.json``: the command's result as JSON."""
    parser.add_argument("--json", required=required, metavar="OUT.json", help=help)


def add_report(parser: argparse.ArgumentParser, *, help: str) -> None:
    """``--report DIR``: ``DIR/report.md`` with its PNG plots."""
    parser.add_argument("--report", metavar="DIR", help=help)


# ----------------------------------------------------------------------------- runs


def add_seed(parser: argparse.ArgumentParser, *, default: int = 0, what: str) -> None:
    """``--seed K``: same seed, same result. ``what`` says what the seed draws."""
    parser.add_argument(
        "--seed", type=int, default=default, metavar="K", help=f"{what} (default: {default})"
    )


def add_epochs(parser: argparse.ArgumentParser, *, default: int | None = None) -> None:
    """``--epochs N``: training epochs of the residual networks."""
    tail = "preset" if default is None else "%(default)s"
    parser.add_argument(
        "--epochs",
        type=int,
        default=default,
        metavar="N",
        help=f"maximum training epochs of the networks (default: {tail})",
    )


def add_noise(parser: argparse.ArgumentParser, *, mm: float, deg: float) -> None:
    """``--noise-mm S`` and ``--noise-deg S``: measurement noise of a simulated campaign."""
    parser.add_argument(
        "--noise-mm",
        type=float,
        default=mm,
        metavar="S",
        help="std of the position noise per coordinate [mm] (default: %(default)s)",
    )
    parser.add_argument(
        "--noise-deg",
        type=float,
        default=deg,
        metavar="S",
        help="std of the orientation noise per rotation axis [deg] (default: %(default)s)",
    )


def add_progress(parser: argparse.ArgumentParser) -> None:
    """``--no-progress``: no progress bar on stderr (the summary is printed anyway)."""
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")


# ----------------------------------------------------------------------------- targets


def add_approach(parser: argparse.ArgumentParser) -> None:
    """``--approach SPEC``: backlash approach direction of IK targets
    (:func:`hybrid_pk.ik.parse_approach` reads it)."""
    parser.add_argument("--approach", metavar="SPEC", help=APPROACH_HELP)


def add_frame_set(parser: argparse.ArgumentParser) -> None:
    """``--frame-set K``: which base/tool frame set of MODEL (``ik``, ``compensate``);
    :func:`hybrid_pk.cli.common.frame_set_index` checks it."""
    parser.add_argument(
        "--frame-set",
        type=int,
        default=None,
        metavar="K",
        help="base/tool frame set of a model calibrated with one set per file (0-based)",
    )
