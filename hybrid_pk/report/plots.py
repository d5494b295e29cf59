"""Diagnosis figures: the evidence of a cause and the scan of what is left.

Drawn like every figure of the package with :mod:`hybrid_pk.evaluation.plots` (matplotlib's
object API on the Agg canvas, no pyplot).
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from hybrid_pk.evaluation.plots import (
    LAW_COLOR,
    MEDIAN_COLOR,
    as_array,
    binned_median,
    new_figure,
    save_figure,
    thin,
)
from hybrid_pk.report.markdown import with_unit

__all__ = ["evidence_plot", "residual_scan", "sequence_plot"]

POINT_COLOR = "#4c72b0"  # measured points


def _measured_points(ax, x: np.ndarray, y: np.ndarray, size: float, alpha: float) -> None:
    """Scatter the measured points of an evidence plot (rasterised: thousands of them)."""
    ax.scatter(
        x, y, s=size, alpha=alpha, color=POINT_COLOR, lw=0, rasterized=True, label="measured"
    )


# Characters per line that fit the 7 in wide figure: a medium (10 pt) title, a small
# (8 pt) legend entry. Longer ones ran off the page and squeezed the axes.
TITLE_CHARS, LEGEND_CHARS = 90, 100


def wrap_title(title: str) -> str:
    """``title`` in lines of at most :data:`TITLE_CHARS`: one line when it fits, else a
    line per '; ' part (the value, then the gain), a part too long wrapped itself."""
    if len(title) <= TITLE_CHARS:
        return title
    return "\n".join(p for chunk in title.split("; ") for p in textwrap.wrap(chunk, TITLE_CHARS))


def evidence_plot(evidence, path: str | Path) -> Path:
    """Points, binned median and the fitted law of one cause (an ``Evidence``).

    Continuous law variables give a scatter plot; categorical ones (backlash: approach
    direction) a strip plot with box plots per level.
    """
    ev = evidence
    zoom = _needs_zoom(ev)
    # room for the legend below the axes (and for the zoom under the points)
    fig = new_figure(7.0, 8.2 if zoom else 5.2)
    ax, zoom_ax = fig.subplots(2, 1, height_ratios=[3, 2]) if zoom else (fig.subplots(), None)
    idx = thin(ev.x.size)
    # ' + ' held together (no-break spaces): a line break inside √(a² + b²) split the formula
    law = ev.law.replace(" + ", "\u00a0+\u00a0")
    law_label = textwrap.fill(f"diagnosed law: {law}", LEGEND_CHARS)
    if ev.categorical:
        levels = np.unique(ev.x)
        rng = np.random.default_rng(0)  # jitter only; deterministic figures
        jitter = rng.uniform(-0.15, 0.15, idx.size)
        _measured_points(ax, ev.x[idx] + jitter, ev.y[idx], size=5, alpha=0.35)
        groups = [ev.y[ev.x == level] for level in levels]
        ax.boxplot(
            groups,
            positions=levels,
            widths=0.45,
            showfliers=False,
            medianprops={"color": MEDIAN_COLOR, "lw": 2},
        )
        for cx, cy in zip(ev.curve_x, ev.curve_y, strict=True):
            ax.hlines(
                cy,
                cx - 0.3,
                cx + 0.3,
                color=LAW_COLOR,
                lw=2.5,
                label=law_label if cx == ev.curve_x[0] else None,
            )
        names = {-1.0: "negative", 0.0: "unknown", 1.0: "positive"}
        ax.set_xticks(levels, [names.get(float(v), f"{v:g}") for v in levels])
    else:
        _measured_points(ax, ev.x[idx], ev.y[idx], size=8, alpha=0.4)
        ax.plot(ev.curve_x, ev.curve_y, color=LAW_COLOR, lw=2.5, label=law_label)
        ax.plot(
            ev.median_x,
            ev.median_y,
            "o-",
            color=MEDIAN_COLOR,
            ms=5,
            lw=1.2,
            label="binned median",
        )
    ax.axhline(0.0, color="grey", lw=0.6)
    ax.set_xlabel(ev.x_label)
    ax.set_ylabel(ev.y_label)
    ax.set_title(wrap_title(ev.title), fontsize="medium")
    text = with_unit(f"law fitted to the points alone: {ev.points_value:.4g}", ev.unit)
    if ev.nominal_points_value is not None:
        nominal = f"in the nominal model's residual: {ev.nominal_points_value:.4g}"
        text += "\n" + with_unit(nominal, ev.unit)
    ax.text(
        0.01,
        0.99,
        text,
        transform=ax.transAxes,
        va="top",
        fontsize="small",
        bbox={"facecolor": "white", "alpha": 0.8, "lw": 0},
    )
    _clip_y(ax, ev.y, ev.curve_y)
    if zoom_ax is not None:
        _zoom_panel(zoom_ax, ev)
    # Below the axes: inside, the long law label covered the fitted-law text or points.
    fig.legend(*ax.get_legend_handles_labels(), fontsize="small", loc="outside lower center")
    return save_figure(fig, path)


# Below a tenth of the axis (about 0.4 in on the page) a law or a trend of the medians is
# a flat line: whether the data carry it is then shown on a panel of its own.
ZOOM_SHARE = 0.1
FINER = {"[mrad]": "[µrad]", "[mm]": "[µm]"}  # the zoom's unit, 1000 times finer


def _needs_zoom(ev) -> bool:
    """Whether the law and the binned medians of a continuous evidence plot span less
    than :data:`ZOOM_SHARE` of the points' range (a 3.5 µrad sinusoid in ±80 µrad)."""
    if ev.categorical or ev.y.size < 20 or ev.median_y.size < 2:
        return False
    lo, hi = np.percentile(ev.y, [0.5, 99.5])
    curve = np.asarray(ev.curve_y, float)
    span = max(np.ptp(curve), np.abs(curve).max(), np.ptp(ev.median_y), np.abs(ev.median_y).max())
    return bool(span < ZOOM_SHARE * (hi - lo))


