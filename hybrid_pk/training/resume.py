"""Continuing an interrupted training from its last checkpoint (``hybrid-pk train
--resume``).

Checkpoints (``DIR/version_K/checkpoints/last.ckpt``, written after every epoch with
``--logdir DIR``) carry, besides Lightning's states, the run's record (``RECORD``): a
digest of the training and validation targets (the rows, the split and the base
model that made them), the epochs the run was started for, the steps of its
learning-rate schedule, the networks' best states and the random state. A resume
checks that record against the run asked for before any training, each mismatch a
one-line error, and continues in the same ``version_K`` (TensorBoard curves go on).

A one-cycle (or cosine) learning rate is built for the steps of the epochs the run
was started with and ends at about zero there: a resume asking for other epochs is
refused (train longer in a new run); a run without a schedule (``--preset paper``)
may be given more epochs.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path

import torch

from hybrid_pk.errors import HybridPKError, TrainingInterrupted
from hybrid_pk.startup import Terminated

__all__ = [
    "RECORD",
    "ResumePoint",
    "data_digest",
    "find_resume_point",
    "interruption",
    "schedule_conflict",
]

RECORD = "hybrid_pk"  # the key of the run's record in a checkpoint
_VERSION = re.compile(r"version_(\d+)$")
_SCHEDULES = {"onecycle": "one-cycle", "cosine": "cosine"}


@dataclass(frozen=True)
class ResumePoint:
    """Where a resumed training starts.

    Attributes:
        path: the checkpoint.
        version: the ``version_K`` folder of the logdir it belongs to (logging goes on there).
        epochs_done: epochs completed when it was written.
        max_epochs: the epochs the resumed run trains to.
        step: the training steps done (TensorBoard drops what the interrupted run
            logged from there on: the epoch that is run again).
    """

    path: Path
    version: int
    epochs_done: int
    max_epochs: int
    step: int = 0


def data_digest(train, val) -> str:
    """A digest of the training and validation targets
    (:class:`~hybrid_pk.hybrid.losses.ResidualTargets`): other rows, another split
    (seed, validation share) or another base model give another digest."""
    h = hashlib.sha256()
    for part in (train, val):
        for key, t in sorted(part.tensors().items()):
            h.update(key.encode())
            h.update(t.detach().to(torch.float64).cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def schedule_conflict(record: dict, max_epochs: int, option: str) -> str | None:
    """Why a run started for ``record["max_epochs"]`` epochs cannot go on to
    ``max_epochs`` (named ``option`` in the message), or None."""
    started, done = int(record["max_epochs"]), int(record.get("epochs_done", 0))
    if record.get("schedule_steps", 0) and max_epochs != started:
        return (
            f"its {_SCHEDULES[record.get('scheduler', 'onecycle')]} learning rate was built for "
            f"{started} epochs ({record['schedule_steps']} steps) and ends there: resume with "
            f"{option} {started} (or without {option}), or start a new run for {max_epochs} "
            "epochs"
        )
    if max_epochs < done:
        return f"{done} epochs are done already, {option} {max_epochs} asks for fewer"
    return None


def _last_checkpoint(logdir: str | Path) -> tuple[Path, int]:
    """The ``last.ckpt`` of ``logdir``'s newest run (``version_K``, the highest K) and K."""
    versions = [
        (int(m.group(1)), p)
        for p in Path(logdir).glob("version_*")
        if (m := _VERSION.match(p.name))
    ]
    if not versions:
        raise HybridPKError(
            f"--resume: nothing to resume in {logdir} (no version_K run folder; checkpoints "
            "are written after each epoch of a run with --logdir): run without --resume"
        )
    version, folder = max(versions)
    path = folder / "checkpoints" / "last.ckpt"
    if not path.is_file():
        raise HybridPKError(
            f"--resume: nothing to resume in {folder}, the newest run in {logdir} (no "
            "checkpoints/last.ckpt: stopped before its first epoch ended): run without --resume"
        )
    return path, version


def _read(path: Path) -> dict:
    try:  # the user's own checkpoint, written by Lightning (pickled hyperparameters)
        checkpoint = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # a file cut short by a killed job: any unpickling error
        why = str(exc).split(". ")[0]  # torch's zip errors go on for several sentences
        raise HybridPKError(
            f"--resume: {path} cannot be read ({type(exc).__name__}: {why}); a job killed "
            "while writing it leaves it cut short: rename the best epoch's "
            "checkpoints/epoch=*.ckpt to last.ckpt to resume from there, or start a new run"
        ) from None
    if not isinstance(checkpoint, dict) or RECORD not in checkpoint:
        raise HybridPKError(
            f"--resume: {path} was not written by hybrid-pk train (no run record); "
            "resume a LightningCLI run with python train/cli.py fit --ckpt_path"
        )
    return checkpoint


