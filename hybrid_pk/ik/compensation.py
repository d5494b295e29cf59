"""Program compensation: joints that put the real robot where the nominal model meant.

A controller runs its nominal model. A program row (joint targets ``q_nom``, or a
target pose of the flange in the robot base frame) means the flange pose
``g = fk_nominal(q_nom)``. The real robot, as a calibration describes it (an
:class:`~hybrid_pk.effects.ExtendedModel`, or a hybrid model with residual networks),
maps joints to poses in the measurement frame, ``F(q) = B · E_real(q) · X`` with its
base frame ``B`` and tool frame ``X``. The compensated joints solve

    ``F(q) = B · g · X``,

so the real flange (and every tool point on it) is where the nominal model put it, in
the robot base frame that the calibration identified (a base rotation that the data
cannot tell from a joint 1 offset stays in ``B``: the program's frame is that one).

Each row is solved from its nominal joints within ``±box`` of them and within the joint
limits (the batched projected Levenberg–Marquardt of :func:`~hybrid_pk.ik.refine_ik`),
which keeps the solution on the nominal branch. A row is

- ``ok``: a solution within the tolerances;
- ``joint_limit``: the real robot reaches the pose on this branch only beyond a joint
  limit (solved again without the limits; the joint and how far are in ``note``);
- ``unreachable``: no solution within the box (outside the real robot's workspace, or
  near a singular configuration, where a small correction needs a large joint move);
- ``approach_conflict``: with backlash, the side a joint approaches from is that of the
  *corrected* program's moves; the rows are solved again with those sides until they
  agree, and a row whose corrected move keeps turning around within the play (a joint
  that barely moves) is reported;
- ``no_nominal_solution``: a pose row the nominal model itself cannot reach.

Rows that are not ``ok`` keep their nominal joints and say why: nothing is bent into
the limits silently.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from hybrid_pk.effects import Conditions, ExtendedModel, approach_direction
from hybrid_pk.effects.joint import Backlash
from hybrid_pk.evaluation.metrics import pose_error
from hybrid_pk.ik.batched_lm import batched_levenberg_marquardt
from hybrid_pk.ik.conditions import Approach, resolve_conditions
from hybrid_pk.ik.forward_model import as_ik_model
from hybrid_pk.ik.solver import IKOptions, solve_ik
from hybrid_pk.ik.two_stage import refine_ik
from hybrid_pk.robot import Robot

__all__ = [
    "COMPENSATION_BOX",
    "STATUSES",
    "Compensation",
    "chain_reach",
    "compensate",
    "nearest_branch",
    "program_conditions",
]

F64 = torch.float64


def chain_reach(robot: Robot, origin_xyz: Tensor | None = None) -> float:
    """[m] no joint values put the end link farther from the root origin (triangle
    inequality): the lengths of the joint origins' translations (``origin_xyz (*, n+1,
    3)``, the robot's own by default; the largest over a batch) plus the prismatic
    joints' largest travel."""
    xyz = robot.origin_xyz if origin_xyz is None else origin_xyz
    links = xyz.detach().to(F64).norm(dim=-1).sum(-1).max()
    lo, hi = robot.joint_limits
    corners = robot.chain_q(torch.stack([lo, hi]).to(F64)).abs().amax(0)
    prismatic = torch.tensor([t == "prismatic" for t in robot.chain_joint_types])
    return float(links + corners[prismatic].sum())


COMPENSATION_BOX = 0.1  # [rad] (or m) largest correction of a joint on the same branch
STATUSES = ("ok", "joint_limit", "unreachable", "approach_conflict", "no_nominal_solution")
_ORDER_PASSES = 4  # re-solves with the approach sides of the corrected program
_CONFLICT = (
    "a backlash joint's corrected move from the previous row turns around within the play; "
    "approach the row explicitly (--approach, or an approach move in the program)"
)


