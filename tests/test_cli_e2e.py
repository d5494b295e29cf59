"""The whole command-line pipeline on a small case, as a user would chain it:
simulate -> diagnose -> calibrate -> train -> evaluate (with report) -> ik."""

from __future__ import annotations

import argparse
import json

import pandas as pd
import pytest
import torch

from hybrid_pk.cli.main import build_parser, main

pytestmark = pytest.mark.slow

UNITS = ("[mm]", "[m]", "[m,", "[rad]", "[rad,", "[deg]", "[kg]")


def _run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _commands(parser: argparse.ArgumentParser, prefix=()) -> list[tuple[str, ...]]:
    """Every leaf sub-command of the CLI (``import ipa`` etc. included)."""
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out += _commands(sub, (*prefix, name)) or [(*prefix, name)]
    return out


@pytest.mark.parametrize("command", _commands(build_parser()), ids=" ".join)
def test_every_command_has_help_with_units(command, capsys):
    with pytest.raises(SystemExit) as exc:
        main([*command, "--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert any(unit in text for unit in UNITS), f"{' '.join(command)} --help states no unit"


def test_simulate_diagnose_calibrate_train_evaluate_ik(tmp_path, capsys):
    sim = tmp_path / "campaign.csv"
    rc, _, err = _run(
        capsys, "simulate", "rx160", "--n", 900, "--effects", "joint_offset:joint_2=1e-3",
        "--noise-mm", 0.02, "--noise-deg", 0.002, "--payload", 10, "--seed", 5, "--out", sim,
    )  # fmt: skip
    assert rc == 0, err

    diag = tmp_path / "diagnosis.json"
    rc, _, err = _run(capsys, "diagnose", sim, "--robot", "rx160", "--json", diag)
    assert rc == 0, err
    causes = json.loads(diag.read_text())["causes"]
    assert [(c["effect"], c["joint"]) for c in causes] == [("joint_offset", "joint_2")]
    assert causes[0]["value"] == pytest.approx(1e-3, rel=0.2)

    model = tmp_path / "model.pt"
    rc, out, err = _run(
        capsys, "calibrate", sim, "--robot", "rx160", "--effects", diag, "--out", model
    )
    assert rc == 0, err
    assert "joint_offset:joint_2" in out

    hybrid = tmp_path / "hybrid.pt"
    logdir = tmp_path / "runs"
    rc, _, err = _run(
        capsys, "train", sim, "--model", model, "--out", hybrid, "--epochs", 3,
        "--position-net", "mlp:16x2", "--orientation-net", "mlp:16x2", "--logdir", logdir,
        "--seed", 1, "--no-progress",
    )  # fmt: skip
    assert rc == 0, err
    assert list(logdir.rglob("events.out.tfevents.*"))

    results = {}
    for name, path in (("model", model), ("hybrid", hybrid)):
        js = tmp_path / f"eval_{name}.json"
        rc, _, err = _run(
            capsys, "evaluate", path, sim, "--json", js, "--report", tmp_path / f"rep_{name}"
        )
        assert rc == 0, err
        results[name] = json.loads(js.read_text())
        networks = {"networks"} if name == "hybrid" else set()  # their use and its rule
        assert set(results[name]) == {"n", "position_mm", "orientation_deg", *networks}
        assert results[name]["n"] == 900
    assert results["hybrid"]["networks"]["used"] is True  # as trained: no re-fit judged them
    # calibrated on these rows: at the noise level (0.02 mm per axis -> ~0.032 mm mean)
    assert results["model"]["position_mm"]["mean"] < 0.05
    assert results["hybrid"]["position_mm"]["mean"] < 0.05
    report = (tmp_path / "rep_hybrid" / "report.md").read_text()
    assert "| position mean [mm] |" in report
    pngs = list((tmp_path / "rep_hybrid").glob("*.png"))
    assert len(pngs) >= 2
    assert all(p.stat().st_size > 10_000 for p in pngs)

    targets = tmp_path / "targets.csv"
    pd.read_csv(sim).head(3).to_csv(targets, index=False)
    solutions = tmp_path / "solutions.csv"
    rc, out, err = _run(capsys, "ik", hybrid, targets, "--out", solutions, "--seeds", 16)
    assert rc == 0, err
    assert "two stages" in out
    frame = pd.read_csv(solutions)
    assert sorted(set(frame["target"])) == [0, 1, 2]
    assert float(frame["position_error_mm"].max()) <= 1e-3
    assert float(frame["orientation_error_deg"].max()) <= 1e-3
    # the measured joints of each target are one of its solutions (up to the noise);
    # the contract returns one of the copies 2 pi apart (all RX160 joints are revolute)
    joints = [f"joint_{i}" for i in range(1, 7)]
    measured = torch.tensor(pd.read_csv(targets)[joints].to_numpy())
    for t in range(3):
        q = torch.tensor(frame[frame["target"] == t][joints].to_numpy())
        d = torch.remainder(q - measured[t] + torch.pi, 2 * torch.pi) - torch.pi
        assert float(d.abs().amax(-1).min()) < 1e-3
