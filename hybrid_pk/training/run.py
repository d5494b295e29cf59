"""`train_hybrid`: one call from measured rows + a base model to a trained `HybridFK`.

Used by ``hybrid-pk train`` and ``experiments/reproduce_paper.py``; LightningCLI users run
the same module and datamodule through ``train/cli.py`` and a YAML config.
"""

from __future__ import annotations

import logging
import math
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import lightning as L
import torch
from lightning.pytorch.callbacks import (
    Callback,
    EarlyStopping,
    LearningRateMonitor,
    ModelCheckpoint,
    TQDMProgressBar,
)
from lightning.pytorch.callbacks.progress.tqdm_progress import Tqdm
from lightning.pytorch.loggers import TensorBoardLogger

from hybrid_pk.data import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.errors import HybridPKError
from hybrid_pk.hybrid.hybrid_fk import HybridFK
from hybrid_pk.hybrid.losses import corrected_orientation_errors_deg, corrected_position_errors_mm
from hybrid_pk.hybrid.nets import parse_arch
from hybrid_pk.threads import requested_threads
from hybrid_pk.training.blocked import blocked_blocks, blocked_check, fold_rows, probe_folds
from hybrid_pk.training.datamodule import HybridDataModule
from hybrid_pk.training.figures import log_written_model
from hybrid_pk.training.interrupts import InterruptLatch
from hybrid_pk.training.lightning_module import HybridLitModule
from hybrid_pk.training.presets import full_model_settings, preset
from hybrid_pk.training.resume import data_digest, find_resume_point, interruption

__all__ = [
    "MONITOR",
    "EpochReport",
    "ProgressBar",
    "TrainResult",
    "auto_threads",
    "blocked_hold_out",
    "make_trainer",
    "quiet_lightning",
    "train_hybrid",
]

MONITOR = "val/score"
LAST = "last"  # checkpoints/last.ckpt
# Networks no wider than this train on one thread: their layers are too small for a
# parallel region to pay off, and on a busy machine each region waits for the other
# thread to be scheduled (measured: 70 x slower steps with 2 threads at load 4 on 2
# cores).
SINGLE_THREAD_WIDTH = 512


def auto_threads(archs: list[str]) -> int | None:
    """1 for small networks, None (leave torch's setting) for wide ones."""
    widths = []
    for a in archs:
        if a != "none":
            args = parse_arch(a).args
            widths += list(args.get("hidden", args.get("widths", ())))
    return 1 if max(widths, default=0) <= SINGLE_THREAD_WIDTH else None


class ProgressBar(TQDMProgressBar):
    """Lightning's epoch bar on stderr (stdout keeps the command's summary), with the
    validation errors in its postfix and no separate validation bar."""

    def init_train_tqdm(self) -> Tqdm:
        return Tqdm(
            desc=self.train_description,
            position=2 * self.process_position,
            disable=self.is_disabled,
            leave=True,
            dynamic_ncols=True,
            file=sys.stderr,
            smoothing=0,
            bar_format=self.BAR_FORMAT,
        )

    def init_validation_tqdm(self) -> Tqdm:
        return Tqdm(disable=True)


def quiet_lightning() -> None:
    """Keep Lightning's start-up chatter (accelerators found, tips, 'max_epochs reached')
    and library deprecation notes off the terminal. Lightning sets its loggers up when
    imported, so this runs after the import (this module's)."""
    logging.getLogger("lightning.pytorch").setLevel(logging.WARNING)
    warnings.filterwarnings("ignore", message=".*LeafSpec.*", category=DeprecationWarning)
    warnings.filterwarnings("ignore", message=".*LeafSpec.*", category=FutureWarning)
    warnings.filterwarnings("ignore", message=r".*distributed\.nn\.functional\.all_gather.*")
    # a resumed run writes into its own checkpoint folder (--resume)
    warnings.filterwarnings("ignore", message=r"Checkpoint directory .* exists and is not empty")


class EpochReport(Callback):
    """Calls ``say(text)`` after every epoch with the epoch count and the validation
    mean errors: progress for a caller that draws its own display (the demo).

    At the end of the training epoch, after its validation: Lightning runs a callback's
    ``on_validation_epoch_end`` before the module's, which logs the errors, so there
    the line showed the epoch before's (none after the first)."""

    def __init__(self, say: Callable[[str], None]) -> None:
        self.say = say

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        metrics = trainer.callback_metrics
        errors = [
            f"{float(metrics[f'val/{key}_{unit}_mean']):.4g} {unit}"
            for key, unit in (("position", "mm"), ("orientation", "deg"))
            if f"val/{key}_{unit}_mean" in metrics
        ]
        text = f"epoch {trainer.current_epoch + 1}/{trainer.max_epochs}"
        self.say(text + (f", validation mean {' / '.join(errors)}" if errors else ""))


