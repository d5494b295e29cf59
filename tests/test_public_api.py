"""Every exported name resolves (mink once exported names that did not exist)."""

from __future__ import annotations

import importlib

import pytest

PACKAGES = [
    "hybrid_pk",
    "hybrid_pk.robot",
    "hybrid_pk.effects",
    "hybrid_pk.data",
    "hybrid_pk.geometry",
    "hybrid_pk.evaluation.metrics",
    "hybrid_pk.simulate",
    "hybrid_pk.report",
]


@pytest.mark.parametrize("name", PACKAGES)
def test_all_names_resolve(name):
    module = importlib.import_module(name)
    exported = getattr(module, "__all__", None)
    assert exported, f"{name} has no __all__"
    missing = [n for n in exported if not hasattr(module, n)]
    assert not missing, f"{name}.__all__ lists names that do not exist: {missing}"
    assert len(set(exported)) == len(exported), f"{name}.__all__ has duplicates"


def test_cli_lists_every_contract_command():
    from hybrid_pk.cli.main import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    for command in ("simulate", "diagnose", "calibrate", "evaluate", "import", "demo"):
        assert command in sub.choices, f"hybrid-pk {command} is missing"
