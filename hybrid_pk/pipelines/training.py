"""The hybrid training workflow: a base model (frames fitted to the data where asked)
-> residual networks (:func:`~hybrid_pk.training.train_hybrid`) -> a model file with
the training's record.

    job = train_job(load_model("model.pt"), data, model_label="model.pt", out="hybrid.pt")
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from hybrid_pk.data import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel, conditions_from_data
from hybrid_pk.errors import HybridPKError
from hybrid_pk.hybrid.nets import parse_arch
from hybrid_pk.io.model_file import LoadedModel
from hybrid_pk.pipelines.calibration import refit_frames
from hybrid_pk.pipelines.refit import with_frame_sets

__all__ = ["TrainJob", "base_for_training", "hybrid_overrides", "is_main_process", "train_job"]

# the flags named as the Lightning module's arguments
MODULE_FLAGS = (
    "position_net", "orientation_net", "lr", "input_range", "fade", "inputs", "trust",
    "coverage_ratio", "refine_net", "local_net", "spread", "blocked",
)  # fmt: skip


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


def hybrid_overrides(
    config: str | os.PathLike | None,
    model_flags: dict,
    *,
    batch_size: int | None = None,
    val_fraction: float | None = None,
    epochs: int | None = None,
    patience: int | None = None,
) -> tuple[dict, dict, dict]:
    """Module, datamodule and trainer overrides: the YAML ``config`` first, then the
    given values (None: not given), checked before any data is read.

    Raises:
        HybridPKError: a fade, coverage ratio, trust or architecture out of its range.
    """
    from hybrid_pk.training.presets import settings_from_config

    model, data, trainer = ({}, {}, {})
    if config:
        cfg = settings_from_config(config)
        model, data, trainer = cfg["model"], cfg["data"], cfg["trainer"]
    model.update({k: v for k, v in model_flags.items() if v is not None})
    fade, ratio = model_flags.get("fade"), model_flags.get("coverage_ratio")
    if fade is not None and not 0 <= fade <= 10:  # 10 box sizes: the joints' whole range
        raise HybridPKError(f"--fade must be between 0 and 10, got {fade}")
    if ratio is not None and not ratio > 1:  # beyond the validation rows' own radius
        raise HybridPKError(f"--coverage-ratio must be > 1, got {ratio}")
    if model.get("inputs", "joints") != "joints":
        from hybrid_pk.hybrid.builder import check_trust

        check_trust(model.get("trust", "auto"), model["inputs"])  # naming the forms
    for key in ("position_net", "orientation_net", "refine_net", "local_net"):
        if model.get(key, "none") != "none":
            parse_arch(model[key])
    if batch_size is not None:
        data["batch_size"] = batch_size
    if val_fraction is not None:
        data["val_fraction"] = val_fraction
    if epochs is not None:
        trainer["max_epochs"] = epochs
    if patience is not None:
        trainer["patience"] = patience or None
    return model, data, trainer


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
    preset: str = "fast",
    overrides: tuple[dict, dict, dict] = ({}, {}, {}),
    fit_frames: bool = False,
    seed: int = 0,
    logdir: str | os.PathLike | None = None,
    progress: bool | Callable[[str], None] = True,
    strategy: str = "auto",
    devices: int = 1,
) -> TrainJob:
    """Train the residual networks over ``base`` (:func:`base_for_training`) and write
    ``out``: MODEL (``loaded``, named ``model_label`` in the record) plus the networks.

    Args:
        overrides: module, datamodule and trainer overrides (:func:`hybrid_overrides`).
        preset, seed, logdir, progress, strategy, devices: as in
            :func:`~hybrid_pk.training.train_hybrid`.
    """
    from hybrid_pk.io.hybrid_file import save_hybrid
    from hybrid_pk.training import train_hybrid

    model_over, data_over, trainer_over = overrides
    result = train_hybrid(
        data, base, cond, preset_name=preset, model=model_over, datamodule=data_over,
        max_epochs=trainer_over.get("max_epochs"), patience=trainer_over.get("patience", "preset"),
        seed=seed, logdir=logdir, progress=progress, strategy=strategy, devices=devices,
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
        "seconds": round(result.seconds, 3),
        "validation_base": result.base,
        "validation_hybrid": result.best,
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
