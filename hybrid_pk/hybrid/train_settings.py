"""The settings of one hybrid training job, typed: what ``hybrid-pk train``'s flags set
(derived from these fields: name, type, choices and help) and what its ``--config``
YAML may set, parsed and checked by jsonargparse from this one dataclass.

A field left None takes the preset's value (``hybrid_pk.training.presets``), else
the default of :class:`~hybrid_pk.hybrid.builder.HybridSettings` or of
:class:`~hybrid_pk.training.HybridLitModule` (which takes its defaults from
``HybridSettings``): every default is written once, and each help states it from there.

    settings = TrainSettings.parse({"preset": "joints", "fade": 0.1})
    model, data, trainer = settings.sections()
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

from hybrid_pk.errors import HybridPKError
from hybrid_pk.hybrid.builder import HybridSettings, check_trust
from hybrid_pk.hybrid.nets import parse_arch
from hybrid_pk.hybrid.tuning import HybridTuning
from hybrid_pk.settings import (
    at_least_one,
    in_open_unit,
    non_negative,
    parse_settings,
    positive,
)

__all__ = ["MODULE_FIELDS", "TrainSettings", "field_help"]

_S = HybridSettings()
ARCH_FIELDS = ("position_net", "orientation_net", "refine_net", "local_net")
# the fields that are arguments of the Lightning module (``model`` section)
MODULE_FIELDS = (
    "position_net", "orientation_net", "lr", "input_range", "fade", "inputs", "trust",
    "coverage_ratio", "refine_net", "local_net", "spread", "blocked",
)  # fmt: skip


def _help(text: str, metavar: str | None = None, switch: str | None = None, check=None) -> dict:
    """A field's help (``{...}`` filled from the HybridSettings defaults), its metavar,
    for a boolean the ``--no-X`` switch that turns it off, and its range ``check``
    (what is wrong with a value, or None: the flag's usage error, :meth:`check`)."""
    return {
        "help": text.format(**dataclasses.asdict(_S)),
        "metavar": metavar,
        "switch": switch,
        "check": check,
    }


@dataclass
class TrainSettings:
    """One hybrid training (None: the preset's value, else the settings' default)."""

    position_net: str | None = field(
        default=None, metadata=_help("position network (default: preset)", "ARCH")
    )
    orientation_net: str | None = field(
        default=None, metadata=_help("orientation network (default: preset)", "ARCH")
    )
    preset: Literal["fast", "joints", "paper"] = field(
        default="fast",
        metadata=_help(
            "fast (physics-chosen stages), joints (MLPs on every joint), paper (D4w / Rw); "
            "default: fast"
        ),
    )
    epochs: int | None = field(
        default=None,
        metadata=_help(
            "maximum training epochs of the networks (default: preset)", "N", check=at_least_one
        ),
    )
    batch_size: int | None = field(
        default=None, metadata=_help("training rows per step", "N", check=at_least_one)
    )
    lr: float | None = field(
        default=None, metadata=_help("(peak) learning rate", "LR", check=positive)
    )
    patience: int | None = field(
        default=None,
        metadata=_help(
            "early stopping after N epochs without validation gain (0: off)",
            "N",
            check=non_negative,
        ),
    )
    val_fraction: float | None = field(
        default=None,
        metadata=_help(
            "share of rows held out for validation (default: preset)", "F", check=in_open_unit
        ),
    )
    input_range: Literal["data", "limits"] | None = field(
        default=None, metadata=_help("input normalisation range")
    )
    fade: float | None = field(
        default=None,
        metadata=_help(
            "fade-out width outside the training joint box, fraction of its size per "
            "joint (default {fade:g}: no correction outside the box)",
            "F",
        ),
    )
    inputs: str | None = field(
        default=None,
        metadata=_help(
            "network stages: joints (the paper's), frameK[+qI-J][+gravity][+torque|+full] "
            "or local[+q1], joined by ',' (fall-back) and '/' (refinement), e.g. "
            "frame1+qarm+torque/joints,local+q1 (default: preset)",
            "SPEC",
        ),
    )
    trust: Literal["auto", "box", "coverage", "none"] | None = field(
        default=None,
        metadata=_help(
            "where the networks apply: joint box, coverage of their inputs, everywhere "
            "(default {trust}: box for joints, coverage for frameK inputs)"
        ),
    )
    refine_net: str | None = field(
        default=None,
        metadata=_help(
            "architecture of the refining stages' networks ('/' in --inputs; default: "
            "{refine_net})",
            "ARCH",
        ),
    )
    local_net: str | None = field(
        default=None,
        metadata=_help(
            "architecture of each joint's network in local stages (default: {local_net})",
            "ARCH",
        ),
    )
    coverage_ratio: float | None = field(
        default=None,
        metadata=_help(
            "--trust coverage: networks off beyond R x the full-trust radius "
            "(default {coverage_ratio:g})",
            "R",
        ),
    )
    spread: bool | None = field(
        default=None,
        metadata=_help(
            "keep a refined stage's full correction where its refine stage is off (default: "
            "shrink it by the spread of its training targets)",
            switch="--no-spread",
        ),
    )
    blocked: bool | None = field(
        default=None,
        metadata=_help(
            "no probe fits on blocked hold-out: every stage on physics inputs stays gated to "
            "its training joints (default: freed where the blocked hold-out shows it carries "
            "over)",
            switch="--no-blocked",
        ),
    )
    # no flag: set through the API or the ``tuning`` mapping of a --config YAML
    tuning: HybridTuning = field(default_factory=HybridTuning, metadata={"flag": False})

    @classmethod
    def parse(cls, values: dict, base: dict | None = None) -> TrainSettings:
        """The settings of ``values`` (None: not given) over ``base`` (a YAML's values:
        flag > YAML > default), types and choices checked by jsonargparse against the
        fields; then the ranges (:meth:`check`).

        Raises:
            HybridPKError: a value of the wrong type, choice or range, an unknown key.
        """
        settings = parse_settings(cls, values, base=base)
        settings.check()
        return settings

    def check(self) -> None:
        """Ranges and forms, before any data is read.

        Raises:
            HybridPKError: a fade, coverage ratio, trust or architecture out of range,
                epochs or a batch size below 1, a learning rate not above 0, a negative
                patience (from a YAML; the flags' usage error says it first).
        """
        for f in dataclasses.fields(self):
            check, value = f.metadata.get("check"), getattr(self, f.name)
            why = None if check is None or value is None else check(value)
            if why:
                raise HybridPKError(f"--{f.name.replace('_', '-')} ({f.name}): {why}")
        if self.fade is not None and not 0 <= self.fade <= 10:  # 10: the whole joint range
            raise HybridPKError(f"--fade must be between 0 and 10, got {self.fade}")
        if self.coverage_ratio is not None and not self.coverage_ratio > 1:
            # beyond the validation rows' own radius, or nothing would be trusted
            raise HybridPKError(f"--coverage-ratio must be > 1, got {self.coverage_ratio}")

    def sections(self, config: dict | None = None) -> tuple[dict, dict, dict]:
        """Module, datamodule and trainer overrides: the ``model``/``data``/``trainer``
        sections of a LightningCLI YAML (``config``, read by
        :func:`~hybrid_pk.training.presets.settings_from_config`) first, then these
        settings (the preset is not in them: it is their base). Checked before any data
        is read.

        Raises:
            HybridPKError: inputs that do not parse or suit the trust, an unknown
                architecture.
        """
        config = config or {}
        model, data, trainer = (dict(config.get(k) or {}) for k in ("model", "data", "trainer"))
        model.update({k: getattr(self, k) for k in MODULE_FIELDS if getattr(self, k) is not None})
        if model.get("inputs", "joints") != "joints":
            check_trust(model.get("trust", "auto"), model["inputs"])  # naming the forms
        for key in ARCH_FIELDS:
            if model.get(key, "none") != "none":
                parse_arch(model[key])
        if self.batch_size is not None:
            data["batch_size"] = self.batch_size
        if self.val_fraction is not None:
            data["val_fraction"] = self.val_fraction
        if self.epochs is not None:
            trainer["max_epochs"] = self.epochs
        if self.patience is not None:
            trainer["patience"] = self.patience or None
        return model, data, trainer


def field_help(f: dataclasses.Field) -> dict:
    """``help``, ``metavar`` and ``switch`` of a :class:`TrainSettings` field."""
    return dict(f.metadata)
