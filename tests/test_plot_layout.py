"""Figures a reader can read: legends clear of the data they name, units and row counts
in the labels and titles (layout checked on the drawn figure, never on pixels)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("matplotlib")

import hybrid_pk.evaluation.plots as eval_plots  # noqa: E402


def keep_figures(monkeypatch, module) -> list:
    """Figures ``module`` saves from now on (still written)."""
    figures = []
    real = module.save_figure

    def keep(fig, path):
        figures.append(fig)
        return real(fig, path)

    monkeypatch.setattr(module, "save_figure", keep)
    return figures


def assert_legends_clear(fig) -> None:
    """No legend lies over the axes it belongs to."""
    fig.canvas.draw()
    for ax in fig.axes:
        legend = ax.get_legend()
        if legend is not None and ax.get_visible():
            assert not legend.get_window_extent().overlaps(ax.get_window_extent())


def test_error_histograms_legend_below_with_units(monkeypatch, tmp_path):
    figures = keep_figures(monkeypatch, eval_plots)
    rng = np.random.default_rng(0)
    eval_plots.error_histograms(
        (rng.rayleigh(1.0, 300), rng.rayleigh(0.1, 300)),
        (rng.rayleigh(0.02, 300), rng.rayleigh(0.002, 300)),
        ("nominal", "extended"),
        tmp_path / "h.png",
    )
    (fig,) = figures
    assert_legends_clear(fig)
    pos, ori = (ax.get_legend() for ax in fig.axes)
    assert all(t.get_text().endswith(" mm") for t in pos.get_texts())
    assert all(t.get_text().endswith(" deg") for t in ori.get_texts())
