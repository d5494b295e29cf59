"""Figures a reader can read: legends clear of the data they name, units and row counts
in the labels and titles (layout checked on the drawn figure, never on pixels)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("matplotlib")

import hybrid_pk.evaluation.plots as eval_plots


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
    eval_plots.error_histograms(  # few rows: a bin holds 1-3 of them
        (rng.rayleigh(1.0, 30), None), (rng.rayleigh(0.9, 30), None), ("a", "b"), tmp_path / "s.png"
    )
    ticks = figures[-1].axes[0].get_yticks()
    assert np.array_equal(ticks, np.round(ticks))  # sample counts (was 0.5, 1.5, ...)


def _campaign(n: int = 200):
    """Measured rows of the RX160 (exact poses, 0.01 mm noise) and two models' poses."""
    import torch

    from hybrid_pk import Robot
    from hybrid_pk.data.measured import MeasuredData
    from hybrid_pk.geometry import matrix_to_quat

    robot = Robot.from_urdf("rx160")
    g = torch.Generator().manual_seed(0)
    q = robot.sample_q(n, g)
    T = robot.fk(q)
    data = MeasuredData(
        q=q,
        position=T[:, :3, 3] + 1e-5 * torch.randn(n, 3, generator=g, dtype=T.dtype),
        quat=matrix_to_quat(T[:, :3, :3]),
        joint_names=robot.joint_names,
        file_index=torch.zeros(n, dtype=torch.long),
        rows=torch.arange(1, n + 1),
        sources=("simulated",),
    )
    off = T.clone()
    off[:, :3, 3] += 1e-3  # a model 1.7 mm off
    return data, {"nominal + frames": off, "extended (physics)": T}


def test_evaluation_figures_titled_with_rows_and_legends_clear(monkeypatch, tmp_path):
    import hybrid_pk.report.evaluation_report as report

    data, predictions = _campaign()
    along = keep_figures(monkeypatch, report)
    hists = keep_figures(monkeypatch, eval_plots)
    report.write_evaluation_report(tmp_path, data, predictions)
    (fig,) = along
    assert f"({data.n} rows)" in fig.get_suptitle()
    assert fig.legends
    assert not any(ax.get_legend() for ax in fig.axes)
    fig.canvas.draw()
    box = fig.legends[0].get_window_extent()
    assert not any(box.overlaps(ax.get_window_extent()) for ax in fig.axes if ax.get_visible())
    (hist,) = hists
    assert f"errors on {data.n} rows" in hist.get_suptitle()
    # 1.7 mm against 0.016 mm: a log axis, else the better model lies flat on the floor
    assert all(ax.get_yscale() == "log" for ax in fig.axes if ax.get_visible())
    styles = [line.get_linestyle() for line in fig.axes[0].get_lines()]
    assert len(set(styles)) == len(predictions)  # an equal pair of curves stays in view


def test_evaluation_along_joints_in_degrees_like_the_diagnosis(monkeypatch, tmp_path):
    """With the robot's joint types the along-joints axes read degrees (the diagnosis'
    evidence unit) and span the joints' ranges in degrees; without them, rad."""
    import hybrid_pk.report.evaluation_report as report

    data, predictions = _campaign()
    along = keep_figures(monkeypatch, report)
    report.write_evaluation_report(tmp_path / "a", data, predictions, joint_types=["revolute"] * 6)
    report.write_evaluation_report(tmp_path / "b", data, predictions)
    deg, rad = along
    assert all(ax.get_xlabel().endswith("[deg]") for ax in deg.axes if ax.get_visible())
    assert all(ax.get_xlabel().endswith("[rad]") for ax in rad.axes if ax.get_visible())
    span = float(data.q[:, 0].max() - data.q[:, 0].min())
    x = deg.axes[0].get_lines()[0].get_xdata()
    assert max(x) - min(x) > 0.8 * span * 180 / np.pi  # bin centres: 19 of 20 bin widths


def test_outlier_plot_titled_threshold_in_view_legend_clear(monkeypatch, tmp_path):
    import hybrid_pk.report.limits as limits
    from hybrid_pk import Robot
    from hybrid_pk.effects import ExtendedModel

    data, _ = _campaign()

    class Diagnosis:  # what outlier_plot reads of a diagnosis
        def __init__(self):
            noise = {"position_mm": 0.01, "orientation_rad": 1e-5}
            self.identifiability = {"noise_estimate": noise}
            self.model = ExtendedModel(Robot.from_urdf("rx160"), []).double()

    figures = keep_figures(monkeypatch, limits)
    limits.outlier_plot(Diagnosis(), data, tmp_path)
    (fig,) = figures
    (ax,) = fig.axes
    assert_legends_clear(fig)
    assert f"all {data.n} rows" in ax.get_title()
    threshold = [ln.get_ydata()[0] for ln in ax.get_lines() if ln.get_linestyle() == "--"]
    assert threshold
    assert ax.get_ylim()[1] > 1.1 * threshold[0]
    assert "threshold" in " ".join(t.get_text() for t in ax.get_legend().get_texts())
    low, high = ax.get_ylim()
    labelled = [
        t for t in ax.get_yticklabels() if t.get_text() and low <= t.get_position()[1] <= high
    ]
    assert len(labelled) >= 3  # a log axis read by its numbers (was one label, '1.0')


