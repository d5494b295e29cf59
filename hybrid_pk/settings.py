"""Typed settings of a job, one field per setting: its default, type, range check and
help written once. The Python API takes the dataclass (or reads its defaults), the
CLI's flags are derived from its fields (:mod:`hybrid_pk.cli.settings_flags`) and a
YAML or a dict is parsed into it by jsonargparse (:func:`parse_settings`); a settings
YAML is read by :func:`read_settings` and written by :func:`settings_yaml`.

    @dataclass
    class S(Checked):
        holdout: float = setting(0.2, "fraction kept out", "F", check=in_open_unit)
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import re
import typing
from collections.abc import Callable, Iterator
from contextvars import ContextVar
from pathlib import Path
from typing import Any, Generic, TypeVar

from hybrid_pk.errors import HybridPKError

__all__ = [
    "Active",
    "Checked",
    "at_least_one",
    "flag_name",
    "in_open_unit",
    "non_negative",
    "parse_settings",
    "positive",
    "read_settings",
    "setting",
    "settings_yaml",
]


def setting(
    default: Any,
    help: str,
    metavar: str | None = None,
    *,
    check: Callable[[Any], str | None] | None = None,
    switch: str | None = None,
    flag: str | None = None,
) -> Any:
    """A settings field: ``help`` (``{default}`` filled in), ``metavar``, ``check``
    (returns what is wrong with a value, or None), ``switch`` (a ``--no-X`` flag that
    turns a boolean off) and ``flag`` (the flag's name when it is not the field's)."""
    meta = {"help": help.replace("{default}", f"{default:g}" if isinstance(default, float)
                                 else str(default)),
            "metavar": metavar, "check": check, "switch": switch, "flag": flag}  # fmt: skip
    return dataclasses.field(default=default, metadata=meta)


def in_open_unit(value: float) -> str | None:
    """What is wrong with a fraction of the rows (it must lie in (0, 1))."""
    if not 0.0 < value < 1.0:
        return f"expected a fraction of the rows in (0, 1), got {value:g} (e.g. 0.2 for 20 %)"
    return None


def non_negative(value: float) -> str | None:
    """What is wrong with a finite amount that may be zero."""
    if not 0.0 <= value < math.inf:
        return f"expected a finite value >= 0, got {value:g}"
    return None


def at_least_one(value: int) -> str | None:
    """What is wrong with a count of something that must happen at least once (epochs,
    rows per step)."""
    return None if value >= 1 else f"expected at least 1, got {value}"


def positive(value: float) -> str | None:
    """What is wrong with a finite amount that must be above zero."""
    if not 0.0 < value < math.inf:
        return f"expected a finite value > 0, got {value:g}"
    return None


def flag_name(f: dataclasses.Field) -> str:
    """The CLI flag of a settings field (``--max-causes`` for ``max_causes``)."""
    return f.metadata.get("flag") or f"--{f.name.replace('_', '-')}"


class Checked:
    """Mixin of a settings dataclass: every field's ``check`` runs on construction,
    so a value out of range fails at once, from the API, a YAML or a flag."""

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            check, value = f.metadata.get("check"), getattr(self, f.name)
            if check is not None and value is not None:
                why = check(value)
                if why:
                    raise HybridPKError(f"{flag_name(f)} ({f.name}): {why}")


def parse_settings(cls, values: dict, *, base: dict | None = None):
    """``cls`` from ``values`` (None: not given) over ``base`` (a YAML's mapping),
    types and choices checked by jsonargparse against the fields, ranges by the fields'
    checks.

    Raises:
        HybridPKError: a value of the wrong type, choice or range, an unknown key.
    """
    from jsonargparse import ArgumentParser

    parser = ArgumentParser(exit_on_error=False)
    parser.add_class_arguments(cls, "settings")
    given = dict(base or {}) | {k: v for k, v in values.items() if v is not None}
    try:
        cfg = parser.parse_object({"settings": given})
        return parser.instantiate(cfg).settings
    except HybridPKError:
        raise
    except Exception as exc:  # jsonargparse's ArgumentError names the key and type
        msg = re.sub(r"Expected a <class '(\w+)'>", r"expected \1", " ".join(str(exc).split()))
        raise HybridPKError(msg.replace('Parser key "settings.', 'key "')) from None


def _check_keys(cls, doc, where: str, prefix: str = "") -> None:
    """Every key of the mapping ``doc`` is a field of ``cls`` (a nested settings
    field's mapping checked the same way)."""
    if not isinstance(doc, dict):
        what = f"key {prefix[:-1]!r}" if prefix else "the file"
        raise HybridPKError(f"{where}: {what} must be a mapping, got {doc!r}")
    hints = typing.get_type_hints(cls)
    for key, value in doc.items():
        if key not in hints:
            known = ", ".join(f.name for f in dataclasses.fields(cls))
            raise HybridPKError(
                f"{where}: unknown key '{prefix}{key}' ({cls.__name__} has: {known})"
            )
        if dataclasses.is_dataclass(hints[key]):
            _check_keys(hints[key], value, where, f"{prefix}{key}.")


def read_settings(cls, path: str | Path) -> dict:
    """The mapping of the settings YAML ``path`` (``--config``), its keys and values
    checked against ``cls`` (:func:`parse_settings`).

    Raises:
        HybridPKError: the file cannot be read, an unknown key, a value of the wrong
            type, choice or range; one line naming the file and the key.
    """
    import yaml

    where = f"--config {path}"
    try:
        doc = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise HybridPKError(f"{where}: file not found") from None
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise HybridPKError(f"{where}: not a YAML file: {' '.join(str(exc).split())}") from None
    doc = {} if doc is None else doc
    _check_keys(cls, doc, where)
    try:
        parse_settings(cls, {}, base=doc)
    except HybridPKError as exc:
        raise HybridPKError(f"{where}: {exc}") from None
    return doc


def settings_yaml(settings) -> str:
    """``settings`` as a YAML that :func:`read_settings` reads back into equal settings."""
    import yaml

    return yaml.safe_dump(dataclasses.asdict(settings), sort_keys=False)


T = TypeVar("T")


class Active(Generic[T]):
    """The tuning of the job under way: a job sets it for its duration
    (:meth:`using`, :meth:`tuned`) and the modules it calls read it (:meth:`get`), so a
    tuning constant is neither hidden in a module nor passed through every call
    between the job and the step that uses it. Outside a job: the defaults."""

    def __init__(self, name: str, default: T) -> None:
        self._var: ContextVar[T | None] = ContextVar(name, default=None)
        self._default = default

    def get(self) -> T:
        """The tuning of the job under way (the defaults outside one)."""
        return self._var.get() or self._default

    @contextlib.contextmanager
    def using(self, value: T | None) -> Iterator[T]:
        """Within the block, :meth:`get` is ``value`` (None: the defaults)."""
        token = self._var.set(value)
        try:
            yield self.get()
        finally:
            self._var.reset(token)

    def tuned(self, func: Callable) -> Callable:
        """Runs ``func`` under the tuning of its ``tuning`` keyword (:meth:`using`)."""

        @functools.wraps(func)
        def run(*args, **kwargs):
            with self.using(kwargs.get("tuning")):
                return func(*args, **kwargs)

        return run
