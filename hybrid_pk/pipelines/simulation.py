"""The simulate workflow: a virtual measurement campaign
(:func:`~hybrid_pk.simulate.simulate_campaign`) written as a table plus its truth JSON,
and what a calibration of it could tell about its frames.

    res = simulate_to_files(robot, "sim.csv", 500, effects, noise_mm=0.05)
"""

from __future__ import annotations

import json
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch

from hybrid_pk.calibration.fit import fit
from hybrid_pk.calibration.frames import MAX_TOOL_TRANSLATION_M, FrameSpec
from hybrid_pk.data import MeasuredData
from hybrid_pk.data.table import write_table
from hybrid_pk.effects import (
    ExtendedModel,
    conditions_from_data,
    entry_label,
    make_effect,
    unloaded_reason,
)
from hybrid_pk.errors import DataError
from hybrid_pk.output_file import replacing
from hybrid_pk.pipelines.calibration import FRAME_LABELS
from hybrid_pk.robot import Robot
from hybrid_pk.simulate import simulate_campaign

__all__ = [
    "SimulationResult",
    "beyond_credible_lines",
    "campaign_frame_lines",
    "simulate_to_files",
    "table_path",
    "truth_path",
    "unseen_lines",
]

TABLE_SUFFIXES = (".csv", ".parquet", ".pq")


@dataclass(frozen=True)
class SimulationResult:
    """What :func:`simulate_to_files` returns: the rows, the truth document, the two
    files written and the notes on the campaign's frames (:func:`campaign_frame_lines`)."""

    data: MeasuredData
    truth: dict
    table: Path
    truth_file: Path
    frame_lines: list[str]


def table_path(out: str | os.PathLike) -> Path:
    """``out`` as a table path (.csv, .parquet or .pq; else a :class:`DataError`)."""
    out = Path(out)
    if out.suffix.lower() not in TABLE_SUFFIXES:
        raise DataError(
            f"unsupported file type {out.suffix!r}; expected .csv, .parquet or .pq", file=str(out)
        )
    return out


def truth_path(out: str | os.PathLike) -> Path:
    """``FILE.truth.json`` next to the table ``FILE``."""
    return Path(f"{out}.truth.json")


def _given_frames(base: FrameSpec | None, tool: FrameSpec | None) -> dict:
    """``base``/``tool`` keywords: a transform, or a translation whose rotation the
    campaign draws."""
    out = {}
    for name, spec in (("base", base), ("tool", tool)):
        if spec is not None:
            out[name] = spec.translation if spec.rotation is None else spec.matrix(torch.eye(4))
    return out


def simulate_to_files(
    robot: Robot,
    out: str | os.PathLike,
    n: int | None,
    effects,
    *,
    base: FrameSpec | None = None,
    tool: FrameSpec | None = None,
    **campaign,
) -> SimulationResult:
    """Simulate a campaign of ``robot`` (``n``, ``effects`` and ``campaign`` as in
    :func:`~hybrid_pk.simulate.simulate_campaign`; ``base``/``tool`` the given frames)
    and write the table ``out`` and its ``FILE.truth.json``."""
    out = table_path(out)
    data, truth = simulate_campaign(robot, n, effects, **campaign, **_given_frames(base, tool))
    truth_file = truth_path(out)
    with replacing(truth_file) as tmp:  # the truth written in full before the table is touched
        tmp.write_text(json.dumps(truth, indent=2) + "\n", encoding="utf-8")
        write_table(out, data)
    lines = campaign_frame_lines(robot, data, truth, tool)
    return SimulationResult(data, truth, out, truth_file, lines)


def campaign_frame_lines(robot: Robot, data, truth: dict, tool_spec) -> list[str]:
    """What a calibration of this campaign could tell about its frames: a frames-only
    fit from the true frames (at most 2000 rows), and the plausibility of the tool."""
    base = torch.tensor(truth["base_frame"], dtype=torch.float64)
    tool = torch.tensor(truth["tool_frame"], dtype=torch.float64)
    lines = []
    if tool_spec is not None and float(tool[:3, 3].norm()) > MAX_TOOL_TRANSLATION_M:
        lines.append(
            f"warning: --tool puts the measured point {float(tool[:3, 3].norm()):.3g} m "
            f"from the flange, beyond what a tracker target can be "
            f"({MAX_TOOL_TRANSLATION_M:g} m); calibrations will flag such a tool"
        )
    rows = data.subset(slice(0, None, max(1, data.n // 2000)))  # a frames-only fit's worth
    if rows.n < 3:
        return lines
    model = ExtendedModel(robot, base=base, tool=tool)
    noise = max(float(truth["noise_mm"]), 1e-3)
    noise_rad = max(math.radians(float(truth["noise_deg"])), 1e-5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = fit(
            model, rows, free=list(FRAME_LABELS["frames"]), sigma_pos_mm=noise,
            sigma_rot_rad=noise_rad, max_iter=5,
        )  # fmt: skip
    for d in res.frame_report.directions:
        lines.append(f"note: in this campaign the {d['summary']}")
    return lines


def beyond_credible_lines(robot, truth: dict) -> list[str]:
    """``note:`` lines for the injected effects larger than such an effect can credibly
    be (:func:`~hybrid_pk.effects.limits.effect_limit`: 5 degrees where degrees were
    meant as radians, say): a diagnosis reports a model that far off as structurally
    wrong, not as a cause."""
    from hybrid_pk.effects.limits import effect_limit

    lines = []
    for e in truth["effects"]:
        label = entry_label(e)
        limit = effect_limit(make_effect(robot, label), robot)
        size = float(torch.tensor(e["value"], dtype=torch.float64).norm())
        if limit is not None and size > limit:
            lines.append(
                f"note: {label} = {size:.4g} {e['unit']} is beyond what such an effect can "
                f"credibly be ({limit:.3g} {e['unit']}): a diagnosis of these rows reports "
                "the model as structurally wrong, not this as a cause"
            )
    return lines


def unseen_lines(robot, data, truth: dict) -> list[str]:
    """``note:`` lines for the injected effects whose part no data can see (the frames
    absorb it; a diagnosis reports ~0 there), judged with the true frames."""
    from hybrid_pk.calibration.diagnosis.unseen import mark_unseen

    if data.n < 3:
        return []
    entries, lines = truth["effects"], []
    unloaded = unloaded_reason(robot, data.payload)
    if unloaded:  # what moves nothing is not absorbed by the frames: it is not there
        labels = [entry_label(e) for e in entries]
        injected = ExtendedModel(robot, [make_effect(robot, label) for label in labels])
        loaded = {e.label for e in injected.loaded_effects()}
        lines = [f"note: {', '.join(sorted(loaded))}: {unloaded}"] if loaded else []
        entries = [e for e, label in zip(entries, labels, strict=True) if label not in loaded]
    frames = {k: torch.tensor(truth[f"{k}_frame"], dtype=torch.float64) for k in ("base", "tool")}
    nominal = ExtendedModel(robot, **frames)
    marked = mark_unseen(nominal, data, conditions_from_data(data), entries)
    return lines + [
        f"note: {e['effect']}:{e.get('joint')} ({e['unseen']['words']}): no diagnosis of "
        "these data can find that part"
        for e in marked
        if e.get("unseen")
    ]
