"""A robot from a DH or modified-DH table: the table's chain written as a URDF.

Conventions (angles [rad], lengths [m], ``q`` the joint value; a prismatic joint adds
``q`` to ``d``, a revolute one to ``theta``):

- ``dh`` (standard, distal; row ``i`` maps frame ``i-1`` to frame ``i``, joint ``i``
  moves about / along ``z`` of frame ``i-1``)::

      A_i = Rz(theta_i) · Tz(d_i) · Tx(a_i) · Rx(alpha_i) · Ry(beta_i)

- ``mdh`` (Craig's modified, proximal; row ``i`` holds ``alpha_{i-1}, a_{i-1}`` and
  ``theta_i, d_i``, joint ``i`` moves about / along ``z`` of frame ``i``)::

      A_i = Rx(alpha_i) · Tx(a_i) · Ry(beta_i) · Rz(theta_i) · Tz(d_i)

``beta`` is Hayati's parallel-axis parameter: where two consecutive axes are (nearly)
parallel, the common normal of plain DH is ill defined (``d`` runs off to infinity for
a small tilt); Hayati fixes ``d`` and tilts about ``y`` instead. 0 in plain tables.

The chain is ``T(q) = base · A_1(q_1) · … · A_n(q_n) · flange``: the URDF's root link
``base_link`` is the frame ``base`` is given in (frame 0 itself when ``base`` is the
identity, the default), its end link ``flange`` is frame ``n`` followed by ``flange``
(frame ``n`` itself by default). Joint ``i``'s URDF frame is the table's frame ``i-1``
(``dh``) or frame ``i`` (``mdh``) at zero joint values, so a table read back from the
robot (:mod:`hybrid_pk.io.dh_export`) finds the same frames. Link ``link_i`` carries
the row's optional inertial.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from hybrid_pk.geometry import matrix_to_rpy
from hybrid_pk.robot.dh_table import DHTable, read_dh_table
from hybrid_pk.robot.urdf_copy import urdf_copy

__all__ = ["ROOT_LINK", "TIP_LINK", "dh_row_parts", "dh_urdf", "from_dh", "rot", "trans"]

ROOT_LINK, TIP_LINK = "base_link", "flange"


def rot(axis: str, angle: float) -> np.ndarray:
    """``(4, 4)`` rotation about ``x``, ``y`` or ``z`` by ``angle`` [rad]."""
    c, s = math.cos(angle), math.sin(angle)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    T = np.eye(4)
    T[i, i], T[i, j], T[j, i], T[j, j] = c, -s, s, c
    return T


def trans(axis: str, length: float) -> np.ndarray:
    """``(4, 4)`` translation along ``x``, ``y`` or ``z`` by ``length`` [m]."""
    T = np.eye(4)
    T["xyz".index(axis), 3] = length
    return T


def dh_row_parts(convention: str, row, prismatic: bool) -> tuple[np.ndarray, np.ndarray]:
    """``(before, after)`` of one row ``a, alpha, d, theta, beta``: the row at joint value
    ``q`` is ``before · M(q) · after``, ``M`` the joint's motion about / along ``z``.

    A revolute ``Rz(q)`` commutes with ``Rz(theta)`` and ``Tz(d)``, a prismatic ``Tz(q)``
    with ``Rz(theta)`` and ``Tz(d)``, so the motion can stand first (``dh``: the joint
    frame is frame ``i-1``) or last (``mdh``: the joint frame is frame ``i``).
    """
    a, alpha, d, theta, beta = (float(v) for v in row)
    if convention == "dh":
        after = rot("z", theta) @ trans("z", d) @ trans("x", a) @ rot("x", alpha) @ rot("y", beta)
        return np.eye(4), after
    before = rot("x", alpha) @ trans("x", a) @ rot("y", beta) @ rot("z", theta) @ trans("z", d)
    return before, np.eye(4)


def _num(x: float) -> str:
    x = float(x)
    return repr(0.0 if x == 0 else x)  # shortest text that reads back the same float64


def _origin(T: np.ndarray) -> str:
    rpy = matrix_to_rpy(torch.as_tensor(T[:3, :3], dtype=torch.float64)).tolist()
    xyz = " ".join(_num(v) for v in T[:3, 3])
    return f'<origin xyz="{xyz}" rpy="{" ".join(_num(v) for v in rpy)}"/>'


def _inertial(after: np.ndarray, values: np.ndarray | None) -> str:
    if values is None or values[0] <= 0:
        return ""
    pose = after.copy()  # the inertia's axes are the table frame's
    pose[:3, 3] = after[:3, :3] @ values[1:4] + after[:3, 3]
    ixx, ixy, ixz, iyy, iyz, izz = (_num(v) for v in values[4:])
    return (
        f'\n    <inertial>\n      {_origin(pose)}\n      <mass value="{_num(values[0])}"/>\n'
        f'      <inertia ixx="{ixx}" ixy="{ixy}" ixz="{ixz}" iyy="{iyy}" iyz="{iyz}" izz="{izz}"/>'
        "\n    </inertial>\n  "
    )


def dh_urdf(table: DHTable) -> str:
    """The URDF text of a DH table's chain (see the module docstring)."""
    parts = [
        dh_row_parts(table.convention, row, kind == "prismatic")
        for row, kind in zip(table.rows, table.types, strict=True)
    ]
    links = [f"link_{i}" for i in range(1, table.n + 1)]
    clash = {ROOT_LINK, TIP_LINK}.intersection(links) or {f"{TIP_LINK}_joint"}.intersection(
        table.names
    )
    if clash:
        raise ValueError(f"{table.source}: the name {clash.pop()!r} is reserved for the URDF")
    lines = [
        '<?xml version="1.0"?>',
        f"<!-- written by hybrid_pk from the {table.convention.upper()} table {table.source}:",
        f"     {ROOT_LINK} is the frame the table's base is given in, {TIP_LINK} is frame",
        f"     {table.n} followed by the table's flange transform. -->",
        f'<robot name="{table.name}">',
        f'  <link name="{ROOT_LINK}"/>',
    ]
    after_prev = table.base
    for i, (name, kind) in enumerate(zip(table.names, table.types, strict=True)):
        before, after = parts[i]
        parent = ROOT_LINK if i == 0 else links[i - 1]
        inertial = _inertial(after, None if table.inertial is None else table.inertial[i])
        limit = (
            '<limit effort="0" velocity="0"/>'
            if kind == "continuous"
            else f'<limit lower="{_num(table.lower[i])}" upper="{_num(table.upper[i])}" '
            'effort="0" velocity="0"/>'
        )
        lines += [
            f'  <link name="{links[i]}">{inertial}</link>',
            f'  <joint name="{name}" type="{kind}">',
            f'    <parent link="{parent}"/>',
            f'    <child link="{links[i]}"/>',
            f"    {_origin(after_prev @ before)}",
            '    <axis xyz="0 0 1"/>',
            f"    {limit}",
            "  </joint>",
        ]
        after_prev = after
    lines += [
        f'  <link name="{TIP_LINK}"/>',
        f'  <joint name="{TIP_LINK}_joint" type="fixed">',
        f'    <parent link="{links[-1]}"/>',
        f'    <child link="{TIP_LINK}"/>',
        f"    {_origin(after_prev @ table.flange)}",
        "  </joint>",
        "</robot>",
    ]
    return "\n".join(lines) + "\n"