def median_errors(x: np.ndarray, y: np.ndarray, bins: int):
    """``(x_median, y_median, standard error of y_median)`` in ``bins`` equal-count
    bins of ``x`` (the bins of :func:`binned_median`); the error of a median is
    √(π/2) σ / √n, σ from the bin's median absolute deviation (1.4826 MAD for normal
    noise), so one wild row does not widen it."""
    parts = np.array_split(np.argsort(x, kind="stable"), bins)
    mx = np.array([np.median(x[p]) for p in parts])
    my = np.array([np.median(y[p]) for p in parts])
    mad = np.array([np.median(np.abs(y[p] - m)) for p, m in zip(parts, my, strict=True)])
    size = np.array([p.size for p in parts])
    return mx, my, math.sqrt(math.pi / 2) * 1.4826 * mad / np.sqrt(size)


def _zoom_panel(ax, ev) -> None:
    """The law and the binned medians with their standard errors, on a scale they fill:
    the reader sees whether the medians trace the law or scatter round zero."""
    unit = next((u for u in FINER if ev.y_label.endswith(u)), None)
    scale, label = (1e3, ev.y_label[: -len(unit)] + FINER[unit]) if unit else (1.0, ev.y_label)
    mx, my, se = median_errors(ev.x, ev.y, ev.median_y.size)
    ax.plot(ev.curve_x, scale * ev.curve_y, color=LAW_COLOR, lw=2.5)
    ax.errorbar(mx, scale * my, yerr=scale * se, fmt="o", color=MEDIAN_COLOR, ms=5, capsize=3)
    ax.axhline(0.0, color="grey", lw=0.6)
    ax.set_xlim(
        ev.curve_x.min() - 0.02 * np.ptp(ev.curve_x), ev.curve_x.max() + 0.02 * np.ptp(ev.curve_x)
    )
    ax.set_xlabel(ev.x_label)
    ax.set_ylabel(label)
    lo, hi = np.percentile(ev.y, [0.5, 99.5])
    bottom, top = ax.get_ylim()
    ax.set_title(
        "zoom: law and binned medians ± their standard error (the points above spread "
        f"{(hi - lo) / ((top - bottom) / scale):.0f}x wider)",
        fontsize="small",
    )


