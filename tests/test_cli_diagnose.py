"""``hybrid-pk diagnose``: contract JSON, summary, report, one-line errors, help with units."""

from __future__ import annotations

import json

import pytest
import torch

from hybrid_pk import Robot
from hybrid_pk.cli.main import main
from hybrid_pk.data import write_table
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel, make_effect
from hybrid_pk.geometry import matrix_to_quat, so3_exp, transform

STATS = {"mean", "rms", "p95", "max"}
CAUSE_KEYS = {
    "effect",
    "joint",
    "value",
    "unit",
    "std",
    "position_gain_mm",
    "orientation_gain_deg",
    "evidence",
}


@pytest.fixture(scope="module")
def table(tmp_path_factory):
    """200 rows of an RX160 with a compliant joint 2 and 20 kg payload, as a CSV."""
    robot = Robot.from_urdf("rx160")
    g = torch.Generator().manual_seed(3)
    n = 200
    base = transform(so3_exp(torch.tensor([0.0, 0.0, 2.0])), torch.tensor([3.0, 0.5, -0.2]))
    model = ExtendedModel(
        robot,
        [make_effect(robot, "joint_compliance:joint_2", 2e-6)],
        base=base.double(),
        tool=transform(torch.eye(3), torch.tensor([0.0, 0.05, 0.1])).double(),
    )
    q = robot.sample_q(n, g)
    payload = torch.full((n,), 20.0, dtype=torch.float64)
    with torch.no_grad():
        T = model(q, Conditions(payload=payload))
    data = MeasuredData(
        q=q,
        position=T[:, :3, 3] + 1e-5 * torch.randn(n, 3, generator=g, dtype=torch.float64),
        quat=matrix_to_quat(T[:, :3, :3]),
        joint_names=robot.joint_names,
        file_index=torch.zeros(n, dtype=torch.long),
        rows=torch.arange(1, n + 1),
        sources=("sim",),
        payload=payload,
    )
    path = tmp_path_factory.mktemp("data") / "campaign.csv"
    write_table(path, data)
    return path


def test_diagnose_writes_contract_json_summary_and_report(table, tmp_path, capsys):
    out, report = tmp_path / "sub" / "diag.json", tmp_path / "report"
    argv = ["diagnose", str(table), "--robot", "rx160", "--json", str(out)]
    argv += ["--holdout", "0.25", "--report", str(report), "--seed", "1"]
    argv += ["--candidates", "joint_compliance:joint_2,joint_offset:joint_3"]
    assert main(argv) == 0
    captured = capsys.readouterr()
    result = json.loads(out.read_text())
    for key in ("robot", "n_samples", "n_holdout", "nominal", "causes", "ambiguous"):
        assert key in result
    assert {"extended", "unexplained"} <= set(result)
    assert result["robot"] == "rx160"
    assert (result["n_samples"], result["n_holdout"]) == (200, 50)
    for model in ("nominal", "extended"):
        assert set(result[model]) == {"position_mm", "orientation_deg"}
        assert set(result[model]["position_mm"]) == STATS
        assert set(result[model]["orientation_deg"]) == STATS
    assert {"position_mm_rms", "orientation_deg_rms", "structured"} <= set(result["unexplained"])
    assert isinstance(result["unexplained"]["structured"], bool)
    along = result["unexplained"]["along_joints"]
    assert along == []  # 50 hold-out rows: fewer than two bins of 50
    [cause] = result["causes"]
    assert CAUSE_KEYS <= set(cause)
    assert (cause["effect"], cause["joint"], cause["unit"]) == (
        "joint_compliance",
        "joint_2",
        "rad/Nm",
    )
    assert cause["value"] == pytest.approx(2e-6, rel=0.05)
    for entry in result["ambiguous"]:
        assert set(entry) >= {"effects", "why"}
    # Human summary: both models' errors with units, the cause with value ± std.
    assert "nominal position [mm]" in captured.out
    assert "extended orientation [deg]" in captured.out
    assert "joint_compliance joint_2 = " in captured.out
    assert "± " in captured.out
    assert "structured: " in captured.out
    assert "left error along the joints" not in captured.out
    assert "transfer: not measured (one file)" in captured.out  # what one set-up cannot show
    assert result["transfer"] is None
    # Progress on stderr (not a terminal here: one line per stage, elapsed seconds).
    assert "diagnose [" in captured.err
    assert " s] fitting base and tool frames" in captured.err
    assert (report / "report.md").is_file()
    assert str(report / "report.md") in captured.out


