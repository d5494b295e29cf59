"""Chain specs read before, kept on disk: a robot loads without reading its URDF again.

Reading a URDF takes pytorch-kinematics and yourdfpy, whose imports alone cost ~1.5 s of
every command's start (of ~4 s). The :class:`~.chain_spec.ChainSpec` of a file read once
is kept as JSON in the per-user cache (``$XDG_CACHE_HOME/hybrid_pk/spec``), named by a
hash of the URDF's bytes, the end link asked for, the source of the reader itself and
the readers' versions (a changed reader never meets a spec of the old one). JSON keeps
every float64 digit (a float is written as its shortest exact repr). A file that cannot
be read or written is ignored: the URDF is read as before. ``HYBRID_PK_SPEC_CACHE=off``
turns the cache off.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
from importlib import metadata
from pathlib import Path

import numpy as np

from hybrid_pk.robot.urdf_copy import cache_folder, write_whole

__all__ = ["ENV", "cached_spec", "keep_spec"]

ENV = "HYBRID_PK_SPEC_CACHE"
# the modules whose source decides what a spec holds, and the packages that read the URDF
_READER = [Path(__file__).with_name("chain_spec.py"), Path(__file__)]
_READERS = ("pytorch-kinematics", "yourdfpy")


def _key(urdf: Path, end_link: str | None) -> str | None:
    if os.environ.get(ENV, "").lower() in ("off", "0", "no", "false"):
        return None
    reader = _reader_digest()
    try:
        digest = hashlib.sha256(urdf.read_bytes())
    except OSError:
        return None
    if reader is None:
        return None
    digest.update(f"{end_link!r} {reader}".encode())
    return digest.hexdigest()[:32]


@functools.cache
def _reader_digest() -> str | None:
    """Hash of the reader's source and the URDF readers' versions (once per process: a
    new release of a reader may read the same file otherwise); None where unknown."""
    digest = hashlib.sha256()
    try:
        for source in _READER:
            digest.update(source.read_bytes())
        for reader in _READERS:
            digest.update(f"{reader} {metadata.version(reader)}".encode())
    except (OSError, metadata.PackageNotFoundError):
        return None
    return digest.hexdigest()


def cached_spec(urdf: Path, end_link: str | None, spec_type, branch_type):
    """The spec kept for ``urdf`` (its bytes now) and ``end_link``, with ``urdf_path`` set
    to ``urdf``; None where none is kept (or the cache is off or unreadable)."""
    key, folder = _key(urdf, end_link), cache_folder("spec", temporary=False)
    if key is None or folder is None:
        return None
    try:
        fields = json.loads((folder / f"{key}.json").read_text(encoding="utf-8"))
        branches = tuple(branch_type(**_arrays(b)) for b in fields.pop("branches"))
        spec = spec_type(**_arrays(fields), branches=branches)
    except (OSError, ValueError, TypeError, KeyError):
        return None
    return dataclasses.replace(spec, urdf_path=str(urdf))


def keep_spec(urdf: Path, end_link: str | None, spec) -> None:
    """Keep ``spec``, read from ``urdf`` for ``end_link``, for the next :func:`cached_spec`."""
    key, folder = _key(urdf, end_link), cache_folder("spec", temporary=False)
    if key is None or folder is None:
        return  # no cache folder (a read-only home): the URDF is read every time
    fields = _plain(dataclasses.asdict(spec))
    try:
        write_whole(folder / f"{key}.json", json.dumps(fields))
    except OSError:
        pass  # a read-only cache: read the URDF next time as well


def _plain(value):
    """``value`` with its numpy arrays as ``{"array": nested lists, "dtype", "shape"}``."""
    if isinstance(value, np.ndarray):
        return {"array": value.tolist(), "dtype": str(value.dtype), "shape": value.shape}
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _arrays(fields: dict) -> dict:
    """:func:`_plain`'s fields back as numpy arrays and tuples (the spec's types)."""
    out = {}
    for k, v in fields.items():
        if isinstance(v, dict) and "array" in v:
            v = np.array(v["array"], dtype=v["dtype"]).reshape(v["shape"])
        elif isinstance(v, list):
            v = tuple(v)
        out[k] = v
    return out
