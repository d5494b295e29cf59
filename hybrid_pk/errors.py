"""One small exception hierarchy for everything raised at the public boundary.

Messages say what was expected, what was found, and where (file, row, column,
joint name). The CLI prints ``str(error)`` as a single line and exits non-zero.
"""

from __future__ import annotations

import difflib


class HybridPKError(Exception):
    """Base class of every error hybrid_pk raises on purpose."""


class RobotModelError(HybridPKError):
    """A URDF or robot name that cannot be turned into a serial chain."""


class InvalidFrame(RobotModelError):
    """A link name that is not in the model; lists the valid names."""

    def __init__(
        self, name: str, valid: list[str], what: str = "link", file: str | None = None
    ) -> None:
        close = difflib.get_close_matches(name, valid, n=1)
        hint = f" (close match: {close[0]!r})" if close else ""
        where = f"{file}: " if file else ""
        super().__init__(f"{where}unknown {what} {name!r}{hint}; valid {what}s: {', '.join(valid)}")
        self.name = name
        self.valid = valid


class TrainingInterrupted(HybridPKError):
    """A training stopped by Ctrl-C (SIGINT) or SIGTERM; the message says what was kept
    and how to continue. ``exit_code``: 130 (SIGINT) or 143 (SIGTERM), the shell's."""

    def __init__(self, message: str, exit_code: int) -> None:
        super().__init__(message)
        self.exit_code = exit_code


class DataError(HybridPKError):
    """Bad measured data. ``file``, ``row`` (1-based data row) and ``column`` locate it."""

    def __init__(
        self,
        message: str,
        *,
        file: str | None = None,
        row: int | None = None,
        column: str | None = None,
    ) -> None:
        self.file = file
        self.row = row
        self.column = column
        self.reason = message
        where = []
        if file is not None:
            where.append(str(file))
        if row is not None:
            where.append(f"row {row}")
        if column is not None:
            where.append(f"column {column!r}")
        prefix = ", ".join(where)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class ModelFileError(HybridPKError):
    """A model file that cannot be loaded, or was made for another robot."""


class ShapeError(HybridPKError, ValueError):
    """A tensor argument with the wrong shape or dtype (says expected and found)."""


def missing_file(path, what: str = "file") -> str:
    """Why ``path`` cannot be read as a ``what``: it is a folder, or it is not there."""
    import os

    return f"is a folder, not a {what}" if os.path.isdir(path) else f"{what} not found"


def not_utf8_error(path, table: bool = True) -> DataError:
    """The error for a file that is not UTF-8 text, at its first undecodable byte: of a
    CSV ``table`` the data row it is in (or the header), else its line."""
    from pathlib import Path

    raw = Path(path).read_bytes()
    try:
        raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        at = exc.start + (3 if raw.startswith(b"\xef\xbb\xbf") else 0)
        line = raw[:at].count(b"\n")  # 0: the header
        what = f"byte 0x{raw[at]:02x} (at byte {at}) is not UTF-8 text"
        if not table:
            return DataError(f"line {line + 1}: {what}: save it as UTF-8", file=str(path))
        fix = "save the table as UTF-8 (e.g. 'CSV UTF-8')"
        if line == 0:
            return DataError(f"the header: {what}: {fix}", file=str(path))
        return DataError(f"{what}: {fix}", file=str(path), row=line)
    return DataError("not UTF-8 text", file=str(path))  # decodes whole: a reader's limit
