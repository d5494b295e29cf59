"""The hybrid training workflow: a base model (frames fitted to the data where asked)
-> residual networks (:func:`~hybrid_pk.training.train_hybrid`) -> a model file with
the training's record.

    loaded = load_model("model.pt")
    cond, base = base_for_training(loaded, data, sets=1, fit_frames=False)
    job = train_job(loaded, data, cond, base, model_label="model.pt", out="hybrid.pt")
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from hybrid_pk.data import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel, conditions_from_data
from hybrid_pk.hybrid.train_settings import MODULE_FIELDS
from hybrid_pk.hybrid.train_settings import TrainSettings as TrainSettings
from hybrid_pk.hybrid.tuning import ACTIVE as HYBRID_TUNING
from hybrid_pk.io.model_file import LoadedModel
from hybrid_pk.pipelines.calibration import refit_frames
from hybrid_pk.pipelines.refit import with_frame_sets

__all__ = [
    "TrainJob",
    "TrainSettings",
    "base_for_training",
    "is_main_process",
    "train_job",
    "train_settings",
    "training_sections",
]


@dataclass(frozen=True)
class TrainJob:
    """What :func:`train_job` returns.

    Attributes:
        result: the training (:class:`~hybrid_pk.training.run.TrainResult`).
        frames_fitted: whether the saved model's base and tool frames were fitted.
        metadata: the model file's metadata with this training's record.
        out: the model file written (None in a DDP run's extra processes or without
            ``out``).
    """

    result: object
    frames_fitted: bool
    metadata: dict
    out: Path | None


def train_settings(flags: dict, config: str | os.PathLike | None = None) -> TrainSettings:
    """The :class:`TrainSettings` of ``flags`` (None: not given) over the LightningCLI YAML
    ``config``: flag > YAML > preset > default. The YAML's ``model`` keys that are fields,
    ``data.batch_size`` / ``val_fraction``, ``trainer.max_epochs``, the patience of its
    ``EarlyStopping`` (none: 0, off) and its top-level ``preset`` and ``tuning`` are
    parsed into the fields, checked by jsonargparse like the flags.

    Raises:
        HybridPKError: the YAML cannot be read, or a value of the wrong type or range.
    """
    from hybrid_pk.training.presets import settings_from_config

    base: dict = {}
    if config:
        sections = settings_from_config(config)
        model, data, trainer = (sections[k] for k in ("model", "data", "trainer"))
        base = {k: v for k, v in model.items() if k in MODULE_FIELDS}
        base |= {k: data[k] for k in ("batch_size", "val_fraction") if k in data}
        if "max_epochs" in trainer:
            base["epochs"] = trainer["max_epochs"]
        base["patience"] = trainer.get("patience") or 0
        base |= sections.get("settings", {})
    return TrainSettings.parse(flags, base=base)


def training_sections(
    settings: TrainSettings, config: str | os.PathLike | None = None
) -> tuple[dict, dict, dict]:
    """Module, datamodule and trainer overrides of ``settings`` over the LightningCLI
    YAML ``config`` (:meth:`TrainSettings.sections`), checked before any data is read."""
    from hybrid_pk.training.presets import settings_from_config

    return settings.sections(settings_from_config(config) if config else None)


def is_main_process() -> bool:
    """False in the extra processes a DDP run starts (they re-run the command)."""
    return all(int(os.environ.get(var, "0")) == 0 for var in ("LOCAL_RANK", "NODE_RANK"))


def base_for_training(
    loaded: LoadedModel, data: MeasuredData, sets: int, fit_frames: bool
) -> tuple[Conditions, ExtendedModel]:
    """The rows' conditions and the base model: MODEL's, or with ``fit_frames`` its
    base and tool frames (``sets`` of them) fitted to ``data``."""
    cond = conditions_from_data(data, sets > 1)
    base = loaded.model
    if fit_frames:
        base = with_frame_sets(base, sets)
        refit_frames(base, data, cond)
    return cond, base


def train_job(
    loaded: LoadedModel,
    data: MeasuredData,
    cond: Conditions,
    base: ExtendedModel,
    *,
    model_label: str,
    out: str | os.PathLike | None = None,
    settings: TrainSettings | None = None,
    config: str | os.PathLike | None = None,
    fit_frames: bool = False,
    seed: int = 0,
    logdir: str | os.PathLike | None = None,
    progress: bool | Callable[[str], None] = True,
    strategy: str = "auto",
    devices: int = 1,
    resume: bool = False,
) -> TrainJob:
    """Train the residual networks over ``base`` (:func:`base_for_training`) and write
    ``out``: MODEL (``loaded``, named ``model_label`` in the record) plus the networks.

    Args:
        settings: the preset and what differs from it (default: the ``fast`` preset);
            ``config`` a LightningCLI YAML read first (:func:`training_sections`).
        seed, logdir, progress, strategy, devices, resume: as in
            :func:`~hybrid_pk.training.train_hybrid`.
    """
    from hybrid_pk.io.hybrid_file import save_hybrid
    from hybrid_pk.training import train_hybrid

    settings = settings or TrainSettings()
    preset = settings.preset
    model_over, data_over, trainer_over = training_sections(settings, config)
    with HYBRID_TUNING.using(settings.tuning):  # the modules read it while training
        result = train_hybrid(
            data, base, cond, preset_name=preset, model=model_over, datamodule=data_over,
            max_epochs=trainer_over.get("max_epochs"),
            patience=trainer_over.get("patience", "preset"), seed=seed, logdir=logdir,
            progress=progress, strategy=strategy, devices=devices, resume=resume,
        )  # fmt: skip
    frames_fitted = loaded.frames_fitted or fit_frames
    metadata = {k: v for k, v in loaded.metadata.items() if k != "created"}
    metadata["training"] = {
        "command": "train",
        "base_model": model_label,
        "data": list(data.sources),
        "n_rows": data.n,
        "preset": preset,
        "seed": seed,
        "epochs": result.epochs,
        "resumed": None
        if result.resumed is None
        else {"checkpoint": result.resumed[0], "epochs_done": result.resumed[1]},
        "seconds": round(result.seconds, 3),
        "validation_base": result.base,
        "validation_hybrid": result.final,  # the model as written (after the gates)
        "blocked": result.blocked,
        "logdir": result.logdir,
    }
    written = None
    if result.is_global_zero and out is not None:
        written = Path(out)
        save_hybrid(
            out, result.hybrid, metadata=metadata, frames_fitted=frames_fitted,
            training={"settings": result.settings, "best": result.best},
        )  # fmt: skip
    return TrainJob(result, frames_fitted, metadata, written)
