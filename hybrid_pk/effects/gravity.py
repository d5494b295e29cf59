"""Which way gravity pulls: the mounting of the robot, for every static load.

Robots hang from ceilings, stand on walls and on tilted mobile bases. Compliance and
deflection follow the real gravity, so a model carries a :class:`Gravity`:

- ``frame = "root"``: a fixed vector in the robot's root frame (``--gravity X,Y,Z``
  [m/s²]); the default ``(0, 0, -9.80665)`` is a robot standing level on the floor;
- ``frame = "measurement"`` (``--gravity level-tracker``): the measurement frame is
  levelled, as laser trackers and total stations are, so gravity is ``-z`` there; in
  the robot frame it is ``R_base^T (0, 0, -g)``, with ``R_base`` the rotation of the
  fitted base frame ``T_meas_root`` (one per file with ``--frames-per-file``). Nothing
  about the mounting needs to be known: the fitted base frame carries it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from hybrid_pk.errors import HybridPKError
from hybrid_pk.robot import STANDARD_GRAVITY

__all__ = ["GRAVITY_FRAMES", "LEVEL_TRACKER", "Gravity", "parse_gravity", "unloaded_reason"]

LEVEL_TRACKER = "level-tracker"
GRAVITY_FRAMES = ("root", "measurement")
# Gravity on the Earth's surface is 9.76-9.83 m/s^2; a vector far outside this range is
# a unit mistake (a direction of norm 1, or g in g's).
_CREDIBLE_G = (9.0, 10.5)


@dataclass(frozen=True)
class Gravity:
    """Gravity acceleration for the statics of a model.

    Attributes:
        vector: ``(gx, gy, gz)`` [m/s²] in ``frame``.
        frame: ``"root"`` (robot root frame) or ``"measurement"`` (the levelled
            measurement frame; the robot-frame direction follows from the base frame).
    """

    vector: tuple[float, float, float] = (0.0, 0.0, -STANDARD_GRAVITY)
    frame: str = "root"

    def __post_init__(self) -> None:
        if self.frame not in GRAVITY_FRAMES:
            raise HybridPKError(
                f"gravity frame must be one of {', '.join(GRAVITY_FRAMES)}, got {self.frame!r}"
            )
        vector = tuple(float(v) for v in self.vector)
        if len(vector) != 3 or not all(math.isfinite(v) for v in vector):
            raise HybridPKError(f"gravity must be 3 finite numbers [m/s^2], got {self.vector}")
        object.__setattr__(self, "vector", vector)

    @classmethod
    def level_tracker(cls) -> Gravity:
        """Gravity ``-z`` in a levelled measurement frame (laser tracker, total station)."""
        return cls((0.0, 0.0, -STANDARD_GRAVITY), "measurement")

    @property
    def levelled(self) -> bool:
        """True when gravity is known in the measurement frame (it follows the base)."""
        return self.frame == "measurement"

    @property
    def is_default(self) -> bool:
        return self == Gravity()

    def describe(self) -> str:
        """``level-tracker`` or ``(gx, gy, gz) m/s^2 in the robot root frame``."""
        if self.levelled and self.vector == Gravity.level_tracker().vector:
            return LEVEL_TRACKER
        where = "levelled measurement" if self.levelled else "robot root"
        vec = ", ".join(f"{v:.4g}" for v in self.vector)
        return f"({vec}) m/s^2 in the {where} frame"

    def to_dict(self) -> dict:
        return {"vector": list(self.vector), "frame": self.frame}

    @classmethod
    def from_dict(cls, entry: dict | None) -> Gravity:
        """Inverse of :meth:`to_dict`; None (older model files) is the default."""
        if entry is None:
            return cls()
        return cls(tuple(entry["vector"]), str(entry["frame"]))


def parse_gravity(text: str | None) -> Gravity:
    """``--gravity`` text: ``X,Y,Z`` [m/s²] in the robot root frame, or ``level-tracker``.

    None or empty gives the default (robot level on the floor, ``0,0,-9.80665``).

    Raises:
        HybridPKError: anything else, or a vector whose size is not Earth gravity.
    """
    if text is None or not str(text).strip():
        return Gravity()
    text = str(text).strip()
    if text.lower() in (LEVEL_TRACKER, "level_tracker", "level"):
        return Gravity.level_tracker()
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise HybridPKError(
            f"--gravity {text!r}: give X,Y,Z [m/s^2] in the robot's root frame (a robot on "
            f"the ceiling: 0,0,9.81) or {LEVEL_TRACKER} (gravity is -z in the levelled "
            "measurement frame)"
        )
    norm = math.sqrt(sum(v * v for v in values))
    lo, hi = _CREDIBLE_G
    if not lo <= norm <= hi:
        # the same direction scaled to g (+ 0.0: no "-0"); a zero vector has none: the floor's, -z
        direction = [v / norm for v in values] if norm > 0 else [0.0, 0.0, -1.0]
        example = ",".join(f"{v * STANDARD_GRAVITY + 0.0:.3g}" for v in direction)
        raise HybridPKError(
            f"--gravity {text!r} has magnitude {norm:.4g} m/s^2; gravity is about "
            f"{STANDARD_GRAVITY:.2f} m/s^2: give the acceleration, not a direction (e.g. "
            f"{example}{'' if norm > 0 else ', a robot on the floor'})"
        )
    return Gravity(tuple(values), "root")


def unloaded_reason(robot, payload, so: str = "move nothing") -> str | None:
    """Why gravity loads no joint of ``robot`` in rows carrying ``payload`` [kg] (a
    tensor, or None: no payload column), or None where it loads one: then joint
    compliance and the deflection effects ``so`` (move no point: a DH table without
    masses), and what to give."""
    moving = float(robot.segment_mass[1:].sum()) + sum(b.mass for b in robot.spec.branches)
    if moving > 0 or (payload is not None and float(payload.abs().max()) > 0):
        return None
    return (
        f"gravity loads no joint: {robot.name}'s moving links carry no mass and the rows "
        f"no payload, so joint compliance and deflection {so} (give the links' "
        "masses: a DH table's mass, com_x, com_y, com_z columns or a URDF's <inertial>; "
        "or measure with a payload column)"
    )