def _periodic_evidence(amplitude_mrad: float):
    """Phase-folded evidence of a sinusoid of ``amplitude_mrad`` in 0.03 mrad noise."""
    from hybrid_pk.evaluation.plots import binned_median
    from hybrid_pk.report.evidence import Evidence

    rng = np.random.default_rng(1)
    x = rng.uniform(0.0, 360.0, 1500)
    y = amplitude_mrad * np.sin(np.radians(x)) + rng.normal(0.0, 0.03, x.size)
    curve_x = np.linspace(0.0, 360.0, 181)
    mx, my = binned_median(x, y)
    return Evidence(
        label="cyclic_error_17:joint_2",
        title="cyclic_error_17:joint_2; blocked hold-out gain 0.0004 mm",
        x=x,
        y=y,
        weight=np.ones_like(x),
        rows=np.arange(x.size),
        x_label="phase 17·θ mod 360° of joint_2 [deg]",
        y_label="equivalent angle error of joint_2 [mrad]",
        curve_x=curve_x,
        curve_y=amplitude_mrad * np.sin(np.radians(curve_x)),
        median_x=mx,
        median_y=my,
        value=amplitude_mrad * 1e-3,
        points_value=amplitude_mrad * 1e-3,
        unit="rad",
        law="a sinusoid",
    )


def test_a_law_lost_in_the_scatter_gets_a_zoom_in_finer_units(monkeypatch, tmp_path):
    import hybrid_pk.report.plots as plots

    figures = keep_figures(monkeypatch, plots)
    plots.evidence_plot(_periodic_evidence(0.0035), tmp_path / "small.png")  # 3.5 µrad
    plots.evidence_plot(_periodic_evidence(0.2), tmp_path / "large.png")
    small, large = figures
    points, zoom = small.axes
    assert zoom.get_ylabel().endswith("[µrad]")
    # the zoom spans the law and its medians: the 3.5 µrad curve fills a good part of it
    bottom, top = zoom.get_ylim()
    assert 2 * 3.5 > 0.2 * (top - bottom)
    assert len(large.axes) == 1  # a law that fills its axes needs none
    for fig in figures:
        assert len(fig.legends) == 1
        fig.canvas.draw()
        box = fig.legends[0].get_window_extent()
        assert not any(box.overlaps(ax.get_window_extent()) for ax in fig.axes)
    assert "blocked hold-out gain" in points.get_title()


def test_identifiability_counts_ambiguities_as_the_console_does():
    from types import SimpleNamespace

    from hybrid_pk.cli.diagnose_cmd import ambiguous_lines
    from hybrid_pk.report.diagnosis_report import _identifiability

    frame = {"effects": ["joint_offset:joint_1", "base_frame"], "why": "exactly as base_frame"}
    pairs = [
        {"effects": [f"cyclic_error_{a}:joint_2", f"cyclic_error_{b}:joint_2"], "why": "close",
         "order_not_resolved": "joint_2"}
        for a, b in [(3, 4), (3, 17), (17, 18)]
    ]  # fmt: skip
    diagnosis = SimpleNamespace(
        identifiability={"noise_estimate": {"position_mm": 0.01}},
        ambiguous=[frame, *pairs],
    )
    text = "\n".join(_identifiability(diagnosis))
    assert "ambiguous (1):" in ambiguous_lines(diagnosis.ambiguous)
    assert "1 ambiguous group(s)" in text  # was 4: the order pairs counted as groups
    groups = text[text.index("### Ambiguous groups") : text.index("Periodic errors")]
    assert "base_frame" in groups
    assert "cyclic_error" not in groups
    assert "- joint_2: 3, 4, 17, 18 per turn" in text
    assert "| cyclic_error_17:joint_2, cyclic_error_18:joint_2 | close |" in text


