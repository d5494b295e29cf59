"""The flags that several sub-commands share, declared once with one wording.

Each ``add_*`` function adds one flag (or one group of flags that belong together) to
an ``argparse`` parser. A command module calls them in its ``register`` and keeps only
its own flags. A new flag that more than one command takes belongs here; one that
only a single command takes stays in that command's module.

Groups:
    the command itself: :func:`command_parser` (with :func:`add_threads` and
        :func:`add_progress`, every command)
    robot and model: :func:`add_robot`, :func:`add_end_link`, :func:`add_model`
    data: :func:`add_data` (DATA..., --frames-per-file, --skip-bad-rows, --split-at)
    fits: :func:`add_fit_frames` (the fits' own flags are derived from
        :class:`~hybrid_pk.calibration.settings.FitSettings` and
        :class:`~hybrid_pk.calibration.settings.DiagnosisSettings`:
        :func:`hybrid_pk.cli.settings_flags.add_settings_flags`)
    outputs: :func:`add_out`, :func:`add_json`, :func:`add_report`
    runs: :func:`add_seed`, :func:`add_epochs`, :func:`add_noise`
    solving for targets (ik, compensate): :func:`add_approach`, :func:`add_frame_set`
"""

from __future__ import annotations

import argparse
import math

from hybrid_pk.errors import HybridPKError
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
    "add_frame_set",
    "add_json",
    "add_model",
    "add_noise",
    "add_out",
    "add_progress",
    "add_report",
    "add_robot",
    "add_seed",
    "add_threads",
    "command_parser",
    "count",
    "finite_number",
    "resolve_robot",
]

ROBOT_HELP = f"shipped robot name ({', '.join(shipped_robots())}) or URDF path"
END_LINK_HELP = "end link of the chain, e.g. a tool link (default: the URDF's leaf link)"
_ROBOT_CHECK_HELP = "refuse a MODEL made for another robot than ROBOT"
APPROACH_HELP = (
    "backlash: the side each joint approaches the target from, + (moving in the joint's "
    "positive direction), - or mid, for every backlash joint or per joint as "
    "joint_3=+,joint_4=- (default: {default})"
)
APPROACH_DEFAULT_IK = "the mid-play model, half-way between both; a note says so"


def command_parser(subparsers, name: str, *, help: str, description: str):
    """The parser of sub-command ``name``: ``help`` in the command list, ``description``
    (units, formats) kept as written in ``NAME --help``; every command takes
    ``--threads`` (:func:`add_threads`) and ``--no-progress`` (:func:`add_progress`)."""
    parser = subparsers.add_parser(
        name,
        help=help,
        description=description,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_threads(parser)
    add_progress(parser)
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
        help="torch threads: N, auto (the cores this process may use, one in the fits and "
        "the diagnosis; at most OMP_NUM_THREADS) or torch (torch's own default); waiting "
        f"threads sleep instead of spinning (default: ${THREADS_ENV}, else auto)",
    )


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
    if positional:  # ROBOT or, as every other command takes it, --robot ROBOT
        parser.add_argument("robot", metavar="ROBOT", nargs="?", help=text)
        parser.add_argument("--robot", dest="robot_flag", metavar="ROBOT", help="same as ROBOT")
    else:
        parser.add_argument(
            "--robot", metavar="ROBOT", required=required, default=default, help=text
        )


def resolve_robot(args: argparse.Namespace) -> None:
    """Merge a positional ``ROBOT`` and ``--robot ROBOT`` (:func:`add_robot` with
    ``positional``) into ``args.robot``; refuse neither, or two different robots."""
    if not hasattr(args, "robot_flag"):
        return
    flag = args.__dict__.pop("robot_flag")
    if args.robot is None and flag is None:
        raise HybridPKError("the robot is missing: give ROBOT (or --robot ROBOT)")
    if args.robot is not None and flag is not None and args.robot != flag:
        raise HybridPKError(f"two robots given: ROBOT {args.robot!r} and --robot {flag!r}")
    args.robot = args.robot or flag


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
    """``DATA...``, ``--frames-per-file``, ``--skip-bad-rows`` and ``--split-at``."""
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
    parser.add_argument(
        "--split-at",
        action="append",
        metavar="FILE:ROW",
        help="with --frames-per-file: the rows of FILE from data row ROW on are a file of "
        "their own, with frames of their own (a set-up that moved there, as the diagnosis "
        "names it); repeatable",
    )


# ----------------------------------------------------------------------------- fits


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
    kind: str = "file",
) -> None:
    """``--out PATH``: the file or folder the command writes (``kind``: ``"file"``,
    ``"folder"`` or ``"either"``, for the check before it runs: :mod:`.outputs`)."""
    if default is not None:
        required = False
        help += " (default: %(default)s)"
    parser.add_argument("--out", required=required, default=default, metavar=metavar, help=help)
    parser.set_defaults(out_kind=kind)


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


def count(text: str) -> int:
    """``argparse`` type of a count of at least one (refused before any work)."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return value


def add_epochs(parser: argparse.ArgumentParser, *, default: int | None = None) -> None:
    """``--epochs N``: training epochs of the residual networks (at least one)."""
    tail = "preset" if default is None else "%(default)s"
    parser.add_argument(
        "--epochs",
        type=count,
        default=default,
        metavar="N",
        help=f"maximum training epochs of the networks (default: {tail})",
    )


def finite_number(text: str, expected: str, lowest: float = -math.inf) -> float:
    """``float(text)`` when it is finite and >= ``lowest``; otherwise the ``argparse``
    error ``expected EXPECTED, got 'TEXT'`` (one line: a usage error naming the flag)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= lowest):
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return value


def _noise(text: str) -> float:
    """``argparse`` type of a noise std: a finite number >= 0."""
    return finite_number(text, "a finite number >= 0", lowest=0.0)


def add_noise(parser: argparse.ArgumentParser, *, mm: float, deg: float) -> None:
    """``--noise-mm S`` and ``--noise-deg S``: measurement noise of a simulated campaign."""
    parser.add_argument(
        "--noise-mm",
        type=_noise,
        default=mm,
        metavar="S",
        help="std of the position noise per coordinate [mm] (default: %(default)s)",
    )
    parser.add_argument(
        "--noise-deg",
        type=_noise,
        default=deg,
        metavar="S",
        help="std of the orientation noise per rotation axis [deg] (default: %(default)s)",
    )


def add_progress(parser: argparse.ArgumentParser) -> None:
    """``--no-progress``: no progress bar on stderr (the summary is printed anyway);
    :func:`hybrid_pk.cli.main.main` applies it to every bar the command opens."""
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")


# ----------------------------------------------------------------------------- targets


def add_approach(parser: argparse.ArgumentParser, default: str = APPROACH_DEFAULT_IK) -> None:
    """``--approach SPEC``: backlash approach direction of IK targets
    (:func:`hybrid_pk.ik.parse_approach` reads it); ``default`` says what the command
    assumes without it."""
    parser.add_argument("--approach", metavar="SPEC", help=APPROACH_HELP.format(default=default))


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
