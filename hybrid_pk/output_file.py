"""Writing an output file without losing the one it replaces.

Every file the tool writes (tables, JSON, URDF, DH tables, controller files, reports,
model files) is first written in full to a temporary file beside it, then renamed over
it in one step (``os.replace`` is atomic within a folder). A write that fails (a full
disk, a file-size limit, an interrupt) leaves the old file as it was and no partial
one, and is one line naming the path::

    with replacing("campaign.csv") as tmp:
        frame.to_csv(tmp)          # any writer that takes a path

The temporary file keeps the target's suffix, so writers that choose a format by the
extension (pandas, matplotlib) see the same one.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from hybrid_pk.errors import HybridPKError

__all__ = ["OutputError", "json_text", "read_only", "replacing", "write_text"]


class OutputError(HybridPKError, OSError):
    """An output file that could not be written; what was there before is kept."""


# A file name's limit on every common file system, and what the temporary name adds to
# the target's: the leading dot, a dot, mkstemp's 8 random characters.
_NAME_MAX = 255
_TEMP_EXTRA = 10


def _in_place(path: Path) -> bool:
    """A target that is not a plain file (a device, a pipe, a terminal; ``/dev/stdout``
    even where it leads to a file, as the shell's redirection holds it open): written in
    place, there is no file to keep."""
    if path.parts[:2] in (("/", "dev"), ("/", "proc")):
        return True
    return path.exists() and not path.is_file()


def read_only(path: Path) -> bool:
    """A file this process may not write, or one without any write permission: the
    rename would replace it where a plain ``open`` is refused (and root, who may open
    anything, still finds the file marked as not to be written)."""
    return not os.access(path, os.W_OK) or not path.stat().st_mode & 0o222


def _mode(path: Path) -> int:
    """The permissions the file gets: those of the file it replaces, else what a plain
    ``open(path, "w")`` would give under the process' umask (``mkstemp`` makes 0600)."""
    if path.exists():
        return path.stat().st_mode & 0o7777
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


@contextmanager
def replacing(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` to write the whole file to; once the block ends
    without error it replaces ``path``. On any error the temporary file is removed and
    ``path`` is left as it was; an OS error (disk full, file too large, permission)
    becomes an :class:`OutputError` naming ``path``. Missing parent folders are made."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{path} is a folder; give a file name")
    if _in_place(path):  # a device, a pipe, /dev/stdout: written as it is
        try:
            yield path
        except OSError as exc:
            raise _failed(path, exc, existed=False) from None
        return
    if path.is_symlink():  # write where the link points, and keep the link
        path = path.resolve()
    existed = path.exists()
    if existed and read_only(path):
        raise OutputError(f"{path}: cannot write it (the file is read-only); it is unchanged")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        stem = path.name[: _NAME_MAX - _TEMP_EXTRA - len(path.suffix)]  # room for the rest
        fd, name = tempfile.mkstemp(prefix=f".{stem}.", suffix=path.suffix, dir=path.parent)
        os.close(fd)
    except OSError as exc:
        raise _failed(path, exc, existed) from None
    tmp = Path(name)
    try:
        yield tmp
        os.chmod(tmp, _mode(path))
        os.replace(tmp, path)
    except OutputError:  # a nested output's own error already names its file
        raise
    except OSError as exc:
        raise _failed(path, exc, existed) from None
    finally:
        if tmp.exists():
            tmp.unlink()


def _failed(path: Path, exc: OSError, existed: bool) -> OutputError:
    reason = exc.strerror or str(exc)
    kept = "the file there is unchanged" if existed else "nothing was written"
    return OutputError(f"{path}: cannot write it ({reason}); {kept}")


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` through :func:`replacing`; returns ``path``."""
    path = Path(path)
    with replacing(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


def json_text(obj: object) -> str:
    """``obj`` as the tool's JSON outputs are written: indented, NaN and inf refused
    (they are not JSON), a final newline."""
    return json.dumps(obj, indent=2, allow_nan=False) + "\n"
