"""What the data cannot show, in the diagnosis report: the detection limits of the
candidates not named, and every row's error against the outlier threshold."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

from hybrid_pk.calibration.fit import model_errors
from hybrid_pk.calibration.robust import outlier_cut, row_d2
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import conditions_from_data
from hybrid_pk.evaluation.plots import LAW_COLOR, legend_below, new_figure, save_figure
from hybrid_pk.report.markdown import image, markdown_table, with_unit

__all__ = ["detectable_section", "outlier_plot"]

POINT_COLOR, OUTLIER_COLOR = "#4c72b0", "#d95f02"


def detectable_section(diagnosis) -> list[str]:
    """``## What these data cannot show``: per family its largest detection limit."""
    det = getattr(diagnosis, "detectable", None)
    if not det:
        return []
    worst: dict[str, dict] = {}
    for d in det["limits"]:
        w = worst.get(d["family"])
        if w is None or d["value"] > w["value"]:
            worst[d["family"]] = d
    rows = [
        [f, d["joint"] or "-", with_unit(f"{d['value']:.3g}", d["unit"]), d["mm_rms"], _set_by(d)]
        for f, d in sorted(worst.items(), key=lambda kv: -kv[1]["mm_rms"])
    ]
    lines = ["## What these data cannot show", ""]
    if det.get("little_power"):
        lines += [f"**Warning**: {det['little_power']}.", ""]
    return [
        *lines,
        f"The smallest effect of each kind not named that this campaign would have "
        f"detected with {100 * det['power']:.0f} % power at the diagnosis' level and "
        f"that gains the practical margin ({_mm(det.get('min_gain_mm'))} mm) on the "
        "blocked hold-out, the larger of the two sizes (set by: which one); the largest "
        "over the joints: smaller effects of that kind may hide at some joint; mm: the "
        "rms change of the measured point such an effect makes.",
        "",
        markdown_table(
            rows,
            ["effect", "worst joint", "detectable from", "point [mm rms]", "set by"],
            ["l", "l", "r", "r", "l"],
        ),
        "",
        det["summary"] + ".",
        "",
    ]


def _set_by(limit: dict) -> str:
    return "practical margin" if limit.get("set_by") == "margin" else "80 % power"


def _mm(value) -> str:
    return "-" if value is None else f"{value:.2g}"


def outlier_plot(diagnosis, data: MeasuredData, out: Path) -> list[str]:
    """Every row's noise-normalised error against its row, the outlier threshold drawn
    (the rule of :func:`~hybrid_pk.calibration.robust.list_outliers`)."""
    noise = diagnosis.identifiability["noise_estimate"]
    cond = conditions_from_data(data, diagnosis.model.base.sets > 1)
    with torch.no_grad():
        pos, ori = model_errors(diagnosis.model, data, cond)
    d2, dim = row_d2(pos, ori, noise["position_mm"], noise["orientation_rad"])
    cut = outlier_cut(d2, dim)
    d = np.sqrt(d2.numpy())
    rows = np.arange(1, data.n + 1)
    bad = d2.numpy() > cut
    thr = float(np.sqrt(cut))
    fig = new_figure(8.0, 4.0)
    ax = fig.subplots()
    ax.scatter(rows[~bad], d[~bad], s=4, lw=0, color=POINT_COLOR, rasterized=True, label="rows")
    ax.scatter(rows[bad], d[bad], s=10, lw=0, color=OUTLIER_COLOR, label="listed as outliers")
    ax.axhline(thr, color=LAW_COLOR, ls="--", lw=1.0, label=f"threshold {thr:.3g}")
    ax.set_yscale("log")
    # plain numbers on the log axis (4 reads better than 4 x 10^0); the threshold in view
    ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))  # 1-2-5: labels each decade
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())
    ax.set_ylim(top=1.3 * max(thr, float(d.max())))
    ax.set_xlabel("row (order of the data)")
    ax.set_ylabel(f"√(Σ (error / noise)²) over {dim} coordinates")
    ax.set_title(
        f"extended model, all {data.n} rows: {int(bad.sum())} above the outlier threshold",
        fontsize="medium",
    )
    legend_below(ax, ncols=3)
    path = save_figure(fig, out / "outliers.png")
    return [
        image(path, "every row's error in noise units, listed outliers and the threshold", out),
        "",
    ]
