"""``--effects LIST|DIAG.json``: effect labels from a comma-separated list or from the
causes of a ``diagnose --json`` file."""

from __future__ import annotations

from hybrid_pk.cli.common import read_json
from hybrid_pk.errors import HybridPKError

__all__ = ["diagnosis_labels", "effect_labels"]


def effect_labels(text: str, flag: str = "--effects", others: str = "") -> list[str]:
    """``kind:joint`` labels of ``text``: a comma-separated list, or a diagnosis JSON file.

    Args:
        flag: the option named in error messages.
        others: the option's other accepted words, for the message (``"auto, none, "``).
    """
    if text.lower().endswith(".json"):
        return diagnosis_labels(text, flag)
    labels = [s.strip() for s in text.split(",") if s.strip()]
    if not labels:
        raise HybridPKError(
            f"{flag}: give {others}a comma-separated list of effects, or a diagnosis JSON file"
        )
    seen = set()
    for label in labels:
        if label in seen:
            raise HybridPKError(f"{flag}: {label} is listed twice")
        seen.add(label)
    return labels


def diagnosis_labels(path: str, flag: str = "--effects") -> list[str]:
    """The causes of a ``diagnose --json`` file as effect labels."""
    doc = read_json(path, flag, "diagnosis")
    causes = doc.get("causes") if isinstance(doc, dict) else None
    if not isinstance(causes, list) or not all(
        isinstance(c, dict) and isinstance(c.get("effect"), str) for c in causes
    ):
        raise HybridPKError(
            f"{flag}: {path} has no 'causes' list of a diagnosis JSON file{_truth_hint(doc)}"
        )
    return [c["effect"] + (f":{c['joint']}" if c.get("joint") else "") for c in causes]


def _truth_hint(doc) -> str:
    """What to give instead when ``doc`` is a ``simulate`` truth file (its ``effects``
    list, unless the campaign hides them)."""
    if not (
        isinstance(doc, dict) and "effects_spec" in doc and isinstance(doc.get("effects"), list)
    ):
        return ""
    if doc.get("effects_hidden"):
        return "; it is a simulate truth file whose effects are hidden: diagnose the campaign"
    labels = [e["effect"] + (f":{e['joint']}" if e.get("joint") else "") for e in doc["effects"]]
    return (
        f"; it is a simulate truth file: its effects as a list are {','.join(labels) or '(none)'}"
    )
