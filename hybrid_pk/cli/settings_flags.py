"""Flags derived from a settings dataclass: one per field, named as the contract spells
it (``--coverage-ratio``) with the field's own name (``--coverage_ratio``, as in the
YAML) as an alias; type and choices from its annotation, help and metavar from its
metadata, the default the field's. A boolean field with a ``switch`` in its metadata
becomes that ``--no-X`` flag."""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing

__all__ = ["add_settings_flags", "settings_names"]


def _kind(annotation) -> tuple[type, tuple | None]:
    """``(type, choices)`` of a field annotation, None left out of an optional."""
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    if typing.get_origin(annotation) in (typing.Union, types.UnionType) and len(args) == 1:
        annotation = args[0]
    if typing.get_origin(annotation) is typing.Literal:
        choices = typing.get_args(annotation)
        return type(choices[0]), choices
    return annotation, None


def add_settings_flags(parser: argparse.ArgumentParser, cls) -> None:
    """One flag per field of the dataclass ``cls`` (see the module docstring)."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        meta = f.metadata
        if meta.get("switch"):
            parser.add_argument(
                meta["switch"], dest=f.name, action="store_false", default=f.default,
                help=meta["help"],
            )  # fmt: skip
            continue
        kind, choices = _kind(hints[f.name])
        names = [f"--{f.name.replace('_', '-')}"] + [f"--{f.name}"] * ("_" in f.name)
        parser.add_argument(
            *names, dest=f.name, type=kind, choices=choices, default=f.default,
            metavar=meta.get("metavar"), help=meta["help"],
        )  # fmt: skip


def settings_names(cls) -> list[str]:
    """The field names of the dataclass ``cls`` (the ``dest`` of its flags)."""
    return [f.name for f in dataclasses.fields(cls)]
