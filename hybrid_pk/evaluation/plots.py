"""Error figures, drawn with matplotlib's object API on the Agg canvas.

No pyplot: figures are created and saved without touching matplotlib's global state
(backend, current figure), so reports can be written from scripts, tests and threads.
Every function takes plain arrays (numpy or torch) and writes one PNG.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from hybrid_pk.errors import HybridPKError
from hybrid_pk.output_file import replacing

try:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator
except ImportError as exc:  # pragma: no cover - depends on the installation
    raise HybridPKError("reports need matplotlib: pip install matplotlib") from exc

__all__ = [
    "AFTER_COLOR",
    "BEFORE_COLOR",
    "LAW_COLOR",
    "LOG_SCALE_RATIO",
    "MAX_POINTS",
    "MEDIAN_COLOR",
    "as_array",
    "binned_median",
    "error_histograms",
    "legend_below",
    "new_figure",
    "save_figure",
    "thin",
]

# Errors about an order of magnitude apart share no linear axis (the smaller lie flat on
# its floor): histograms and curves go to a log scale beyond this ratio of their means.
LOG_SCALE_RATIO = 8
MAX_POINTS = 6000  # scatter plots draw at most this many points (evenly spread rows)
DPI = 110
BEFORE_COLOR, AFTER_COLOR, LAW_COLOR, MEDIAN_COLOR = "#d95f02", "#1b9e77", "#c0392b", "black"


def as_array(x) -> np.ndarray | None:
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
    with replacing(path) as tmp:
        fig.savefig(tmp, dpi=DPI)
    return path


def legend_below(ax, **kwargs):
    """The legend of ``ax`` under its x label, centred: inside the axes a legend covers
    the bars or points it names (the constrained layout makes room for it)."""
    return ax.legend(fontsize="small", loc="upper center", bbox_to_anchor=(0.5, -0.16), **kwargs)


def thin(n: int) -> np.ndarray:
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
    pos = [as_array(before[0]), as_array(after[0])]
    ori = [as_array(before[1]), as_array(after[1])]
    panels = [("position error [mm]", "mm", pos)]
    if all(o is not None for o in ori):
        panels.append(("orientation error [deg]", "deg", ori))
    fig = new_figure(5.0 * len(panels) + 1.0, 4.6)  # room for the legends below
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, (xlabel, unit, values) in zip(axes, panels, strict=True):
        hi = max(float(np.max(v)) for v in values)
        means = [float(np.mean(v)) for v in values]
        log = min(means) > 0 and max(means) / min(means) > LOG_SCALE_RATIO
        if log:
            lo = min(float(np.percentile(v[v > 0], 0.5)) for v in values if (v > 0).any())
            bins = np.geomspace(lo, hi * 1.02, 51)
            ax.set_xscale("log")
            xlabel += " (log scale)"
        else:
            bins = np.linspace(0.0, hi * 1.02 if hi > 0 else 1.0, 41)
        for v, label, color in zip(values, labels, (BEFORE_COLOR, AFTER_COLOR), strict=True):
            rms = math.sqrt(float(np.mean(v**2)))
            ax.hist(
                v,
                bins=bins,
                alpha=0.6,
                color=color,
                edgecolor=color,
                label=f"{label}: mean {np.mean(v):.3g} {unit}, RMS {rms:.3g} {unit}",
            )
        ax.set_xlabel(xlabel)
        ax.set_ylabel("samples")
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))  # counts: no 2.5 samples
        legend_below(ax)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)
