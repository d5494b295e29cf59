"""The README's main command: a reduced ``hybrid-pk demo`` names what it injected."""

from __future__ import annotations

import json

import pandas as pd
import pytest

from hybrid_pk.cli.main import main

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
    assert "| effect | injected | found | named |" in report
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
