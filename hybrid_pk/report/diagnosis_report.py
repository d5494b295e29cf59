"""The human report of a diagnosis: ``report.md`` and the PNG plots it links.

Sections: error table nominal -> extended with histograms (hold-out rows); the named
causes with one plot each that shows the cause's law in the measured residuals (see
:mod:`hybrid_pk.report.evidence`); ambiguities; what is left unexplained, plotted
against every joint; identifiability; the selection log.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from hybrid_pk.calibration.diagnosis.carryover import margin_text
from hybrid_pk.calibration.diagnosis.rivals import rival_lines
from hybrid_pk.calibration.diagnosis.settle import order_groups
from hybrid_pk.calibration.diagnosis.statistics import along_joints_text
from hybrid_pk.calibration.fit import model_errors
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import conditions_from_data
from hybrid_pk.errors import HybridPKError
from hybrid_pk.evaluation.plots import error_histograms
from hybrid_pk.output_file import write_text
from hybrid_pk.report.evidence import Evidence, cause_evidence, cause_label
from hybrid_pk.report.findings import (
    frames_section,
    robust_section,
    setup_section,
    structural_section,
    structured_paragraph,
)
from hybrid_pk.report.limits import detectable_section, outlier_plot
from hybrid_pk.report.markdown import (
    fmt,
    image,
    markdown_table,
    stats_table,
    value_with_std,
    with_unit,
)
from hybrid_pk.report.plots import evidence_plot, residual_scan
from hybrid_pk.robot import Robot

__all__ = ["LARGE_CONDITION_NUMBER", "plot_cause_evidence", "write_diagnosis_report"]

# Condition numbers above this make the report warn: some parameters trade off.
LARGE_CONDITION_NUMBER = 1e4
# Mean of the norm of a 3D isotropic Gaussian, in units of its per-axis sigma: sqrt(8/pi).
_NORM_MEAN_3D = math.sqrt(8.0 / math.pi)


def plot_cause_evidence(diagnosis, data: MeasuredData, cause, path: str | Path) -> Evidence:
    """Draw the evidence plot of one cause to ``path`` and return what it shows.

    With a single cause, the plot also says how much of the law the nominal model's
    own residual shows (its frames absorb part of it); with several causes that number
    would mix in the others' errors, so it is left out.
    """
    nominal = diagnosis.nominal_model if len(diagnosis.causes) == 1 else None
    evidence = cause_evidence(cause, data, diagnosis.model, nominal)
    evidence_plot(evidence, path)
    return evidence


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_").lower()


def _holdout_errors(diagnosis, data: MeasuredData):
    """Per-row errors of the nominal and the extended model on the hold-out rows."""
    cond = conditions_from_data(data, diagnosis.model.base.sets > 1)  # order-aware: all rows
    rows = diagnosis.holdout_rows
    test, cond_test = data.subset(rows), cond.subset(rows)
    return (
        model_errors(diagnosis.nominal_model, test, cond_test),
        model_errors(diagnosis.model, test, cond_test),
    )


_CAUSE_COLUMNS = [
    "effect",
    "joint",
    "value ± std",
    "position gain [mm]",
    "orientation gain [deg]",
    "in-sample [mm]",
    "random hold-out [mm]",
    "blocked hold-out [mm]",
    "blocks gained",
    "own-range hold-out [mm]",
]


def _cause_rows(diagnosis) -> list[list[object]]:
    rows = []
    for c in diagnosis.causes:
        value = value_with_std(c.value, c.std, c.unit)
        if c.components is not None:
            value += f" (components {fmt(c.components)})"
        if c.fitted_range_rad is not None:
            value += f"; fitted on {fmt(c.fitted_range_rad)} rad of the joint"
        for u in c.undetermined or []:  # an exact trade-off: the split is not measured
            others = ", ".join(u["with"])
            value += f"; [{u['component']}]: only its combination with {others} is determined"
        gains = (c.in_sample_gain_mm, c.random_holdout_gain_mm, c.blocked_holdout_gain_mm)
        own = getattr(c, "own_range_gain_mm", None)  # periodic causes: ends of their joint
        blocks = getattr(c, "blocked_blocks", None)
        share = "-" if blocks is None else f"{blocks['gained']} of {blocks['of']}"
        gains = (c.position_gain_mm, c.orientation_gain_deg, *gains, share, own)
        rows.append([c.effect, c.joint or "-", value, *gains])
    return rows


def _margin(diagnosis) -> str:
    carry = getattr(diagnosis, "carry_over", None)
    return "-" if not carry else f"{carry['min_gain_mm']:.3g}"


def _channel(diagnosis) -> str:
    """What the gains are measured on (the diagnosis JSON's ``carry_over.channel``)."""
    carry = getattr(diagnosis, "carry_over", None) or {}
    if carry.get("channel", "pose") == "position":
        return "position error"
    return "error (rotation at the noise ratio)"


def _margin_note(diagnosis) -> list[str]:
    """The margin and how the noise behind it was found, as a paragraph."""
    text = margin_text(getattr(diagnosis, "carry_over", None))
    return [] if text is None else [text[0].upper() + text[1:] + ".", ""]


def _evidence_section(diagnosis, data, out: Path, say=None) -> list[str]:
    lines = ["## Evidence for each cause", ""]
    if not diagnosis.causes:
        return [*lines, "No cause: the nominal model's errors are measurement noise.", ""]
    lines += [
        "Each plot starts from the measured positions. The points are the residual of "
        "the diagnosed model *without* the cause (URDF + base and tool frames + the "
        "other causes), reduced to the quantity the cause's law predicts; the red line "
        "is the law with the diagnosed value, the black dots the binned median of the "
        "points. A real cause makes the medians follow the line; a spurious one leaves "
        "a flat cloud around zero. (The nominal model's own residual is not used: its "
        "frames, fitted without any cause, absorb part of some effects and flatten "
        "their law.)",
        "",
    ]
    for i, cause in enumerate(diagnosis.causes, start=1):
        label = cause_label(cause)
        if say is not None:
            say(f"evidence plot {i}/{len(diagnosis.causes)}: {label}")
        lines += [f"### {i}. {label}", ""]
        path = out / f"evidence_{i:02d}_{_slug(label)}.png"
        try:
            ev = plot_cause_evidence(diagnosis, data, cause, path)
        except HybridPKError as exc:
            lines += [f"No evidence plot: {exc}.", ""]
            continue
        lines += [
            f"Law: {ev.law}. Diagnosed value {value_with_std(cause.value, cause.std, cause.unit)};"
            " the same law fitted to the plotted points alone gives "
            f"{with_unit(fmt(ev.points_value), ev.unit)} ({ev.x.size} points).",
            "",
        ]
        if ev.nominal_points_value is not None and ev.value != 0:
            share = 100.0 * ev.nominal_points_value / ev.value
            lines += [
                "In the nominal model's residual the law shows "
                f"{with_unit(fmt(ev.nominal_points_value), ev.unit)} ({share:.0f} % of the "
                "diagnosed value): the frames fitted "
                "without the cause absorb the rest.",
                "",
            ]
        lines += [image(path, f"evidence for {label}", out), "", f"Test: {cause.evidence}.", ""]
    return lines


def _what_is_left(diagnosis, data, robot: Robot, out: Path, ext) -> list[str]:
    rows = diagnosis.holdout_rows
    test = data.subset(rows)
    variables = {
        f"{name} [deg]" if robot.joint_types[j] != "prismatic" else f"{name} [mm]": (
            np.degrees(test.q[:, j].numpy())
            if robot.joint_types[j] != "prismatic"
            else 1e3 * test.q[:, j].numpy()
        )
        for j, name in enumerate(robot.joint_names)
    }
    for column, label in (("temperature", "temperature [°C]"), ("payload", "payload [kg]")):
        values = getattr(test, column)
        if values is not None and float(values.max() - values.min()) > 0:
            variables[label] = values.numpy()
    errors = {"position error [mm]": ext[0]}
    if ext[1] is not None:
        errors["orientation error [deg]"] = ext[1]
    noise = diagnosis.identifiability.get("noise_estimate", {})
    reference = {}
    if noise.get("position_mm"):
        reference["position error [mm]"] = _NORM_MEAN_3D * noise["position_mm"]
    if noise.get("orientation_rad"):
        reference["orientation error [deg]"] = math.degrees(
            _NORM_MEAN_3D * noise["orientation_rad"]
        )
    un = diagnosis.unexplained
    verdict = "structured" if un.get("structured") else "no structure found"
    path = residual_scan(
        variables,
        errors,
        out / "residual_left.png",
        reference,
        title=f"extended model, {test.n} hold-out rows: {verdict}",
    )
    corr = un.get("neighbour_correlation")
    text = structured_paragraph(un)
    lines = [
        "## What is left",
        "",
        f"RMS of the extended model on the hold-out rows: {fmt(un.get('position_mm_rms'))} mm,"
        f" {fmt(un.get('orientation_deg_rms'))} deg. {text}"
        + (f" (neighbour correlation {fmt(corr, 3)})" if corr is not None else ""),
        "",
    ]
    along = along_joints_text(un.get("along_joints"))
    if along is not None:
        lines += [
            f"How much of it varies along each joint alone: {along}. A share far above "
            "the noise's on the first joint means the error is not the same at every turn "
            "of the arm: a residual network that assumes it is (inputs without joint 1) "
            "cannot carry it to joint-1 angles it was not trained on.",
            "",
        ]
    lines += [
        "Hold-out errors against each joint (black: binned median; dashed red: the mean "
        "error measurement noise alone would give). Flat medians on the dashed line mean "
        "nothing structured remains.",
        "",
        image(path, "hold-out errors of the extended model against each joint", out),
        "",
    ]
    margin = (diagnosis.carry_over or {}).get("min_gain_mm")
    stories = rival_lines(diagnosis.rival_stories, margin, diagnosis.ambiguous)
    if stories:
        lines += [
            "## Rival stories",
            "",
            "A named cause that another candidate of the vocabulary stands in for: the "
            "rival, refitted, predicts the blocked hold-out as well (within the practical "
            "margin) or better, so these rows cannot choose between the two stories. "
            "Where the two models part, outside the measured rows, a measurement tells "
            "them apart (blocked hold-out RMS error of the named model / the rival's):",
            "",
            *[f"- {x}" for x in stories],
            "",
        ]
    return lines


def _identifiability(diagnosis) -> list[str]:
    ident = diagnosis.identifiability
    cond = ident.get("condition_number")
    noise = ident.get("noise_estimate", {})
    rot, lost = noise.get("orientation_rad"), ident.get("unidentifiable_directions")
    rows = [
        ["fitted parameters", ident.get("n_parameters")],
        ["directions not determined at all", lost],
        ["condition number (unit-norm columns, determined directions)", cond],
        ["observability index", ident.get("observability_index")],
        ["noise estimate, position [mm per axis]", noise.get("position_mm")],
        ["noise estimate, orientation [deg per axis]", None if rot is None else math.degrees(rot)],
    ]
    lines = ["## Identifiability", ""]
    warnings = [
        f"{lost} direction(s) of the fitted parameters are not determined at all by this "
        "data (exact trade-offs: singular values of round-off, reported as 0)"
    ] if lost else []  # fmt: skip
    if cond is not None and cond > LARGE_CONDITION_NUMBER:
        warnings.append(
            f"condition number {fmt(cond)} > {LARGE_CONDITION_NUMBER:g}: some fitted "
            "parameters trade off against each other in this data"
        )
    orders, others = order_groups(diagnosis.ambiguous)
    if others:  # counted as the console counts them; the cyclic orders per joint below
        warnings.append(
            f"{len(others)} ambiguous group(s): this data cannot tell "
            "their members apart (see below)"
        )
    lines += [f"> **Warning:** {w}." for w in warnings]
    if warnings:
        lines.append("")
    lines += [markdown_table(rows, ["quantity", "value"], ["l", "r"])]
    lines += ["### Ambiguous groups", ""]
    if others:
        amb = [[", ".join(a["effects"]), a["why"]] for a in others]
        lines.append(markdown_table(amb, ["effects", "why"], ["l", "l"]))
    else:
        lines += ["None.", ""]
    if orders:
        lines += ["Periodic errors whose order the rows do not resolve (none is named; the "
                  "data show a periodic error at the joint, not at which order):", ""]  # fmt: skip
        lines += [f"- {j}: {', '.join(map(str, o))} per turn" for j, o in orders.items()] + [""]
        pairs = [a for a in diagnosis.ambiguous if a not in others]
        lines += ["The pairs of orders, by their blocked hold-out:", ""]
        amb = [[", ".join(a["effects"]), a["why"]] for a in pairs]
        lines.append(markdown_table(amb, ["orders", "why"], ["l", "l"]))
    unobservable = ident.get("unobservable_candidates") or []
    lines += [
        "### Unobservable candidates",
        "",
        (
            "No signature at all in this data: " + ", ".join(unobservable) + "."
            if unobservable
            else "None."
        ),
        "",
    ]
    return lines


def _selection_log(diagnosis) -> list[str]:
    if not diagnosis.steps:
        return []
    rows = [
        [
            s.get("candidate"),
            s.get("score_F"),
            s.get("score_p"),
            s.get("threshold"),
            s.get("fit_F"),
            s.get("delta_bic"),
            "removed" if s.get("removed") else s.get("accepted"),
            s.get("why", ""),
        ]
        for s in diagnosis.steps
    ]
    headers = ["candidate", "score F", "score p", "threshold", "refit F", "ΔBIC", "accepted", "why"]
    return [
        "## Selection log",
        "",
        "Forward selection: at each step the best-scoring candidate is refitted and kept "
        "only if its F-test passes the Bonferroni threshold, BIC drops and the hold-out "
        "error drops. After each acceptance, earlier causes are re-tested by the F-test of "
        "removing them and dropped when no longer significant (backward elimination).",
        "",
        markdown_table(rows, headers, ["l", "r", "r", "r", "r", "r", "l", "l"]),
    ]


def write_diagnosis_report(
    diagnosis,
    data: MeasuredData,
    robot: Robot,
    out_dir: str | Path,
    progress: Callable[[str], None] | None = None,
) -> Path:
    """Write ``out_dir/report.md`` and its PNG plots for a diagnosis.

    Args:
        diagnosis: result of :func:`hybrid_pk.calibration.diagnosis.diagnose`.
        data: the rows it was computed on (same order).
        robot: the nominal robot.
        out_dir: folder to write to (created); image links are relative to it.
        progress: called with a short text before each plot.

    Returns:
        Path of ``report.md``.

    Raises:
        HybridPKError: if ``data`` is not the data of the diagnosis.
    """
    if data.n != diagnosis.n_samples:
        raise HybridPKError(
            f"the diagnosis was computed on {diagnosis.n_samples} rows, the data has {data.n}"
        )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with torch.no_grad():
        nom, ext = _holdout_errors(diagnosis, data)
    hist = error_histograms(
        nom,
        ext,
        ("nominal", "extended"),
        out / "error_histograms.png",
        title=f"hold-out errors ({diagnosis.n_holdout} rows)",
    )
    sources = ", ".join(f"`{s}`" for s in data.sources)
    lines = [
        f"# Diagnosis of {diagnosis.robot}",
        "",
        f"{diagnosis.n_samples} measured rows from {sources}; {diagnosis.n_holdout} hold-out "
        f"rows (kept out of every fit) compare the models. Position-only data: "
        f"{'yes' if data.quat is None else 'no'}.",
        "",
        "- **nominal**: the URDF with only the base and tool frames fitted.",
        "- **extended**: the URDF with frames and every cause below.",
        "",
        "## Errors on the hold-out rows",
        "",
        stats_table({"nominal": diagnosis.nominal, "extended": diagnosis.extended}),
        image(hist, "hold-out error histograms, nominal vs extended", out),
        "",
        *structural_section(diagnosis),
        *setup_section(diagnosis, data, out),
        "## Causes",
        "",
    ]
    if diagnosis.causes:
        lines += [
            "Ordered by gain: how much the hold-out mean error grows when the cause is "
            "left out and the rest refitted. The in-sample, random and blocked hold-out "
            "columns: the drop of the RMS "
            f"{_channel(diagnosis)} [mm] it brings on the fit rows, on the "
            "random hold-out rows and on rows held out in blocks (regions of joint space, "
            "whole files), where each cause must gain at least "
            f"{_margin(diagnosis)} mm (carry_over in the JSON).",
            "",
            *_margin_note(diagnosis),
            markdown_table(
                _cause_rows(diagnosis),
                _CAUSE_COLUMNS,
                ["l", "l", "l", "r", "r", "r", "r", "r", "r", "r"],
            ),
        ]
    elif diagnosis.structural and diagnosis.structural["structurally_wrong"]:
        lines += ["Withheld: the URDF looks structurally wrong (see above).", ""]
    else:
        lines += ["None: no effect beyond measurement noise is statistically supported.", ""]
        det = getattr(diagnosis, "detectable", None)
        if det:  # 'none' never comes without what the data could have shown
            lines += [f"With {100 * det['power']:.0f} % power: {det['summary']}.", ""]
    if diagnosis.ambiguous:
        orders, others = order_groups(diagnosis.ambiguous)
        told = [f"{len(others)} group(s)"] if others else []
        told += [f"periodic orders not resolved at {len(orders)} joint(s)"] if orders else []
        lines += [f"Ambiguities: {', '.join(told)}, see [Identifiability](#identifiability).", ""]
    lines += _evidence_section(diagnosis, data, out, progress)
    if progress is not None:
        progress("plots of what is left")
    lines += _what_is_left(diagnosis, data, robot, out, ext)
    lines += _identifiability(diagnosis)
    lines += detectable_section(diagnosis)
    lines += frames_section(diagnosis) + robust_section(diagnosis)
    lines += outlier_plot(diagnosis, data, out)
    lines += _selection_log(diagnosis)
    return write_text(out / "report.md", "\n".join(lines).rstrip() + "\n")
