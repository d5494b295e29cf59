"""Evaluation report: errors of one or more models on the same measured rows.

``report.md`` + PNGs: the error table (model columns, e.g. nominal -> extended ->
hybrid; mean, RMS, p95, max; position mm, orientation deg), histograms of the errors
before/after like Fig. 4 of Ojer et al. 2024 (first model against each later one),
the error of each model along every joint, and ISO 9283 pose accuracy / repeatability
where the data has repeated poses. Used by ``evaluate --report`` and ``demo``.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter
from torch import Tensor

from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.errors import DataError
from hybrid_pk.evaluation.iso9283 import iso9283
from hybrid_pk.evaluation.metrics import evaluate_json, row_errors
from hybrid_pk.evaluation.plots import (
    LOG_SCALE_RATIO,
    error_histograms,
    new_figure,
    save_figure,
)
from hybrid_pk.output_file import write_text
from hybrid_pk.report.markdown import image, markdown_table, stats_table

__all__ = ["write_evaluation_report"]


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in text).strip("_").lower()


def _along_joints(
    errors: Mapping[str, Tensor], data: MeasuredData, path: Path, joint_types=None
) -> Path:
    """Binned mean position error of every model against every joint: revolute joints
    in degrees and prismatic ones in mm where ``joint_types`` are known (as the
    diagnosis report draws them), the table's rad and m otherwise."""
    q = data.q.detach().cpu().numpy().copy()
    units = ["rad"] * q.shape[1]
    for j, kind in enumerate(joint_types or ()):
        q[:, j] *= 1000.0 if kind == "prismatic" else 180.0 / np.pi
        units[j] = "mm" if kind == "prismatic" else "deg"
    dof = q.shape[1]
    cols = min(dof, 3)
    rows = -(-dof // cols)
    fig = new_figure(4.0 * cols, 3.0 * rows + 0.8)  # + title and legend
    overall = [float(e.detach().double().mean()) for e in errors.values()]
    log = min(overall) > 0 and max(overall) / min(overall) > LOG_SCALE_RATIO
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
    for j in range(dof):
        ax = axes[j]
        edges = np.linspace(q[:, j].min(), q[:, j].max(), 21)
        which = np.clip(np.digitize(q[:, j], edges) - 1, 0, 19)
        centres = 0.5 * (edges[1:] + edges[:-1])
        # own line styles: a model equal to another (hybrid = extended) stays in view
        for (name, e), style in zip(
            errors.items(), itertools.cycle(("-", "--", ":")), strict=False
        ):
            v = e.detach().cpu().numpy()
            counts = np.bincount(which, minlength=20)
            sums = np.bincount(which, weights=v, minlength=20)
            means = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
            ax.plot(centres, means, marker="o", ls=style, ms=3, label=name)
        ax.set_xlabel(f"{data.joint_names[j]} [{units[j]}]")
        ax.set_ylabel("mean position error [mm]" + (" (log scale)" if log else ""))
        if log:  # 1-2-5 ticks in plain numbers: every panel labelled within its range
            ax.set_yscale("log")
            ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            ax.yaxis.set_minor_formatter(NullFormatter())
    for ax in axes[dof:]:
        ax.set_visible(False)
    # One legend for all panels, under them: inside the first panel it covered its curves.
    fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncols=3)
    fig.suptitle(f"mean position error in 20 bins of each joint ({data.n} rows)")
    return save_figure(fig, path)


def _iso_figure(value) -> bool:
    return isinstance(value, dict) and set(value) == {"mean", "max"}


def _iso_name(key: str) -> str:
    """``AP_p_mm`` -> ``AP_p [mm]``: the figure as ISO 9283 names it, its unit apart."""
    head, _, unit = key.rpartition("_")
    return f"{head} [{unit}]" if unit in ("mm", "deg") else key


