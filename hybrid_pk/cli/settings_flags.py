"""Flags derived from a settings dataclass: one per field, named as the contract spells
it (``--coverage-ratio``) with the field's own name (``--coverage_ratio``, as in the
YAML) as an alias; type and choices from its annotation, help and metavar from its
metadata, the default the field's, the range check the field's (an out-of-range value
is argparse's usage error). A boolean field with a ``switch`` in its metadata becomes
that ``--no-X`` flag, one that defaults to False a ``--X`` switch; ``list[str]`` is a
comma-separated list. Fields whose metadata says ``flag: False`` (tuning constants,
nested settings) have no flag: the API or a YAML sets them."""

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
    if typing.get_origin(annotation) is list:
        return _comma_list, None
    return annotation, None


def _comma_list(text: str) -> list[str]:
    return [item.strip() for item in text.split(",") if item.strip()]


def _checked(kind, check):
    """``argparse`` type: ``kind`` of the text, then the field's ``check``."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {kind.__name__}, got {text!r}") from None
        why = check(value)
        if why:
            raise argparse.ArgumentTypeError(why)
        return value

    parse.__name__ = kind.__name__
    return parse


def _flagged(cls, only, skip) -> list[dataclasses.Field]:
    fields = [f for f in dataclasses.fields(cls) if f.metadata.get("flag", True) is not False]
    if only is not None:
        fields = [f for f in fields if f.name in only]
    return [f for f in fields if f.name not in skip]


def add_settings_flags(
    parser: argparse.ArgumentParser,
    cls,
    *,
    only: typing.Collection[str] | None = None,
    skip: typing.Collection[str] = (),
    helps: dict[str, str] | None = None,
) -> None:
    """One flag per field of the dataclass ``cls`` (see the module docstring): the
    fields named in ``only`` (default all) but not in ``skip``; ``helps`` replaces the
    help of a field where a command words it otherwise."""
    hints = typing.get_type_hints(cls)
    for f in _flagged(cls, only, skip):
        meta = f.metadata
        text = (helps or {}).get(f.name, meta["help"])
        name = meta.get("flag") or f"--{f.name.replace('_', '-')}"
        aliases = [f"--{f.name}"] * ("_" in f.name)
        if meta.get("switch"):
            parser.add_argument(
                meta["switch"], dest=f.name, action="store_false", default=f.default, help=text
            )
            continue
        if hints[f.name] is bool and f.default is False:
            parser.add_argument(name, *aliases, dest=f.name, action="store_true", help=text)
            continue
        kind, choices = _kind(hints[f.name])
        if meta.get("check") is not None:
            kind = _checked(kind, meta["check"])
        parser.add_argument(
            name, *aliases, dest=f.name, type=kind, choices=choices, default=f.default,
            metavar=meta.get("metavar"), help=text,
        )  # fmt: skip


def settings_names(cls, *, only=None, skip=()) -> list[str]:
    """The names of the flagged fields of ``cls`` (the ``dest`` of their flags)."""
    return [f.name for f in _flagged(cls, only, skip)]
