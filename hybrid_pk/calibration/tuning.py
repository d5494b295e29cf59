"""The tuning constants of the diagnosis (filled in below)."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["DiagnosisTuning"]


@dataclass
class DiagnosisTuning:
    """The diagnosis' tuning constants, each with its reason."""
