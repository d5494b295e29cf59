"""The README's main command: a reduced ``hybrid-pk demo`` names what it injected."""

from __future__ import annotations

import json

import pandas as pd
import pytest
import torch

from hybrid_pk.cli.main import main
from hybrid_pk.geometry import so3_exp
from hybrid_pk.pipelines.demo import STAGES, run_demo

pytestmark = pytest.mark.slow


def test_reduced_demo_names_the_hidden_effects(tmp_path, capsys):
    out = tmp_path / "demo"
    argv = ["demo", "--out", str(out), "--n", "1200", "--effects", "random:2", "--seed", "3"]
    code = main([*argv, "--epochs", "5"])
    assert code == 0
    truth = json.loads((out / "campaign.csv.truth.json").read_text())
    diag = json.loads((out / "diagnosis.json").read_text())
    injected = {(e["effect"], e["joint"]) for e in truth["effects"]}
    named = {(c["effect"], c.get("joint")) for c in diag["causes"]}
    # Every injected effect is named. The unmodelled spring is no effect of the
    # vocabulary: what physics can absorb of it may be named as well (stand-ins), each
    # worth less than any injected effect.
    assert injected <= named, f"injected {injected}, diagnosis named {named}"
    assert len(truth["unmodelled"]) == 1
    gain = {(c["effect"], c.get("joint")): c["position_gain_mm"] for c in diag["causes"]}
    smallest = min(gain[k] for k in injected)
    assert all(gain[k] < smallest for k in named - injected), gain

    evaluation = json.loads((out / "evaluation.json").read_text())
    nominal = evaluation["nominal + frames"]["position_mm"]["mean"]
    extended = evaluation["extended (physics)"]["position_mm"]["mean"]
    hybrid = evaluation["hybrid (physics + networks)"]["position_mm"]["mean"]
    assert extended < nominal / 5, f"held-out error {nominal:.3f} -> {extended:.3f} mm"
    assert hybrid < nominal / 5

    report = (out / "report.md").read_text()
    assert "| effect | unit | injected | found | named |" in report
    assert "| position mean [mm] | " in report
    assert (out / "diagnosis" / "report.md").is_file()
    pngs = list((out / "evaluation").glob("*.png")) + list((out / "diagnosis").rglob("*.png"))
    assert len(pngs) >= 4
    assert all(p.stat().st_size > 10_000 for p in pngs)  # real plots, not empty canvases
    assert list((out / "tensorboard").rglob("events.out.tfevents.*"))

    solutions = pd.read_csv(out / "ik_solutions.csv")
    assert len(set(solutions["target"])) == 4  # every target solved
    assert float(solutions["position_error_mm"].max()) <= 1e-3
    assert "NOT FOUND" not in capsys.readouterr().out


def _relative_error(injected: dict, cause, robot) -> float:
    """Relative error of the found value on the part the data determines: a link-length
    error of the last joint along its axis is the tool frame's (a translation along an
    axis commutes with the rotation about it), so that component is not compared."""
    got = cause.components or cause.value
    got, want = (torch.tensor(x if isinstance(x, list) else [x], dtype=torch.float64)
                 for x in (got, injected["value"]))  # fmt: skip
    if injected["effect"] == "link_length" and injected["joint"] == robot.joint_names[-1]:
        k = robot.joint_names.index(injected["joint"])
        axis = so3_exp(robot.origin_rotvec[k].detach()) @ torch.tensor(robot.spec.axes[k])
        got, want = (x - (x @ axis) * axis for x in (got, want))
    return float((got - want).norm() / want.norm())


@pytest.mark.parametrize("seed", [2, 5, 9])
def test_reduced_demo_over_seeds_names_each_injected_effect(tmp_path, seed):
    """Other seeds draw other effects (link lengths, two backlashes, eccentricity,
    misalignments): each is named, close to its value, and every stage reports."""
    events = []
    result = run_demo(
        tmp_path / "demo", n=1500, epochs=3, seed=seed, progress=lambda *e: events.append(e)
    )
    robot = result.diagnosis.model.robot
    found = {(c.effect, c.joint): c for c in result.diagnosis.causes}
    for e in result.truth["effects"]:
        cause = found.get((e["effect"], e.get("joint")))
        assert cause is not None, f"seed {seed}: {e['effect']}:{e.get('joint')} not named"
        # The right size. On 1,125 calibration rows (n = 1500) an effect on the joint of the
        # unmodelled spring shares its signature with the spring's stand-ins (seed 2:
        # gear_ratio:joint_2 15 % low); bench/demo.py checks 5 % on the full demos.
        assert _relative_error(e, cause, robot) < 0.25, (seed, e, cause.value)
    stages = [stage for stage, step in events if step is None]
    assert stages == [text for _, text in STAGES]
    steps = {stage: [s for st, s in events if st == stage and s] for stage in stages}
    assert any("scoring" in s for s in steps[STAGES[1][1]])  # the diagnosis's inner steps
    assert any(s.startswith("epoch 3/3") for s in steps[STAGES[3][1]])
    assert set(result.stage_seconds) == {name for name, _ in STAGES}
    assert "Run time" in (result.report.read_text().splitlines()[2])
