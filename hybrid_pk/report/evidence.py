"""Evidence for a named cause: the measured residuals, seen through the cause's law.

The points of an evidence plot are a *partial residual* (the regression diagnostic of
that name): ``r = p_meas - p_model`` of the diagnosed model *without* this cause
(URDF + the jointly fitted base and tool frames + every other cause), on all rows.
It is the measured error that is left for this cause to explain; the law drawn over
it uses the diagnosed value, so the points follow the line only if the data carry it
(a spurious cause leaves a flat cloud around zero). The nominal model's own residual
(frames fitted without any cause) is not plotted because its frames absorb part of
the effect and flatten the law (a compliance of joint 2 shows about 60 % of its slope
there); how much of the law it shows is reported as ``nominal_points_value``.

The residual is rotated into the robot root frame with the base rotation, then reduced
to one number per row that the cause's law predicts:

- joint effects (offset, gear ratio, eccentricity, backlash, compliance): the
  equivalent joint-angle error ``e_j = (J_j . r) / |J_j|^2`` [rad], where ``J_j`` is
  the velocity of the measured point per unit motion of joint ``j`` at the commanded
  ``q`` (``v_point = v_end + omega x (p_point - p_end)``). Plotted against the law's
  variable: ``theta_j`` (offset, gear ratio, eccentricity), the approach direction
  (backlash), the gravity torque acting on the joint ``-g_j(q, payload)`` [Nm]
  (compliance).
- thermal expansion: the equivalent strain ``(p_end . r) / |p_end|^2`` (scaling every
  link translation by ``1 + eps`` moves the flange by ``eps p_end``) against
  temperature.
- deflection (tilt compliance, column bending): the tilt about the two axes
  perpendicular to the joint that the residual shows against the tilt the gravity
  moment predicts, a slope-1 line (``evidence_deflection.py``).
- geometric effects (link length, axis misalignment): the displacement ``d`` the fitted
  effect makes at each row; every coordinate of the residual against the same
  coordinate of ``d``, a slope-1 line if the effect is there. Both are taken without
  the part that a change of the base and tool frames makes (projected off the frames'
  columns), so the plot shows the effect's physical signature, not a trade-off with
  the frames. (Not the residual along ``d`` against ``|d|``: a link-length error moves
  the point by the same distance at every row, in a direction that turns with the arm,
  so ``|d|`` does not vary.)

Rows where the joint barely moves the measured point (``|J_j|`` under 20 % of its
median) say nothing about that joint and are left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor

from hybrid_pk.calibration.diagnosis.frame_share import off_frames
from hybrid_pk.calibration.diagnosis.statistics import equivalent_angle_error
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.effects.geometric import REFERENCE_TEMPERATURE
from hybrid_pk.effects.joint import GearRatio, JointEccentricity, JointOffset
from hybrid_pk.errors import HybridPKError
from hybrid_pk.evaluation.plots import binned_median
from hybrid_pk.report.evidence_deflection import deflection_evidence
from hybrid_pk.report.evidence_periodic import gain_text, phase_folded
from hybrid_pk.report.markdown import with_unit

__all__ = [
    "Evidence",
    "ResidualView",
    "cause_evidence",
    "cause_label",
    "residual_view",
    "without_effect",
]

# Rows whose |J_j| is below this fraction of the median carry no information on joint j.
MIN_LEVER_FRACTION = 0.2


@dataclass(frozen=True)
class Evidence:
    """What an evidence plot shows (numpy arrays in the plotted units).

    Attributes:
        label: the cause, ``kind:joint`` or ``kind``.
        title: plot title (label and diagnosed value ± std).
        x, y: ``(n,)`` per-row law variable and residual measure, in the units of
            ``x_label`` and ``y_label``.
        weight: ``(n,)`` information of each row, the weights of the fit of
            ``points_value`` (``|J_j|^2`` [m^2/rad^2] for joint effects).
        rows: ``(n,)`` row in the data of each point (geometric effects: each row three
            times, one point per coordinate).
        curve_x, curve_y: the law with the diagnosed value.
        median_x, median_y: binned medians of the points (one per level for backlash).
        value: the diagnosed value (amplitude or norm for vector effects), SI unit.
        points_value: the same quantity fitted to the plotted points alone.
        nominal_points_value: fitted the same way to the nominal model's residual (frames
            fitted without any cause), or None when not computed.
        unit: unit of the three values.
        law: the law in words.
        categorical: True when ``x`` takes a few discrete values (backlash).
    """

    label: str
    title: str
    x: np.ndarray
    y: np.ndarray
    weight: np.ndarray
    rows: np.ndarray
    x_label: str
    y_label: str
    curve_x: np.ndarray
    curve_y: np.ndarray
    median_x: np.ndarray
    median_y: np.ndarray
    value: float
    points_value: float
    unit: str
    law: str
    categorical: bool = False
    nominal_points_value: float | None = None


@dataclass(frozen=True)
class ResidualView:
    """Residual of a model on every row, in the robot root frame, with the Jacobian.

    Attributes:
        model: the model whose residual this is.
        r_meas: ``(N, 3)`` ``p_meas - p_model`` in the measurement frame [m].
        r_root: ``(N, 3)`` the same in the robot root frame [m].
        p_end: ``(N, 3)`` flange (end link) position in the root frame [m].
        J_point: ``(N, 3, dof)`` velocity of the measured point per joint velocity,
            root frame [m/rad].
        cond: operating conditions of the rows.
    """

    model: ExtendedModel
    r_meas: Tensor
    r_root: Tensor
    p_end: Tensor
    J_point: Tensor
    cond: Conditions


def cause_label(cause) -> str:
    """``kind:joint`` (or ``kind``) of a diagnosed cause, as effects are labelled."""
    return f"{cause.effect}:{cause.joint}" if cause.joint else cause.effect


def without_effect(model: ExtendedModel, label: str | None) -> ExtendedModel:
    """A copy of ``model`` (frames and effect values) without the effect ``label``."""
    robot = model.robot
    effects = [
        make_effect(robot, e.label, e.value.detach().clone())
        for e in model.effects
        if e.label != label
    ]
    out = ExtendedModel(robot, effects, frame_sets=model.base.sets, gravity=model.gravity)
    out.base.reset_to(model.base.matrix().detach())
    out.tool.reset_to(model.tool.matrix().detach())
    return out


def _frames(model: ExtendedModel, cond: Conditions) -> tuple[Tensor, Tensor]:
    """Base and tool transforms, ``(4, 4)`` shared or ``(N, 4, 4)`` per row."""
    if cond.group is None or model.base.sets == 1:
        return model.base.matrix()[0], model.tool.matrix()[0]
    return model.base.matrix(cond.group), model.tool.matrix(cond.group)


@torch.no_grad()
def residual_view(model: ExtendedModel, data: MeasuredData) -> ResidualView:
    """Residual of ``model`` on all rows, in the root frame, with the point Jacobian."""
    cond = conditions_from_data(data, model.base.sets > 1)
    T_end = model.end_pose(data.q, cond)
    base, tool = _frames(model, cond)
    base, tool = base.to(T_end.dtype), tool.to(T_end.dtype)
    p_model = (base @ T_end @ tool)[..., :3, 3]
    r_meas = data.position - p_model
    R_base = base[..., :3, :3]
    r_root = (R_base.transpose(-1, -2) @ r_meas[..., None])[..., 0]
    lever = (T_end[..., :3, :3] @ tool[..., :3, 3, None])[..., 0]  # p_point - p_end
    J = model.robot.jacobian(model.joint_values(data.q, cond))
    v, w = J[:, :3, :], J[:, 3:, :]
    J_point = v + torch.linalg.cross(w, lever[..., None].expand_as(w), dim=1)
    return ResidualView(model, r_meas, r_root, T_end[:, :3, 3], J_point, cond)


def _wls(basis: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted least squares coefficients of ``y ~ basis`` (``basis (n, k)``)."""
    sw = np.sqrt(w)[:, None]
    return np.linalg.lstsq(basis * sw, y * sw[:, 0], rcond=None)[0]