@dataclass
class TrainResult:
    """Outcome of :func:`train_hybrid`.

    Attributes:
        hybrid: the trained model (eval mode), each network at its best validation state.
        best: best validation mean errors, ``position_mm`` / ``orientation_deg``.
        final: the validation mean errors of ``hybrid`` as returned, same keys: after the
            blocked hold-out freed or kept each stage's gate (``best`` is the fit's own,
            every stage gated to its training joints).
        base: the base model's validation mean errors, same keys.
        epochs: epochs run.
        seconds: wall time of the fit [s].
        logdir: TensorBoard folder of this run, or None.
        is_global_zero: False in the extra processes of a multi-process (DDP) run.
        settings: the preset with the overrides applied.
        blocked: the blocked hold-out test of each stage with a joint-space gate
            (``"<index>:<label>"`` -> record, see
            :func:`~hybrid_pk.training.blocked.blocked_check`); empty when not run.
        resumed: (checkpoint, epochs it had done) of a resumed run, else None.
    """

    hybrid: HybridFK
    best: dict[str, float]
    base: dict[str, float]
    epochs: int
    seconds: float
    logdir: str | None
    is_global_zero: bool
    settings: dict = field(default_factory=dict)
    blocked: dict = field(default_factory=dict)
    final: dict = field(default_factory=dict)
    resumed: tuple[str, int] | None = None


def make_trainer(
    *,
    max_epochs: int,
    patience: int | None = None,
    logdir: str | Path | None = None,
    progress: bool | Callable[[str], None] = True,
    strategy: str = "auto",
    devices: int = 1,
    num_nodes: int = 1,
    batches_per_epoch: int | None = None,
    resumed: dict | None = None,
) -> L.Trainer:
    """A CPU Lightning trainer with our callbacks and (with ``logdir``) TensorBoard.

    Args:
        max_epochs: at most this many epochs.
        patience: early stopping on ``val/score`` after this many epochs without
            improvement; None: off.
        logdir: TensorBoard logs and checkpoints go to ``logdir/version_K``.
        progress: show Lightning's progress bar; a callable instead gets one line of
            text per epoch (:class:`EpochReport`).
        strategy: Lightning strategy, e.g. ``"ddp"`` (one process per device).
        devices: processes (CPU devices) per node.
        num_nodes: machines.
        batches_per_epoch: training steps per epoch, if known (logging interval).
        resumed: a resumed run's ``{"version": K, "purge_step": S}``: log to
            ``logdir/version_K``, TensorBoard dropping its events from step S on;
            None: a new ``version_K``.
    """
    callbacks: list = [InterruptLatch()]  # armed by train_hybrid during its fit
    if patience is not None:
        callbacks.append(EarlyStopping(monitor=MONITOR, mode="min", patience=int(patience)))
    logger = False
    if logdir is not None:
        logger = TensorBoardLogger(
            str(logdir), name="", default_hp_metric=False, **(resumed or {"version": None})
        )
        callbacks.append(LearningRateMonitor(logging_interval="epoch"))
        callbacks.append(ModelCheckpoint(monitor=MONITOR, mode="min"))  # the best epoch
        # every epoch's end, what --resume continues from (Lightning's save_last writes
        # only when the monitored score improved)
        callbacks.append(ModelCheckpoint(filename=LAST, enable_version_counter=False))
    if callable(progress):
        callbacks.append(EpochReport(progress))
    elif progress:
        callbacks.append(ProgressBar(refresh_rate=20))
    return L.Trainer(
        accelerator="cpu",
        devices=devices,
        num_nodes=num_nodes,
        strategy=strategy,
        max_epochs=max_epochs,
        deterministic=True,
        logger=logger,
        callbacks=callbacks,
        enable_checkpointing=logdir is not None,
        enable_progress_bar=bool(progress) and not callable(progress),
        enable_model_summary=False,
        num_sanity_val_steps=0,
        log_every_n_steps=max(1, min(10, batches_per_epoch or 10)),
    )


