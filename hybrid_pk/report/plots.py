"""Report figures, drawn with matplotlib's object API on the Agg canvas.

No pyplot: figures are created and saved without touching matplotlib's global state
(backend, current figure), so reports can be written from scripts, tests and threads.
Every function takes plain arrays (numpy or torch) and writes one PNG.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from hybrid_pk.errors import HybridPKError

try:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
except ImportError as exc:  # pragma: no cover - depends on the installation
    raise HybridPKError("reports need matplotlib: pip install matplotlib") from exc

__all__ = [
    "MAX_POINTS",
    "binned_median",
    "error_histograms",
    "evidence_plot",
    "new_figure",
    "residual_scan",
    "save_figure",
]

MAX_POINTS = 6000  # scatter plots draw at most this many points (evenly spread rows)
DPI = 110
_BEFORE, _AFTER, _LAW, _MEDIAN = "#d95f02", "#1b9e77", "#c0392b", "black"


def _np(x) -> np.ndarray | None:
    if x is None:
        return None
    if hasattr(x, "detach"):
        x = x.detach().cpu().double().numpy()
    return np.asarray(x, dtype=float).reshape(-1)


def new_figure(width: float = 7.0, height: float = 4.5) -> Figure:
    """A figure on its own Agg canvas (size in inches)."""
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Figure, path: str | Path) -> Path:
    """Write ``fig`` as PNG to ``path`` (folders created) and return the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI)
    return path


def _thin(n: int) -> np.ndarray:
    """Indices of at most :data:`MAX_POINTS` rows spread evenly over ``n``."""
    if n <= MAX_POINTS:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, MAX_POINTS).round().astype(int))


