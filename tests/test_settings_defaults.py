"""One default per setting: what a CLI flag does when it is not given is what the
Python API does when the keyword is not given (the dataclass or function the command
calls), and what its help says."""

from __future__ import annotations

import dataclasses
import inspect
import re
import typing
from pathlib import Path

import pytest

from hybrid_pk.calibration.diagnosis import diagnose
from hybrid_pk.calibration.settings import DiagnosisSettings, FitSettings
from hybrid_pk.cli.main import build_parser
from hybrid_pk.errors import HybridPKError
from hybrid_pk.hybrid.builder import HybridSettings
from hybrid_pk.hybrid.train_settings import MODULE_FIELDS, TrainSettings
from hybrid_pk.hybrid.tuning import HybridTuning
from hybrid_pk.pipelines.calibration import calibrate
from hybrid_pk.pipelines.training import train_settings, training_sections
from hybrid_pk.training.lightning_module import HybridLitModule
from hybrid_pk.training.presets import PRESETS

# Flags whose CLI word stands for the API's None.
NONE_WORDS = {"none"}


def _options(command: str) -> dict:
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    return {a.dest: a for a in sub.choices[command]._actions if a.option_strings}


def _api_defaults(func) -> dict:
    return {
        name: p.default
        for name, p in inspect.signature(func).parameters.items()
        if p.default is not inspect.Parameter.empty
    }


def _same(text: str, value) -> bool:
    try:
        return float(text) == float(value)
    except (TypeError, ValueError):
        return text == str(value)


# The commands whose fit flags are derived from a settings dataclass, and which fields
# they leave out (calibrate --effects auto takes diagnose's own from --config, else the
# defaults).
FIT_COMMANDS = [
    ("diagnose", DiagnosisSettings, ()),
    ("calibrate", DiagnosisSettings, ("candidates", "alpha", "max_causes", "stability")),
    ("evaluate", FitSettings, ("gravity",)),
]


@pytest.mark.parametrize(("command", "cls", "left_out"), FIT_COMMANDS)
def test_fit_flags_are_the_settings_fields(command, cls, left_out):
    """Every flagged field of the command's settings is a flag with the field's default,
    choices and range check, its contract name and the YAML name as alias; the help
    states that default; no field's flag is hand-written beside it."""
    options = _options(command)
    hints = typing.get_type_hints(cls)
    fields = [f for f in dataclasses.fields(cls) if f.metadata.get("flag", True) is not False]
    assert {f.name for f in fields} - set(left_out) <= set(options), sorted(options)
    for f in fields:
        if f.name in left_out:
            assert f.name not in options, f"{command} --{f.name} is not its setting"
            continue
        action = options[f.name]
        assert action.default == f.default, f"{command} --{f.name}: {action.default!r}"
        assert f"--{f.name.replace('_', '-')}" in action.option_strings
        if "_" in f.name:
            assert f"--{f.name}" in action.option_strings, action.option_strings
        if typing.get_origin(hints[f.name]) is typing.Literal:
            assert tuple(action.choices) == typing.get_args(hints[f.name])
        stated = re.search(r"\(default:? ([^)\s,:]+)", action.help or "")
        if stated and f.default is not None:
            assert _same(stated.group(1), f.default), f"{command} --{f.name}: {stated[0]}"


def test_settings_check_ranges_from_the_api_and_the_flags(capsys):
    with pytest.raises(HybridPKError, match="holdout"):
        DiagnosisSettings(holdout=1.5)
    with pytest.raises(HybridPKError, match="max-causes"):
        DiagnosisSettings.parse({"max_causes": 0})
    with pytest.raises(HybridPKError, match="robust"):
        FitSettings.parse({"robust": "l1"})
    with pytest.raises(SystemExit):
        build_parser().parse_args(["diagnose", "d.csv", "--robot", "ur10", "--json", "x",
                                   "--alpha", "2"])  # fmt: skip
    assert "expected a probability in (0, 1), got 2" in capsys.readouterr().err
    settings = DiagnosisSettings.parse({"candidates": ["joint_offset:joint_2"], "seed": 3})
    assert (settings.candidates, settings.seed, settings.holdout) == (
        ["joint_offset:joint_2"],
        3,
        DiagnosisSettings().holdout,
    )


def test_calibrate_takes_the_settings_object():
    """pipelines.calibrate has no default of its own: its fits and its diagnosis take
    one DiagnosisSettings (the object calibrate's flags and --config give)."""
    params = inspect.signature(calibrate).parameters
    assert typing.get_type_hints(calibrate)["settings"] == DiagnosisSettings | None
    names = {f.name for f in dataclasses.fields(DiagnosisSettings)}
    assert not names & set(params), sorted(names & set(params))


@pytest.mark.parametrize(("command", "func"), [("diagnose", diagnose)])
def test_flag_defaults_are_the_functions(command, func):
    api = _api_defaults(func)
    shared = {d: a for d, a in _options(command).items() if d in api}
    assert {"holdout", "seed"} <= set(shared), sorted(shared)
    for dest, action in shared.items():
        cli = None if action.default in NONE_WORDS else action.default
        assert cli == api[dest], f"{command} --{dest}: CLI {cli!r}, {func.__name__} {api[dest]!r}"
        stated = re.search(r"\(default:? ([^)\s]+)\)", action.help or "")
        if stated:
            assert _same(stated.group(1), action.default), f"{command} --{dest} help: {stated[0]}"


