"""The fit settings of a command's flags (:func:`settings_of`), and the lines that
report what a fit could not determine, found implausible or down-weighted (calibrate,
diagnose, evaluate --fit-frames, simulate)."""

from __future__ import annotations

import argparse
from pathlib import Path

from hybrid_pk.calibration.diagnosis.plausibility import effect_std, implausibility
from hybrid_pk.calibration.robust import (
    CUT_WEIGHT,
    OUTLIER_K,
    down_weighted,
    list_outliers,
)
from hybrid_pk.cli.settings_flags import given_values
from hybrid_pk.settings import read_settings, settings_yaml

__all__ = [
    "diagnosis_notes",
    "fit_lines",
    "frame_report_lines",
    "implausible_effect_lines",
    "print_settings",
    "robust_lines",
    "robust_summary",
    "settings_of",
]


def settings_of(args: argparse.Namespace, cls):
    """The settings ``cls`` (:mod:`hybrid_pk.calibration.settings`) of a command: the
    flags given, over its ``--config`` YAML (if it has one), over the defaults.

    Raises:
        HybridPKError: the YAML cannot be read, or has an unknown key or a bad value.
    """
    config = getattr(args, "config", None)
    base = read_settings(cls, config) if config else None
    return cls.parse(given_values(args, cls), base=base)


def print_settings(args: argparse.Namespace, settings) -> bool:
    """With ``--print-config``: print ``settings`` as a ``--config`` YAML; whether it did."""
    if getattr(args, "print_config", False):
        print(settings_yaml(settings), end="")
    return bool(getattr(args, "print_config", False))


def frame_report_lines(result) -> list[str]:
    """The frame report of a fit as ``note:`` / ``warning:`` lines."""
    report = getattr(result, "frame_report", None)
    if report is None:
        return []
    lines = [f"warning: {d['text']}" for d in report.directions]
    return lines + [f"warning: {w}" for w in report.warnings]


def _rows_text(rows: list[dict], what: str, limit: int = 8) -> str:
    listed = ", ".join(f"{Path(r['file']).name}:{r['row']} ({r[what]:.3g})" for r in rows[:limit])
    return listed + (f" and {len(rows) - limit} more" if len(rows) > limit else "")


def robust_lines(outliers: list[dict], robust: dict | None) -> list[str]:
    """Down-weighted rows of a robust fit and outlier rows, one line each."""
    lines = []
    if robust is not None and robust.get("down_weighted"):
        rows = robust["down_weighted"]
        cut = [r for r in rows if r["weight"] < CUT_WEIGHT]
        text = f"robust fit ({robust['loss']}): {len(rows)} row(s) down-weighted to under half "
        text += f"their weight, {len(cut)} of them under {CUT_WEIGHT:g}"
        if cut:
            text += f" (file:row (weight)): {_rows_text(cut, 'weight')}"
        lines.append(text + "; all listed in the JSON")
    if outliers:
        active = robust is not None and robust.get("loss")
        hint = "" if active else "; --robust cauchy down-weights them"
        lines.append(
            f"warning: {len(outliers)} outlier row(s) beyond {OUTLIER_K:g} sigma (file:row "
            f"(position error mm)): {_rows_text(outliers, 'position_mm')}{hint}"
        )
    return lines


def diagnosis_notes(diagnosis) -> list[str]:
    """Frames, structural findings, outliers and down-weighted rows of a diagnosis."""
    lines = []
    structural = getattr(diagnosis, "structural", None)
    if structural is not None:
        lines.append(f"structural: {structural['message']}")
        for f in structural["findings"]:
            lines.append(f"  not a plain cause: {f['cause']}: {f['why']}")
    frames = getattr(diagnosis, "frames", None) or {}
    lines += [f"warning: {d['text']}" for d in frames.get("directions", [])]
    lines += [f"warning: {w}" for w in frames.get("warnings", [])]
    return lines + robust_lines(
        getattr(diagnosis, "outliers", []), getattr(diagnosis, "robust", None)
    )


def robust_summary(data, res) -> dict:
    """Outlier rows of a fit (beyond ``OUTLIER_K`` sigma) and, if it was robust, the rows
    it down-weighted: the ``"robust"`` entry of a model file's metadata."""
    out = {
        "loss": res.robust,
        "outliers": list_outliers(
            data, res.position_mm, res.orientation_deg, res.sigma_pos_mm, res.sigma_rot_rad
        ),
    }
    if res.weights is not None:
        out["down_weighted"] = down_weighted(data, res.weights)
    return out


def fit_lines(data, res) -> list[str]:
    """What a fit could not determine about its frames, implausible frames, and its
    outliers and down-weighted rows, as ``warning:`` lines."""
    summary = robust_summary(data, res)
    return frame_report_lines(res) + robust_lines(summary["outliers"], summary)


def implausible_effect_lines(model, data, res=None) -> list[str]:
    """A ``warning:`` for each fitted effect of ``model`` that is not a small correction
    of the URDF (``calibrate --effects LIST`` fits what it is told; it does not let such
    a value pass for a cause). ``res``: the fit, whose standard deviations the sign
    rules read."""
    lines = []
    for effect in model.effects:
        why = implausibility(effect, model.robot, data, effect_std(res, effect.label))
        if why is not None:
            lines.append(
                f"warning: {effect.label}: {why['why']}; this is no calibration error but a "
                "sign that the URDF is wrong there (diagnose names where and by how much)"
            )
    return lines
