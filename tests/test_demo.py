"""The README's main command: a reduced ``hybrid-pk demo`` names what it injected."""

from __future__ import annotations

import json

import pytest

from hybrid_pk.cli.main import main

pytestmark = pytest.mark.slow


def test_reduced_demo_names_the_hidden_effects(tmp_path, capsys):
    out = tmp_path / "demo"
    code = main(["demo", "--out", str(out), "--n", "1200", "--effects", "random:2", "--seed", "3"])
    assert code == 0
    truth = json.loads((out / "campaign.csv.truth.json").read_text())
    diag = json.loads((out / "diagnosis.json").read_text())
    injected = {(e["effect"], e["joint"]) for e in truth["effects"]}
    named = {(c["effect"], c.get("joint")) for c in diag["causes"]}
    assert injected == named, f"injected {injected}, diagnosis named {named}"
    evaluation = json.loads((out / "evaluation.json").read_text())
    nominal = evaluation["nominal + frames"]["position_mm"]["mean"]
    extended = evaluation["extended (physics)"]["position_mm"]["mean"]
    assert extended < nominal / 5, f"held-out error {nominal:.3f} -> {extended:.3f} mm"
    summary = (out / "summary.md").read_text()
    assert "| effect | injected | found | named |" in summary
    assert (out / "report" / "report.md").is_file()
    assert "NOT FOUND" not in capsys.readouterr().out
