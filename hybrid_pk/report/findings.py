"""Report sections of what the diagnosis would not list as causes, and of what it
could not determine or had to down-weight: a structurally wrong URDF, frames the data
leave open, outlier and down-weighted rows."""

from __future__ import annotations

from pathlib import Path

from hybrid_pk.calibration.diagnosis.leftovers import left_verdict
from hybrid_pk.report.markdown import fmt, markdown_table

__all__ = ["frames_section", "robust_section", "structural_section", "structured_paragraph"]


def structural_section(diagnosis) -> list[str]:
    """``## The URDF looks structurally wrong`` (or ``## Not small corrections``)."""
    structural = getattr(diagnosis, "structural", None)
    if not structural:
        return []
    wrong = structural["structurally_wrong"]
    lines = [
        "## The URDF looks structurally wrong" if wrong else "## Not small corrections",
        "",
        f"> **{structural['message']}.**",
        "",
        "A cause is a small correction of the URDF: a rotation of at most a few degrees, "
        "a translation of a few centimetres, a compliance metal joints can have, with a "
        "signature of its own (not mostly what a change of the base and tool frames "
        "makes). These candidates were not:",
        "",
    ]
    rows = [[f["cause"], f["why"]] for f in structural["findings"]]
    if rows:
        lines += [markdown_table(rows, ["candidate", "why it is not a cause"], ["l", "l"])]
    loc = structural.get("location")
    if loc:
        axis = ", ".join(f"{x:+.2f}" for x in loc["rotation_axis"])
        lines += [
            "A full correction of one joint's origin (rotation about and across its axis, "
            "translation), fitted without limits at every joint, explains the errors best "
            f"at **{loc['joint']}**: rotation {fmt(loc['rotation_deg'])}° about ({axis}), "
            f"translation {fmt(loc['translation_mm'])} mm; hold-out mean position error "
            f"{fmt(loc['holdout_mean_mm_before'])} mm → {fmt(loc['holdout_mean_mm_after'])} mm.",
            "",
        ]
    cut = structural.get("budget_cut")
    if cut:
        share = diagnosis.budget["share"]  # the tuning's optional_share
        lines += [
            f"The search stopped on its work budget ({100 * share:g} % of the main "
            f"search's work, shared by the optional stages) before: {', '.join(cut['not_done'])}.",
            "",
        ]
    withheld = structural.get("withheld_causes") or []
    if withheld:
        names = ", ".join(
            c["effect"] + (f":{c['joint']}" if c.get("joint") else "") for c in withheld
        )
        lines += [f"Causes fitted on this structure and withheld: {names}.", ""]
    return lines


def frames_section(diagnosis) -> list[str]:
    """``## Frames the data do not determine`` and frame plausibility warnings."""
    frames = getattr(diagnosis, "frames", None) or {}
    directions, warnings = frames.get("directions", []), frames.get("warnings", [])
    if not directions and not warnings:
        return []
    lines = ["## Frames the data do not determine", ""]
    if directions:
        rows = [[d["label"], d["status"], d["sensitivity"], d["text"]] for d in directions]
        lines += [
            "Frame components whose change moves the measured points by less than 5 % of "
            "its size (rms over the rows): the base and tool frames trade off there, so an "
            "unmodelled error of 1 mm moves them by more than 20 mm. *Not determined* ones "
            "are held by the fit's prior.",
            "",
            markdown_table(
                rows, ["component", "status", "mm per mm", "what it means"], ["l", "l", "r", "l"]
            ),
        ]
    lines += [f"> **Warning:** {w}." for w in warnings]
    return [*lines, ""] if warnings else lines


def robust_section(diagnosis) -> list[str]:
    """``## Outliers and down-weighted rows``: nothing is dropped silently."""
    outliers = getattr(diagnosis, "outliers", None) or []
    robust = getattr(diagnosis, "robust", None)
    if not outliers and robust is None:
        return []
    lines = ["## Outliers and down-weighted rows", ""]
    if robust is not None:
        rows = robust["down_weighted"]
        lines += [
            f"Robust fits ({robust['loss']}): {len(rows)} fit row(s) got less than half "
            "their weight; none was dropped.",
            "",
        ]
        if rows:
            table = [[Path(r["file"]).name, r["row"], r["weight"]] for r in rows]
            lines += [markdown_table(table, ["file", "row", "weight"], ["l", "r", "r"])]
    if outliers:
        lines += [
            f"{len(outliers)} row(s) lie beyond {fmt(robust['outlier_k'] if robust else 4.0)} "
            "sigma of the noise under the extended model (rows are 1-based data rows):",
            "",
            markdown_table(
                [
                    [
                        Path(o["file"]).name,
                        o["row"],
                        o["position_mm"],
                        o["orientation_deg"],
                        o["sigma"],
                    ]
                    for o in outliers
                ],
                ["file", "row", "position [mm]", "orientation [deg]", "sigma"],
                ["l", "r", "r", "r", "r"],
            ),
        ]
        if robust is None:
            lines += ["`--robust cauchy` fits without their pull.", ""]
    else:
        lines += ["No row lies beyond 4 sigma of the noise.", ""]
    return lines


def structured_paragraph(un: dict) -> str:
    """The report's verdict on the left error (the diagnosis's ``unexplained``), as
    :func:`~hybrid_pk.calibration.diagnosis.leftovers.left_verdict` decides it."""
    beyond, left = un.get("beyond_noise") or {}, left_verdict(un)
    if left == "smooth":
        text = (
            "**Structured: yes.** Neighbouring configurations share their residuals, so a "
            "smooth error is left that no named cause explains (an unmodelled effect, or "
            "one for the residual networks)."
        )
    elif left == "beyond_noise":
        text = (
            f"**Structured: yes.** What is left is {fmt(beyond['ratio'], 3)} times the "
            f"measurement noise per axis (noise alone stays below {fmt(beyond['limit'], 3)}"
            "), an error no named cause explains; the hold-out configurations lie too far "
            "apart for their neighbours to show its shape."
        )
    else:
        text = (
            "**Structured: no.** The residuals of neighbouring configurations are not "
            "correlated and stay within the measurement noise: what is left looks like "
            "measurement noise."
        )
        if "pair_distance_mm" in beyond:
            text += (
                " The noise is estimated from pairs of poses up to "
                f"{fmt(beyond['pair_distance_mm'], 3)} mm apart (point motion): an error "
                "that varies over less than that is not told from noise."
            )
    return text
