"""The operating conditions an IK target is solved under, stated when not given.

A model with backlash maps a commanded joint value to a true one that depends on the
side the joint approaches from: ``theta_true = theta + (b / 2) * direction``. Measured
rows have a direction (their acquisition order, :func:`~hybrid_pk.effects.
approach_direction`); an IK target does not, unless the caller says how the robot will
approach it. So the IK functions take ``approach``:

- ``None`` (default): the directions of ``cond`` if it has them, else the **mid-play**
  model (direction 0: half-way between both approaches, at most ``b / 2`` from either);
- ``+1`` / ``-1`` (or ``"+"`` / ``"-"``): every backlash joint arrives moving in its
  positive / negative direction; ``0`` or ``"mid"``: mid-play;
- a mapping ``{"joint_3": +1, ...}``: per joint (joints not named: mid-play);
- a tensor ``(dof,)`` or ``(N, dof)`` of +1 / -1 / 0 per joint (and per target).

Likewise a model with thermal expansion is solved at the reference temperature
(20 °C) and a compliant one at 0 kg payload when ``cond`` gives none. Whatever was
assumed is said once, as an :class:`IKAssumption` warning, and kept in the result's
``info["assumed"]``.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import replace

import torch
from torch import Tensor

from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.effects.geometric import REFERENCE_TEMPERATURE
from hybrid_pk.effects.joint import Backlash
from hybrid_pk.errors import HybridPKError

__all__ = ["FIXES", "Approach", "IKAssumption", "parse_approach", "resolve_conditions"]

Approach = int | str | Mapping[str, int | str] | Tensor | None

_SIDES = {"+": 1.0, "+1": 1.0, "1": 1.0, "-": -1.0, "-1": -1.0, "mid": 0.0, "0": 0.0}
# How to state each condition instead of having it assumed (callers may word it their way).
FIXES = {
    "approach": "pass approach=+1 / -1 (all backlash joints), {'joint': +1, ...} or a (dof,) "
    "tensor to state how the robot will approach the target",
    "temperature": "pass cond=Conditions(temperature=...) [°C] per target",
    "payload": "pass cond=Conditions(payload=...) [kg] per target",
}


_STATED = f"{Backlash.kind} approach as stated"  # a note, not an assumption: no warning


class IKAssumption(UserWarning):
    """An operating condition the IK had to assume (approach direction, temperature,
    payload): the message says which, and how to state it instead."""


def _base_model(model) -> ExtendedModel | None:
    """The extended model of a forward model (itself, or a hybrid model's base)."""
    if isinstance(model, ExtendedModel):
        return model
    base = getattr(model, "base", None)
    return base if isinstance(base, ExtendedModel) else None


def _needs(models: Sequence) -> tuple[ExtendedModel | None, list[str], bool, bool]:
    """(an extended model, backlash joints, needs temperature, has compliance)."""
    bases = [b for b in map(_base_model, models) if b is not None]
    joints: list[str] = []
    temperature = compliance = False
    for base in bases:
        for e in base.effects:
            if e.needs == "direction" and e.joint not in joints:
                joints.append(e.joint)
            temperature |= e.needs == "temperature"
            compliance |= e.stage == "compliance"
    return (bases[0] if bases else None), joints, temperature, compliance


def _side(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | str):
        raise HybridPKError(f"{where}: expected +1, -1, 0, '+', '-' or 'mid', got {value!r}")
    key = str(value).strip() if isinstance(value, str) else None
    if key is not None:
        if key not in _SIDES:
            raise HybridPKError(f"{where}: expected '+', '-' or 'mid', got {value!r}")
        return _SIDES[key]
    if value not in (1, -1, 0):
        raise HybridPKError(f"{where}: expected +1, -1 or 0, got {value!r}")
    return float(value)


def _direction(approach: Approach, model: ExtendedModel, joints: list[str], n: int) -> Tensor:
    """``(n, dof)`` directions of ``approach`` (backlash joints; the others 0)."""
    names = list(model.robot.joint_names)
    dof = len(names)
    if isinstance(approach, Tensor):
        d = approach.to(torch.float64)
        if d.shape not in ((dof,), (n, dof)):
            raise HybridPKError(
                f"approach: expected a ({dof},) or ({n}, {dof}) tensor of +1 / -1 / 0, found "
                f"shape {tuple(d.shape)}"
            )
        return d.expand(n, dof).clone()
    d = torch.zeros(n, dof, dtype=torch.float64)
    if isinstance(approach, Mapping):
        for joint, value in approach.items():
            if joint not in joints:
                raise HybridPKError(
                    f"approach: {joint!r} has no backlash in this model (backlash joints: "
                    f"{', '.join(joints) or 'none'})"
                )
            d[:, names.index(joint)] = _side(value, f"approach[{joint!r}]")
        return d
    side = _side(approach, "approach")
    for joint in joints:
        d[:, names.index(joint)] = side
    return d


def _describe(direction: Tensor, model: ExtendedModel, joints: list[str], fix: str | None) -> str:
    names = list(model.robot.joint_names)
    parts = []
    for joint in joints:
        values = set(direction[:, names.index(joint)].tolist())
        side = {1.0: "positive", -1.0: "negative", 0.0: "mid-play"}
        how = side[values.pop()] if len(values) == 1 else "per target"
        parts.append(f"{joint} {how}")
    if fix is None:
        return f"{_STATED}: {', '.join(parts)}"
    return (
        f"{Backlash.kind} on {', '.join(joints)} without an approach direction: solved for the "
        f"mid-play model (half-way between both approaches); {fix}"
    )


def resolve_conditions(
    models: Sequence,
    cond: Conditions | None,
    n_targets: int,
    approach: Approach = None,
    *,
    fixes: Mapping[str, str] | None = None,
) -> tuple[Conditions | None, list[str]]:
    """Conditions for IK on ``models``, with what they need and ``cond`` lacks filled in.

    Args:
        models: the forward models the IK evaluates (``ExtendedModel``, a hybrid model
            with a ``base``, ``Robot`` or any callable).
        cond: conditions per flat target, or None.
        n_targets: number of flat targets.
        approach: see the module docstring; overrides ``cond.direction``.
        fixes: how to state each assumed condition, by key of :data:`FIXES` (the
            command line words them as flags).

    Returns:
        The conditions and one line per assumption made (also warned as
        :class:`IKAssumption`); ``cond`` unchanged when nothing was missing.

    Raises:
        HybridPKError: ``approach`` that names a joint without backlash, or a value that
            is not +1 / -1 / 0.
    """
    model, joints, needs_temperature, compliance = _needs(models)
    if model is None:
        if approach is not None:
            raise HybridPKError("approach: the model has no backlash effect to apply it to")
        return cond, []
    fix = {**FIXES, **(fixes or {})}
    notes: list[str] = []
    out = cond or Conditions()
    if approach is not None and not joints:
        raise HybridPKError("approach: the model has no backlash effect to apply it to")
    if joints and (approach is not None or out.direction is None):
        direction = _direction(0 if approach is None else approach, model, joints, n_targets)
        out = replace(out, direction=direction)
        notes.append(
            _describe(direction, model, joints, None if approach is not None else fix["approach"])
        )
    if needs_temperature and out.temperature is None:
        temperature = torch.full((n_targets,), REFERENCE_TEMPERATURE, dtype=torch.float64)
        out = replace(out, temperature=temperature)
        notes.append(
            f"thermal expansion without a temperature: solved at {REFERENCE_TEMPERATURE:g} °C "
            f"(no expansion); {fix['temperature']}"
        )
    if compliance and out.payload is None:
        out = replace(out, payload=torch.zeros(n_targets, dtype=torch.float64))
        notes.append(f"joint compliance without a payload: solved at 0 kg; {fix['payload']}")
    for note in notes:
        if not note.startswith(_STATED):
            warnings.warn(note, IKAssumption, stacklevel=3)
    return (out if notes else cond), notes


def parse_approach(text: str | None) -> Approach:
    """``--approach`` of the command line: ``mid``, ``+``, ``-``, or per joint
    ``joint_3=+,joint_5=-`` (``None`` stays None: the default)."""
    if text is None:
        return None
    text = text.strip()
    if "=" not in text:
        _side(text, "--approach")
        return text
    out = {}
    for item in text.split(","):
        joint, sep, value = item.partition("=")
        if not sep or not joint.strip():
            raise HybridPKError(f"--approach: expected JOINT=+|-|mid items, got {item!r}")
        out[joint.strip()] = value.strip()
        _side(out[joint.strip()], f"--approach {joint.strip()}")
    return out
