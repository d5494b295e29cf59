"""Command line interface ``hybrid-pk`` (entry point :func:`hybrid_pk.cli.main.main`).

One module per sub-command (``*_cmd.py``) with its options and output; the flags
several commands share in :mod:`~hybrid_pk.cli.options`, data loading and frames in
:mod:`~hybrid_pk.cli.common`, progress display in :mod:`~hybrid_pk.cli.progress`.
Commands, flags, outputs and exit codes are described in ``docs/contract.md``. The
work itself is done by the library layers below; whole jobs live in
:mod:`hybrid_pk.pipelines`.
"""

import importlib
from types import ModuleType

__all__ = ["main"]


def __getattr__(name: str) -> ModuleType:
    if name == "main":  # the entry-point module, imported on first use
        return importlib.import_module(f"{__name__}.main")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
