"""Entry point of ``hybrid-pk``: one sub-command module per command, one error policy.

Every sub-command module declares ``NAME``, ``HELP`` (one line for the command list),
``DESCRIPTION`` (its ``--help`` text, units and formats, kept as written),
``add_arguments(parser)`` (its flags; the shared ones come from
:mod:`hybrid_pk.cli.options`) and ``run(args) -> int``. A command with sub-commands of
its own (``import FORMAT``) defines ``register(subparsers)`` instead.

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

from hybrid_pk.cli.options import command_parser, resolve_robot
from hybrid_pk.cli.outputs import check_outputs
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

# Sub-command modules, in the order `--help` lists them.
_COMMANDS = (
    "hybrid_pk.cli.plan_cmd",
    "hybrid_pk.cli.simulate_cmd",
    "hybrid_pk.cli.diagnose_cmd",
    "hybrid_pk.cli.calibrate_cmd",
    "hybrid_pk.cli.train_cmd",
    "hybrid_pk.cli.evaluate_cmd",
    "hybrid_pk.cli.ik_cmd",
    "hybrid_pk.cli.compensate_cmd",
    "hybrid_pk.cli.import_cmd",
    "hybrid_pk.cli.export_cmd",
    "hybrid_pk.cli.demo_cmd",
)


class _OneLineParser(argparse.ArgumentParser):
    """argparse with the error policy of every other error: a missing or malformed
    flag is one line on stderr and exit code 2 (argparse's usage block before it made
    it a dozen); ``--help`` still shows the usage. Sub-command parsers inherit it."""

    def error(self, message: str):
        msg = " ".join(message.split())
        self.exit(2, f"{self.prog}: error: {msg} ({self.prog} --help lists the options)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _OneLineParser(
        prog="hybrid-pk",
        description="Accurate, differentiable kinematics for serial robot arms: "
        "diagnose, calibrate, learn residuals, solve IK.",
    )
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on error")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in _COMMANDS:
        module = importlib.import_module(name)
        if hasattr(module, "register"):
            module.register(sub)
            continue
        p = command_parser(sub, module.NAME, help=module.HELP, description=module.DESCRIPTION)
        module.add_arguments(p)
        p.set_defaults(func=module.run)
    parser.set_defaults(commands=sub.choices)  # for the hint on an unknown flag
    return parser


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
    parser = build_parser()  # imports every command: seconds on a loaded machine
    release_interrupt()  # imported: Ctrl-C is the commands' KeyboardInterrupt from here on
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # as argparse would, with the flag's owner or its closest match named
        hint = unknown_flag_hint(args.commands, args.command, unknown)
        args.commands[args.command].error(f"unrecognized arguments: {' '.join(unknown)}{hint}")
    name = f"import {args.format}" if args.command == "import" else args.command  # as argparse
    try:
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