def train_hybrid(
    data: MeasuredData,
    base: ExtendedModel,
    cond: Conditions | None = None,
    *,
    preset_name: str = "fast",
    model: dict | None = None,
    datamodule: dict | None = None,
    max_epochs: int | None = None,
    patience: int | str | None = "preset",
    seed: int = 0,
    logdir: str | Path | None = None,
    progress: bool | Callable[[str], None] = True,
    strategy: str = "auto",
    devices: int = 1,
    threads: int | None = None,
    resume: bool = False,
) -> TrainResult:
    """Train the residual networks of a :class:`HybridFK` on ``data`` over ``base``.

    Args:
        data: measured rows.
        base: the base model (nominal + fitted frames, or a calibrated model); frozen.
        cond: conditions of the rows (default from ``data``).
        preset_name: ``fast`` (ours) or ``paper`` (:mod:`~hybrid_pk.training.presets`).
        model: overrides of the module arguments (e.g. ``{"position_net": "D4w"}``).
        datamodule: overrides of the datamodule arguments (``batch_size``, ...).
        max_epochs: override of the preset's epochs.
        patience: early-stopping patience override (None: off); ``"preset"`` keeps it.
        seed: seeds the split, the initialisation and the shuffling (same seed, same
            networks).
        logdir: TensorBoard logs and checkpoints; None: no logging.
        progress: Lightning's progress bar; a callable instead gets one line of text
            per epoch (epoch count, validation errors), and Lightning's start-up
            chatter is silenced (:func:`quiet_lightning`): the caller draws the display.
        strategy: ``"auto"`` or ``"ddp"`` (with ``devices`` processes).
        devices: number of processes.
        threads: torch threads during the fit; None: the count fixed by ``--threads`` /
            ``HYBRID_PK_THREADS``, else one for networks up to
            :data:`SINGLE_THREAD_WIDTH` wide, torch's setting for wider ones.
        resume: continue the run whose last checkpoint is in ``logdir`` (same data,
            seed and settings; ``max_epochs`` None: the run's own; a one-cycle run
            cannot be given other epochs): :mod:`~hybrid_pk.training.resume`.

    Raises:
        TrainingInterrupted: Ctrl-C or SIGTERM; the message names the checkpoint kept
            and how to resume.
    """
    settings = preset(preset_name)
    _override(settings, base, model, datamodule, max_epochs, patience)
    if callable(progress):
        quiet_lightning()
    L.seed_everything(seed, workers=True, verbose=False)
    dm = HybridDataModule.from_measured(data, base, cond, seed=seed, **settings["data"])
    module = HybridLitModule(**settings["model"])
    point = _resume_point(dm, module, logdir, devices, max_epochs, progress) if resume else None
    if point is not None:
        settings["trainer"]["max_epochs"] = point.max_epochs
    trainer = make_trainer(
        logdir=logdir,
        progress=progress,
        strategy=strategy,
        devices=devices,
        batches_per_epoch=math.ceil(dm.train_targets.n / (dm.batch_size * devices)),
        resumed=None if point is None else {"version": point.version, "purge_step": point.step},
        **settings["trainer"],
    )
    previous = torch.get_num_threads()
    threads = threads or _fit_threads(settings)
    probing = settings["model"].get("blocked", True) and trainer.world_size == 1
    module.figure_at_end = False  # drawn below, of the model the decisions leave
    start, stage = time.perf_counter(), "training"
    try:
        if threads:
            torch.set_num_threads(threads)
        hybrid, stage = _fit(trainer, module, dm, point), "blocked"
        blocked = blocked_hold_out(hybrid, dm, settings, seed, progress) if probing else {}
    except (KeyboardInterrupt, SystemExit) as exc:  # Lightning exits on Ctrl-C and SIGTERM
        raise interruption(exc, trainer, stage) from None
    finally:
        torch.set_num_threads(previous)
    seconds = time.perf_counter() - start
    best = module.best_metrics()
    final = validation_errors(hybrid, dm.val_targets) if blocked else dict(best)
    if trainer.is_global_zero:
        log_written_model(module, dm.val_targets, blocked)
    return TrainResult(
        hybrid=hybrid,
        best=best,
        final=final,
        base=module.base_metrics(),
        epochs=trainer.current_epoch,
        seconds=seconds,
        logdir=None if trainer.logger is None else trainer.logger.log_dir,
        is_global_zero=trainer.is_global_zero,
        settings=settings,
        blocked=blocked,
        resumed=None if point is None else (str(point.path), point.epochs_done),
    )


def _fit(trainer: L.Trainer, module: HybridLitModule, dm: HybridDataModule, point) -> HybridFK:
    """Lightning's fit (from the checkpoint of ``point``, if any) with Ctrl-C latched
    (:mod:`~hybrid_pk.training.interrupts`); the trained hybrid model, in eval mode."""
    latch = next(c for c in trainer.callbacks if isinstance(c, InterruptLatch))
    with latch.armed():
        trainer.fit(module, datamodule=dm, ckpt_path=None if point is None else point.path)
        latch.check()  # one dropped after the last batch's check
    return module.hybrid.eval()


def _fit_threads(settings: dict) -> int | None:
    """Threads of a fit not given any: ``--threads`` / ``HYBRID_PK_THREADS``
    (:mod:`hybrid_pk.threads`), else :func:`auto_threads` of the networks."""
    archs = [settings["model"]["position_net"], settings["model"]["orientation_net"]]
    fixed = requested_threads()
    return (fixed if isinstance(fixed, int) else None) or auto_threads(archs)