def _value_text(cause) -> str:
    value, std = cause.value, cause.std
    if isinstance(value, list):
        vals = ", ".join(f"{v:.3g}" for v in value)
        stds = ", ".join(f"{s:.2g}" for s in std)
        return with_unit(f"({vals}) ± ({stds})", cause.unit)
    return with_unit(f"{value:.4g} ± {std:.2g}", cause.unit)


def cause_evidence(
    cause,
    data: MeasuredData,
    model: ExtendedModel,
    nominal_model: ExtendedModel | None = None,
) -> Evidence:
    """The evidence of one diagnosed cause (see the module doc for the computation).

    Args:
        cause: a :class:`~hybrid_pk.calibration.diagnosis.Cause`.
        data: all measured rows.
        model: the fitted extended model that holds the cause's effect.
        nominal_model: URDF + frames fitted without any cause; when given,
            ``nominal_points_value`` says how much of the law its residual shows.

    Raises:
        HybridPKError: for an effect kind without an evidence plot, or one that is not
            in ``model``.
    """
    label = cause_label(cause)
    if label not in [e.label for e in model.effects]:
        raise HybridPKError(f"cause {label} is not an effect of the model")
    evidence = _evidence(
        cause, label, data, model, residual_view(without_effect(model, label), data)
    )
    if nominal_model is not None:
        nominal = _evidence(cause, label, data, model, residual_view(nominal_model, data))
        evidence = replace(evidence, nominal_points_value=nominal.points_value)
    gain = gain_text(cause)
    evidence = replace(evidence, title=evidence.title + (f"; {gain}" if gain else ""))
    return phase_folded(evidence, model.effect(label), data)


