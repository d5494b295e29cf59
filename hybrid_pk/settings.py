"""Typed settings of a job, one field per setting: its default, type, range check and
help written once. The Python API takes the dataclass (or reads its defaults), the
CLI's flags are derived from its fields (:mod:`hybrid_pk.cli.settings_flags`) and a
YAML or a dict is parsed into it by jsonargparse (:func:`parse_settings`).

    @dataclass
    class S(Checked):
        holdout: float = setting(0.2, "fraction kept out", "F", check=in_open_unit)
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
from collections.abc import Callable, Iterator
from contextvars import ContextVar
from typing import Any, Generic, TypeVar

from hybrid_pk.errors import HybridPKError

__all__ = [
    "Active",
    "Checked",
    "in_open_unit",
    "non_negative",
    "parse_settings",
    "positive",
    "setting",
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
        raise HybridPKError(" ".join(str(exc).split())) from None


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
