"""One default per setting: what a CLI flag does when it is not given is what the
Python API does when the keyword is not given (the dataclass or function the command
calls), and what its help says."""

from __future__ import annotations

import dataclasses
import inspect
import re

import pytest

from hybrid_pk.calibration.diagnosis import diagnose
from hybrid_pk.cli.main import build_parser
from hybrid_pk.hybrid.builder import HybridSettings
from hybrid_pk.pipelines.calibration import calibrate
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


@pytest.mark.parametrize(("command", "func"), [("diagnose", diagnose), ("calibrate", calibrate)])
def test_flag_defaults_are_the_functions(command, func):
    api = _api_defaults(func)
    shared = {d: a for d, a in _options(command).items() if d in api}
    assert {"holdout", "seed", "frames_per_file"} <= set(shared), sorted(shared)
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
