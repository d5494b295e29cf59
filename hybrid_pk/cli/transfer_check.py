"""The leave-one-file-out transfer check (:mod:`hybrid_pk.pipelines.transfer`) of
``diagnose`` and ``calibrate`` (``--refit-rows N``) when DATA holds several files, and
the report sections such checks append."""

from __future__ import annotations

from pathlib import Path

from hybrid_pk.pipelines.transfer import TransferResult, leave_one_file_out

__all__ = ["append_to_report", "transfer_check", "transfer_lines"]


def transfer_check(
    settings, frames_per_file, robot, data, labels, *, gravity, start, progress
) -> TransferResult | None:
    """The check of ``settings`` (:class:`DiagnosisSettings`; None with one file or
    ``--refit-rows 0``)."""
    if settings.refit_rows == 0 or len(data.sources) < 2:
        return None
    return leave_one_file_out(
        robot,
        data,
        labels,
        refit_rows=settings.refit_rows,
        frames_per_file=frames_per_file,
        gravity=gravity,
        priors=settings.priors(),
        robust=settings.loss(),
        seed=settings.seed,
        start=start,
        progress=progress,
    )


def append_to_report(report: Path, title: str, body: list[str]) -> None:
    """A section ``title`` with the text lines ``body`` (as printed) at the end of a
    ``report.md`` (the transfer check's table, the seeds' stability)."""
    lines = ["", f"## {title}", "", "```", *body, "```", ""]
    with open(report, "a", encoding="utf-8") as f:
        f.write("\n".join(lines))


def transfer_lines(transfer: TransferResult | None, settings, data) -> list[str]:
    """The check's table, or why there is none: what these rows cannot show."""
    if transfer is not None:
        return transfer.lines()
    if len(data.sources) < 2:
        return [
            "transfer: not measured (one file): how the causes carry to another set-up "
            "(the robot re-mounted, the instrument moved) needs rows of a second one; "
            "the blocked hold-out holds out regions of this one only"
        ]
    return [f"transfer: not measured (--refit-rows {settings.refit_rows})"]
