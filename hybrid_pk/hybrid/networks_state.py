"""The ``networks`` entry of a model file: residual networks as tensors and plain data.

Format (``format: hybrid_pk.residual_networks``)::

    {"format": ..., "version": 1 to 4, "joint_names": [...],
     "frame": "flange origin, joint-1 axes",
     "input": {"lower", "upper", "trust_lower", "trust_upper": (dof,) tensors,
               "fade": float}                     the paper's inputs (InputBox), or None
     "features": {"kind": "physics", "frame": k, "gravity_input": bool,
                  "wrench": str, "angles": [first, last] or None, "gravity": (3,),
                  "shift", "scale": (F,)}
               or {"kind": "local", "joint_1_angle": bool, "gravity": (3,),
                   "shift", "scale": (dof, 8)} or None,
     "coverage": {"reference": (M, F) or (dof, M, F), "radius_in", "radius_out":
                  () or (dof,) tensors, "neighbours": int} or None,
     "position" / "orientation": {"arch": str, "scale": (3,) tensor,
                                  "dtype": str, "state_dict": {...}} or None,
     "spread": {"position", "orientation": (3,) tensors} or None,
     "gate": {"input": {...as above}, "coverage": {...as above}} or None,
     "blocked": {"mode": "gated" | "free" | "shrunk", "physics", "gated", "free",
                 "shrunk": {"position_mm", "orientation_deg", "rows"}, "blocks": [...],
                 "families": {family: {"rows", "gain", "se", "z", "beats"}}}
                or None,
     "stages": [{"role": "cascade" or "refine", "input", "features", "coverage",
                 "spread", "gate", "blocked", "position", "orientation"}, ...],
                                                   the stages after the first
     "training": {...}}

Version 1 (hybrid_pk before issue 13) has only ``input``; it is still written for the
paper's inputs without a coverage in one stage, so older installations read such
files. Version 2 adds ``features``, ``coverage`` and ``stages``; version 3 ``spread``
(written only when a stage has one: an older reader would silently drop the shrink);
version 4 ``gate`` and ``blocked`` (issue 27: a stage's trust in joint space and the
blocked hold-out test that set or lifted it; written only when a stage has one).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence

import torch

from hybrid_pk.errors import ModelFileError
from hybrid_pk.hybrid.blocked_trust import JointGate
from hybrid_pk.hybrid.coverage import Coverage
from hybrid_pk.hybrid.features import PhysicsFeatures
from hybrid_pk.hybrid.inputs import InputBox
from hybrid_pk.hybrid.local import LocalFeatures, LocalHead
from hybrid_pk.hybrid.nets import ResidualHead
from hybrid_pk.hybrid.spread import TargetSpread
from hybrid_pk.hybrid.stage import ResidualStage
from hybrid_pk.robot import Robot

__all__ = ["NETWORKS_FORMAT", "NETWORKS_VERSION", "networks_state", "stages_from_state"]

NETWORKS_FORMAT = "hybrid_pk.residual_networks"
NETWORKS_VERSION = 4


def _head_state(h: ResidualHead | LocalHead | None) -> dict | None:
    if h is None:
        return None
    net = h.nets if isinstance(h, LocalHead) else h.net
    sd = OrderedDict((k, v.detach().cpu().clone()) for k, v in net.state_dict().items())
    return {
        "arch": h.arch,
        "scale": h.scale.detach().cpu().clone(),
        "dtype": str(h.net_dtype).removeprefix("torch."),
        "state_dict": sd,
    }


def _stage_state(stage: ResidualStage) -> dict:
    box = stage.box
    return {
        "role": stage.role,
        "input": None if box is None else box.state(),
        "features": None if box is not None else stage.inputs.state(),
        "coverage": None if stage.coverage is None else stage.coverage.state(),
        "spread": None if stage.spread is None else stage.spread.state(),
        "gate": None if stage.gate is None else stage.gate.state(),
        "blocked": None if stage.blocked is None else dict(stage.blocked),
        "position": _head_state(stage.position),
        "orientation": _head_state(stage.orientation),
    }


def networks_state(
    joint_names: Sequence[str], stages: Sequence[ResidualStage], metadata: dict | None = None
) -> dict:
    """The ``networks`` entry for these stages (see the module docstring).

    Args:
        joint_names: the robot's joints (checked on loading).
        stages: the hybrid model's stages; the first one's entries are at the top level,
            the others in ``stages``.
        metadata: plain values stored as ``training``.
    """
    first = _stage_state(stages[0])
    plain = first["input"] is not None and first["coverage"] is None and len(stages) == 1
    spread = any(stage.spread is not None for stage in stages)
    gated = any(stage.gate is not None or stage.blocked is not None for stage in stages)
    state = {
        "format": NETWORKS_FORMAT,
        "version": 1 if plain else 4 if gated else 3 if spread else 2,
        "joint_names": list(joint_names),
        "frame": "flange origin, joint-1 axes",
        "input": first["input"],
        "position": first["position"],
        "orientation": first["orientation"],
        "training": dict(metadata or {}),
    }
    if not plain:
        state["features"] = first["features"]
        state["coverage"] = first["coverage"]
        if spread or gated:
            state["spread"] = first["spread"]
        if gated:
            state["gate"], state["blocked"] = first["gate"], first["blocked"]
        state["stages"] = [_stage_state(stage) for stage in stages[1:]]
    return state


def _check_header(robot: Robot, state: dict, source: str) -> int:
    if not isinstance(state, dict) or state.get("format") != NETWORKS_FORMAT:
        raise ModelFileError(f"{source}: its networks are not hybrid_pk residual networks")
    version = int(state.get("version", 0))
    if version > NETWORKS_VERSION:
        raise ModelFileError(
            f"{source}: residual networks of format version {version}; this "
            f"hybrid_pk reads up to {NETWORKS_VERSION}: upgrade hybrid_pk"
        )
    joints = list(state["joint_names"])
    if joints != list(robot.joint_names):
        raise ModelFileError(
            f"{source}: its residual networks were trained for joints {joints}, the "
            f"model's robot {robot.name!r} has {robot.joint_names}"
        )
    return version


def _head(
    entry: dict | None, inputs, n_inputs: int, name: str, source: str
) -> ResidualHead | LocalHead | None:
    if entry is None:
        return None
    if isinstance(inputs, LocalFeatures):
        h = LocalHead(entry["arch"], inputs.dof, entry["scale"])
        net = h.nets
    else:
        h = ResidualHead(entry["arch"], n_inputs, entry["scale"])
        net = h.net
    net.to(getattr(torch, entry.get("dtype", "float32")))
    try:
        net.load_state_dict(entry["state_dict"])
    except RuntimeError as exc:
        raise ModelFileError(
            f"{source}: the {name} network does not match its architecture "
            f"{entry['arch']!r}: {' '.join(str(exc).split())[:200]}"
        ) from exc
    return h


def _stage_from_state(robot: Robot, entry: dict, source: str) -> ResidualStage:
    features = entry.get("features")
    inputs: InputBox | PhysicsFeatures | LocalFeatures
    if features is None:
        inputs, n_inputs = InputBox.from_state(entry["input"]), robot.dof
    elif features.get("kind") == "physics":
        inputs = PhysicsFeatures.from_state(features, robot)
        n_inputs = inputs.n_features
    elif features.get("kind") == "local":
        inputs, n_inputs = LocalFeatures.from_state(features, robot), 0
    else:
        raise ModelFileError(f"{source}: unknown network inputs {features.get('kind')!r}")
    cov, spread, gate = entry.get("coverage"), entry.get("spread"), entry.get("gate")
    heads = {
        k: _head(entry.get(k), inputs, n_inputs, k, source) for k in ("position", "orientation")
    }
    return ResidualStage(
        inputs,
        heads["position"],
        heads["orientation"],
        None if cov is None else Coverage.from_state(cov),
        entry.get("role", "cascade"),
        None if spread is None else TargetSpread.from_state(spread),
        None if gate is None else JointGate.from_state(gate),
        entry.get("blocked"),
    )


def stages_from_state(robot: Robot, state: dict, source: str = "model file") -> list[ResidualStage]:
    """The stages of a ``networks`` entry (format 1 to 4) for ``robot``.

    Raises:
        ModelFileError: not a networks entry, a newer version, networks made for other
            joints, or a network that does not match its architecture.
    """
    version = _check_header(robot, state, source)
    if version < 2:
        first = {k: state.get(k) for k in ("input", "position", "orientation")}
        return [_stage_from_state(robot, first, source)]
    stages = [_stage_from_state(robot, state, source)]
    return stages + [_stage_from_state(robot, e, source) for e in state.get("stages") or []]
