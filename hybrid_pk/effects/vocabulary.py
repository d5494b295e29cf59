"""The effect vocabulary as users read it, made from the registered classes: the
contract's and the README's tables (``tests/test_vocabulary.py`` checks both documents
hold them) and the list of kinds and units in the CLI's help.

    python -m hybrid_pk.effects.vocabulary contract   # the contract's table
    python -m hybrid_pk.effects.vocabulary readme     # the README's table
"""

from __future__ import annotations

import sys

from hybrid_pk.effects.base import EFFECTS, Effect, family_members

__all__ = ["vocabulary", "vocabulary_table", "vocabulary_units"]

# Listed in this order: where the effect acts, then the order its module registers it.
_STAGE_ORDER = ("joint", "compliance", "geometry", "deflection")


def vocabulary() -> list[tuple[str, type[Effect]]]:
    """``(name, class)`` of every kind users can name, a family once by its pattern
    (``cyclic_error_<n>``) after the class it derives from."""
    joint_first = sorted(EFFECTS.items(), key=lambda item: _STAGE_ORDER.index(item[1].stage))
    out = []
    for kind, cls in joint_first:
        out.append((kind, cls))
        out += [(shown, member) for shown, member in family_members() if member.__base__ is cls]
    return out


def vocabulary_table(which: str = "contract") -> str:
    """The Markdown table ``| effect | model | unit |``: ``"contract"`` with each
    class's one-line ``equation``, ``"readme"`` with its ``description``."""
    rows = ["| effect | model | unit |", "|---|---|---|"]
    for name, cls in vocabulary():
        text = cls.equation if which == "contract" else cls.description
        rows.append(f"| `{name}` | {text} | {cls.unit} |")
    return "\n".join(rows)


def vocabulary_units() -> str:
    """``kind [unit], ...`` for help texts (not per joint, prismatic joints said)."""
    parts = []
    for name, cls in vocabulary():
        notes = [cls.unit]
        if cls.shape and cls.shape[0] == 3:
            notes.append("vector")
        if cls.joints in ("prismatic", "none"):
            notes.append("not per joint" if cls.joints == "none" else "prismatic joints")
        parts.append(f"{name} [{', '.join(notes)}]")
    return ", ".join(parts)


if __name__ == "__main__":  # pragma: no cover - prints a table to paste
    print(vocabulary_table(sys.argv[1] if len(sys.argv) > 1 else "contract"))
