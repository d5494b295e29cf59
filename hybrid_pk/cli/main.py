"""Entry point of ``hybrid-pk``: one sub-command module per command, one error policy.

Every sub-command module declares ``DESCRIPTION`` (its ``--help`` text, units and
formats, kept as written), ``add_arguments(parser)`` (its flags; the shared ones come
from :mod:`hybrid_pk.cli.options`) and ``run(args) -> int``. A command with
sub-commands of its own (``import FORMAT``) defines ``register(subparsers, name,
help)`` instead. Its name and one-line help (the command list) are in
:data:`COMMANDS`, so that a command imports only its own module: the others' (torch,
scipy, matplotlib, pandas) took seconds of every command's start, and ``hybrid-pk
--help`` imports none.

Errors of the ``HybridPKError`` hierarchy (and OS errors such as a missing file) become
one line on stderr and exit code 2; anything else (a bug) becomes one ``internal
error`` line and exit code 1. A traceback is shown only with ``--debug``.
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import sys
from collections.abc import Sequence

from hybrid_pk.cli.progress import shown
from hybrid_pk.errors import HybridPKError
from hybrid_pk.startup import (
    EXIT_INTERRUPTED,
    EXIT_TERMINATED,
    Terminated,
    terminable,
)
from hybrid_pk.startup import release as release_interrupt
from hybrid_pk.threads import configure as configure_threads

__all__ = ["COMMANDS", "build_parser", "main", "unknown_flag_hint"]

# Sub-commands, in the order `--help` lists them: name -> (module, one-line help).
COMMANDS = {
    "plan": (
        "hybrid_pk.cli.plan_cmd",
        "choose the poses to measure (D-optimal for the frames + named effects)",
    ),
    "simulate": (
        "hybrid_pk.cli.simulate_cmd",
        "virtual measurement campaign: pose table + truth JSON",
    ),
    "diagnose": (
        "hybrid_pk.cli.diagnose_cmd",
        "name the physical causes of the nominal model's errors (JSON + report)",
    ),
    "calibrate": (
        "hybrid_pk.cli.calibrate_cmd",
        "fit frames + physical effects to measured poses; write a MODEL file",
    ),
    "train": (
        "hybrid_pk.cli.train_cmd",
        "train the residual networks of a hybrid model (Lightning, TensorBoard)",
    ),
    "evaluate": (
        "hybrid_pk.cli.evaluate_cmd",
        "position [mm] / orientation [deg] errors of a model on measured data",
    ),
    "ik": (
        "hybrid_pk.cli.ik_cmd",
        "all distinct joint solutions [rad] of target poses (errors in mm / deg)",
    ),
    "compensate": (
        "hybrid_pk.cli.compensate_cmd",
        "correct a robot program's joint targets for the calibrated model",
    ),
    "import": (
        "hybrid_pk.cli.import_cmd",
        "convert measurement files of other formats to the pose table",
    ),
    "export": (
        "hybrid_pk.cli.export_cmd",
        "the calibrated geometry as a DH / modified-DH table, a URDF or UR's kinematics YAML",
    ),
    "demo": (
        "hybrid_pk.cli.demo_cmd",
        "run the whole pipeline on a simulated RX160 campaign and write a report",
    ),
}


class _OneLineParser(argparse.ArgumentParser):
    """argparse with the error policy of every other error: a missing or malformed
    flag is one line on stderr and exit code 2 (argparse's usage block before it made
    it a dozen); ``--help`` still shows the usage. Sub-command parsers inherit it."""

    def error(self, message: str):
        msg = " ".join(message.split())
        self.exit(2, f"{self.prog}: error: {msg} ({self.prog} --help lists the options)\n")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The ``hybrid-pk`` parser: every command's flags, or (``only``) those of that
    command alone, the others listed with their help but not imported."""
    parser = _OneLineParser(
        prog="hybrid-pk",
        description="Accurate, differentiable kinematics for serial robot arms: "
        "diagnose, calibrate, learn residuals, solve IK.",
    )
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on error")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (path, text) in COMMANDS.items():
        if only is not None and name != only:
            sub.add_parser(name, help=text, add_help=False)  # listed; its flags not built
        else:
            _add_command(sub, name, path, text)
    parser.set_defaults(commands=sub.choices)  # for the hint on an unknown flag
    return parser


