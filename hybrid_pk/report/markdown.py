"""Markdown building blocks for reports: pipe tables, error-statistics tables, images.

Everything returns plain strings (GitHub-flavoured markdown) so that any report can
assemble them; nothing here knows about diagnosis or calibration.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

__all__ = ["fmt", "image", "markdown_table", "stats_table", "value_with_std", "with_unit"]

# Rows of :func:`stats_table`: (key in the stats dict, row label).
_STAT_ROWS = (("mean", "mean"), ("rms", "RMS"), ("p95", "p95"), ("max", "max"))


def fmt(x: object, digits: int = 4) -> str:
    """A number with ``digits`` significant digits; ``-`` for None, text as is."""
    if x is None:
        return "-"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return str(x)
    if isinstance(x, float):
        if math.isnan(x):
            return "nan"
        if math.isinf(x):
            return "inf" if x > 0 else "-inf"
        return f"{x:.{digits}g}"
    if isinstance(x, Sequence) and not isinstance(x, str):
        return "(" + ", ".join(fmt(v, digits) for v in x) + ")"
    return str(x)


def with_unit(text: str, unit: str = "") -> str:
    """``text unit``; a ratio's unit ``1`` left out (``3.5e-04 ± 8.8e-07 1`` read as a
    digit more)."""
    return f"{text} {unit}".rstrip() if unit and unit != "1" else text


def value_with_std(value: object, std: object, unit: str = "", digits: int = 4) -> str:
    """``1.998e-06 ± 6.6e-10 rad/Nm``; vectors as ``(a, b, c) ± (sa, sb, sc) m``; a
    ratio (unit ``1``) without a unit."""
    return with_unit(f"{fmt(value, digits)} ± {fmt(std, 2)}", unit)


def _cell(x: object) -> str:
    """Table cell text: numbers formatted, pipes escaped, no line breaks."""
    text = x if isinstance(x, str) else fmt(x)
    return " ".join(text.replace("|", "\\|").split())


def markdown_table(
    rows: Sequence[Sequence[object]],
    headers: Sequence[str],
    align: Sequence[str] | None = None,
) -> str:
    """A pipe table with a header separator row.

    Args:
        rows: table body, each row as many cells as ``headers`` (numbers are formatted
            with :func:`fmt`).
        headers: column titles.
        align: per column ``"l"``, ``"r"`` or ``"c"``; default text left, numbers right
            (decided from the first row).

    Returns:
        The table, ending with a newline.

    Raises:
        ValueError: if a row or ``align`` has not as many cells as there are headers (a
            separator row of another width does not render as a table).
    """
    n = len(headers)
    for i, row in enumerate(rows):
        if len(row) != n:
            raise ValueError(f"markdown_table: row {i} has {len(row)} cells, expected {n}")
    if align is None:
        first = rows[0] if rows else [""] * n
        align = [
            "r" if isinstance(c, int | float) and not isinstance(c, bool) else "l" for c in first
        ]
    if len(align) != n:
        raise ValueError(f"markdown_table: {len(align)} alignments, expected {n}")
    marks = {"l": ":---", "r": "---:", "c": ":---:"}
    lines = [
        "| " + " | ".join(_cell(h) for h in headers) + " |",
        "|" + "|".join(marks[a] for a in align) + "|",
    ]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def stats_table(columns: Mapping[str, Mapping | None], change: bool = True) -> str:
    """Error statistics side by side: one column per model, one row per statistic.

    Args:
        columns: model label -> ``{"position_mm": {mean, rms, p95, max},
            "orientation_deg": {...} | None}`` (contract sections 4 and 5).
        change: with exactly two columns, add the relative change of the second
            against the first [%].

    Returns:
        A pipe table with rows ``position mean [mm]`` … ``orientation max [deg]``;
        orientation rows are left out when no column has orientation.
    """
    labels = list(columns)
    show_change = change and len(labels) == 2
    headers = ["error", *labels] + (["change"] if show_change else [])
    rows = []
    for key, name, unit in (
        ("position_mm", "position", "mm"),
        ("orientation_deg", "orientation", "deg"),
    ):
        blocks = [(columns[c] or {}).get(key) for c in labels]
        if all(b is None for b in blocks):
            continue
        for stat, stat_name in _STAT_ROWS:
            values = [None if b is None else b.get(stat) for b in blocks]
            row: list[object] = [f"{name} {stat_name} [{unit}]", *values]
            if show_change:
                a, b = values
                row.append(
                    f"{100.0 * (b - a) / a:+.1f} %" if a not in (None, 0) and b is not None else "-"
                )
            rows.append(row)
    align = ["l"] + ["r"] * (len(headers) - 1)
    return markdown_table(rows, headers, align)


def image(path: str | Path, alt: str, relative_to: str | Path | None = None) -> str:
    """A markdown image link; ``path`` is written relative to ``relative_to`` (the
    folder of the markdown file) so the report can be moved as a whole."""
    p = Path(path)
    if relative_to is not None:
        p = Path(os.path.relpath(p, Path(relative_to)))
    return f"![{alt.replace(']', ')')}]({p.as_posix()})"
