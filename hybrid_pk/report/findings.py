"""Report sections of what the diagnosis would not list as causes, and of what it
could not determine or had to down-weight: a structurally wrong URDF, frames the data
leave open, outlier and down-weighted rows."""

from __future__ import annotations

from pathlib import Path

import torch

from hybrid_pk.calibration.diagnosis.leftovers import left_verdict
from hybrid_pk.calibration.diagnosis.setup_moves import setup_move_text
from hybrid_pk.calibration.poses import predicted_poses
from hybrid_pk.effects import conditions_from_data
from hybrid_pk.report.markdown import fmt, image, markdown_table
from hybrid_pk.report.plots import sequence_plot

__all__ = [
    "frames_section",
    "robust_section",
    "setup_section",
    "structural_section",
    "structured_paragraph",
]


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


def setup_section(diagnosis, data, out: Path) -> list[str]:
    """``## The set-up moved during the rows``: each named move (the diagnosis JSON's
    ``setup_moves``), its evidence, and its file's errors row by row (a plot)."""
    moves = getattr(diagnosis, "setup_moves", None) or []
    if not moves:
        return []
    lines = [
        "## The set-up moved during the rows",
        "",
        "The final model's errors on the fit rows, in the order measured, were predicted "
        "region by region (each region of the blocked hold-out from the others) with one "
        "correction of the base and tool frames for all rows, one before and one from a "
        "row, one growing with the rows, and the last two together. Where a moved set-up "
        "predicts them better by the practical margin, the rows were not measured from "
        "one set-up:",
        "",
    ]
    table = []
    for m in moves:
        held = m["blocked_mean_mm"]
        table.append([
            m["file"], m["kind"], m["row"] if m["row"] is not None else "-",
            f"{fmt(m['shift_mm']['mean'])} / {fmt(m['shift_mm']['max'])}",
            " / ".join(fmt(held.get(k)) for k in ("one", "change", "drift", "both")),
            f"{fmt(m['gain_mm'])} ({fmt(m['min_gain_mm'])})",
        ])  # fmt: skip
    header = ["file", "move", "row", "shift mean / max [mm]",
              "held-out mean [mm]: one / change / drift / both",
              "gain (margin) [mm]"]  # fmt: skip
    lines += [markdown_table(table, header, ["l", "l", "r", "r", "r", "r"])]
    lines += [f"> **Warning:** {setup_move_text(m)}." for m in moves] + [""]
    per_file = diagnosis.model.base.sets > 1  # a frame group is a file, else all rows
    cond = conditions_from_data(data, per_file)
    for k, m in enumerate(moves):
        rows = torch.ones(data.n, dtype=torch.bool)
        if per_file:
            rows = data.file_index == data.sources.index(m["file"])
        part = data.subset(rows.nonzero().squeeze(1))
        with torch.no_grad():
            T = predicted_poses(diagnosis.model, part.q, cond.subset(rows))
        errors = (part.position - T[:, :3, 3]) * 1e3
        title = f"{Path(m['file']).name}: the errors of the final model, row by row"
        path = sequence_plot(part.rows, errors, out / f"setup_{k}.png", m["row"], title)
        lines += [image(path, f"errors row by row, {m['file']}", out), ""]
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
