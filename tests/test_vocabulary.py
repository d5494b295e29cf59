"""The vocabulary the documents show is the one the effect classes state."""

from __future__ import annotations

from pathlib import Path

import pytest

from hybrid_pk.effects.vocabulary import vocabulary, vocabulary_table

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(
    ("doc", "which"), [("docs/contract.md", "contract"), ("README.md", "readme")]
)
def test_documents_hold_the_generated_table(doc, which):
    table = vocabulary_table(which)
    assert table in (ROOT / doc).read_text(), (
        f"{doc}'s effect table differs from the classes': regenerate it with "
        f"python -m hybrid_pk.effects.vocabulary {which}"
    )


def test_every_kind_describes_itself():
    for name, cls in vocabulary():
        missing = [a for a in ("unit", "equation", "description") if not getattr(cls, a, "")]
        assert not missing, f"{name} states no {', '.join(missing)}"
        assert cls.joints in ("revolute", "prismatic", "any", "none"), name
        assert (cls.joints == "none") == (not cls.per_joint), name