def _evidence(cause, label: str, data, model, view: ResidualView) -> Evidence:
    title = f"{label} = {_value_text(cause)}"
    effect = model.effect(label)  # its class says where it acts and what shows it
    if effect.stage in ("joint", "compliance"):
        return _joint_evidence(cause, label, title, data, model, view)
    if effect.evidence == "temperature":
        return _thermal_evidence(cause, label, title, data, view)
    if effect.stage == "geometry":
        return _geometric_evidence(cause, label, title, data, model, view)
    if effect.stage == "deflection":
        return Evidence(**deflection_evidence(cause, label, title, data, model, view, _frames))
    raise HybridPKError(f"no evidence plot for effect {cause.effect!r}")


def _joint_evidence(cause, label, title, data, model, res: ResidualView) -> Evidence:
    robot = model.robot
    j = robot.joint_names.index(cause.joint)
    Jj = res.J_point[:, :, j]
    e_all, w_all, keep = equivalent_angle_error(Jj, res.r_root, MIN_LEVER_FRACTION)  # [rad]
    keep = keep.numpy()
    rows = np.flatnonzero(keep)
    y = 1e3 * e_all.numpy()[rows]  # [mrad]
    w = w_all.numpy()[rows]
    theta = data.q[rows, j].numpy()
    y_label = f"equivalent angle error of {cause.joint} [mrad]"
    effect = model.effect(label)
    v = effect.value.detach().to(torch.float64).numpy()
    categorical = False
    if effect.evidence == "torque":
        payload = 0.0 if data.payload is None else data.payload
        with torch.no_grad():
            tau = -robot.gravity_torques(data.q, payload=payload)[:, j].numpy()
        x = tau[rows]
        x_label = f"gravity torque on {cause.joint} [Nm]"
        curve_x = np.linspace(x.min(), x.max(), 100)
        curve_y = 1e3 * float(v) * curve_x
        points = float(_wls(np.stack([x, np.ones_like(x)], 1), y, w)[0]) * 1e-3
        law = effect.law
        value = float(v)
    elif isinstance(effect, (JointOffset, GearRatio, JointEccentricity)):
        x = np.degrees(theta)
        x_label = f"{cause.joint} angle θ [deg]"
        curve_x = np.linspace(x.min(), x.max(), 200)
        th = np.radians(curve_x)
        if isinstance(effect, JointOffset):
            curve_y = np.full_like(curve_x, 1e3 * float(v))
            points = float(np.average(y, weights=w)) * 1e-3
            law, value = effect.law, float(v)
        elif isinstance(effect, GearRatio):
            curve_y = 1e3 * float(v) * th
            points = float(_wls(np.stack([theta, np.ones_like(theta)], 1), y, w)[0]) * 1e-3
            law, value = effect.law, float(v)
        else:
            a, b, n = float(v[0]), float(v[1]), effect.order
            curve_y = 1e3 * (a * np.sin(n * th) + b * np.cos(n * th))
            basis = np.stack([np.sin(n * theta), np.cos(n * theta), np.ones_like(theta)], 1)
            ca, cb, _ = _wls(basis, y, w) * 1e-3
            points = math.hypot(ca, cb)
            nth = "θ" if n == 1 else f"{n}θ"
            law = (
                f"θ_true - θ = a sin {nth} + b cos {nth}: a sinusoid"
                + ("" if n == 1 else f" of {n} cycles per turn")
                + ", amplitude √(a² + b²)"
            )
            value = math.hypot(a, b)
    elif effect.evidence == "row_order":  # backlash
        categorical = True
        direction = res.cond.direction[:, j].numpy()
        rows = rows[direction[rows] != 0]  # unknown direction (first row of a file)
        direction, y, w = direction[rows], 1e3 * e_all.numpy()[rows], w_all.numpy()[rows]
        x = direction.astype(float)
        x_label = f"approach direction of {cause.joint}"
        curve_x = np.array([-1.0, 1.0])
        curve_y = 1e3 * float(v) * 0.5 * curve_x
        plus, minus = direction > 0, direction < 0
        if plus.any() and minus.any():
            points = float(
                np.average(y[plus], weights=w[plus]) - np.average(y[minus], weights=w[minus])
            )
            points *= 1e-3
        else:
            points = math.nan
        law = effect.law
        value = float(v)
    else:  # any other joint-space law: the effect's own response, against its variable
        x, x_label, curve_x, curve_y, points, law, value = _law_evidence(
            effect, data, res, rows, y, w
        )
    return _points_evidence(
        cause,
        label,
        title,
        points=(x, y, w, rows),
        axes=(x_label, y_label),
        curve=(curve_x, curve_y),
        values=(value, points),
        law=law,
        categorical=categorical,
    )