def _add_command(sub, name: str, path: str, text: str) -> None:
    """Import the module ``path`` of command ``name`` and add its parser to ``sub``."""
    # the shared flags import torch (robot names): only where a command is built
    from hybrid_pk.cli.options import command_parser

    module = importlib.import_module(path)
    if hasattr(module, "register"):
        module.register(sub, name, text)
        return
    p = command_parser(sub, name, help=text, description=module.DESCRIPTION)
    module.add_arguments(p)
    p.set_defaults(func=module.run)


def _command_named(argv: Sequence[str]) -> str | None:
    """The command ``argv`` names (its first word that is not a flag), if it is one."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return word if word in COMMANDS else None


def unknown_flag_hint(commands: dict, command: str, unknown: Sequence[str]) -> str:
    """For each unknown ``--flag`` of ``command``: the other commands that take it (a
    flag of ``simulate`` tried on ``diagnose``), else the closest flag of its own."""
    own = commands[command]
    hints = []
    for token in unknown:
        if not token.startswith("--"):
            continue
        flag = token.split("=")[0]
        others = [
            n for n, p in commands.items() if n != command and flag in p._option_string_actions
        ]
        if others:
            hints.append(f"{flag} is a flag of {', '.join(others)}, not of {command}")
            continue
        close = difflib.get_close_matches(flag, list(own._option_string_actions), n=1)
        if close:
            hints.append(f"{flag}: did you mean {close[0]}?")
    return f" ({'; '.join(hints)})" if hints else ""  # the parser's error adds --help


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = _command_named(argv)
    # Only the command's own module: the others' imports cost seconds on a loaded
    # machine. Without a command (`--help`, a misspelt one) none is imported.
    parser = build_parser(only=command or "")
    release_interrupt()  # imported: Ctrl-C is the commands' KeyboardInterrupt from here on
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # as argparse would, with the flag's owner or its closest match named
        every = build_parser().get_default("commands")  # the other commands' flags too
        hint = unknown_flag_hint(every, args.command, unknown)
        args.commands[args.command].error(f"unrecognized arguments: {' '.join(unknown)}{hint}")
    name = f"import {args.format}" if args.command == "import" else args.command  # as argparse
    try:
        from hybrid_pk.cli.options import resolve_robot  # the command's imports are done
        from hybrid_pk.cli.outputs import check_outputs

        resolve_robot(args)
        check_outputs(args)  # before any work: nothing is written over an input
        asked = getattr(args, "threads", None)
        threads = configure_threads(asked)
        if isinstance(asked, int) and isinstance(threads, int) and asked > threads:
            print(f"note: --threads {asked}: this process may use {threads} cores")
        with terminable(), shown(not getattr(args, "no_progress", False)):
            return int(args.func(args) or 0)
    except (HybridPKError, OSError, ValueError) as exc:
        if args.debug:
            raise
        msg = " ".join(str(exc).split())  # one line, whatever the exception carried
        print(f"hybrid-pk {name}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM (Terminated)
        ended = isinstance(exc, Terminated)
        print(f"hybrid-pk {name}: {'terminated' if ended else 'interrupted'}", file=sys.stderr)
        return EXIT_TERMINATED if ended else EXIT_INTERRUPTED
    except Exception as exc:  # a bug, not bad input: still one line, the traceback on demand
        if args.debug:
            raise
        msg = " ".join(f"{type(exc).__name__}: {exc}".split())
        print(
            f"hybrid-pk {name}: internal error: {msg} (rerun with --debug for the "
            "traceback, and please report it)",
            file=sys.stderr,
        )
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
