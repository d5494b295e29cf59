"""An effect family added from outside the library works end to end.

The family below, a joint whose zero drifts with temperature (θ_true = θ + k (T − 20 °C),
an encoder or gearbox warming up), is defined here only: no library file names it. It
must be simulated, diagnosed (found among the candidates, named with its value),
calibrated, plotted as evidence, written to and read from a model file, and left out
of pose planning as its class says. Joint and size are drawn per run (``run_rng``).
"""

from __future__ import annotations

import json

import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.diagnosis.selection import candidate_labels
from hybrid_pk.calibration.planning import plan_poses
from hybrid_pk.cli.main import main
from hybrid_pk.effects import EFFECTS, Conditions, Effect, make_effect
from hybrid_pk.effects.vocabulary import vocabulary_table, vocabulary_units
from hybrid_pk.errors import HybridPKError
from hybrid_pk.io.model_file import load_model
from tests.helpers import RUN_SEED, run_rng

pytestmark = pytest.mark.slow

KIND = "temperature_offset"
REFERENCE_C = 20.0  # [°C] the temperature at which the URDF's zero holds


class TemperatureOffset(Effect):
    """θ_true = θ + k (T − 20 °C) [rad/K]: a joint zero that drifts as the joint warms."""

    kind, unit, stage, scale, needs = KIND, "rad/K", "joint", 1e-5, "temperature"
    evidence = "temperature"
    limit = 1e-3  # [rad/K]: 1 mrad per kelvin is far beyond any encoder's or gear's drift
    unplannable = "its information comes from the temperature spread, not from the poses"
    law = "θ_true - θ = k (T - 20 °C): a line in the temperature, slope k"
    equation = description = "θ_true = θ + k (T − 20 °C)"

    def apply_q(self, q: torch.Tensor, cond: Conditions) -> torch.Tensor:
        if cond.temperature is None:
            raise HybridPKError(f"{KIND} needs the temperature of each row [°C]")
        dT = (cond.temperature - REFERENCE_C).to(q.dtype)
        onehot = torch.zeros(q.shape[-1], dtype=q.dtype)
        onehot[self.joint_index] = 1
        return q + (self.value.to(q.dtype) * dT)[..., None] * onehot


@pytest.fixture
def plugin():
    """Registered for the test only, removed after (other tests see the stock vocabulary)."""
    EFFECTS[KIND] = TemperatureOffset
    yield TemperatureOffset
    dict.pop(EFFECTS, KIND)


def test_plugin_family_end_to_end(plugin, tmp_path):
    rng = run_rng("effect_plugin")
    robot = hpk.Robot.from_urdf("ur10")
    robot.requires_grad_(False)
    joint = str(rng.choice(robot.joint_names[1:4]))  # shoulder..wrist 1: a lever to the tool
    k = float(rng.uniform(2e-5, 5e-5))  # [rad/K]: 0.3-0.75 mrad over the 15 K warm-up
    label = f"{KIND}:{joint}"
    where = f"(HYBRID_PK_TEST_SEED={RUN_SEED}, {label} = {k:.3g} rad/K)"

    # simulate: the CLI reads the new kind from the registry like any other
    data_path = tmp_path / "campaign.csv"
    argv = ["simulate", "ur10", "--n", "1500", "--effects", f"{label}={k}", "--noise-mm", "0.01"]
    argv += ["--temperature-range", "20", "35", "--seed", str(RUN_SEED % 1000), "--out"]
    assert main([*argv, str(data_path)]) == 0, where
    truth = json.loads(data_path.with_name("campaign.csv.truth.json").read_text())
    assert KIND in json.dumps(truth), where
    data = hpk.read_table_for(data_path, robot)
    assert label in candidate_labels(robot, data), where

    # diagnose (without cyclic orders, for time) with the evidence report
    pool = [c for c in candidate_labels(robot, data) if ":" in c and "cyclic" not in c]
    diag_json, report = tmp_path / "diag.json", tmp_path / "report"
    argv = ["diagnose", str(data_path), "--robot", "ur10", "--json", str(diag_json)]
    argv += ["--candidates", ",".join(pool), "--report", str(report)]
    assert main(argv) == 0, where
    causes = json.loads(diag_json.read_text())["causes"]
    found = [c for c in causes if c["effect"] == KIND and c["joint"] == joint]
    assert found, f"{where}: diagnosed {[(c['effect'], c.get('joint')) for c in causes]}"
    assert found[0]["value"] == pytest.approx(k, rel=0.05), where
    assert found[0]["unit"] == "rad/K", where
    plots = list(report.glob(f"*{KIND}*.png"))
    assert plots, f"{where}: no evidence plot in {sorted(p.name for p in report.iterdir())}"
    assert "No evidence plot" not in (report / "report.md").read_text(), where

    # calibrate: the model file holds the effect and reads back with its value
    model_path = tmp_path / "model.pt"
    argv = ["calibrate", str(data_path), "--robot", "ur10", "--effects", label]
    assert main([*argv, "--out", str(model_path), "--no-urdf"]) == 0, where
    loaded = load_model(model_path)
    fitted = loaded.model.effect(label)
    assert isinstance(fitted, TemperatureOffset), where
    assert float(fitted.value.detach()) == pytest.approx(k, rel=0.05), where

    # what the class says reaches limits, planning and the vocabulary
    assert make_effect(robot, label).limit == TemperatureOffset.limit
    plan = plan_poses(robot, 20, effects=[label], candidates=200, seed=0)
    assert [e for e, _ in plan.left_out] == [label], where
    assert f"`{KIND}`" in vocabulary_table()
    assert f"{KIND} [rad/K]" in vocabulary_units()
