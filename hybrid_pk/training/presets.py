"""Training presets: the paper's settings and our faster defaults.

Each preset has the three sections of a LightningCLI config: ``model`` (arguments of
:class:`~hybrid_pk.training.HybridLitModule`), ``data`` (of
:class:`~hybrid_pk.training.HybridDataModule`, without the file paths) and
``trainer`` (``max_epochs`` and ``patience`` of early stopping on ``val/score``;
None: no early stopping, each network still keeps its best validation state).
``train/configs/{paper,fast,joints}.yaml`` spell the same values (a test keeps them
equal). Ours state only what differs from the module's defaults (one source of each);
:func:`full_model_settings` fills in the rest for the record of a training.
"""

from __future__ import annotations

import copy
from pathlib import Path

from hybrid_pk.errors import HybridPKError, not_utf8_error

__all__ = ["PRESETS", "full_model_settings", "preset", "settings_from_config"]


def _ours(networks: dict) -> dict[str, dict]:
    """One of our presets: the ``networks`` (inputs and architectures) over the module's
    own defaults (Adam + one-cycle, lr 0.003, MSE, inputs scaled to the data,
    zero-initialised outputs; :class:`~hybrid_pk.training.HybridLitModule`, whose network
    defaults are :class:`~hybrid_pk.hybrid.builder.HybridSettings`'), with our batches and
    epochs; fresh dicts on every call."""
    return {
        "model": dict(networks),
        "data": {"batch_size": 256, "val_fraction": 0.1},
        "trainer": {"max_epochs": 150, "patience": None},
    }


PRESETS: dict[str, dict[str, dict]] = {
    # Ojer et al. 2024, 4.1.1: min-max input normalisation over the full joint range,
    # Adagrad, lr 0.005, batch 128, at most 300 epochs, early stopping on validation;
    # the paper's best networks D4w (position) and Rw (orientation); the paper's losses
    # (mean distance, mean angle); default initialisation.
    "paper": {
        "model": {
            "position_net": "D4w",
            "orientation_net": "Rw",
            "optimizer": "adagrad",
            "lr": 0.005,
            "weight_decay": 0.0,
            "scheduler": "none",
            "loss": "norm",
            "input_range": "limits",
            "inputs": "joints",
            "zero_init": False,
        },
        "data": {"batch_size": 128, "val_fraction": 0.2},
        "trainer": {"max_epochs": 300, "patience": 10},
    },
    # Ours (issue 13): networks whose frames and inputs the physics chooses, in a cascade
    # of fall-backs: posture networks in link 1's frame (qarm: the joints after it that
    # move the flange point, and the gravity torques) refined by networks on every joint
    # where both are covered, then local deformation networks (one per joint: its angle
    # and static wrench), then the base model; the posture and local stages used away
    # from their training joints only where blocked hold-out frees them (issue 27).
    # Small smooth MLPs starting at the base model, Adam + one-cycle.
    "fast": _ours(
        {
            "inputs": "frame1+qarm+torque/joints,local+q1",
            "position_net": "mlp:128x3",
            "orientation_net": "mlp:128x3",
        }
    ),
    # Ours before issue 13: the same schedule, MLPs on every joint (the paper's inputs),
    # the base model outside the training rows' joint box.
    "joints": _ours({"inputs": "joints"}),
}


def preset(name: str) -> dict[str, dict]:
    """A deep copy of preset ``name`` (``paper``, ``fast`` or ``joints``)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; one of {', '.join(PRESETS)}")
    return copy.deepcopy(PRESETS[name])


def full_model_settings(model: dict) -> dict:
    """Every argument of :class:`~hybrid_pk.training.HybridLitModule`: its defaults,
    then ``model``'s values."""
    import inspect

    from hybrid_pk.training.lightning_module import HybridLitModule

    params = inspect.signature(HybridLitModule.__init__).parameters.values()
    defaults = {p.name: p.default for p in params if p.default is not inspect.Parameter.empty}
    return {**defaults, **model}


def _init_args(section) -> dict:
    """``{class_path, init_args}`` or plain keys of a LightningCLI section."""
    if not isinstance(section, dict):
        return {}
    return dict(section.get("init_args", section))


def _check_keys(path, section: str, values: dict, cls) -> None:
    """Refuse keys of a section that its Lightning class does not take (before: a
    TypeError from its constructor after the data were read, an 'internal error')."""
    import inspect

    known = [n for n in inspect.signature(cls.__init__).parameters if n != "self"]
    unknown = sorted(set(values) - set(known) - {"seed"})
    if unknown:
        raise HybridPKError(
            f"config {path}: unknown {section} key(s) {', '.join(unknown)}; known: "
            f"{', '.join(known)}"
        )


def settings_from_config(path: str | Path) -> dict[str, dict]:
    """The ``model`` / ``data`` / ``trainer`` settings of a LightningCLI YAML config.

    ``data`` leaves out the file paths (``data``, ``model``); ``trainer`` keeps
    ``max_epochs`` and the ``patience`` of an ``EarlyStopping`` callback (None when the
    config has none); ``settings`` (if any) the top-level ``preset`` and ``tuning`` that
    ``hybrid-pk train`` reads (:func:`hybrid_pk.pipelines.training.train_settings`).

    Raises:
        HybridPKError: the file cannot be read or is not a mapping, or a ``model`` /
            ``data`` key is no argument of the Lightning module / datamodule.
    """
    import yaml

    try:
        cfg = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise not_utf8_error(path, table=False) from None
    except (OSError, yaml.YAMLError) as exc:
        raise HybridPKError(f"cannot read config {path}: {exc}") from exc
    if not isinstance(cfg, dict):
        raise HybridPKError(f"config {path}: expected a YAML mapping with model/data/trainer")
    model = _init_args(cfg.get("model"))
    data = {k: v for k, v in _init_args(cfg.get("data")).items() if k not in ("data", "model")}
    data.pop("seed", None)
    from hybrid_pk.training.datamodule import HybridDataModule
    from hybrid_pk.training.lightning_module import HybridLitModule

    _check_keys(path, "model", model, HybridLitModule)
    _check_keys(path, "data", data, HybridDataModule)
    raw = cfg.get("trainer") or {}
    trainer: dict = {"patience": None}
    if "max_epochs" in raw:
        trainer["max_epochs"] = int(raw["max_epochs"])
    for cb in raw.get("callbacks") or []:
        if isinstance(cb, dict) and str(cb.get("class_path", "")).endswith("EarlyStopping"):
            trainer["patience"] = int(cb.get("init_args", {}).get("patience", 3))
    # hybrid-pk train's own keys: the preset the sections sit over, the hybrid's tuning
    settings = {k: cfg[k] for k in ("preset", "tuning") if k in cfg}
    return {"model": model, "data": data, "trainer": trainer} | (
        {"settings": settings} if settings else {}
    )
