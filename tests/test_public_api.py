"""Public names: every subpackage has a docstring and an ``__all__`` whose names exist
(mink once exported names that did not exist), no package name hides a submodule, and
the README's "How it works" tree lists every subpackage."""

from __future__ import annotations

import importlib
import pkgutil
import re
import types
from pathlib import Path

import pytest

import hybrid_pk

README = Path(__file__).resolve().parents[1] / "README.md"
_WALK = list(pkgutil.walk_packages(hybrid_pk.__path__, "hybrid_pk."))
PACKAGES = ["hybrid_pk", *sorted(m.name for m in _WALK if m.ispkg)]
MODULES = sorted(m.name for m in _WALK)


def test_every_layer_is_covered():
    for layer in ("robot", "data", "evaluation", "calibration", "hybrid", "io", "training"):
        assert f"hybrid_pk.{layer}" in PACKAGES
    assert {"hybrid_pk.ik", "hybrid_pk.cli", "hybrid_pk.calibration.diagnosis"} <= set(PACKAGES)


@pytest.mark.parametrize("name", PACKAGES)
def test_package_has_docstring_and_all(name):
    module = importlib.import_module(name)
    assert (module.__doc__ or "").strip(), f"{name} has no docstring"
    exported = getattr(module, "__all__", None)
    assert exported, f"{name} has no __all__"
    assert len(set(exported)) == len(exported), f"{name}.__all__ has duplicates"


@pytest.mark.parametrize("name", MODULES)
def test_all_names_resolve(name):
    module = importlib.import_module(name)
    missing = [n for n in getattr(module, "__all__", ()) if not hasattr(module, n)]
    assert not missing, f"{name}.__all__ lists names that do not exist: {missing}"


@pytest.mark.parametrize("name", PACKAGES)
def test_no_name_hides_a_submodule(name):
    """``from pkg.fit import fit`` in ``pkg/__init__`` would make ``pkg.fit`` the function,
    and ``import pkg.fit as m`` / ``monkeypatch.setattr("pkg.fit.x", ...)`` would break."""
    package = importlib.import_module(name)
    for sub in pkgutil.iter_modules(package.__path__):
        importlib.import_module(f"{name}.{sub.name}")
        value = getattr(package, sub.name)
        assert isinstance(value, types.ModuleType), f"{name}.{sub.name} is {value!r}"


def test_readme_tree_lists_every_subpackage():
    text = README.read_text(encoding="utf-8")
    section = text.split("## How it works", 1)[1].split("\n## ", 1)[0]
    tree = section.split("```", 2)[1]
    listed, stack = set(), []  # folders by indentation: "  calibration/" then "    diagnosis/"
    for line in tree.splitlines():
        m = re.match(r"^( {0,7})([a-z_]+)/(\s|$)", line)
        if m:
            indent = len(m.group(1))
            while stack and stack[-1][0] >= indent:
                stack.pop()
            stack.append((indent, m.group(2)))
            listed.add("/".join(name for _, name in stack[1:]))  # below hybrid_pk/
    listed.discard("")
    packages = {n.removeprefix("hybrid_pk.").replace(".", "/") for n in PACKAGES[1:]}
    assert packages <= listed, f"missing from the README tree: {sorted(packages - listed)}"
    assert listed <= packages, f"README tree lists folders that do not exist: {listed - packages}"


def test_cli_lists_every_contract_command():
    from hybrid_pk.cli.main import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    for command in ("simulate", "diagnose", "calibrate", "evaluate", "import", "demo"):
        assert command in sub.choices, f"hybrid-pk {command} is missing"
