"""A command's outputs, checked before it computes anything.

A command may not write over one of its own inputs (``calibrate runs.csv --out
runs.csv`` would replace the measurements by a model), nor write two of its outputs to
one path, nor a file where a folder is or a folder where a file is, nor into a folder
it may not write in, nor a file inside an output folder. Each refusal is one line
naming the option and the path, and comes before any work or any file written.
Each file itself is then written through :func:`hybrid_pk.output_file.replacing`, so a
write that fails keeps what was there.

Outputs are read from the parsed flags: ``--out`` (a file, or a folder where the
command says so with ``out_kind``), ``--json``, ``--urdf`` (files), ``--report`` and
``--logdir`` (folders), plus what a command writes beside them (``also_writes(args)``,
e.g. ``simulate``'s ``FILE.truth.json``). Inputs are every flag or argument naming an
existing file.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from hybrid_pk.errors import HybridPKError
from hybrid_pk.io.model_file import NOMINAL_PREFIX
from hybrid_pk.output_file import read_only

__all__ = ["check_outputs"]

_FILES = {"out": "--out", "json": "--json", "urdf": "--urdf"}
_FOLDERS = {"report": "--report", "logdir": "--logdir"}
# Arguments that may name an input file (positional ones by their metavar in messages).
_INPUTS = {
    "data": "DATA",
    "model": "MODEL",
    "targets": "TARGETS",
    "program": "PROGRAM",
    "poses": "--poses",
    "joint_box": "--joint-box",
    "effects": "--effects",
    "candidates": "--candidates",
    "config": "--config",
    "controller": "--controller",
    "sources": "SRC",
    "robot_stream": "ROBOT_STREAM",
    "tracker_stream": "TRACKER_STREAM",
    "table": "TABLE",
    "robot": "ROBOT",
    "robot_flag": "--robot",
}


def _outputs(args: argparse.Namespace) -> list[tuple[str, Path, str]]:
    """``(option, path, "file" | "folder" | "either")`` of every output ``args`` names."""
    found = []
    for dest, flag in _FILES.items():
        value = getattr(args, dest, None)
        if isinstance(value, (str, os.PathLike)):
            kind = getattr(args, "out_kind", "file") if dest == "out" else "file"
            found.append((flag, Path(value), kind))
    for dest, flag in _FOLDERS.items():
        value = getattr(args, dest, None)
        if isinstance(value, (str, os.PathLike)):
            found.append((flag, Path(value), "folder"))
    also = getattr(args, "also_writes", None)
    if also is not None:
        found += [(what, Path(path), "file") for what, path in also(args)]
    return found


def _inputs(args: argparse.Namespace) -> list[tuple[str, Path]]:
    """``(argument, path)`` of every argument of ``args`` that names an existing file."""
    found = []
    for dest, name in _INPUTS.items():
        value = getattr(args, dest, None)
        for item in value if isinstance(value, (list, tuple)) else [value]:
            if isinstance(item, str) and item.startswith(NOMINAL_PREFIX):  # nominal:X.urdf
                item = item[len(NOMINAL_PREFIX) :]
            if isinstance(item, (str, os.PathLike)) and Path(item).is_file():
                found.append((name, Path(item)))
    return found


def _check_parent(flag: str, path: Path) -> None:
    """The nearest folder above ``path`` that exists (the rest is made) must be a folder
    the process may write in."""
    parent = path.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise HybridPKError(f"{flag} {path}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise HybridPKError(f"{flag} {path}: the folder {parent} is not writable")


def check_outputs(args: argparse.Namespace) -> None:
    """Refuse, before any work, outputs that would overwrite an input or each other, or
    a file given where a folder is (and the other way round): :class:`HybridPKError`."""
    inputs, outputs, seen = _inputs(args), _outputs(args), {}
    for flag, path, kind in outputs:
        if kind == "file" and path.is_dir():
            raise HybridPKError(f"{flag} {path} is a folder; give a file name")
        if kind == "folder" and path.exists() and not path.is_dir():
            raise HybridPKError(f"{flag} {path} is a file; give a folder (it holds several)")
        _check_parent(flag, path)
        if kind != "folder" and path.is_file() and read_only(path):
            raise HybridPKError(
                f"{flag} {path}: the file is read-only; make it writable or give another name"
            )
        for name, source in inputs:
            if path.exists() and os.path.samefile(path, source):
                raise HybridPKError(
                    f"{flag} {path} is also the input {name}: writing it would lose that "
                    "input; give another name"
                )
        key = path.resolve()
        if key in seen:
            raise HybridPKError(f"{flag} and {seen[key]} are one file, {path}: give each its own")
        seen[key] = flag
    _check_folders(outputs)


def _check_folders(outputs: list[tuple[str, Path, str]]) -> None:
    """No file output inside a folder output: the folder's files are the command's to
    name (``--json R/report.md --report R`` would leave one of the two)."""
    folders = [(flag, path.resolve()) for flag, path, kind in outputs if kind == "folder"]
    for flag, path, kind in outputs:
        for folder_flag, folder in folders:
            if kind == "file" and path.resolve().is_relative_to(folder):
                raise HybridPKError(
                    f"{flag} {path} is inside {folder_flag} {folder}, whose files the "
                    "command writes: give it outside that folder"
                )