def test_train_flags_state_the_settings_defaults():
    fields = {f.name: f.default for f in dataclasses.fields(HybridSettings)}
    checked = 0
    for dest, action in _options("train").items():
        if dest not in fields or isinstance(fields[dest], bool):
            continue  # a --no-X switch's help says in words what it turns off
        stated = re.search(r"default:? ([\w.]+(?::\w+)?)", " ".join((action.help or "").split()))
        if stated is None or stated.group(1) == "preset":
            continue
        value = fields[dest]
        shown = f"{value:g}" if isinstance(value, float) else str(value)
        assert stated.group(1) == shown, f"train --{dest}: help {stated[0]!r}, settings {shown}"
        for name, preset in PRESETS.items():  # no preset changes what the help states
            assert preset["model"].get(dest, value) == value, f"preset {name} sets {dest}"
        checked += 1
    assert checked >= 5


def test_training_module_takes_the_settings_defaults():
    module = _api_defaults(HybridLitModule.__init__)
    for f in dataclasses.fields(HybridSettings):
        if f.name in module:
            assert module[f.name] == f.default, f"HybridLitModule {f.name}: {module[f.name]!r}"


def test_train_flags_are_the_train_settings_fields():
    """train's training flags are derived from TrainSettings: one per field, its default
    the field's, its choices the field's Literal; the YAML's name an alias."""
    options = _options("train")
    for f in dataclasses.fields(TrainSettings):
        if f.metadata.get("flag", True) is False:
            assert f.name not in options, f"train --{f.name}: a tuning, not a flag"
            continue
        action = options[f.name]
        assert action.default == f.default, f"train --{f.name}: {action.default!r}"
        if "_" in f.name and not f.metadata.get("switch"):
            assert f"--{f.name}" in action.option_strings, action.option_strings
    preset = options["preset"]
    assert set(preset.choices) == set(PRESETS), preset.choices
    module = _api_defaults(HybridLitModule.__init__)
    assert set(MODULE_FIELDS) <= set(module), set(MODULE_FIELDS) - set(module)
    assert set(MODULE_FIELDS) <= {f.name for f in dataclasses.fields(TrainSettings)}


def test_train_settings_parse_checks_types_choices_and_ranges():
    settings = TrainSettings.parse({"preset": "joints", "fade": 0.25, "epochs": 3, "lr": None})
    model, data, trainer = settings.sections()
    assert (settings.preset, model, data, trainer) == (
        "joints",
        {"fade": 0.25},
        {},
        {"max_epochs": 3},
    )
    for bad in ({"trust": "boxes"}, {"epochs": "three"}, {"fade": 11.0}, {"coverage_ratio": 1.0}):
        with pytest.raises(HybridPKError):
            TrainSettings.parse(bad)


def test_contract_train_flags_are_accepted():
    """The flag names docs/contract.md gives for train parse (aliases kept)."""
    text = (Path(__file__).resolve().parent.parent / "docs" / "contract.md").read_text()
    section = text[text.index("- `train`: ") :].split("\n- `", 1)[0]
    flags = set(re.findall(r"`(--[a-z_-]+)", section))
    known = {s for a in _options("train").values() for s in a.option_strings}
    assert len(flags) >= 8, flags
    assert flags <= known, sorted(flags - known)


def test_our_presets_state_only_what_differs_from_the_defaults():
    """fast and joints name what they choose; every other value is the module's default
    (HybridSettings' for the networks): written once."""
    module = _api_defaults(HybridLitModule.__init__)
    for name in ("fast", "joints"):
        for key, value in PRESETS[name]["model"].items():
            defining = (name, key) == ("joints", "inputs")  # what names the preset
            assert defining or value != module[key], f"preset {name} restates {key}={value!r}"


def test_train_config_yaml_is_parsed_into_the_settings_flag_over_yaml_over_default(tmp_path):
    """train --config: the YAML's values are TrainSettings fields (checked by
    jsonargparse), a flag wins over them, a field neither sets keeps its default."""
    config = tmp_path / "run.yaml"
    config.write_text(
        "preset: joints\n"
        "tuning: {freeing_z: 3.0}\n"
        "trainer: {max_epochs: 7}\n"
        "model: {fade: 0.2, trust: coverage, optimizer: adamw}\n"
        "data: {batch_size: 64}\n"
    )
    settings = train_settings({"fade": 0.3, "epochs": None}, config)
    assert (settings.fade, settings.trust, settings.epochs) == (0.3, "coverage", 7)
    assert (settings.batch_size, settings.preset, settings.lr) == (64, "joints", None)
    assert settings.tuning == HybridTuning(freeing_z=3.0)
    assert settings.patience == 0  # the YAML has no EarlyStopping: off
    model, data, trainer = training_sections(settings, config)
    assert (model["optimizer"], model["fade"], data["batch_size"]) == ("adamw", 0.3, 64)
    assert trainer == {"max_epochs": 7, "patience": None}
    bad = tmp_path / "bad.yaml"
    bad.write_text("model: {fade: wide}\n")
    with pytest.raises(HybridPKError, match="fade"):
        train_settings({}, bad)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_shipped_train_configs_parse_into_the_settings(name):
    config = Path(__file__).resolve().parent.parent / "train" / "configs" / f"{name}.yaml"
    settings = train_settings({}, config)
    model = PRESETS[name]["model"]
    assert settings.inputs == model.get("inputs")
    assert settings.batch_size == PRESETS[name]["data"]["batch_size"]