def from_dh(
    cls,
    table,
    convention: str | None = None,
    *,
    name: str | None = None,
    base=None,
    flange=None,
    units=None,
    dtype: torch.dtype = torch.float64,
):
    """Robot from a DH or modified-DH table (``Robot.from_dh``).

    Args:
        table: a ``.csv`` / ``.yaml`` file, a list of row mappings, a pandas DataFrame
            or a :class:`~hybrid_pk.robot.dh_table.DHTable` (columns and units:
            :mod:`hybrid_pk.robot.dh_table`).
        convention: ``"dh"`` or ``"mdh"`` (see :mod:`hybrid_pk.robot.dh`); required
            unless a YAML file states it.
        name: robot name (default the file's, else its stem).
        base: ``(4, 4)`` or ``{xyz, rpy}``: root link -> table frame 0 (default identity).
        flange: table frame ``n`` -> end link ``flange`` (default identity).
        units: the units the table is written in, ``{"length": "mm", "angle": "deg"}``
            (default m and rad; a YAML file may state them as ``units``).
        dtype: floating dtype of the robot's parameters.

    Raises:
        DataError: a bad table, naming file, row and column.
    """
    checked = read_dh_table(table, convention, name=name, base=base, flange=flange, units=units)
    return cls.from_urdf(urdf_copy(dh_urdf(checked), checked.name), end_link=TIP_LINK, dtype=dtype)