def _law_evidence(effect, data, res: ResidualView, rows, y, w) -> tuple:
    """Evidence of a joint-space effect from its own law: ``x`` its evidence variable
    (the joint's angle or the row's temperature), the curve its angle change on each
    row, the points' value the diagnosed one scaled by the fit of ``y`` to that change."""
    j, index = effect.joint_index, torch.from_numpy(rows)
    with torch.no_grad():
        q = data.q[index]
        delta = (effect.apply_q(q, res.cond.subset(index)) - q)[:, j].double().numpy()
    if effect.evidence == "temperature":
        if data.temperature is None:
            raise HybridPKError(f"{effect.kind} evidence needs the temperature column")
        x, x_label = data.temperature[index].numpy(), "temperature [°C]"
    elif effect.evidence == "joint_angle":
        x, x_label = np.degrees(q[:, j].numpy()), f"{effect.joint} angle θ [deg]"
    else:
        raise HybridPKError(f"no evidence plot for effect {effect.kind!r}")
    order = np.argsort(x, kind="stable")
    value = effect.magnitude()
    fit = _wls(np.stack([1e3 * delta, np.ones_like(delta)], 1), y, w)[0] if rows.size else math.nan
    law = effect.law or f"θ_true - θ = the {effect.kind} law, against {effect.evidence}"
    return x, x_label, x[order], 1e3 * delta[order], float(fit) * value, law, value


