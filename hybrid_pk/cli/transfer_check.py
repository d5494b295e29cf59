"""``--refit-rows N`` of ``diagnose`` and ``calibrate``: the leave-one-file-out transfer
check (:mod:`hybrid_pk.pipelines.transfer`) when DATA holds several files."""

from __future__ import annotations

import argparse
from pathlib import Path

from hybrid_pk.cli.fit_settings import frame_priors, robust_loss
from hybrid_pk.errors import HybridPKError
from hybrid_pk.pipelines.transfer import DEFAULT_REFIT_ROWS, TransferResult, leave_one_file_out

__all__ = ["add_refit_rows", "append_to_report", "transfer_check"]


def add_refit_rows(parser: argparse.ArgumentParser) -> None:
    """The ``--refit-rows`` flag."""
    parser.add_argument(
        "--refit-rows",
        type=int,
        default=DEFAULT_REFIT_ROWS,
        metavar="N",
        help="with several DATA files: leave each file out, fit on the others, re-fit the "
        "frames on N random rows of it and report the errors on its other rows (default "
        f"{DEFAULT_REFIT_ROWS}: the re-fit then adds about 0.3x the noise; 0: no check)",
    )


def transfer_check(args, robot, data, labels, *, gravity, start, progress) -> TransferResult | None:
    """The check for ``args`` (None with one file or ``--refit-rows 0``)."""
    if args.refit_rows < 0:
        raise HybridPKError(f"--refit-rows must be 0 or more, got {args.refit_rows}")
    if args.refit_rows == 0 or len(data.sources) < 2:
        return None
    return leave_one_file_out(
        robot,
        data,
        labels,
        refit_rows=args.refit_rows,
        frames_per_file=args.frames_per_file,
        gravity=gravity,
        priors=frame_priors(args),
        robust=robust_loss(args),
        seed=args.seed,
        start=start,
        progress=progress,
    )


def append_to_report(report: Path, transfer: TransferResult) -> None:
    """A section with the check's table at the end of a ``report.md``."""
    lines = ["", "## Transfer: leave one file out", "", "```", *transfer.lines(), "```", ""]
    with open(report, "a", encoding="utf-8") as f:
        f.write("\n".join(lines))
