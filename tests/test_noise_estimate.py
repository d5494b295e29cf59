"""The model-free measurement noise behind the diagnosis' practical margin
(``calibration/diagnosis/noise.py``): close pairs of poses, per file, pooled.

Campaigns drawn per run (``tests.helpers.run_rng``). Tolerance: 50 pairs give sigma to
8 % (one standard deviation, Monte Carlo of the median of chi^2_3 draws), so 30 % is
3.7 standard deviations.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.diagnosis.blocked import practical_margin
from hybrid_pk.calibration.diagnosis.noise import NOISE_PAIRS, measurement_noise
from hybrid_pk.data import MeasuredData
from hybrid_pk.effects import conditions_from_data, make_effect
from hybrid_pk.simulate import simulate_campaign
from tests.helpers import RUN_SEED, run_rng, smooth_field

TOLERANCE = 0.30


@pytest.fixture(scope="module")
def ur10() -> hpk.Robot:
    robot = hpk.Robot.from_urdf("ur10")
    robot.requires_grad_(False)
    return robot


def _campaign(robot, rng, noise_mm: float, pairs: str, field_mm: float = 0.0) -> MeasuredData:
    """Random poses with some measured twice (``repeats``: the same joint values;
    ``near``: within 1 mrad per joint), a 1 mrad shoulder offset the nominal model does
    not know and, with ``field_mm``, an unmodelled smooth error field of that RMS."""
    g = torch.Generator().manual_seed(int(rng.integers(1 << 30)))
    n, m = int(rng.integers(300, 700)), int(rng.integers(NOISE_PAIRS + 10, 2 * NOISE_PAIRS))
    q = robot.sample_q(n, g)
    twin = q[torch.randperm(n, generator=g)[:m]]
    if pairs == "near":
        twin = twin + 1e-3 * (2 * torch.rand(twin.shape, generator=g, dtype=q.dtype) - 1)
    offset = make_effect(robot, "joint_offset:shoulder_lift_joint", 1e-3)
    data, _ = simulate_campaign(
        robot, None, [offset], poses=torch.cat([q, twin]), noise_mm=noise_mm,
        noise_deg=noise_mm / 10, known_frames=True, seed=int(rng.integers(1 << 30)),
    )  # fmt: skip
    if field_mm:
        moved = data.position + smooth_field(data.q, field_mm, rng)
        data = dataclasses.replace(data, position=moved)
    return data


def _estimate(robot, data):
    return measurement_noise(hpk.ExtendedModel(robot), data, conditions_from_data(data))


@pytest.mark.parametrize("pairs", ["repeats", "near"])
def test_close_pairs_recover_the_noise(ur10, pairs):
    """Known noise, a geometric error of ~1 mm the nominal model leaves in: the estimate
    is the noise within the tolerance, from the closest pairs (repeats first)."""
    rng = run_rng(f"noise-{pairs}")
    noise = float(rng.uniform(0.005, 0.05))
    est = _estimate(ur10, _campaign(ur10, rng, noise, pairs))
    where = f"seed {RUN_SEED}, {pairs}, noise {noise:.4f} mm: {est.files}"
    assert abs(est.sigma_mm / noise - 1) <= TOLERANCE, where
    (f,) = est.files
    assert f["pairs"] == NOISE_PAIRS, where
    assert f["repeats"] == (NOISE_PAIRS if pairs == "repeats" else 0), where


def test_an_unmodelled_smooth_field_stays_out_of_the_estimate(ur10):
    """A smooth error field ten to forty times the noise (that the fit's sigma holds):
    the estimate stays at the noise, not at the field."""
    rng = run_rng("noise-field")
    noise = float(rng.uniform(0.005, 0.02))
    field = float(rng.uniform(10, 40)) * noise * 3**0.5  # RMS of the 3-D displacement
    data = _campaign(ur10, rng, noise, "near", field)
    est = _estimate(ur10, data)
    where = f"seed {RUN_SEED}, noise {noise:.4f} mm, field {field:.3f} mm: {est.files}"
    assert abs(est.sigma_mm / noise - 1) <= TOLERANCE, where
    # the fit's sigma (per coordinate, of a model without the field) would be ~ field/sqrt 3
    assert practical_margin(field / 3**0.5, noise_mm=est.sigma_mm) == pytest.approx(
        est.sigma_mm / 10
    )


def test_files_are_estimated_apart_and_pooled(ur10):
    """Two set-ups with different noise: each file's own estimate, pooled as the
    pair-weighted mean variance; pairs never cross files."""
    rng = run_rng("noise-files")
    noises = sorted(float(x) for x in rng.uniform(0.005, 0.05, 2))
    parts = []
    for i, noise in enumerate(noises):
        part = _campaign(ur10, rng, noise, "repeats")
        parts.append(dataclasses.replace(part, sources=[f"setup_{i}.csv"]))
    est = _estimate(ur10, MeasuredData.concat(parts))
    where = f"seed {RUN_SEED}, noises {noises}: {est.files}"
    assert [f["file"] for f in est.files] == ["setup_0.csv", "setup_1.csv"], where
    for f, noise in zip(est.files, noises, strict=True):
        assert abs(f["sigma_mm"] / noise - 1) <= TOLERANCE, where
    pooled = (sum(f["sigma_mm"] ** 2 for f in est.files) / 2) ** 0.5
    assert est.sigma_mm == pytest.approx(pooled), where


def test_copied_rows_are_not_measurements(ur10):
    """Rows copied verbatim (identical joints and measurement) are no second draw of the
    noise: the estimate ignores them and uses the real repeats."""
    rng = run_rng("noise-copies")
    noise = float(rng.uniform(0.005, 0.05))
    data = _campaign(ur10, rng, noise, "repeats")
    rows = torch.cat([torch.arange(data.n), torch.arange(NOISE_PAIRS * 2)])
    est = _estimate(ur10, data.subset(rows))
    where = f"seed {RUN_SEED}, noise {noise:.4f} mm: {est.files}"
    assert abs(est.sigma_mm / noise - 1) <= TOLERANCE, where


def test_the_margin_takes_the_smaller_of_noise_and_fit_sigma():
    """The model-free noise can only lower the margin (the fit's sigma caps it), and
    ``--min-gain-mm`` overrides both."""
    assert practical_margin(0.2, noise_mm=0.02) == pytest.approx(0.002)
    assert practical_margin(0.02, noise_mm=0.2) == pytest.approx(0.002)
    assert practical_margin(0.2, None, None) == pytest.approx(0.02)
    assert practical_margin(0.2, 0.5, 0.02) == 0.5


def test_the_margin_line_says_how_the_noise_was_found():
    """The CLI/report line of the margin names the noise, its source per file and the
    fit's sigma that caps it; ``--min-gain-mm`` is named when it set the margin."""
    from hybrid_pk.calibration.diagnosis.carryover import margin_text

    files = [{"file": "/data/a.csv", "sigma_mm": 0.025, "pairs": 50}]
    carry = {
        "min_gain_mm": 0.0025, "rule": "noise ...", "noise_position_mm": 0.025,
        "fit_sigma_mm": 0.22, "noise": {"sigma_mm": 0.025, "files": files}, "blocks": {},
        "check_rows": 50,
    }  # fmt: skip
    text = margin_text(carry)
    assert text.startswith("practical margin 0.0025 mm = noise 0.025 mm / sqrt(2 x 50)")
    assert "a.csv 0.025 mm (50 pairs)" in text
    assert "fit's sigma 0.22 mm" in text
    assert "(--min-gain-mm)" in margin_text({**carry, "rule": "--min-gain-mm"})
    assert margin_text({**carry, "blocks": None}) is None  # no blocks: no margin used
    # three digits, as every other line that names the margin (the steps, settle)
    assert margin_text({**carry, "min_gain_mm": 0.001922124}).startswith(
        "practical margin 0.00192 mm"
    )
    # the check's size is the tuning's, not a fixed 50
    assert "/ sqrt(2 x 200)" in margin_text({**carry, "check_rows": 200})
    # the entry rule is named where the search used it (a JSON of today's diagnose)
    assert "standard error over the blocks" not in text
    assert margin_text({**carry, "entry": "..."}).endswith(
        "; to enter, a gain also above its standard error over the blocks"
    )
