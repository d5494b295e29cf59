"""``diagnose`` / ``calibrate --config YAML``: the settings read from a YAML into
DiagnosisSettings (tuning included), a flag given wins over the YAML, the YAML over
the defaults; a bad key is a one-line error naming the file and the key;
``--print-config`` writes a YAML that ``--config`` reads back into the same settings."""

from __future__ import annotations

import json
import math

import pytest

from hybrid_pk.calibration.settings import DiagnosisSettings
from hybrid_pk.calibration.tuning import DiagnosisTuning
from hybrid_pk.cli.fit_settings import settings_of
from hybrid_pk.cli.main import build_parser, main
from hybrid_pk.cli.settings_flags import given_values
from hybrid_pk.hybrid.train_settings import TrainSettings
from hybrid_pk.pipelines.training import train_settings
from tests.test_cli_diagnose import table  # noqa: F401  (the 200-row RX160 campaign)


def _settings(argv: list[str]) -> DiagnosisSettings:
    return settings_of(build_parser().parse_args(argv), DiagnosisSettings)


def _write(path, text: str):
    path.write_text(text, encoding="utf-8")
    return str(path)


@pytest.mark.parametrize("command", ["diagnose", "calibrate"])
def test_flag_over_yaml_over_default(command, tmp_path):
    config = _write(
        tmp_path / "run.yaml",
        "holdout: 0.3\nseed: 5\nrobust: cauchy\nalpha: 0.01\ntuning: {check_rows: 200}\n",
    )
    argv = [command, "d.csv", "--robot", "rx160", "--config", config]
    argv += ["--json", "d.json"] if command == "diagnose" else ["--out", "m.pt"]
    # --holdout 0.2 is the default's value: given, it still wins over the YAML's 0.3
    settings = _settings([*argv, "--holdout", "0.2", "--robust", "huber"])
    assert (settings.holdout, settings.robust) == (0.2, "huber")  # flags
    assert (settings.seed, settings.alpha) == (5, 0.01)  # the YAML
    assert settings.tuning == DiagnosisTuning(check_rows=200)
    assert (settings.max_causes, settings.refit_rows) == (24, 50)  # the defaults
    assert _settings(argv).holdout == 0.3


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("holdotu: 0.3\n", "'holdotu'"),
        ("tuning: {check_rowz: 10}\n", "'tuning.check_rowz'"),
        ("tuning: {check_rows: many}\n", "tuning.check_rows"),
        ("robust: l1\n", "robust"),
        ("holdout: 2.0\n", "holdout"),
        ("tuning: 3\n", "'tuning'"),
        ("- holdout\n", "mapping"),
    ],
)
def test_bad_yaml_is_one_line_error_naming_file_and_key(text, key, tmp_path, capsys):
    config = _write(tmp_path / "bad.yaml", text)
    argv = ["diagnose", "d.csv", "--robot", "rx160", "--json", str(tmp_path / "d.json")]
    assert main([*argv, "--config", config]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert err.startswith(f"hybrid-pk diagnose: error: --config {config}: "), err
    assert key in err, err


@pytest.mark.parametrize("command", ["diagnose", "calibrate"])
def test_print_config_round_trip(command, tmp_path, capsys):
    """--print-config needs no DATA or --robot; its YAML, read back by --config, gives
    the same settings, flags and tuning included."""
    config = _write(tmp_path / "run.yaml", "candidates: [joint_offset:joint_2]\n"
                    "tuning: {power: 0.9}\ngravity: level-tracker\n")  # fmt: skip
    flags = ["--holdout", "0.25", "--tool", "0,0,0.1", "--min-gain-mm", "0.004"]
    assert main([command, "--config", config, *flags, "--print-config"]) == 0
    printed = capsys.readouterr().out
    again = _write(tmp_path / "printed.yaml", printed)
    expected = DiagnosisSettings(
        holdout=0.25, tool="0,0,0.1", min_gain_mm=0.004, gravity="level-tracker",
        candidates=["joint_offset:joint_2"], tuning=DiagnosisTuning(power=0.9),
    )  # fmt: skip
    argv = [command, "d.csv", "--robot", "rx160", "--config", again]
    argv += ["--json", "d.json"] if command == "diagnose" else ["--out", "m.pt"]
    assert _settings(argv) == expected
    assert main([command, "--config", again, "--print-config"]) == 0
    assert capsys.readouterr().out == printed


def test_a_tuning_field_of_the_yaml_reaches_the_diagnosis(table, tmp_path):  # noqa: F811
    """check_rows sets the default practical margin sigma / sqrt(2 check_rows)."""
    config = _write(tmp_path / "tuned.yaml", "tuning: {check_rows: 200}\n")
    out = tmp_path / "d.json"
    argv = ["diagnose", str(table), "--robot", "rx160", "--json", str(out), "--config", config]
    assert main([*argv, "--candidates", "joint_compliance:joint_2", "--refit-rows", "0"]) == 0
    carry = json.loads(out.read_text())["carry_over"]
    assert carry["min_gain_mm"] == pytest.approx(carry["noise_position_mm"] / math.sqrt(400))
    assert "check of 200 poses" in carry["rule"]


def test_train_flags_given_win_and_defaults_do_not_hide_the_yaml(tmp_path):
    """train --config: a preset the YAML names is not overridden by --preset's default."""
    config = _write(tmp_path / "t.yaml", "preset: joints\nmodel: {fade: 0.2}\n")
    argv = ["train", "d.csv", "--model", "m.pt", "--out", "h.pt", "--config", config]
    args = build_parser().parse_args(argv)
    assert given_values(args, TrainSettings) == {}
    assert train_settings(given_values(args, TrainSettings), config).preset == "joints"
    args = build_parser().parse_args([*argv, "--preset", "fast", "--fade", "0.1"])
    settings = train_settings(given_values(args, TrainSettings), config)
    assert (settings.preset, settings.fade) == ("fast", 0.1)