def test_stability_diagnoses_again_with_the_next_seeds_and_says_what_holds(table, tmp_path, capsys):
    """--stability 3: the user's seed is the diagnosis, two more seeds re-diagnose the
    same rows; the compliance the rows were made with is named in every run; a
    candidate the data do not hold is in no run; JSON, printed lines and report agree."""
    out, report = tmp_path / "diag.json", tmp_path / "report"
    argv = ["diagnose", str(table), "--robot", "rx160", "--json", str(out), "--seed", "4"]
    argv += ["--candidates", "joint_compliance:joint_2,joint_offset:joint_3"]
    assert main([*argv, "--stability", "3", "--report", str(report)]) == 0
    printed = capsys.readouterr().out
    stability = json.loads(out.read_text())["stability"]
    assert stability["seeds"] == [4, 5, 6]
    assert len(stability["runs"]) == 3
    assert stability["runs"][0] == ["joint_compliance:joint_2"]  # the diagnosis itself
    assert stability["in_every_run"] == ["joint_compliance:joint_2"]
    assert stability["named"] == {"joint_compliance:joint_2": 3}
    assert stability["in_some_runs"] == []
    assert "stability over seeds 4-6 (3 diagnoses of the same rows):" in printed
    assert " s (3 diagnoses, --stability)" in printed.splitlines()[0]
    assert "named in every run: joint_compliance:joint_2" in printed
    assert "## Stability over seeds" in (report / "report.md").read_text()
    assert main(argv) == 0  # once, by default: no stability entry
    assert json.loads(out.read_text())["stability"] is None
    assert "stability over seeds" not in capsys.readouterr().out


def test_stability_lines_name_what_only_some_runs_name():
    from hybrid_pk.calibration.diagnosis.stability import stability_lines

    stability = {
        "seeds": [0, 1, 2],
        "runs": [["a", "b"], ["a", "c"], ["a", "b"]],
        "named": {"a": 3, "b": 2, "c": 1},
        "in_every_run": ["a"],
        "in_some_runs": ["b", "c"],
    }
    lines = stability_lines(stability)
    assert lines[1] == "  named in every run: a"
    assert lines[2].endswith("b (2 of 3), c (1 of 3)")


def test_missing_data_file_is_one_line_error(tmp_path, capsys):
    missing = tmp_path / "nope.csv"
    argv = ["diagnose", str(missing), "--robot", "rx160", "--json", str(tmp_path / "d.json")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("hybrid-pk diagnose: error:")
    assert str(missing) in err
    assert not (tmp_path / "d.json").exists()


def test_unknown_candidate_is_one_line_error(table, tmp_path, capsys):
    argv = ["diagnose", str(table), "--robot", "rx160", "--json", str(tmp_path / "d.json")]
    assert main([*argv, "--candidates", "joint_offset:joint_9"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "joint_9" in err


def test_holdout_must_be_a_fraction(table, tmp_path, capsys):
    argv = ["diagnose", str(table), "--robot", "rx160", "--json", str(tmp_path / "d.json")]
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--holdout", "20"])
    assert exc.value.code == 2
    assert "fraction of the rows in (0, 1)" in capsys.readouterr().err


def test_help_states_units(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["diagnose", "--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "Errors are reported in mm" in text
    assert "deg (orientation" in text
    assert "--holdout is a fraction of the rows" in text
    assert "x y z [m]" in text