def binned_median(
    x: np.ndarray, y: np.ndarray, bins: int = 12, min_count: int = 5
) -> tuple[np.ndarray, np.ndarray]:
    """Medians of ``y`` in equal-count bins of ``x``: ``(x_median, y_median)``."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if x.size < min_count:
        return np.empty(0), np.empty(0)
    bins = max(1, min(bins, x.size // min_count))
    parts = np.array_split(np.argsort(x, kind="stable"), bins)
    return (
        np.array([np.median(x[p]) for p in parts]),
        np.array([np.median(y[p]) for p in parts]),
    )


def error_histograms(
    before: Sequence,
    after: Sequence,
    labels: Sequence[str],
    path: str | Path,
    title: str | None = None,
) -> Path:
    """Overlaid error histograms of two models, position and orientation side by side.

    Like Fig. 4 of Ojer et al. 2024: the distribution of the per-sample errors before
    and after (e.g. nominal vs extended model, on the hold-out rows).

    Args:
        before: ``(position_mm (n,), orientation_deg (n,) | None)`` of the first model.
        after: the same for the second model.
        labels: names of the two models.
        path: PNG to write.
        title: figure title.
    """
    pos = [_np(before[0]), _np(after[0])]
    ori = [_np(before[1]), _np(after[1])]
    panels = [("position error [mm]", pos)]
    if all(o is not None for o in ori):
        panels.append(("orientation error [deg]", ori))
    fig = new_figure(5.0 * len(panels) + 1.0, 4.0)
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, (xlabel, values) in zip(axes, panels, strict=True):
        hi = max(float(np.max(v)) for v in values)
        means = [float(np.mean(v)) for v in values]
        # Errors an order of magnitude apart share no linear axis: use log bins then.
        log = min(means) > 0 and max(means) / min(means) > 8
        if log:
            lo = min(float(np.percentile(v[v > 0], 0.5)) for v in values if (v > 0).any())
            bins = np.geomspace(lo, hi * 1.02, 51)
            ax.set_xscale("log")
            xlabel += " (log scale)"
        else:
            bins = np.linspace(0.0, hi * 1.02 if hi > 0 else 1.0, 41)
        for v, label, color in zip(values, labels, (_BEFORE, _AFTER), strict=True):
            rms = math.sqrt(float(np.mean(v**2)))
            ax.hist(
                v,
                bins=bins,
                alpha=0.6,
                color=color,
                edgecolor=color,
                label=f"{label}: mean {np.mean(v):.3g}, RMS {rms:.3g}",
            )
        ax.set_xlabel(xlabel)
        ax.set_ylabel("samples")
        ax.legend(fontsize="small")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)


def evidence_plot(evidence, path: str | Path) -> Path:
    """Points, binned median and the fitted law of one cause (an ``Evidence``).

    Continuous law variables give a scatter plot; categorical ones (backlash: approach
    direction) a strip plot with box plots per level.
    """
    ev = evidence
    fig = new_figure(7.0, 4.6)
    ax = fig.subplots()
    idx = _thin(ev.x.size)
    law_label = f"diagnosed law: {ev.law}"
    if ev.categorical:
        levels = np.unique(ev.x)
        rng = np.random.default_rng(0)  # jitter only; deterministic figures
        jitter = rng.uniform(-0.15, 0.15, idx.size)
        ax.scatter(
            ev.x[idx] + jitter,
            ev.y[idx],
            s=5,
            alpha=0.35,
            color="#4c72b0",
            lw=0,
            rasterized=True,
            label="measured",
        )
        groups = [ev.y[ev.x == level] for level in levels]
        ax.boxplot(
            groups,
            positions=levels,
            widths=0.45,
            showfliers=False,
            medianprops={"color": _MEDIAN, "lw": 2},
        )
        for cx, cy in zip(ev.curve_x, ev.curve_y, strict=True):
            ax.hlines(
                cy,
                cx - 0.3,
                cx + 0.3,
                color=_LAW,
                lw=2.5,
                label=law_label if cx == ev.curve_x[0] else None,
            )
        names = {-1.0: "negative", 0.0: "unknown", 1.0: "positive"}
        ax.set_xticks(levels, [names.get(float(v), f"{v:g}") for v in levels])
    else:
        ax.scatter(
            ev.x[idx],
            ev.y[idx],
            s=8,
            alpha=0.4,
            color="#4c72b0",
            lw=0,
            rasterized=True,
            label="measured",
        )
        ax.plot(ev.curve_x, ev.curve_y, color=_LAW, lw=2.5, label=law_label)
        ax.plot(
            ev.median_x,
            ev.median_y,
            "o-",
            color=_MEDIAN,
            ms=5,
            lw=1.2,
            label="binned median",
        )
    ax.axhline(0.0, color="grey", lw=0.6)
    ax.set_xlabel(ev.x_label)
    ax.set_ylabel(ev.y_label)
    ax.set_title(ev.title, fontsize="medium")
    text = f"law fitted to the points alone: {ev.points_value:.4g} {ev.unit}"
    if ev.nominal_points_value is not None:
        text += f"\nin the nominal model's residual: {ev.nominal_points_value:.4g} {ev.unit}"
    ax.text(
        0.01,
        0.99,
        text,
        transform=ax.transAxes,
        va="top",
        fontsize="small",
        bbox={"facecolor": "white", "alpha": 0.8, "lw": 0},
    )
    ax.legend(fontsize="small", loc="best")
    _clip_y(ax, ev.y, ev.curve_y)
    return save_figure(fig, path)


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
    fig = new_figure(3.2 * ncol + 0.5, 2.6 * nrow_per * len(rows) + 0.6)
    axes = fig.subplots(nrow_per * len(rows), ncol, squeeze=False)
    for r, err_label in enumerate(rows):
        e = _np(errors[err_label])
        idx = _thin(e.size)
        for k, name in enumerate(names):
            ax = axes[r * nrow_per + k // ncol][k % ncol]
            x = _np(variables[name])
            ax.scatter(x[idx], e[idx], s=4, alpha=0.35, lw=0, color="#4c72b0", rasterized=True)
            mx, my = binned_median(x, e)
            ax.plot(mx, my, "o-", color=_MEDIAN, ms=3, lw=1.0)
            if reference and err_label in reference:
                ax.axhline(reference[err_label], color=_LAW, ls="--", lw=1.0)
            ax.set_xlabel(name)
            if k % ncol == 0:
                ax.set_ylabel(err_label)
        for k in range(len(names), nrow_per * ncol):
            axes[r * nrow_per + k // ncol][k % ncol].set_visible(False)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)