def find_resume_point(
    logdir: str | Path | None,
    digest: str,
    hparams: dict,
    batches: tuple[int, int],
    max_epochs: int | None,
) -> ResumePoint:
    """The checkpoint a resumed run continues from, checked against the run asked for:
    its data (``digest``, :func:`data_digest`), the module's arguments ``hparams``, its
    ``batches`` (batch size, processes) and ``max_epochs`` (None: the run's own).

    Raises:
        HybridPKError: no ``logdir`` or no checkpoint in it, an unreadable checkpoint,
            one of another run (data, settings, batches) or epochs its schedule does
            not reach.
    """
    if logdir is None:
        raise HybridPKError(
            "--resume needs the --logdir DIR of the run to continue (its checkpoints are there)"
        )
    path, version = _last_checkpoint(logdir)
    checkpoint = _read(path)
    record = checkpoint[RECORD]
    where = f"--resume: {path}"
    if record["data"] != digest:
        raise HybridPKError(
            f"{where} belongs to a run on other rows or another base model ({record['rows']} "
            "training/validation rows): give the run's DATA, --model, --seed and "
            "--val-fraction, or another --logdir for a new run"
        )
    saved = dict(checkpoint.get("hyper_parameters") or {})
    differ = [k for k in sorted(set(saved) | set(hparams)) if saved.get(k) != hparams.get(k)]
    if differ:
        said = ", ".join(f"{k} {saved.get(k)!r} (this run {hparams.get(k)!r})" for k in differ)
        raise HybridPKError(
            f"{where} was trained with other settings: {said}; give the run's flags, "
            "--preset and --config"
        )
    if (record["batch_size"], record["world_size"]) != tuple(batches):
        raise HybridPKError(
            f"{where} ran batches of {record['batch_size']} rows in {record['world_size']} "
            f"process(es), this run {batches[0]} in {batches[1]}: give the run's --batch-size "
            "and --devices"
        )
    done = int(checkpoint.get("epoch", -1)) + 1  # saved after that epoch's validation
    if _stopped_early(checkpoint):  # complete: another epoch would be one too many
        return ResumePoint(path, version, done, done, int(checkpoint["global_step"]))
    asked = int(record["max_epochs"]) if max_epochs is None else int(max_epochs)
    why = schedule_conflict({**record, "epochs_done": done}, asked, "--epochs")
    if why:
        raise HybridPKError(f"{where} ({done} of {record['max_epochs']} epochs done): {why}")
    return ResumePoint(path, version, done, asked, int(checkpoint["global_step"]))


def _stopped_early(checkpoint: dict) -> bool:
    """Whether the run's early stopping had ended it (Lightning's EarlyStopping state)."""
    states = checkpoint.get("callbacks") or {}
    return any(
        key.startswith("EarlyStopping") and int(state.get("stopped_epoch", 0)) > 0
        for key, state in states.items()
    )


def interruption(exc: BaseException, trainer, stage: str) -> BaseException:
    """The :class:`TrainingInterrupted` for Lightning's exit on Ctrl-C (``SystemExit(1)``
    after its clean-up) or SIGTERM (``SIGTERMException``, or that exit) in ``stage``
    (``"training"`` or ``"blocked"``, the probe fits after it), naming the checkpoint
    kept; ``exc`` itself when it is no interruption."""
    from lightning.pytorch.trainer.states import TrainerStatus
    from lightning.pytorch.utilities.exceptions import SIGTERMException

    # SIGTERM: Lightning's own exception, or the command's (:class:`.startup.Terminated`),
    # which Lightning turns into its exit during the fit (it noted the signal)
    sigterm = isinstance(exc, (SIGTERMException, Terminated)) or bool(
        getattr(trainer, "received_sigterm", False)
    )
    stopped = stage == "blocked" or trainer.state.status == TrainerStatus.INTERRUPTED
    if not (sigterm or isinstance(exc, KeyboardInterrupt) or stopped):
        return exc
    what, code = ("SIGTERM", 143) if sigterm else ("Ctrl-C", 130)
    folder = getattr(trainer.logger, "log_dir", None)
    last = Path(folder, "checkpoints", "last.ckpt") if folder else None
    if stage == "blocked":
        where = f"interrupted ({what}) in the blocked hold-out's probe fits, after the training"
    else:
        epoch = min(trainer.current_epoch + 1, trainer.max_epochs)  # past the last: its end
        where = f"interrupted ({what}) in epoch {epoch}/{trainer.max_epochs}"
    if last is None or not last.is_file():
        why = "yet" if trainer.logger else "(they are written with --logdir DIR)"
        return TrainingInterrupted(f"{where}; no checkpoint kept {why}: a rerun starts over", code)
    done = int(torch.load(last, map_location="cpu", weights_only=False).get("epoch", -1)) + 1
    return TrainingInterrupted(
        f"{where}; kept {last} ({done} of {trainer.max_epochs} epochs done): rerun the same "
        "command with --resume to continue",
        code,
    )