@dataclass(frozen=True)
class Compensation:
    """Outcome of :func:`compensate`, one entry per program row, in order.

    Attributes:
        q: ``(N, dof)`` compensated joints [rad, m]; the nominal joints where the row
            is not ``ok`` (NaN for a pose row without a nominal solution).
        q_nominal: ``(N, dof)`` the nominal joints of each row.
        residual_mm, residual_deg: ``(N,)`` predicted error of the real robot at ``q``
            w.r.t. the intended pose [mm, deg].
        nominal_mm, nominal_deg: ``(N,)`` the same at the nominal joints (what the
            uncompensated program does, as the model predicts it).
        status: one of :data:`STATUSES` per row.
        note: what limited a row that is not ``ok`` ("" otherwise).
        assumed: operating conditions that had to be assumed (one line each).
    """

    q: Tensor
    q_nominal: Tensor
    residual_mm: Tensor
    residual_deg: Tensor
    nominal_mm: Tensor
    nominal_deg: Tensor
    status: tuple[str, ...]
    note: tuple[str, ...]
    assumed: tuple[str, ...] = ()

    @property
    def ok(self) -> Tensor:
        return torch.tensor([s == "ok" for s in self.status], dtype=torch.bool)


def _unwrapped(sols: Tensor, prev: Tensor, robot: Robot) -> Tensor:
    """Solutions with each revolute joint moved by whole turns towards ``prev`` where the
    limits allow (the IK returns one representative of the same pose per 2 pi)."""
    lo, hi = robot.joint_limits
    turns = torch.round((prev - sols) / (2 * math.pi)) * robot.revolute.to(F64)
    moved = sols + 2 * math.pi * turns
    return torch.where((moved >= lo) & (moved <= hi), moved, sols)


def nearest_branch(
    robot: Robot, targets: Tensor, reference: Tensor | None = None, seeds: int = 64
) -> Tensor:
    """Nominal joints of flange poses ``targets (N, 4, 4)`` (robot base frame), each the
    solution nearest the previous row's (the first: nearest ``reference``, default the
    middle of the joint range), as a controller moving along the program would take.

    Returns:
        ``(N, dof)``; NaN rows where the nominal model has no solution.
    """
    result = solve_ik(robot, targets, seeds=seeds)
    lo, hi = robot.joint_limits
    mid = torch.where(torch.isfinite(lo) & torch.isfinite(hi), (lo + hi) / 2, 0.0).to(F64)
    prev = mid if reference is None else torch.as_tensor(reference, dtype=F64)
    out = torch.full((targets.shape[0], robot.dof), math.nan, dtype=F64)
    for i in range(targets.shape[0]):
        sols = _unwrapped(result.solutions(i).to(F64), prev, robot)
        if sols.shape[0] == 0:
            continue
        out[i] = sols[(sols - prev).abs().amax(-1).argmin()]
        prev = out[i]
    return out


def program_conditions(
    real, q_nominal: Tensor, cond: Conditions | None
) -> tuple[Conditions | None, list[str]]:
    """``cond`` with the approach direction of every joint from the program order
    (:func:`~hybrid_pk.effects.approach_direction`; the first row: mid-play) when the
    model has backlash and ``cond`` gives no direction. A joint that barely moves in
    the program could approach from the other side once corrected: state the approach
    (``approach=``) where that matters."""
    extended = real if isinstance(real, ExtendedModel) else getattr(real, "base", None)
    effects = extended.effects if isinstance(extended, ExtendedModel) else ()
    joints = [e.joint for e in effects if e.needs == "direction"]
    if not joints or (cond is not None and cond.direction is not None):
        return cond, []
    note = f"{Backlash.kind} on {', '.join(joints)}: approach direction from the program order"
    return replace(cond or Conditions(), direction=approach_direction(q_nominal)), [note]


def _errors(ikm, q: Tensor, T: Tensor) -> tuple[Tensor, Tensor]:
    rows = torch.arange(q.shape[0])
    with torch.no_grad():
        err = pose_error(T, ikm.pose(q, rows).to(F64))
    return err.position_mm, err.orientation_deg


def _beyond_limits(ikm, q0, T, rows, box, options: IKOptions) -> tuple[Tensor, list[str]]:
    """For rows that failed: do they reach the pose without the joint limits? Returns
    ``(M,)`` bool and a note per row."""
    half = torch.as_tensor(box, dtype=F64).expand(ikm.dof)
    with torch.no_grad():
        out = batched_levenberg_marquardt(
            ikm.evaluate, q0, rows, T, q0 - half, q0 + half, options.lm_settings(False),
            ikm.revolute,
        )  # fmt: skip
    reached = (out.position_error * 1e3 <= options.tol_mm) & (
        torch.rad2deg(out.rotation_error) <= options.tol_deg
    )
    notes = []
    for k in range(q0.shape[0]):
        over = (out.q[k] - ikm.upper).clamp_min(0) + (ikm.lower - out.q[k]).clamp_min(0)
        j = int(over.argmax())
        if bool(reached[k]) and float(over[j]) > 0:
            side = "upper" if float(out.q[k, j]) > float(ikm.upper[j]) else "lower"
            notes.append(f"{ikm.joint_names[j]} {float(over[j]):.3g} beyond its {side} limit")
        else:
            notes.append("")
    limited = torch.tensor([bool(n) for n in notes], dtype=torch.bool)
    return limited, notes


