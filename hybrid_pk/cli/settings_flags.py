"""Flags derived from a settings dataclass: one per field, named as the contract spells
it (``--coverage-ratio``) with the field's own name (``--coverage_ratio``, as in the
YAML) as an alias; type and choices from its annotation, help and metavar from its
metadata, the default the field's, the range check the field's (an out-of-range value
is argparse's usage error). A boolean field with a ``switch`` in its metadata becomes
that ``--no-X`` flag, one that defaults to False a ``--X`` switch; ``list[str]`` is a
comma-separated list. Fields whose metadata says ``flag: False`` (tuning constants,
nested settings) have no flag: the API or a YAML sets them.

argparse cannot tell a flag left at its default from one given with the default's
value, so each flag's action also notes that it was given (:func:`given_values`): a
given flag wins over a ``--config`` YAML (:func:`add_config_flags`), the YAML over the
field's default."""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing

from hybrid_pk.settings import flag_name

__all__ = ["add_config_flags", "add_settings_flags", "given_values", "settings_names"]

# The namespace attribute that holds the names of the settings flags given.
_GIVEN = "given_settings"


class _Given(argparse.Action):
    """Stores the flag's value (a switch's ``const``) and notes that it was given."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, self.const if self.nargs == 0 else values)
        given = getattr(namespace, _GIVEN, None) or set()
        setattr(namespace, _GIVEN, given | {self.dest})


class _PrintConfig(argparse.Action):
    """``--print-config``: the command prints its settings and stops, so the
    arguments it would need to run (DATA, --robot, ...) may be left out."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, True)
        for action in parser._actions:  # read when argparse lists what is missing
            action.required = False


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
        name = flag_name(f)
        aliases = [f"--{f.name}"] * ("_" in f.name)
        if meta.get("switch"):
            parser.add_argument(
                meta["switch"], dest=f.name, action=_Given, nargs=0, const=False,
                default=f.default, help=text,
            )  # fmt: skip
            continue
        if hints[f.name] is bool and f.default is False:
            parser.add_argument(
                name, *aliases, dest=f.name, action=_Given, nargs=0, const=True, default=False,
                help=text,
            )  # fmt: skip
            continue
        kind, choices = _kind(hints[f.name])
        if meta.get("check") is not None:
            kind = _checked(kind, meta["check"])
        parser.add_argument(
            name, *aliases, dest=f.name, action=_Given, type=kind, choices=choices,
            default=f.default, metavar=meta.get("metavar"), help=text,
        )  # fmt: skip


def settings_names(cls, *, only=None, skip=()) -> list[str]:
    """The names of the flagged fields of ``cls`` (the ``dest`` of their flags)."""
    return [f.name for f in _flagged(cls, only, skip)]


def given_values(args: argparse.Namespace, cls, **select) -> dict:
    """``{name: value}`` of the flags of ``cls``'s fields given on the command line
    (``select``: ``only`` / ``skip`` as in :func:`add_settings_flags`)."""
    given = getattr(args, _GIVEN, None) or set()
    return {n: getattr(args, n) for n in settings_names(cls, **select) if n in given}


def add_config_flags(parser: argparse.ArgumentParser, cls) -> None:
    """``--config YAML`` (a mapping of the fields of ``cls``, nested settings as
    mappings) and ``--print-config`` (the settings as such a YAML, then stop)."""
    parser.add_argument(
        "--config",
        metavar="YAML",
        help=f"read the settings from YAML: the {cls.__name__} fields, named as the flags' "
        "second names (max_causes), the tuning constants under tuning:; a flag given wins "
        "over the YAML, the YAML over the defaults",
    )
    parser.add_argument(
        "--print-config",
        action=_PrintConfig,
        nargs=0,
        default=False,
        help="print the settings this command would run with (defaults, --config, flags) as "
        "a --config YAML and stop",
    )