def _iso_section(data: MeasuredData, T: Tensor, name: str) -> tuple[list[str], dict | None]:
    try:
        result = iso9283(data, T)
    except DataError:
        return [
            "## ISO 9283 pose accuracy and repeatability",
            "",
            "No repeated poses in these rows (ISO 9283 AP/RP need the same commanded "
            "joints visited several times).",
            "",
        ], None
    summary = result.summary()
    rows = sorted(
        ([_iso_name(k), v["mean"], v["max"]] for k, v in summary.items() if _iso_figure(v)),
        key=lambda row: not row[0].startswith("AP"),  # accuracy first, as ISO 9283 lists
    )
    low, high = summary["cycles"]["min"], summary["cycles"]["max"]
    lines = [
        "## ISO 9283 pose accuracy and repeatability",
        "",
        f"{summary['n_poses']} repeated poses, {low if low == high else f'{low}-{high}'} "
        "visits each (ISO 9283 asks for "
        f"{summary['iso_cycles']}); accuracy AP against the poses {name} predicts. "
        f"Pooled noise level {summary['sigma_pooled_mm']:.4f} mm per axis (from the median, "
        f"which a bad visit does not inflate: {summary['sigma_robust_mm']:.4f} mm).",
        "",
        markdown_table(rows, ["figure", "mean over poses", "max over poses"], ["l", "r", "r"]),
        "",
    ]
    return lines, summary


def write_evaluation_report(
    out: str | Path,
    data: MeasuredData,
    predictions: Mapping[str, Tensor],
    *,
    title: str = "Evaluation",
    intro: str = "",
    joint_types: Sequence[str] | None = None,
) -> tuple[Path, dict[str, dict]]:
    """Write ``out/report.md`` (+ PNGs, ``evaluation.json``) comparing models on ``data``.

    Args:
        out: folder (created).
        data: measured rows.
        predictions: model label -> predicted poses ``(N, 4, 4)`` of the rows, in the
            order of the table (the first is the baseline of the histograms).
        title: heading.
        intro: paragraph under the heading.
        joint_types: the robot's ``"revolute"`` / ``"prismatic"`` per joint: the
            along-joints figure then reads degrees and mm (None: rad and m).

    Returns:
        ``(path of report.md, {model label: contract-5 errors})``; ``evaluation.json``
        holds the same errors plus ``iso9283`` when the rows have repeated poses.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if not predictions:
        raise ValueError("predictions is empty: give at least one model")
    errors = {}
    for name, T in predictions.items():
        with torch.no_grad():
            errors[name] = row_errors(T, data)
    results = {name: evaluate_json(data.n, p, o) for name, (p, o) in errors.items()}
    names = list(predictions)
    lines = [f"# {title}", ""]
    if intro:
        lines += [intro, ""]
    lines += [
        f"## Errors on {data.n} rows",
        "",
        "Position error: distance between measured and predicted point [mm]; "
        "orientation error: angle of R_measured R_model^T [deg].",
        "",
        stats_table(results),
        "",
    ]
    if len(names) > 1:
        lines += ["## Error distributions (like Fig. 4 of Ojer et al. 2024)", ""]
        for later in names[1:]:
            png = out / f"histogram_{_slug(names[0])}_vs_{_slug(later)}.png"
            error_histograms(
                errors[names[0]],
                errors[later],
                [names[0], later],
                png,
                title=f"errors on {data.n} rows: {names[0]} vs {later}",
            )
            lines += [image(png, f"errors of {names[0]} and {later}", out), ""]
    png = _along_joints(
        {n: e[0] for n, e in errors.items()}, data, out / "error_along_joints.png", joint_types
    )
    lines += [
        "## Error along each joint",
        "",
        "Mean position error in 20 bins of each joint: structure left in a curve is what "
        "the model still misses there.",
        "",
        image(png, "mean position error against each joint", out),
        "",
    ]
    iso_lines, iso = _iso_section(data, predictions[names[-1]], names[-1])
    lines += iso_lines
    saved = results if iso is None else {**results, "iso9283": iso}
    write_text(out / "evaluation.json", json.dumps(saved, indent=2) + "\n")
    path = write_text(out / "report.md", "\n".join(lines))
    return path, results