def _singular_note(robot, q: Tensor, err_mm: float, err_deg: float, box: float) -> str:
    """Why a row is unreachable when its nominal joints ``q`` are near a singular
    configuration: a move of the whole ``box`` along the arm's strongest direction there
    would reach the correction (the nominal model's error at the row), along its weakest
    one not (the Jacobian's singular values, its velocity rows over the flange's
    distance from the root). "" otherwise (a box too small for any direction, say)."""
    with torch.no_grad():
        J = robot.jacobian(q[None].to(F64))[0]
        lever = float(robot.fk(q[None].to(F64))[0, :3, 3].norm().clamp_min(1e-3))  # [m]
    J = torch.cat([J[:3] / lever, J[3:]])  # dimensionless per radian of joint motion
    gains = torch.linalg.svdvals(J)
    strongest, weakest = float(gains[0]), float(gains[-1])
    need = 1e-3 * err_mm / lever + math.radians(err_deg)
    if weakest * box >= need or strongest * box < need:
        return ""
    return (
        f"; the nominal joints are near a singular configuration: along the arm's weakest "
        f"direction there a joint move of {box:g} reaches {weakest * box:.2g} of the "
        f"{need:.2g} the correction needs (rotation in rad, position over the flange's reach)"
    )


class _Solver:
    """Rows solved from their nominal joints within the box, on the model."""

    def __init__(self, real, robot, T, start, has_nominal, box, options) -> None:
        self.real, self.robot, self.T, self.start = real, robot, T, start
        self.has_nominal, self.box, self.options = has_nominal, box, options

    def __call__(self, cond: Conditions | None) -> tuple[Tensor, Tensor]:
        """``q (N, dof)`` (the start where a row failed) and ``ok (N,)``."""
        n = self.start.shape[0]
        refined = refine_ik(
            self.real, self.T, self.start[:, None, :], box=self.box, cond=cond,
            robot=self.robot, options=self.options,
        )  # fmt: skip
        if refined.q.shape[1]:  # at most one solution per row: the box excludes others
            ok, q = refined.valid[:, 0] & self.has_nominal, refined.q[:, 0].nan_to_num()
        else:  # no row solved
            ok, q = torch.zeros(n, dtype=torch.bool), self.start
        return torch.where(ok[:, None], q, self.start), ok

    def in_order(self, cond, joints: list[int]) -> tuple[Tensor, Tensor, Conditions, Tensor]:
        """Solve; with approach sides from the program order (backlash ``joints``), again
        with the sides of the corrected program until they agree. Returns ``q``, ``ok``,
        the conditions used and the rows whose side still flips (``ok`` False there)."""
        q, ok = self(cond)
        conflict = torch.zeros_like(ok)
        for _ in range(_ORDER_PASSES if joints else 0):
            side = approach_direction(q)
            conflict = (side[:, joints] != cond.direction[:, joints]).any(-1) & ok
            if not bool(conflict.any()):
                break
            cond = replace(cond, direction=side)
            q, ok = self(cond)
        ok = ok & ~conflict
        return torch.where(ok[:, None], q, self.start), ok, cond, conflict


def _backlash_joints(real, robot: Robot) -> list[int]:
    extended = real if isinstance(real, ExtendedModel) else getattr(real, "base", None)
    effects = extended.effects if isinstance(extended, ExtendedModel) else ()
    return [robot.joint_names.index(e.joint) for e in effects if e.needs == "direction"]


