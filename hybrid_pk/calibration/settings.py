"""The settings of a fit and of a diagnosis, typed: what ``diagnose``, ``calibrate`` and
``evaluate --fit-frames`` take as flags (derived from these fields by
:mod:`hybrid_pk.cli.settings_flags`), what :func:`~hybrid_pk.calibration.diagnose` and
:func:`~hybrid_pk.pipelines.calibration.calibrate` take as keywords (their defaults
are read from here) and what a YAML may set (:meth:`DiagnosisSettings.parse`).

    settings = DiagnosisSettings(holdout=0.3, robust="cauchy", gravity="level-tracker")
    result = diagnose(robot, data, **settings.keywords())
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from hybrid_pk.calibration.frames import (
    DEFAULT_TOOL_STD_M,
    MAX_TOOL_TRANSLATION_M,
    FramePriors,
    FrameSpec,
    parse_frame_spec,
)
from hybrid_pk.calibration.robust import check_robust
from hybrid_pk.calibration.tuning import DiagnosisTuning
from hybrid_pk.effects import ExtendedModel
from hybrid_pk.effects.gravity import Gravity, parse_gravity
from hybrid_pk.errors import HybridPKError
from hybrid_pk.settings import (
    Checked,
    in_open_unit,
    non_negative,
    parse_settings,
    positive,
    setting,
)

__all__ = ["DiagnosisSettings", "FitSettings"]

_FRAME_HELP = (
    "{what} known from outside the data, X,Y,Z[,RX,RY,RZ] in metres and roll-pitch-yaw "
    "radians ({frame}): fixed as given (only the translation with three values), or "
    "after 'seed:' a start and prior that the data refine where they determine it"
)


def _at_least_one(value: int) -> str | None:
    return None if value >= 1 else f"expected at least 1, got {value}"


def _probability(value: float) -> str | None:
    return None if 0.0 < value < 1.0 else f"expected a probability in (0, 1), got {value:g}"


def _count(value: int) -> str | None:
    return None if value >= 0 else f"expected 0 or more, got {value}"


@dataclass
class FitSettings(Checked):
    """How every fit of a calibration runs: known frames, loss, mounting."""

    tool: str | None = setting(
        None,
        _FRAME_HELP.format(
            what="tool frame (the measured point on the flange, e.g. from the target's "
            "mount drawing)",
            frame="flange frame",
        ),
        "X,Y,Z[,RX,RY,RZ]",
    )
    base: str | None = setting(
        None,
        _FRAME_HELP.format(
            what="base frame (the robot root in the measurement frame)",
            frame="measurement frame",
        ),
        "X,Y,Z[,RX,RY,RZ]",
    )
    max_tool_offset: float = setting(
        MAX_TOOL_TRANSLATION_M,
        "a fitted tool translation beyond M metres from the flange is reported as "
        "implausible (default: {default})",
        "M",
        check=positive,
    )
    robust: Literal["none", "huber", "cauchy"] = setting(
        "none",
        "down-weight rows with gross errors (a broken beam, a bad visit): huber "
        "(bounded influence) or cauchy (a wild row has no pull); every down-weighted row "
        "is reported (default: none, plain least squares)",
    )
    gravity: str | None = setting(
        None,
        "how the robot is mounted, for compliance and deflection: gravity in the "
        "robot's root frame [m/s^2] (ceiling: 0,0,9.81), or level-tracker: the "
        "measurement frame is levelled (laser tracker, total station), so gravity is -z "
        "there and its direction in the robot frame follows from the fitted base frame "
        "(default: upright, 0,0,-9.81)",
        "X,Y,Z|level-tracker",
    )

    @classmethod
    def parse(cls, values: dict, base: dict | None = None) -> FitSettings:
        """The settings of ``values`` (None: not given) over ``base`` (a YAML's
        mapping), checked by jsonargparse and the fields' checks.

        Raises:
            HybridPKError: a value of the wrong type, choice or range.
        """
        return parse_settings(cls, values, base=base)

    def priors(self, previous: ExtendedModel | None = None) -> FramePriors:
        """The known frames of ``tool``/``base``; without ``tool``, the tool of a
        ``previous`` model (one frame set) is the centre of the tool's prior.

        Raises:
            HybridPKError: a frame that does not parse, a fixed tool beyond
                ``max_tool_offset``.
        """
        tool = None if self.tool is None else parse_frame_spec(self.tool, "--tool")
        base = None if self.base is None else parse_frame_spec(self.base, "--base")
        if tool is None and previous is not None and previous.tool.sets == 1:
            T = previous.tool.matrix()[0].detach()
            tool = FrameSpec(
                T[:3, 3].clone(), None, fixed=False, std_m=DEFAULT_TOOL_STD_M,
                source="the model's tool frame",
            )  # fmt: skip
        limit = self.max_tool_offset
        if tool is not None and tool.fixed and float(tool.translation.norm()) > limit:
            raise HybridPKError(
                f"--tool {self.tool}: a tool {float(tool.translation.norm()):.3g} m from the "
                f"flange is beyond --max-tool-offset ({limit:g} m); check the units (metres)"
            )
        return FramePriors(tool=tool, base=base, max_tool_m=limit)

    def loss(self) -> str | None:
        """The robust loss, or None for least squares."""
        return check_robust(self.robust)

    def mounting(self) -> Gravity:
        """The mounting (``gravity``; default upright)."""
        return parse_gravity(self.gravity)


@dataclass
class DiagnosisSettings(FitSettings):
    """One diagnosis (``diagnose``; ``calibrate --effects auto`` takes the hold-out,
    seed, margin and transfer check from here)."""

    holdout: float = setting(
        0.2,
        "fraction of the rows (0-1) kept out of every fit to compare the models "
        "(default: {default})",
        "F",
        check=in_open_unit,
    )
    seed: int = setting(
        0,
        "seed of the hold-out split, of the blocked hold-out's k-means starts and of the "
        "--refit-rows rows (default: {default})",
        "K",
    )
    candidates: list[str] | None = setting(
        None,
        "comma-separated effects to consider, e.g. "
        "joint_offset:joint_2,joint_compliance:joint_3 (default: every effect the data "
        "could reveal)",
        "LIST",
    )
    alpha: float = setting(
        1e-3,
        "false-positive rate of the significance test per selection step (default: {default})",
        check=_probability,
    )
    # 24: a bound on the work, not a selection rule: four causes per joint of a six-axis
    # arm (a zero, a length, a tilt, an elastic or transmission error). The search's own
    # rules (significance, the blocked margin, resolved orders, plausibility of every
    # effect) end it first: 13 causes on the shared UR10 series. A search that reaches
    # it says so (the next candidate's gain); --max-causes N names fewer or more.
    max_causes: int = setting(24, "stop after N causes (default: {default})", "N",
                               check=_at_least_one)  # fmt: skip
    min_gain_mm: float | None = setting(
        None,
        "practical margin: a cause is named only if it lowers the RMS error on "
        "blocked hold-out rows (regions of joint space, whole files) by at least MM "
        "(default: the measurement noise / 10, the standard error of an RMS error "
        "measured on 50 check poses; the noise from residual differences of the closest "
        "pairs of poses per file, capped by the fit's sigma)",
        "MM",
        check=non_negative,
    )
    # 12 frame parameters (9 position-only) from 3 N position equations leave a re-fit
    # error of about sqrt(12 / 150) = 0.28 of the noise at N = 50, well under the noise
    # itself; and 50 rows are a few minutes' measuring.
    refit_rows: int = setting(
        50,
        "with several DATA files: leave each file out, fit on the others, re-fit the "
        "frames on N random rows of it and report the errors on its other rows (default "
        "{default}: the re-fit then adds about 0.3x the noise; 0: no check)",
        "N",
        check=_count,
    )
    stability: int = setting(
        1,
        "diagnose the same rows N times, with the seeds from --seed on, and report in "
        "how many runs each cause is named (the first run stays the diagnosis; each "
        "run costs a diagnosis; default: {default}, once)",
        "N",
        check=_at_least_one,
    )
    tuning: DiagnosisTuning = field(default_factory=DiagnosisTuning, metadata={"flag": False})

    def keywords(self) -> dict:
        """The keywords of :func:`~hybrid_pk.calibration.diagnose` these settings give
        (the data's ``frames_per_file`` and the ``progress`` are the caller's)."""
        return {
            "holdout": self.holdout, "seed": self.seed, "candidates": self.candidates,
            "alpha": self.alpha, "max_causes": self.max_causes, "frames": self.priors(),
            "robust": self.loss(), "gravity": self.mounting(),
            "min_gain_mm": self.min_gain_mm, "tuning": self.tuning,
        }  # fmt: skip
