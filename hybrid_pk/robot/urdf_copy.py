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

__all__ = ["urdf_copy"]


def urdf_copy(text: str, name: str) -> Path:
    """A file holding the URDF ``text``; ``name`` (a robot or file name) starts its name."""
    digest = hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]
    folder = _folder()
    path = folder / f"{Path(name).name or 'robot'}-{digest}.urdf"
    if path.is_file() and path.read_text(encoding="utf-8") == text:
        return path
    fd, partial = tempfile.mkstemp(dir=folder, prefix=f".{path.stem}.", suffix=".part")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(partial, path)
    finally:
        if os.path.exists(partial):
            os.unlink(partial)
    return path


def _folder() -> Path:
    home = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    folder = Path(home) / "hybrid_pk" / "urdf"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        return folder
    except OSError:
        return Path(tempfile.mkdtemp(prefix="hybrid_pk_urdf_"))  # read-only home
