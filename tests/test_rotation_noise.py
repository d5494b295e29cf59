"""Orientation measured without noise beside noisy positions (a simulation with
``--noise-deg 0``, orientation columns copied from a model): the fit's rotation noise
stops at the position noise over ``LEVER_M`` instead of falling to rounding, so the
orientation rows do not outweigh every position row (outliers out of plain position
noise, blocked gains of 1e4 mm)."""

from __future__ import annotations

import math

import pytest
import torch

from hybrid_pk import load_model
from hybrid_pk.calibration.fit import fit, initialise_frames, model_errors
from hybrid_pk.calibration.robust import LEVER_M, list_outliers, rotation_noise
from hybrid_pk.cli.main import main
from hybrid_pk.effects import ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.simulate import simulate_campaign
from tests.dh_reader import erd_root
from tests.helpers import RUN_SEED, run_rng

pytestmark = pytest.mark.usefixtures("one_thread")


def test_the_floor_is_the_position_noise_over_the_lever():
    assert rotation_noise(1e-12, 0.02) == pytest.approx(0.02e-3 / LEVER_M)
    assert rotation_noise(1e-3, 0.02) == 1e-3  # a measured orientation noise stays
    assert rotation_noise(0.0, 0.0) == 1e-9  # nothing measured at all: rounding's floor


def test_exact_orientation_beside_noisy_positions_lists_no_outliers(ur10):
    """A random offset on a random joint and a shoulder compliance, positions with
    0.02 mm of noise, orientation exact: every row is plain noise, and the calibrated fit
    lists none beyond 4 sigma (with the rotation noise at rounding it listed ~40 of 600:
    the orientation rows' compromise with the positions, against that noise)."""
    rng = run_rng("rotation_noise")
    joint = str(rng.choice(ur10.joint_names[2:5]))
    value = float(rng.choice([-1, 1]) * rng.uniform(2e-4, 8e-4))
    soft = float(rng.uniform(3e-6, 8e-6))  # 0.3-0.8 mrad of sag at ~100 Nm
    labels = [f"joint_offset:{joint}", "joint_compliance:shoulder_lift_joint"]
    data, _ = simulate_campaign(
        ur10, 600, f"{labels[0]}={value:.4g}; {labels[1]}={soft:.3g}", noise_mm=0.02,
        noise_deg=0.0, known_frames=True, temperature_range=None, seed=RUN_SEED,
    )  # fmt: skip
    model = ExtendedModel(ur10, [make_effect(ur10, label) for label in labels])
    cond = conditions_from_data(data)
    initialise_frames(model, data, cond)
    res = fit(model, data, cond=cond)
    where = f"seed {RUN_SEED}: {labels[0]} = {value:.4g} rad, compliance {soft:.3g} rad/Nm"
    assert res.sigma_rot_rad == pytest.approx(1e-3 * res.sigma_pos_mm / LEVER_M), where
    assert float(model.effect(f"joint_offset:{joint}").value.detach()) == pytest.approx(
        value, rel=0.02
    )
    pos, rot = model_errors(model, data, cond)
    outliers = list_outliers(data, pos, rot, res.sigma_pos_mm, res.sigma_rot_rad)
    # 4 sigma of 6-D Gaussian rows: a chance of ~1e-4 per row
    assert len(outliers) <= 1, (where, outliers[:3])
    assert math.isclose(res.sigma_pos_mm, 0.02, rel_tol=0.15), where
    assert torch.isfinite(rot).all()


def test_a_simulation_without_orientation_noise_calibrates_without_outliers(tmp_path, capsys):
    """``simulate --noise-mm 0.02`` (orientation noise 0, its default) on a UR5
    (example-robot-data) with an elbow offset and a shoulder compliance, then
    ``calibrate`` with its defaults: no row is listed as an outlier (with the rotation
    noise at rounding, 38 of 600 plain rows were) and the effects come out right."""
    urdf = erd_root() / "ur_description/urdf/ur5_robot.urdf"
    sim, model = tmp_path / "ur5.csv", tmp_path / "ur5.pt"
    effects = "joint_offset:elbow_joint=5e-4; joint_compliance:shoulder_lift_joint=5e-5"
    common = ("--end-link", "tool0", "--no-progress")
    argv = ["simulate", urdf, *common, "--n", 600, "--effects", effects, "--noise-mm", 0.02,
            "--seed", 3, "--out", sim]  # fmt: skip
    assert main([str(a) for a in argv]) == 0
    argv = ["calibrate", sim, "--robot", urdf, *common, "--out", model, "--no-urdf"]
    assert main([str(a) for a in argv]) == 0
    out = capsys.readouterr().out
    assert "outlier" not in out, out
    fitted = {e.label: float(e.value.detach()) for e in load_model(model).model.effects}
    assert fitted["joint_compliance:shoulder_lift_joint"] == pytest.approx(5e-5, rel=0.01), out
    assert fitted["joint_offset:elbow_joint"] == pytest.approx(5e-4, rel=0.01), out