def _override(settings, base, model, datamodule, max_epochs, patience) -> None:
    """Apply :func:`train_hybrid`'s overrides to the preset ``settings`` (in place)."""
    settings["model"] = full_model_settings({**settings["model"], **(model or {})})
    settings["notes"] = _preset_inputs_for(base.robot, settings["model"], model or {})
    settings["data"].update(datamodule or {})
    if max_epochs is not None:
        settings["trainer"]["max_epochs"] = int(max_epochs)
    if not settings["trainer"]["max_epochs"] >= 1:  # 0 would store untrained networks
        raise HybridPKError(
            f"max_epochs must be at least 1, got {settings['trainer']['max_epochs']}"
        )
    if patience != "preset":
        settings["trainer"]["patience"] = patience


def _resume_point(dm, module, logdir, devices, max_epochs, progress):
    """The checked :class:`~hybrid_pk.training.resume.ResumePoint` of a resumed run, said."""
    digest = data_digest(dm.train_targets, dm.val_targets)
    batches = (dm.batch_size, devices)
    point = find_resume_point(logdir, digest, dict(module.hparams), batches, max_epochs)
    _say(progress, f"resuming {point.path}: {point.epochs_done} of {point.max_epochs} epochs done")
    return point


def _say(progress: bool | Callable[[str], None], text: str) -> None:
    """A line of progress: to ``progress`` (a callable), else on stderr (with a bar)."""
    if callable(progress):
        progress(text)
    elif progress:
        print(text, file=sys.stderr, flush=True)


@torch.no_grad()
def validation_errors(hybrid: HybridFK, rows) -> dict[str, float]:
    """Mean position [mm] / orientation [deg] errors of ``hybrid`` on validation targets
    ``rows`` (:class:`~hybrid_pk.hybrid.losses.ResidualTargets`), keys as
    :attr:`TrainResult.best`."""
    dp, dw = hybrid.corrections(rows.q)
    out = {
        "position_mm": float(corrected_position_errors_mm(rows.position, rows.lever, dp, dw).mean())
    }
    if rows.rotation is not None:
        out["orientation_deg"] = float(corrected_orientation_errors_deg(rows.rotation, dw).mean())
    return out


def _preset_inputs_for(robot, module: dict, given: dict) -> list[str]:
    """The preset's physics inputs replaced by the joints on a robot they do not handle
    yet (mimic joints), unless the caller chose them: a default that works, said so
    (the notes). Inputs the caller gave are kept and checked as given."""
    if not robot.has_mimic or "inputs" in given or module.get("inputs", "joints") == "joints":
        return []
    preset_inputs, module["inputs"] = module["inputs"], "joints"
    return [
        f"{robot.name!r} has mimic joints, which the physics inputs ({preset_inputs}) do not "
        "handle yet: the networks read every joint instead (--inputs joints; trusted inside "
        "the training rows' joint box)"
    ]


def blocked_hold_out(
    hybrid: HybridFK,
    dm: HybridDataModule,
    settings: dict,
    seed: int,
    progress: bool | Callable[[str], None] = False,
) -> dict:
    """Probe fits on blocked hold-out of ``dm``'s rows (:mod:`~hybrid_pk.training.blocked`),
    each with ``settings`` (a preset with overrides), that lift or keep the gate of each
    of ``hybrid``'s gated stages. Returns ``{"<index>:<label>": record}``.
    ``progress``: as in :func:`train_hybrid` (True: a line and Lightning's bar per
    probe fit, which together take about as long as the training)."""
    if not any(stage.gate is not None for stage in hybrid.stages):
        return {}
    blocks = blocked_blocks(hybrid.base.robot, dm.train_targets.q, dm.files[0])
    folds = probe_folds(blocks)
    probes = []
    for k, fold in enumerate(folds):
        fit, check, held = fold_rows(dm.train_targets, dm.val_targets, fold, dm.files)
        if fit.n < 2 or check.n < 1 or not held:
            continue
        text = f"blocked hold-out {k + 1}/{len(folds)}: {', '.join(b.label for b in fold)}"
        if callable(progress):
            progress(text)
        elif progress:  # Lightning's bar (a terminal): the probe fits get their own bar
            print(f"{text} (probe fit)", file=sys.stderr, flush=True)
        L.seed_everything(seed, workers=True, verbose=False)
        probe = HybridDataModule(batch_size=dm.batch_size, val_batch_size=dm.val_batch_size)
        probe.base, probe.train_targets, probe.val_targets = dm.base, fit, check
        module = HybridLitModule(**{**settings["model"], "blocked": False, "histogram_every": 0})
        trainer = make_trainer(progress=progress is True, **settings["trainer"])
        trainer.fit(module, datamodule=probe)
        probes.append((module.hybrid.eval(), held))
    if not probes:
        return {}
    decisions = blocked_check(hybrid, probes, [b.label for b in blocks])
    return {f"{i}:{hybrid.stages[i].label}": record for i, record in decisions.items()}