def _clip_y(ax, y: np.ndarray, curve: np.ndarray) -> None:
    """Keep a few far outliers from squashing the law into a flat line; keep zero in view
    (an offset is only seen as one against the zero line)."""
    if y.size < 20:
        return
    lo, hi = np.percentile(y, [0.5, 99.5])
    lo, hi = min(lo, float(np.min(curve)), 0.0), max(hi, float(np.max(curve)), 0.0)
    pad = 0.08 * (hi - lo if hi > lo else 1.0)
    ax.set_ylim(lo - pad, hi + pad)


def residual_scan(
    variables: Mapping[str, object],
    errors: Mapping[str, object],
    path: str | Path,
    reference: Mapping[str, float] | None = None,
    title: str | None = None,
) -> Path:
    """Errors against every variable (joints, temperature, …): what is left to explain.

    Args:
        variables: axis label -> ``(n,)`` values (e.g. ``"joint_1 [deg]"``).
        errors: axis label -> ``(n,)`` per-sample errors (one row of panels each).
        path: PNG to write.
        reference: error label -> level drawn as a dashed line (e.g. the mean error
            that measurement noise alone would give).
        title: figure title.
    """
    names, rows = list(variables), list(errors)
    ncol = min(len(names), 4)
    nrow_per = math.ceil(len(names) / ncol)
    fig = new_figure(3.2 * ncol + 0.5, 2.6 * nrow_per * len(rows) + 0.9)  # + the legend
    axes = fig.subplots(nrow_per * len(rows), ncol, squeeze=False)
    for r, err_label in enumerate(rows):
        e = as_array(errors[err_label])
        idx = thin(e.size)
        for k, name in enumerate(names):
            ax = axes[r * nrow_per + k // ncol][k % ncol]
            x = as_array(variables[name])
            ax.scatter(
                x[idx], e[idx], s=4, alpha=0.35, lw=0, color=POINT_COLOR, rasterized=True,
                label="rows",
            )  # fmt: skip
            mx, my = binned_median(x, e)
            ax.plot(mx, my, "o-", color=MEDIAN_COLOR, ms=3, lw=1.0, label="binned median")
            if reference and err_label in reference:
                ax.axhline(
                    reference[err_label], color=LAW_COLOR, ls="--", lw=1.0,
                    label="mean error the noise estimate alone gives",
                )  # fmt: skip
            ax.set_xlabel(name)
            if k % ncol == 0:
                ax.set_ylabel(err_label)
        for k in range(len(names), nrow_per * ncol):
            axes[r * nrow_per + k // ncol][k % ncol].set_visible(False)
    # what the dots, the line and the dashed level are: said once, under the panels
    fig.legend(*axes[0][0].get_legend_handles_labels(), loc="outside lower center", ncols=3)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)


def sequence_plot(rows: object, errors: object, path: str | Path, mark=None, title=None) -> Path:
    """The x, y, z error [mm] of each row against its row number, as measured (binned
    medians of 60 equal-count bins over the points): a set-up move shows as a step
    (``mark``: the row drawn as a dashed line) or a slope.

    Args:
        rows: ``(n,)`` row numbers in the order measured.
        errors: ``(n, 3)`` measured minus predicted position [mm].
        path: PNG to write.
        mark: the row of a change, or None.
        title: figure title.
    """
    x, e = as_array(rows), as_array(errors).reshape(-1, 3)
    fig = new_figure(7.0, 3.6)
    ax = fig.subplots()
    for k, (name, color) in enumerate(zip("xyz", SEQUENCE_COLORS, strict=True)):
        mx, my = binned_median(x, e[:, k], bins=60)
        ax.plot(mx, my, "o-", ms=2.5, lw=1.0, color=color, label=f"{name} error")
    if mark is not None:
        ax.axvline(mark, color=LAW_COLOR, ls="--", lw=1.0, label=f"change, row {mark}")
    ax.axhline(0.0, color="0.6", lw=0.6)
    ax.set_xlabel("row, in the order measured")
    ax.set_ylabel("measured - predicted [mm] (binned median)")
    ax.legend(loc="best", fontsize="small")
    if title:
        ax.set_title(wrap_title(title), fontsize="medium")
    return save_figure(fig, path)


SEQUENCE_COLORS = ("#c44e52", "#55a868", "#4c72b0")  # x, y, z
