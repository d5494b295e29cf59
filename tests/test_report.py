"""The diagnosis report: files, real images, markdown that renders, evidence that holds."""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from matplotlib.image import imread

from hybrid_pk import HybridPKError, Robot
from hybrid_pk.calibration.diagnosis.search import diagnose
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel, make_effect
from hybrid_pk.geometry import matrix_to_quat, so3_exp, transform
from hybrid_pk.report import (
    error_histograms,
    markdown_table,
    plot_cause_evidence,
    stats_table,
    write_diagnosis_report,
)

COMPLIANCE = 2e-6  # [rad/Nm] injected on joint_2
N_ROWS = 800
# Few candidates keep the diagnosis fast; the injected one must win among them.
CANDIDATES = ["joint_compliance:joint_2", "joint_compliance:joint_3", "joint_offset:joint_3"]
SEPARATOR = re.compile(r"^\|(\s*:?-{3,}:?\s*\|)+$")


def simulated_compliance(n: int = N_ROWS, seed: int = 0) -> tuple[Robot, MeasuredData]:
    """RX160 with 20 kg payload and a compliant joint 2, seen by a tracker in the room."""
    robot = Robot.from_urdf("rx160")
    g = torch.Generator().manual_seed(seed)
    f64 = {"dtype": torch.double}
    # A tracker 2.7 m away, turned by ~57 deg; a tool 12 cm off the flange.
    base = transform(
        so3_exp(torch.tensor([0.01, -0.02, 1.0], **f64)), torch.tensor([2.5, -1.0, 0.3], **f64)
    )
    tool = transform(
        so3_exp(torch.tensor([0.3, 0.1, 0.2], **f64)), torch.tensor([0.02, 0.03, 0.12], **f64)
    )
    truth = ExtendedModel(
        robot, [make_effect(robot, "joint_compliance:joint_2", COMPLIANCE)], base=base, tool=tool
    )
    q = robot.sample_q(n, g)
    payload = torch.full((n,), 20.0, **f64)
    with torch.no_grad():
        T = truth(q, Conditions(payload=payload))
    position = T[:, :3, 3] + 1e-5 * torch.randn(n, 3, generator=g, **f64)  # 0.01 mm
    noise_rot = so3_exp(math.radians(0.001) * torch.randn(n, 3, generator=g, **f64))
    data = MeasuredData(
        q=q,
        position=position,
        quat=matrix_to_quat(T[:, :3, :3] @ noise_rot),
        joint_names=robot.joint_names,
        file_index=torch.zeros(n, dtype=torch.long),
        rows=torch.arange(1, n + 1),
        sources=("simulated",),
        payload=payload,
    )
    return robot, data


@pytest.fixture(scope="module")
def diagnosed():
    robot, data = simulated_compliance()
    return robot, data, diagnose(robot, data, candidates=CANDIDATES, seed=0)


@pytest.fixture(scope="module")
def report(diagnosed, tmp_path_factory) -> Path:
    robot, data, diagnosis = diagnosed
    return write_diagnosis_report(diagnosis, data, robot, tmp_path_factory.mktemp("report"))


def _links(text: str) -> list[str]:
    return re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)


def test_diagnosis_names_the_injected_compliance(diagnosed):
    _, _, diagnosis = diagnosed
    assert [(c.effect, c.joint) for c in diagnosis.causes] == [("joint_compliance", "joint_2")]


def test_report_pngs_are_real_images(report):
    pngs = sorted(report.parent.glob("*.png"))
    names = {p.name for p in pngs}
    assert {"error_histograms.png", "residual_left.png"} <= names
    assert any(n.startswith("evidence_01_joint_compliance_joint_2") for n in names), names
    for png in pngs:
        assert png.stat().st_size > 10_000, f"{png.name} is only {png.stat().st_size} bytes"
        pixels = imread(png)
        assert pixels.ndim == 3, png.name
        assert min(pixels.shape[:2]) > 200, png.name
        assert float(pixels[..., :3].std()) > 0.01, f"{png.name} is a single color"


def test_report_markdown_has_tables_and_links_every_png(report):
    text = report.read_text(encoding="utf-8")
    lines = text.splitlines()
    header = "| error | nominal | extended | change |"
    assert header in lines
    assert SEPARATOR.match(lines[lines.index(header) + 1])
    # Every table header is followed by its separator row (pipe tables render).
    for i, line in enumerate(lines[:-1]):
        if line.startswith("|") and (i == 0 or not lines[i - 1].startswith("|")):
            assert SEPARATOR.match(lines[i + 1]), f"table without separator: {line}"
            cells = len(line.replace("\\|", "").split("|"))
            assert len(lines[i + 1].split("|")) == cells, f"separator of another width: {line}"
    for row in ("position RMS [mm]", "position p95 [mm]", "orientation max [deg]"):
        assert f"| {row} |" in text
    assert "| joint_compliance | joint_2 |" in text
    assert "condition number" in text
    assert "observability index" in text
    links = _links(text)
    for link in links:
        assert not Path(link).is_absolute()
        assert (report.parent / link).is_file(), f"broken image link {link}"
    assert {Path(link).name for link in links} == {p.name for p in report.parent.glob("*.png")}


