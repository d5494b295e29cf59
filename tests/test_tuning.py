"""The diagnosis' and the hybrid's tuning constants are fields of their settings, each
with a reason, and the modules read the tuning of the job under way (not a copy of the
defaults)."""

from __future__ import annotations

import dataclasses
import inspect
import math

import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.calibration import diagnose
from hybrid_pk.calibration.diagnosis.blocked import practical_margin
from hybrid_pk.calibration.settings import DiagnosisSettings
from hybrid_pk.calibration.tuning import ACTIVE as DIAGNOSIS
from hybrid_pk.calibration.tuning import DiagnosisTuning, diagnosis_tuning
from hybrid_pk.hybrid.blocked_trust import beats
from hybrid_pk.hybrid.train_settings import TrainSettings
from hybrid_pk.hybrid.tuning import ACTIVE as HYBRID
from hybrid_pk.hybrid.tuning import HybridTuning
from hybrid_pk.simulate import simulate_campaign


@pytest.mark.parametrize("cls", [DiagnosisTuning, HybridTuning])
def test_every_tuning_constant_states_its_reason(cls):
    """The lines before each field are a comment giving its reason."""
    lines = [line.strip() for line in inspect.getsource(cls).splitlines()]
    for f in dataclasses.fields(cls):
        at = next(i for i, line in enumerate(lines) if line.startswith(f"{f.name}:"))
        reason = []
        while lines[at - 1 - len(reason)].startswith("# "):
            reason.append(lines[at - 1 - len(reason)])
        assert len(" ".join(reason)) > 40, f"{cls.__name__}.{f.name}: no reason above it"


def test_tunings_are_reached_from_the_settings_and_their_yaml():
    settings = DiagnosisSettings.parse({"tuning": {"check_rows": 200, "power": 0.9}})
    assert (settings.tuning.check_rows, settings.tuning.power) == (200, 0.9)
    assert settings.keywords()["tuning"] is settings.tuning
    train = TrainSettings.parse({"tuning": {"freeing_z": 3.0}})
    assert train.tuning == HybridTuning(freeing_z=3.0)
    assert DiagnosisSettings().tuning == DiagnosisTuning()


def test_the_modules_read_the_tuning_of_the_job_under_way():
    assert practical_margin(1.0) == pytest.approx(1 / math.sqrt(2 * 50))
    with DIAGNOSIS.using(DiagnosisTuning(check_rows=200)):
        assert practical_margin(1.0) == pytest.approx(1 / math.sqrt(400))
    assert diagnosis_tuning() == DiagnosisTuning()  # back to the defaults after the job
    reference = torch.ones(100)
    noise = torch.rand(100, generator=torch.Generator().manual_seed(0))
    candidate = reference - 0.1 + 0.02 * noise  # gains 0.09 +- 0.006: about 150 std errors
    assert beats(candidate, reference)
    with HYBRID.using(HybridTuning(freeing_z=1e3)):
        assert not beats(candidate, reference)


def test_diagnose_runs_under_its_tuning_keyword():
    robot = hpk.Robot.from_urdf("rx160")
    data, _ = simulate_campaign(robot, 150, "joint_offset:joint_2=5e-4", noise_mm=0.05, seed=1)
    tuning = DiagnosisTuning(optional_share=0.5, power=0.9)
    result = diagnose(robot, data, candidates=["joint_offset:joint_2"], tuning=tuning)
    assert result.budget["share"] == 0.5
    assert result.detectable["power"] == 0.9
    assert diagnosis_tuning() == DiagnosisTuning()
