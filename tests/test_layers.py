"""The package's layers import downward only: each subpackage may import the layers
listed before it (and itself), never one after it. Lazy imports inside functions count."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "hybrid_pk"

# Lowest first. Modules in one layer may import each other's layer.
LAYERS = [
    (
        "errors",
        "geometry",
        "startup",
        "threads",
        "settings",
        "units",
        "output_file",
        "distributions",
    ),
    ("robot",),
    ("data",),
    ("evaluation",),
    ("effects",),
    ("simulate",),
    ("calibration",),
    ("hybrid",),
    ("io",),
    ("training",),
    ("ik",),
    ("report",),
    ("pipelines",),
    ("cli",),
]
RANK = {name: i for i, layer in enumerate(LAYERS) for name in layer}


def _top(module: str) -> str | None:
    """``hybrid_pk.calibration.fit`` -> ``calibration``; None for the package root."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "hybrid_pk" else None


def imported_modules(source: str, module: str) -> set[str]:
    """Absolute names of every hybrid_pk module that ``source`` imports."""
    out = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the importing module
                base = module.split(".")[: -node.level]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            if name.startswith("hybrid_pk"):
                out.add(name)
                out.update(f"{name}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.startswith("hybrid_pk"))
        elif (
            isinstance(node, ast.Call)
            and getattr(node.func, "attr", getattr(node.func, "id", None)) == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and str(node.args[0].value).startswith("hybrid_pk")
        ):
            out.add(node.args[0].value)
    return out


def violations(sources: dict[str, str]) -> list[str]:
    """``module -> source`` of a package tree -> the upward imports found, one line each."""
    bad = []
    for module, source in sorted(sources.items()):
        layer = _top(module)
        if layer is None:
            continue  # hybrid_pk/__init__.py re-exports the public API of every layer
        assert layer in RANK, f"{module}: subpackage {layer!r} has no place in LAYERS"
        for target in sorted(imported_modules(source, module)):
            other = _top(target)
            if other is not None and other in RANK and RANK[other] > RANK[layer]:
                bad.append(f"{module} ({layer}) imports {target} ({other}, a higher layer)")
    return bad


def _package_sources() -> dict[str, str]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        name = ".".join(rel.parts).removesuffix(".__init__")
        out[name] = path.read_text(encoding="utf-8")
    return out


def test_every_subpackage_has_a_layer():
    found = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    found |= {p.stem for p in PACKAGE.glob("*.py") if p.stem != "__init__"}
    assert found <= set(RANK), f"not in LAYERS: {sorted(found - set(RANK))}"


def test_layers_import_downward_only():
    bad = violations(_package_sources())
    assert not bad, "upward imports:\n" + "\n".join(bad)


def test_an_upward_import_is_caught():
    # The check itself must be able to fail: a robot module that imports the CLI, an
    # effects module that lazily imports calibration, and one through importlib.
    sources = _package_sources()
    sources["hybrid_pk.robot.bad"] = "from hybrid_pk.cli.main import main\n"
    sources["hybrid_pk.effects.bad"] = "def f():\n    from hybrid_pk.calibration import fit\n"
    sources["hybrid_pk.data.bad"] = "import importlib\nimportlib.import_module('hybrid_pk.io')\n"
    bad = violations(sources)
    assert len(bad) >= 3
    assert any(line.startswith("hybrid_pk.robot.bad (robot) imports hybrid_pk.cli") for line in bad)
    assert any(line.startswith("hybrid_pk.effects.bad") for line in bad)
    assert any(line.startswith("hybrid_pk.data.bad") for line in bad)