def test_compliance_evidence_slope_matches_injected_value(diagnosed, tmp_path):
    robot, data, diagnosis = diagnosed
    cause = diagnosis.causes[0]
    ev = plot_cause_evidence(diagnosis, data, cause, tmp_path / "evidence.png")
    assert (tmp_path / "evidence.png").stat().st_size > 10_000
    assert ev.x.shape == ev.y.shape == ev.weight.shape
    assert ev.x.size > 0.8 * data.n
    # x: gravity torque on joint 2 [Nm], y: equivalent angle error [mrad].
    tau = -robot.gravity_torques(data.q[ev.rows], payload=20.0)[:, 1].numpy()
    np.testing.assert_allclose(ev.x, tau, rtol=1e-9, atol=1e-9)
    slope_mrad_per_nm, _ = np.polyfit(ev.x, ev.y, 1, w=np.sqrt(ev.weight))
    assert slope_mrad_per_nm * 1e-3 == pytest.approx(COMPLIANCE, rel=0.1)
    assert ev.points_value == pytest.approx(COMPLIANCE, rel=0.1)
    # The drawn law is the diagnosed value, through the origin.
    law_slope = np.polyfit(ev.curve_x, ev.curve_y, 1)
    assert law_slope[0] * 1e-3 == pytest.approx(cause.value, rel=1e-9)
    assert abs(law_slope[1]) < 1e-9
    # Medians follow the law: within 5 % of the law's span.
    span = np.ptp(ev.curve_y)
    law_at_medians = 1e3 * cause.value * ev.median_x
    assert np.max(np.abs(ev.median_y - law_at_medians)) < 0.05 * span
    # The nominal model's own frames absorb part of the effect, never more than all of it.
    assert 0.0 < ev.nominal_points_value < 1.05 * COMPLIANCE


def test_report_without_causes_warns_on_large_condition_number(diagnosed, tmp_path):
    robot, data, diagnosis = diagnosed
    ident = {**diagnosis.identifiability, "condition_number": 3.0e6}
    bare = dataclasses.replace(diagnosis, causes=[], identifiability=ident)
    text = write_diagnosis_report(bare, data, robot, tmp_path).read_text(encoding="utf-8")
    assert "None: no effect beyond measurement noise" in text
    assert re.search(r"\*\*Warning:\*\* condition number 3e\+06 > 10000", text)
    assert not list(tmp_path.glob("evidence_*.png"))


def test_report_rejects_other_data(diagnosed, tmp_path):
    robot, data, diagnosis = diagnosed
    with pytest.raises(HybridPKError, match="800 rows, the data has 10"):
        write_diagnosis_report(diagnosis, data.subset(slice(0, 10)), robot, tmp_path)


def test_markdown_table_renders_and_checks_row_length():
    table = markdown_table([["a|b", 1.23456789], ["c", None]], ["name", "value"])
    lines = table.splitlines()
    assert lines[0] == "| name | value |"
    assert lines[1] == "|:---|---:|"
    assert lines[2] == "| a\\|b | 1.235 |"
    assert lines[3] == "| c | - |"
    with pytest.raises(ValueError, match="row 0 has 1 cells, expected 2"):
        markdown_table([["only one"]], ["name", "value"])
    with pytest.raises(ValueError, match="1 alignments, expected 2"):
        markdown_table([["a", 1.0]], ["name", "value"], ["l"])


def test_stats_table_position_only_and_change():
    stats = {"mean": 2.0, "rms": 2.5, "p95": 3.0, "max": 4.0}
    half = {k: v / 2 for k, v in stats.items()}
    table = stats_table(
        {
            "before": {"position_mm": stats, "orientation_deg": None},
            "after": {"position_mm": half, "orientation_deg": None},
        }
    )
    assert "| position mean [mm] | 2 | 1 | -50.0 % |" in table
    assert "orientation" not in table
    assert len(table.splitlines()) == 2 + 4


def test_error_histograms_position_only(tmp_path):
    rng = np.random.default_rng(0)
    path = error_histograms(
        (rng.rayleigh(1.0, 300), None),
        (rng.rayleigh(0.02, 300), None),
        ("nominal", "extended"),
        tmp_path / "h.png",
    )
    pixels = imread(path)
    assert path.stat().st_size > 10_000
    assert float(pixels[..., :3].std()) > 0.01
    assert pixels.shape[1] / pixels.shape[0] < 2.0  # one panel (two would be 11 x 4 in)


def test_report_counts_directions_not_determined_at_all(diagnosed, tmp_path):
    """An exact trade-off is a count and a warning, not a round-off singular value."""
    robot, data, diagnosis = diagnosed
    ident = {**diagnosis.identifiability, "unidentifiable_directions": 1}
    bare = dataclasses.replace(diagnosis, identifiability=ident)
    text = write_diagnosis_report(bare, data, robot, tmp_path).read_text(encoding="utf-8")
    assert re.search(r"\*\*Warning:\*\* 1 direction\(s\) of the fitted parameters", text)
    assert "| directions not determined at all | 1 |" in text