def _thermal_evidence(cause, label, title, data, res: ResidualView) -> Evidence:
    if data.temperature is None:
        raise HybridPKError(f"{cause.effect} evidence needs the temperature column")
    p = res.p_end
    w = (p * p).sum(-1)
    strain = ((p * res.r_root).sum(-1) / w.clamp_min(1e-300)).numpy()
    rows = np.arange(data.n)
    x = data.temperature.numpy()
    y = 1e6 * strain  # [µm/m]
    wn = w.numpy()
    dT = x - REFERENCE_TEMPERATURE
    points = float(_wls(np.stack([dT, np.ones_like(dT)], 1), y, wn)[0]) * 1e-6
    curve_x = np.linspace(x.min(), x.max(), 50)
    curve_y = 1e6 * float(cause.value) * (curve_x - REFERENCE_TEMPERATURE)
    return _points_evidence(
        cause,
        label,
        title,
        points=(x, y, wn, rows),
        axes=("temperature [°C]", "equivalent strain of the links [µm/m]"),
        curve=(curve_x, curve_y),
        values=(float(cause.value), points),
        law=f"strain = α · (T - {REFERENCE_TEMPERATURE:g} °C): a line, slope α",
    )


def _geometric_evidence(cause, label, title, data, model, res: ResidualView) -> Evidence:
    cond = res.cond
    with torch.no_grad():
        reduced = without_effect(model, label)
        d = model(data.q, cond)[:, :3, 3] - reduced(data.q, cond)[:, :3, 3]  # [m]
    # The physical signature: what a change of the base and tool frames would make is
    # taken out of both (a misalignment that mostly turns the whole arm would otherwise
    # draw a long slope-1 line of pure frame trade-off).
    d, r = off_frames(model, data, cond, d, res.r_meas)
    # Every coordinate of every row is a point: a link-length error moves the point by a
    # constant distance in a direction that turns with the arm, so the coordinates (not
    # the distance) are what varies from row to row.
    x = 1e3 * d.numpy().T.reshape(-1)  # [mm], x coordinates of all rows, then y, then z
    y = 1e3 * r.numpy().T.reshape(-1)
    rows = np.tile(np.arange(data.n), 3)
    w = np.ones_like(x)
    slope = float((x * y).sum() / max(float((x * x).sum()), 1e-300))
    magnitude = float(model.effect(label).value.detach().norm())
    span = float(np.abs(x).max()) if x.size else 1.0
    curve_x = np.array([-span, span])
    return _points_evidence(
        cause,
        label,
        title,
        points=(x, y, w, rows),
        axes=(
            "displacement the effect makes beyond any frame change, x/y/z of every row [mm]",
            "residual beyond any frame change, same coordinate [mm]",
        ),
        curve=(curve_x, curve_x.copy()),
        values=(magnitude, slope * magnitude),
        law="residual = displacement of the effect, both without what a change of the "
        "base and tool frames makes: a slope-1 line",
    )


def _points_evidence(
    cause,
    label: str,
    title: str,
    *,
    points: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    axes: tuple[str, str],
    curve: tuple[np.ndarray, np.ndarray],
    values: tuple[float, float],
    law: str,
    categorical: bool = False,
) -> Evidence:
    """The :class:`Evidence` of the plotted ``points`` ``(x, y, weight, rows)`` with
    their medians: binned, or one per level of a ``categorical`` ``x``. ``axes`` are the
    x and y labels, ``curve`` the law's ``(curve_x, curve_y)``, ``values`` the diagnosed
    value and the one fitted to the points."""
    x, y = points[0], points[1]
    if categorical:
        levels = [d for d in (-1.0, 0.0, 1.0) if (x == d).any()]
        mx = np.array(levels)
        my = np.array([np.median(y[x == d]) for d in levels])
    else:
        mx, my = binned_median(x, y)
    # the groups stand in the order of the Evidence fields
    return Evidence(
        label, title, *points, *axes, *curve, mx, my, *values, cause.unit, law, categorical
    )