def compensate(
    real,
    robot: Robot,
    *,
    base: Tensor,
    tool: Tensor,
    q_nominal: Tensor | None = None,
    targets: Tensor | None = None,
    cond: Conditions | None = None,
    box: float = COMPENSATION_BOX,
    options: IKOptions | None = None,
    reference: Tensor | None = None,
    approach: Approach = None,
    fixes: Mapping[str, str] | None = None,
) -> Compensation:
    """Joints for every program row that put the real robot at the nominal pose.

    Args:
        real: the calibrated model: ``ExtendedModel`` or a hybrid model, ``(q, cond) ->
            (N, 4, 4)`` in the measurement frame.
        robot: the nominal robot (the controller's model; limits and joint types).
        base, tool: ``(4, 4)`` the model's base frame (measurement <- robot base) and
            tool frame (flange -> measured point) [m].
        q_nominal: ``(N, dof)`` program joints [rad, m], or ...
        targets: ``(N, 4, 4)`` program flange poses in the robot base frame [m] (the
            nominal joints are then the branch nearest the previous row's).
        cond: conditions per row (payload, temperature, approach direction of backlash
            joints, frame set); the program order gives the direction by default.
        box: largest joint correction [rad, m]: the same branch.
        options: tolerances of an ``ok`` row and the iteration budget.
        reference: joints the first pose row's branch is chosen near.
        approach: how backlash joints approach every row (``+1``, ``-1``, ``"mid"``,
            per joint; :mod:`~hybrid_pk.ik.conditions`), instead of the program order.
        fixes: how a caller's user states each assumed condition (a column, a flag), for
            the ``assumed`` notes; default: the Python arguments.
    """
    options = options or IKOptions()
    if (q_nominal is None) == (targets is None):
        raise ValueError("give q_nominal (joint program) or targets (pose program)")
    base, tool = base.to(F64), tool.to(F64)
    if q_nominal is not None:
        q_nom = torch.as_tensor(q_nominal, dtype=F64)
        with torch.no_grad():
            g = robot.fk(q_nom).to(F64)
    else:
        g = torch.as_tensor(targets, dtype=F64)
        q_nom = nearest_branch(robot, g, reference)
    n = q_nom.shape[0]
    T = base @ g @ tool  # intended pose in the measurement frame
    has_nominal = torch.isfinite(q_nom).all(-1)
    start = torch.where(has_nominal[:, None], q_nom, 0.0)
    ordered: list[str] = []
    if approach is None:
        cond, ordered = program_conditions(real, start, cond)
    cond, assumed = resolve_conditions([real], cond, n, approach, fixes=fixes)
    nominal_model = as_ik_model(real, cond=cond, robot=robot, n_targets=n)
    solve = _Solver(real, robot, T, start, has_nominal, box, options)
    q, ok, cond, conflict = solve.in_order(cond, _backlash_joints(real, robot) if ordered else [])
    ikm = as_ik_model(real, cond=cond, robot=robot, n_targets=n)
    status = ["ok" if bool(v) else "unreachable" for v in ok]
    note = ["" if bool(v) else f"no solution within {box:g} of the nominal joints" for v in ok]
    failed = (~ok & has_nominal & ~conflict).nonzero()[:, 0]
    if failed.numel():
        limited, why = _beyond_limits(ikm, start[failed], T[failed], failed, box, options)
        for k, i in enumerate(failed.tolist()):
            if bool(limited[k]):
                status[i], note[i] = "joint_limit", why[k]
    for i in conflict.nonzero()[:, 0].tolist():
        status[i], note[i] = "approach_conflict", _CONFLICT
    reach = chain_reach(robot)
    for i in (~has_nominal).nonzero()[:, 0].tolist():
        status[i], note[i] = "no_nominal_solution", "the nominal model has no solution"
        far = float(g[i, :3, 3].norm())
        if far > reach:  # a target no joint values reach: mm, or another frame
            note[i] += (
                f" ({far:.3g} m from the robot's root, beyond the {reach:.3g} m its links and "
                "joint travel add up to: flange poses are in the robot base frame [m])"
            )
    res_mm, res_deg = _errors(ikm, q, T)
    nom_mm, nom_deg = _errors(nominal_model, start, T)
    for i in [i for i, s in enumerate(status) if s == "unreachable"]:
        note[i] += _singular_note(robot, start[i], float(nom_mm[i]), float(nom_deg[i]), box)
    nan = torch.tensor(math.nan, dtype=F64)
    q = torch.where(has_nominal[:, None], q, nan)
    res_mm, res_deg = (torch.where(has_nominal, x, nan) for x in (res_mm, res_deg))
    nom_mm, nom_deg = (torch.where(has_nominal, x, nan) for x in (nom_mm, nom_deg))
    assumed = ordered + list(assumed)
    return Compensation(
        q, q_nom, res_mm, res_deg, nom_mm, nom_deg, tuple(status), tuple(note), tuple(assumed)
    )