def test_a_long_evidence_title_and_law_stay_on_the_page(monkeypatch, tmp_path):
    import dataclasses

    import hybrid_pk.report.plots as plots

    figures = keep_figures(monkeypatch, plots)
    title = (
        "link_length:elbow_joint = (-0.000258, 0.000182, 0.0012) ± (1.1e-05, 2.4e-05, "
        "1.8e-05) m; blocked hold-out gain 0.261 mm"
    )
    law = "residual = displacement of the effect, both without what a change of the base " * 2
    ev = dataclasses.replace(_periodic_evidence(0.2), title=title, law=law)
    plots.evidence_plot(ev, tmp_path / "long.png")
    (fig,) = figures
    fig.canvas.draw()
    page = fig.bbox
    (ax,) = fig.axes
    for artist in (ax.title, fig.legends[0]):
        box = artist.get_window_extent()
        assert page.x0 <= box.x0, artist
        assert box.x1 <= page.x1, artist
    assert ax.title.get_text().splitlines()[-1] == "blocked hold-out gain 0.261 mm"
    assert ax.get_position().width > 0.7  # the axes keep the page's width


def test_residual_scan_says_what_its_marks_are(monkeypatch, tmp_path):
    import hybrid_pk.report.plots as plots

    figures = keep_figures(monkeypatch, plots)
    rng = np.random.default_rng(2)
    plots.residual_scan(
        {f"joint_{k} [deg]": rng.uniform(-90, 90, 300) for k in range(1, 6)},
        {"position error [mm]": rng.rayleigh(0.05, 300)},
        tmp_path / "scan.png",
        reference={"position error [mm]": 0.06},
        title="extended model, 300 hold-out rows: no structure found",
    )
    (fig,) = figures
    (legend,) = fig.legends
    texts = [t.get_text() for t in legend.get_texts()]
    assert texts == ["rows", "binned median", "mean error the noise estimate alone gives"]
    fig.canvas.draw()
    box = legend.get_window_extent()
    assert not any(box.overlaps(ax.get_window_extent()) for ax in fig.axes if ax.get_visible())


def test_demo_ik_table_gives_joint_units():
    import pandas as pd

    from hybrid_pk.pipelines.demo_report import _ik_section

    frame = pd.DataFrame(
        [{"target": 0, "solution": 0, "lift": 0.5, "joint_1": 1.0,
          "position_error_mm": 1e-9, "orientation_error_deg": 1e-10}]
    )  # fmt: skip
    ik = {"frame": frame, "targets": 1, "solutions": 1, "per_target": [1], "failed": 0,
          "seconds": 0.1}  # fmt: skip
    text = "\n".join(_ik_section(ik, ["lift", "joint_1"], ["prismatic", "revolute"]))
    assert "| target | solution | lift [m] | joint_1 [rad] | position error [mm] |" in text


def test_demo_compares_a_sinusoid_by_its_amplitude():
    from types import SimpleNamespace

    from hybrid_pk.pipelines.demo_report import found_table

    truth = {
        "effects": [{"effect": "cyclic_error_17", "joint": "j2", "value": [3e-5, 4e-5]}],
        "unmodelled": [],
    }
    cause = SimpleNamespace(effect="cyclic_error_17", joint="j2", value=5.01e-5, unit="rad")
    extra = SimpleNamespace(effect="gear_ratio", joint="j3", value=1e-4, unit="1")
    rows = found_table(truth, SimpleNamespace(causes=[cause, extra]))
    assert rows[0][2] == "(3e-05, 4e-05), amplitude 5e-05"  # was the bare (a, b)
    assert rows[1][2:] == ["(not injected)", 1e-4, "false positive"]


def test_the_law_in_the_legend_is_not_broken_inside_a_formula(monkeypatch, tmp_path):
    import dataclasses

    import hybrid_pk.report.plots as plots

    figures = keep_figures(monkeypatch, plots)
    law = (
        "θ_true - θ = a sin 17θ + b cos 17θ: a sinusoid of 17 cycles per turn, amplitude √(a² + b²)"
    )
    ev = dataclasses.replace(_periodic_evidence(0.2), law=law)
    plots.evidence_plot(ev, tmp_path / "law.png")
    texts = [t.get_text() for t in figures[0].legends[0].get_texts()]
    (label,) = [t for t in texts if t.startswith("diagnosed law")]
    assert all(line.count("(") == line.count(")") for line in label.splitlines()), label


def test_a_ratio_is_written_without_its_unit_one():
    from hybrid_pk.report.markdown import value_with_std, with_unit

    assert value_with_std(3.497e-4, 8.8e-7, "1") == "0.0003497 ± 8.8e-07"  # was '… 8.8e-07 1'
    assert value_with_std(2e-6, 1e-8, "rad/Nm") == "2e-06 ± 1e-08 rad/Nm"
    assert with_unit("2.85e-05", "1") == "2.85e-05"
