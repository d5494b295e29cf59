"""The evidence of a periodic joint error is phase-folded (issue 27): against
``n θ mod 360°`` the binned medians trace the sinusoid that bins of the joint angle,
wider than its period, average away."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import torch

from hybrid_pk.calibration.fit import fit, initialise_frames
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel, make_effect
from hybrid_pk.evaluation.plots import binned_median
from hybrid_pk.report.evidence import cause_evidence
from hybrid_pk.report.evidence_periodic import gain_text
from hybrid_pk.report.plots import evidence_plot
from tests.helpers import RUN_SEED, run_rng

N_ROWS = 1500
NOISE_M = 1e-5  # a laser tracker's 0.01 mm per coordinate


def _campaign(robot, label: str, value, seed: int) -> MeasuredData:
    truth = ExtendedModel(robot, [make_effect(robot, label, value)])
    g = torch.Generator().manual_seed(seed)
    q = robot.sample_q(N_ROWS, g)
    with torch.no_grad():
        p = truth(q, Conditions())[:, :3, 3]
    return MeasuredData(
        q=q,
        position=p + NOISE_M * torch.randn(N_ROWS, 3, generator=g, dtype=torch.float64),
        quat=None,
        joint_names=robot.joint_names,
        file_index=torch.zeros(N_ROWS, dtype=torch.long),
        rows=torch.arange(1, N_ROWS + 1),
        sources=("simulated",),
    )


def test_cyclic_error_evidence_is_folded_onto_its_period(rx160, tmp_path):
    rng = run_rng("evidence-periodic")
    n = int(rng.integers(12, 37))  # periods of 10-30 deg: shorter than an angle bin
    amplitude = float(rng.uniform(1e-4, 3e-4))  # [rad]: 0.1-0.3 mm at a metre
    phase = float(rng.uniform(0, 2 * math.pi))
    label = f"cyclic_error_{n}:joint_2"
    ab = [amplitude * math.cos(phase), amplitude * math.sin(phase)]
    data = _campaign(rx160, label, ab, seed=RUN_SEED % 1000)
    model = ExtendedModel(rx160, [make_effect(rx160, label)])
    initialise_frames(model, data, Conditions())
    fit(model, data, cond=Conditions(), covariance=False)
    cause = SimpleNamespace(
        effect=f"cyclic_error_{n}", joint="joint_2", value=amplitude, std=1e-6, unit="rad",
        position_gain_mm=0.1, blocked_holdout_gain_mm=0.0123,
    )  # fmt: skip
    ev = cause_evidence(cause, data, model)
    theta = data.q[ev.rows, 1].numpy()
    np.testing.assert_allclose(ev.x, np.degrees(np.mod(n * theta, 2 * math.pi)), atol=1e-9)
    assert "blocked hold-out gain 0.0123 mm" in ev.title
    assert "phase" in ev.x_label
    # The folded medians follow the law (within a quarter of its amplitude: the noise
    # of a median of ~100 rows); against the joint angle they would not.
    a, b = (float(v) for v in model.effect(label).value.detach())
    law = lambda x_deg: 1e3 * (a * np.sin(np.radians(x_deg)) + b * np.cos(np.radians(x_deg)))  # noqa: E731
    worst = np.max(np.abs(ev.median_y - law(ev.median_x)))
    assert worst < 0.25 * 1e3 * amplitude, (n, amplitude, worst, RUN_SEED)
    assert np.ptp(ev.median_y) > 1.2 * 1e3 * amplitude, (n, amplitude, RUN_SEED)
    _, unfolded = binned_median(np.degrees(theta), ev.y)
    assert np.ptp(unfolded) < np.ptp(ev.median_y), (n, RUN_SEED)
    path = evidence_plot(ev, tmp_path / "evidence.png")
    assert path.stat().st_size > 10_000


def test_gain_text_prefers_the_blocked_gain():
    assert gain_text(SimpleNamespace(position_gain_mm=0.5)) == "hold-out gain 0.5 mm"
    both = SimpleNamespace(position_gain_mm=0.5, blocked_holdout_gain_mm=0.002)
    assert gain_text(both) == "blocked hold-out gain 0.002 mm"
    assert gain_text(SimpleNamespace(position_gain_mm=math.nan)) == ""


def test_eccentricity_over_one_turn_stays_against_the_angle(rx160):
    label = "joint_eccentricity:joint_2"
    data = _campaign(rx160, label, [2e-4, 1e-4], seed=3)
    model = ExtendedModel(rx160, [make_effect(rx160, label)])
    initialise_frames(model, data, Conditions())
    fit(model, data, cond=Conditions(), covariance=False)
    cause = SimpleNamespace(
        effect="joint_eccentricity", joint="joint_2", value=2.2e-4, std=1e-6, unit="rad",
        position_gain_mm=0.1,
    )  # fmt: skip
    ev = cause_evidence(cause, data, model)
    np.testing.assert_allclose(ev.x, np.degrees(data.q[ev.rows, 1].numpy()), atol=1e-9)
    assert "hold-out gain 0.1 mm" in ev.title
