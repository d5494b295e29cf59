"""The plan workflow: the named effects checked, a D-optimal set of poses
(:func:`~hybrid_pk.calibration.planning.plan_poses`) written as a joint table, and the
plan's JSON document (predicted 1-sigma per parameter beside random poses).

    res = plan_to_file(robot, 60, labels, "poses.csv")  # labels: effect:joint
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from hybrid_pk.calibration.planning import Plan, plan_poses
from hybrid_pk.data.joint_table import write_joint_table
from hybrid_pk.effects import make_effect
from hybrid_pk.errors import HybridPKError
from hybrid_pk.output_file import json_text, replacing
from hybrid_pk.robot import Robot

__all__ = ["PlanResult", "parameter_units", "plan_to_file"]


@dataclass(frozen=True)
class PlanResult:
    """What :func:`plan_to_file` returns: the plan, the effect labels planned for and
    the settings it was made with; :meth:`document` is its JSON."""

    plan: Plan
    labels: list[str]
    settings: dict
    out: str

    def document(self, robot_name: str) -> dict:
        """The plan as JSON (std per parameter, condition numbers, settings)."""
        plan, s = self.plan, self.settings

        def finite(v: float) -> float | None:
            return v if math.isfinite(v) else None

        rows = zip(
            plan.names, parameter_units(plan), plan.planned.std.tolist(),
            plan.random.std.tolist(), strict=True,
        )  # fmt: skip
        return {
            "robot": robot_name,
            "n": int(plan.q.shape[0]),
            "candidates": plan.candidates,
            "criterion": s.get("criterion", "d"),
            "seed": s.get("seed", 0),
            "effects": self.labels,
            "left_out": [{"effect": e, "reason": why} for e, why in plan.left_out],
            "noise_mm": s.get("noise_mm", 0.02),
            "noise_deg": None if s.get("position_only") else s.get("noise_deg", 0.002),
            "payload": s.get("payload", 0.0),
            "parameters": [
                {"name": name, "unit": unit, "planned_std": finite(a), "random_std": finite(b)}
                for name, unit, a, b in rows
            ],
            "condition": {"planned": plan.planned.condition, "random": plan.random.condition},
            "position_rms_mm": {
                "planned": finite(plan.planned.position_rms_mm),
                "random": finite(plan.random.position_rms_mm),
            },
            "poses": self.out,
        }


def parameter_units(plan: Plan) -> list[str]:
    """The unit of each of the plan's parameters."""
    return [b.unit for b in plan.blocks for _ in range(b.size)]


def plan_to_file(
    robot: Robot,
    n: int,
    labels: Sequence[str],
    out: str | os.PathLike,
    *,
    box: Mapping[str, tuple[float, float]] | None = None,
    progress=None,
    json_out: tuple[str | os.PathLike, str] | None = None,
    **settings,
) -> PlanResult:
    """Plan ``n`` poses for the frames and the effects ``labels`` (checked before any
    work) and write them to ``out``; ``settings``: :func:`plan_poses`' keywords.
    ``json_out``: ``(path, robot name)`` of the plan's JSON document as well, the two
    files written both or neither where a write fails (the JSON in full first).

    Raises:
        HybridPKError: an unknown effect or joint, or a noise that is not positive.
    """
    for label in labels:  # unknown kinds / joints fail before any work
        make_effect(robot, label)
    noise_mm, noise_deg = settings.get("noise_mm", 0.02), settings.get("noise_deg", 0.002)
    if noise_mm <= 0 or (not settings.get("position_only") and noise_deg <= 0):
        raise HybridPKError("--noise-mm and --noise-deg must be positive")
    plan = plan_poses(robot, n, effects=list(labels), box=box, progress=progress, **settings)
    result = PlanResult(plan, list(labels), dict(settings), str(out))
    if json_out is None:
        write_joint_table(out, plan.q, robot.joint_names)
        return result
    document = json_text(result.document(json_out[1]))
    with replacing(json_out[0]) as tmp:
        tmp.write_text(document, encoding="utf-8")
        write_joint_table(out, plan.q, robot.joint_names)
    return result
