"""Warnings about what a model's errors on DATA mean: a model that misses the rows by
more than small corrections make (rows of another set-up, frames not fitted to them,
or of another robot with the same joint names, a UR5 table and a UR10 model, which no
column check can tell), and DATA that is the file the model was fitted on (errors
that are not held out)."""

from __future__ import annotations

import os
from collections.abc import Sequence

from hybrid_pk.calibration.tuning import diagnosis_tuning

__all__ = ["fitted_on_note", "gross_warning"]


def gross_warning(
    what: str, mean_mm: float, frames_fitted: bool, then: str = "", cause: str | None = None
) -> str | None:
    """The warning line when ``what`` misses the rows by a mean position error above the
    diagnosis' ``gross_error_mm`` (what small corrections make), else None.
    ``frames_fitted``: the frames were fitted to these rows (then only the robot is
    left to blame); ``then`` is appended (what follows from it); ``cause``, when given,
    replaces the causes named."""
    gross = diagnosis_tuning().gross_error_mm
    if not mean_mm > gross:
        return None
    if cause is None:
        cause = (
            "the rows are not this robot's"
            if frames_fitted
            else "the rows are of another set-up (--fit-frames fits the base and tool frames "
            "to them first) or not this robot's"
        )
    return (
        f"warning: {what} misses these rows by {mean_mm:.4g} mm (mean), more than small "
        f"corrections make ({gross:g} mm): {cause}{then}"
    )


def _same_file(a: str, b: str) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:  # a file recorded relative to another folder, or gone: not known
        return False


def fitted_on_note(label: str, metadata: dict, sources: Sequence[str]) -> str | None:
    """A note when DATA holds a file the model file was calibrated or trained on (its
    metadata's ``data`` / ``training.data``, the paths as given then, read from here):
    its errors there are on fitting rows, not held out."""
    used = {
        "calibrated": metadata.get("data") or [],
        "trained": (metadata.get("training") or {}).get("data") or [],
    }
    verbs = [
        v for v, files in used.items() if any(_same_file(s, f) for s in sources for f in files)
    ]
    if not verbs:
        return None
    same = sorted(
        {s for s in sources for files in used.values() for f in files if _same_file(s, f)}
    )
    return (
        f"note: {label} was {' and '.join(verbs)} on {', '.join(same)}: these errors are on "
        "its fitting rows, not held out (evaluate on rows of another campaign, or hold rows "
        "out before calibrating)"
    )
