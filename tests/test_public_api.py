"""Public names: every subpackage has a docstring and an ``__all__`` whose names exist
(mink once exported names that did not exist), no package name hides a submodule, the
README's "How it works" tree lists every subpackage, and every "contract section N" a
docstring cites is a section of docs/contract.md."""

from __future__ import annotations

import ast
import importlib
import pkgutil
import re
import subprocess
import sys
import types
from pathlib import Path

import pytest

import hybrid_pk

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
CONTRACT = REPO / "docs" / "contract.md"
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


def _contract_sections() -> dict[int, str]:
    text = CONTRACT.read_text(encoding="utf-8")
    return {int(n): title for n, title in re.findall(r"^## (\d+)\. (.+)$", text, re.MULTILINE)}


def test_cited_contract_sections_exist():
    sections = _contract_sections()
    assert sorted(sections) == list(range(1, len(sections) + 1)), "sections are numbered 1..N"
    cite = re.compile(r"contract(?: sections?|-| )\s*(\d+)(?:\s*(?:and|,)\s*(\d+))?", re.I)
    cited = {}
    for path in sorted((REPO / "hybrid_pk").rglob("*.py")):
        for m in cite.finditer(path.read_text(encoding="utf-8")):
            for n in filter(None, m.groups()):
                cited.setdefault(int(n), []).append(path.relative_to(REPO).as_posix())
    assert len(cited) >= 4, f"the citation pattern finds almost nothing: {cited}"
    missing = {n: where for n, where in cited.items() if n not in sections}
    assert not missing, f"docstrings cite sections docs/contract.md does not have: {missing}"


def test_contract_python_block_runs():
    text = CONTRACT.read_text(encoding="utf-8")
    blocks = re.findall(r"```python\n(.*?)```", text, re.DOTALL)
    assert blocks, "docs/contract.md has no Python block"
    for block in blocks:
        exec(compile(block, str(CONTRACT), "exec"), {})


def _cli_flags(parser, command=()):
    """``(command words, long option)`` of every sub-command, recursively."""
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield (*command, name), None
                yield from _cli_flags(sub, (*command, name))
        for option in action.option_strings:
            if option.startswith("--") and option != "--help":
                yield command, option


def test_contract_documents_every_command_and_flag():
    """A new sub-command or flag needs its line in docs/contract.md (section 3 or 9)."""
    from hybrid_pk.cli.main import build_parser

    text = CONTRACT.read_text(encoding="utf-8")
    missing = []
    for command, option in _cli_flags(build_parser()):
        if option is None:
            if f"`{' '.join(command)}" not in text:  # in code form: `import columns ...`
                missing.append(" ".join(command))
        elif option not in text and f"--{option[2:].split('-')[0]}-*" not in text:
            missing.append(f"{' '.join(command)} {option}")
    assert not missing, f"not in docs/contract.md: {missing}"


def test_import_loads_names_on_first_use():
    """``import hybrid_pk`` loads no torch; a public name or a subpackage loads on use."""
    code = (
        "import sys, hybrid_pk as h\nprint('torch' in sys.modules)\n"
        "print(h.ik.IKOptions is h.IKOptions, 'torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "True", "True"]


def test_type_checking_imports_match_the_lazy_exports():
    """``hybrid_pk/__init__``'s imports for type checkers name the same modules and
    names as ``_HOME``, the table the lazy exports load from."""
    tree = ast.parse(Path(hybrid_pk.__file__).read_text(encoding="utf-8"))
    block = next(n for n in tree.body if isinstance(n, ast.If))  # `if TYPE_CHECKING:`
    imported = {a.name: n.module for n in block.body for a in n.names}
    assert imported == hybrid_pk._HOME
