"""A model that misses measured rows by more than small corrections make: rows of
another set-up (frames not fitted to them) or of another robot with the same joint
names (a UR5 table and a UR10 model), which no column check can tell."""

from __future__ import annotations

from hybrid_pk.calibration.tuning import diagnosis_tuning

__all__ = ["gross_warning"]


def gross_warning(what: str, mean_mm: float, frames_fitted: bool, then: str = "") -> str | None:
    """The warning line when ``what`` misses the rows by a mean position error above the
    diagnosis' ``gross_error_mm`` (what small corrections make), else None.
    ``frames_fitted``: the frames were fitted to these rows (then only the robot is
    left to blame); ``then`` is appended (what follows from it)."""
    gross = diagnosis_tuning().gross_error_mm
    if not mean_mm > gross:
        return None
    cause = (
        "the rows are not this robot's"
        if frames_fitted
        else "the rows are of another set-up (--fit-frames fits the base and tool frames to "
        "them first) or not this robot's"
    )
    return (
        f"warning: {what} misses these rows by {mean_mm:.4g} mm (mean), more than small "
        f"corrections make ({gross:g} mm): {cause}{then}"
    )
