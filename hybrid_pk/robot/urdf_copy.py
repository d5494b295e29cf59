"""URDF text kept as a file: the robot's FK reads a URDF file, and a robot made from a
DH table or loaded from a model file has only the text.

One copy per content (named by its hash) in a per-user cache folder
(``$XDG_CACHE_HOME/hybrid_pk/urdf``, else ``~/.cache/...``; a private temporary folder
where the home is read-only), written whole and then renamed, so no reader ever sees a
half-written URDF and two processes writing the same text agree.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

__all__ = ["cache_folder", "urdf_copy", "write_whole"]


def urdf_copy(text: str, name: str) -> Path:
    """A file holding the URDF ``text``; ``name`` (a robot or file name) starts its name."""
    digest = hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]
    folder = cache_folder("urdf")  # a private temporary folder at worst, never None
    path = Path(folder) / f"{Path(name).name or 'robot'}-{digest}.urdf"
    if path.is_file() and path.read_text(encoding="utf-8") == text:
        return path
    write_whole(path, text)
    return path


def write_whole(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` whole: into a temporary file beside it, then renamed."""
    fd, partial = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".part")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(partial, path)
    finally:
        if os.path.exists(partial):
            os.unlink(partial)


def cache_folder(kind: str, temporary: bool = True) -> Path | None:
    """The per-user cache folder ``kind`` (``$XDG_CACHE_HOME/hybrid_pk/KIND``, else
    ``~/.cache/hybrid_pk/KIND``); where that cannot be made, a private temporary folder
    (``temporary``) or None."""
    home = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    folder = Path(home) / "hybrid_pk" / kind
    try:
        folder.mkdir(parents=True, exist_ok=True)
        return folder
    except OSError:  # a read-only home
        return Path(tempfile.mkdtemp(prefix=f"hybrid_pk_{kind}_")) if temporary else None
