"""`HybridLitModule`: Lightning glue around :class:`~hybrid_pk.hybrid.HybridFK`.

The networks are built in :meth:`HybridLitModule.setup` from the datamodule (base
model, joint range and residual sizes of the training rows), so a LightningCLI YAML
only names architectures and optimiser settings.

Logged (TensorBoard): ``train/loss``, ``train/position_mm``, ``train/orientation_deg``
(epoch means of the losses), ``val/position_mm_{mean,p95}``,
``val/orientation_deg_{mean,p95}``, ``val/score`` (hybrid / base mean error, summed
over position and orientation: what early stopping watches); histograms of
the validation errors; at the end of the fit a Fig.-4-like figure (base model vs
hybrid error distributions, :func:`~hybrid_pk.training.figures.log_error_figure`;
:func:`~hybrid_pk.training.train_hybrid` draws it itself after the blocked hold-out,
of the model as written).

A checkpoint carries the run's record (:mod:`~hybrid_pk.training.resume`): the best
states so far, the random state and what a resume checks, so a resumed fit ends as an
uninterrupted one.

Each network keeps its own best state (lowest validation mean error of its quantity)
and both are restored at the end of the fit: the paper trains the two networks as
separate models with their own early stopping. With zero output layers (``zero_init``)
the start, the base model, is a candidate too: a network that no epoch makes better
than the base model on the validation rows ends at zero.
"""

from __future__ import annotations

import copy
import math

import lightning as L
import torch
from torch import Tensor

from hybrid_pk.errors import HybridPKError
from hybrid_pk.evaluation.metrics import error_stats
from hybrid_pk.hybrid.builder import (
    TRUSTS,
    HybridSettings,
    build_hybrid,
    check_trust,
    fit_coverages,
    fit_gates,
    fit_spreads,
)
from hybrid_pk.hybrid.hybrid_fk import HybridFK
from hybrid_pk.hybrid.losses import (
    LOSSES,
    corrected_orientation_errors_deg,
    corrected_position_errors_mm,
    reduce_errors,
)
from hybrid_pk.hybrid.nets import parse_arch
from hybrid_pk.training.figures import log_error_figure
from hybrid_pk.training.resume import RECORD, data_digest, schedule_conflict

__all__ = ["OPTIMIZERS", "SCHEDULERS", "HybridLitModule"]

OPTIMIZERS = ("adagrad", "adam", "adamw")
SCHEDULERS = ("none", "cosine", "onecycle")
_KEYS = {"position": "position_mm", "orientation": "orientation_deg"}


_DEFAULTS = HybridSettings()  # one source of the network settings' defaults


class HybridLitModule(L.LightningModule):
    """Trains the position and orientation networks of a :class:`HybridFK`.

    Args:
        position_net: architecture of the position network (``D4w``, ``mlp``, ...), or
            ``"none"``.
        orientation_net: architecture of the orientation network, or ``"none"`` (always
            none for position-only data).
        optimizer: ``adagrad`` (paper), ``adam`` or ``adamw``.
        lr: (peak) learning rate.
        weight_decay: decoupled (adamw) or L2 weight decay.
        scheduler: ``none`` (paper), ``cosine`` (to 0 over the run) or ``onecycle``.
        loss: ``norm`` (paper: mean distance / angle) or ``mse`` (mean square).
        input_range: ``limits`` (normalise over the joint limits, paper 4.1) or ``data``
            (over the training rows' range, paper 4.2).
        fade: fade-out width outside the training box (fraction of its size).
        inputs: the stages of networks (:mod:`~hybrid_pk.hybrid.builder`): ``joints``
            (the paper's: every joint, min-max normalised), physics inputs
            ``frameK[+qI-J][+gravity][+torque|+full]`` or ``local[+q1]``, several joined
            by ``,`` (cascade of fall-backs) and ``/`` (refinement).
        trust: where the networks apply: ``box`` (the training rows' joint box; joints
            alone only), ``coverage`` (distance to the training rows in input space,
            :class:`~hybrid_pk.hybrid.coverage.Coverage`), ``none`` (everywhere), or
            ``auto``: ``box`` for the joints alone, ``coverage`` otherwise.
        coverage_quantile: share of the validation rows inside the full-trust radius
            (stages on all joints or physics features).
        coverage_ratio: radius where the networks are off / full-trust radius (same).
        refine_net: architecture of the refine stages' networks.
        local_net: architecture of each joint's network in local stages.
        local_coverage_quantile, local_coverage_ratio: the same for local stages.
        zero_init: zero output layers (training starts from the base model).
        spread: shrink a refined stage's correction where its refine stage is off, by
            the spread of its training targets (:mod:`~hybrid_pk.hybrid.spread`).
        blocked: stages on physics inputs are gated to their training joints unless
            blocked hold-out says they carry over (probe fits run by
            :func:`~hybrid_pk.training.train_hybrid`;
            :mod:`~hybrid_pk.hybrid.blocked_trust`).
        histogram_every: log error histograms every this many validation epochs (0: off).
    """

    def __init__(
        self,
        position_net: str = _DEFAULTS.position_net,
        orientation_net: str = _DEFAULTS.orientation_net,
        optimizer: str = "adam",
        lr: float = 3e-3,
        weight_decay: float = 0.0,
        scheduler: str = "onecycle",
        loss: str = "mse",
        input_range: str = _DEFAULTS.input_range,
        fade: float = _DEFAULTS.fade,
        inputs: str = "joints",
        trust: str = _DEFAULTS.trust,
        coverage_quantile: float = _DEFAULTS.coverage_quantile,
        coverage_ratio: float = _DEFAULTS.coverage_ratio,
        refine_net: str = _DEFAULTS.refine_net,
        local_net: str = _DEFAULTS.local_net,
        local_coverage_quantile: float = _DEFAULTS.local_coverage_quantile,
        local_coverage_ratio: float = _DEFAULTS.local_coverage_ratio,
        zero_init: bool = _DEFAULTS.zero_init,
        spread: bool = _DEFAULTS.spread,
        blocked: bool = _DEFAULTS.blocked,
        histogram_every: int = 5,
    ) -> None:
        super().__init__()
        for name, value, allowed in (
            ("optimizer", optimizer, OPTIMIZERS),
            ("scheduler", scheduler, SCHEDULERS),
            ("loss", loss, LOSSES),
            ("input_range", input_range, ("limits", "data")),
            ("trust", trust, TRUSTS),
        ):
            if value not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(allowed)}, got {value!r}")
        for arch in (position_net, orientation_net, refine_net, local_net):
            if arch != "none":
                parse_arch(arch)  # fail before any data is read
        try:
            check_trust(trust, inputs)  # parses the stages too
        except HybridPKError as exc:
            raise ValueError(str(exc)) from None
        self.save_hyperparameters()
        self.hybrid: HybridFK | None = None
        self._val: dict[str, list[Tensor]] = {}
        self._train_sums: dict[str, float] = {}
        self._base_val: dict[str, Tensor] = {}
        self._best: dict[str, tuple[float, dict]] = {}
        self._record: dict = {}  # what a checkpoint says of its run (resume.RECORD)
        # False: the caller draws the figure itself, after decisions that change the
        # model (train_hybrid's blocked hold-out)
        self.figure_at_end = True

    # ------------------------------------------------------------------ construction
    def setup(self, stage: str) -> None:
        if self.hybrid is not None:
            return
        dm = self.trainer.datamodule
        hp = self.hparams
        train, val = dm.train_targets, dm.val_targets
        pos_scale, rot_scale = train.scales()
        settings = self.settings(has_orientation=train.rotation is not None)
        self.hybrid = build_hybrid(dm.base, hp.inputs, settings, train.q, pos_scale, rot_scale)
        self._encode_once(dm, settings)
        self.hybrid.base.requires_grad_(False)
        self.hybrid.train()  # a base model shared with an earlier (eval-mode) hybrid
        zero = torch.zeros_like(val.position)
        self._base_val["position"] = corrected_position_errors_mm(
            val.position, val.lever, zero, zero
        )
        if val.rotation is not None:
            self._base_val["orientation"] = corrected_orientation_errors_deg(val.rotation, zero)
        self.keep_start()
        self._record = {"data": data_digest(train, val), "rows": [train.n, val.n]}
        self._record["batch_size"] = dm.batch_size

    def keep_start(self) -> None:
        """With zero output layers the start is the base model: a candidate for the
        best state like every epoch, so networks that no epoch makes better than the
        base model on the validation rows end at zero (the base model), not at their
        least bad epoch."""
        if self.hparams.zero_init:
            for k, errors in self._base_val.items():
                self._keep_best(k, float(errors.mean()))

    def settings(self, has_orientation: bool = True) -> HybridSettings:
        """The :class:`~hybrid_pk.hybrid.builder.HybridSettings` of these arguments."""
        hp = self.hparams

        def arch(name: str) -> str | None:
            return None if name == "none" else name

        return HybridSettings(
            position_net=arch(hp.position_net),
            orientation_net=arch(hp.orientation_net) if has_orientation else None,
            refine_net=hp.refine_net,
            local_net=hp.local_net,
            trust=hp.trust,
            input_range=hp.input_range,
            fade=hp.fade,
            coverage_quantile=hp.coverage_quantile,
            coverage_ratio=hp.coverage_ratio,
            local_coverage_quantile=hp.local_coverage_quantile,
            local_coverage_ratio=hp.local_coverage_ratio,
            zero_init=hp.zero_init,
            spread=hp.spread,
            blocked=hp.blocked,
        )

    @torch.no_grad()
    def _encode_once(self, dm, settings: HybridSettings) -> None:
        """Encode every stage's inputs once, fit the coverages on them, and hand them to
        the datamodule as batch columns (``u{i}``, ``geo{i}_*``; ``w{i}``, the stages'
        effective weights, for validation)."""
        hybrid = self.hybrid
        encoded = {
            p: hybrid.encode_all(r.q)
            for p, r in (("train", dm.train_targets), ("val", dm.val_targets))
        }
        fit_coverages(hybrid, encoded["train"], encoded["val"], settings)
        fit_gates(hybrid, dm.train_targets.q, dm.val_targets.q, settings)
        fit_spreads(hybrid, encoded["train"], dm.train_targets, settings)
        columns: dict[str, dict[str, Tensor]] = {"train": {}, "val": {}}
        for part, stages in encoded.items():
            for i, (u, geo) in enumerate(stages):
                columns[part][f"u{i}"] = u
                columns[part].update({f"geo{i}_{k}": v for k, v in geo.items()})
        weights = hybrid.weights(dm.val_targets.q, encoded["val"])
        columns["val"].update({f"w{i}": w for i, w in enumerate(weights)})
        dm.add_columns(columns["train"], columns["val"])

    def configure_optimizers(self):
        hp = self.hparams
        params = list(self.hybrid.networks().parameters())
        if hp.optimizer == "adagrad":
            # Keras' Adagrad (the paper's framework, as in [22]'s published code) starts
            # its accumulator at 0.1; PyTorch's at 0 makes the first step +-lr for every
            # weight, which throws 5000-wide layers far off.
            opt = torch.optim.Adagrad(
                params, lr=hp.lr, weight_decay=hp.weight_decay, initial_accumulator_value=0.1
            )
        elif hp.optimizer == "adam":
            opt = torch.optim.Adam(params, lr=hp.lr, weight_decay=hp.weight_decay)
        else:
            opt = torch.optim.AdamW(params, lr=hp.lr, weight_decay=hp.weight_decay)
        steps = max(int(self.trainer.estimated_stepping_batches), 1)
        self._record["schedule_steps"] = 0
        if hp.scheduler == "none" or steps < 4:  # a schedule needs a few steps
            return opt
        self._record |= {"schedule_steps": steps, "scheduler": hp.scheduler}
        if hp.scheduler == "cosine":
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=steps)
        else:  # warm-up over 10 % of the steps (at least 2), then cosine annealing
            sched = torch.optim.lr_scheduler.OneCycleLR(
                opt, max_lr=hp.lr, total_steps=steps, pct_start=max(0.1, 2.5 / steps)
            )
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    # ------------------------------------------------------------------ steps
    def _encoded(self, batch: dict[str, Tensor]) -> list[tuple[Tensor, dict]]:
        out = []
        for i in range(len(self.hybrid.stages)):
            prefix = f"geo{i}_"
            geo = {k[len(prefix) :]: v for k, v in batch.items() if k.startswith(prefix)}
            out.append((batch[f"u{i}"], geo))
        return out

    def _row_errors(self, batch: dict[str, Tensor], dp: Tensor, dw: Tensor) -> dict[str, Tensor]:
        out = {"position": corrected_position_errors_mm(batch["position"], batch["lever"], dp, dw)}
        if "rotation" in batch and self.hybrid.orientation is not None:
            out["orientation"] = corrected_orientation_errors_deg(batch["rotation"], dw)
        return out

    def _errors(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """Per-row position [mm] and orientation [deg] errors of the hybrid model, every
        stage at its weight (validation rows)."""
        if "u0" not in batch:
            return self._row_errors(batch, *self.hybrid.corrections(batch["q"]))
        weights = [batch[f"w{i}"] for i in range(len(self.hybrid.stages))]
        return self._row_errors(batch, *self.hybrid.predict_all(self._encoded(batch), weights))

    def _stage_errors(self, batch: dict[str, Tensor]) -> list[dict[str, Tensor]]:
        """Training rows: each stage's errors on its own target, networks unweighted. A
        cascade stage fits what the base model leaves; a refine stage what its cascade
        stage (and earlier refinements, held fixed) leave."""
        out, group = [], None
        for stage, (u, geo) in zip(self.hybrid.stages, self._encoded(batch), strict=True):
            dp, dw = stage.predict(u, geo, None)
            if stage.role == "refine":
                dp, dw = dp + group[0].detach(), dw + group[1].detach()
            group = (dp, dw)
            out.append(self._row_errors(batch, dp, dw))
        return out

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        stages = self._stage_errors(batch)
        loss = sum(reduce_errors(v, self.hparams.loss) for e in stages for v in e.values())
        errors = stages[0]  # logged: the first stage's errors
        # Epoch means are summed here and logged once per epoch: self.log costs more
        # per call than a step of the small networks.
        n = batch["q"].shape[0]
        sums = self._train_sums
        sums["rows"] = sums.get("rows", 0) + n
        sums["train/loss"] = sums.get("train/loss", 0.0) + float(loss.detach()) * n
        for k, v in errors.items():
            key = f"train/{_KEYS[k]}"
            sums[key] = sums.get(key, 0.0) + float(v.detach().sum())
        return loss

    def on_train_epoch_end(self) -> None:
        sums, self._train_sums = self._train_sums, {}
        rows = sums.pop("rows", 0)
        for key, total in sums.items():
            self.log(key, total / max(rows, 1), on_step=False, on_epoch=True, sync_dist=True)

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        for k, v in self._errors(batch).items():
            self._val.setdefault(k, []).append(v.detach())

    def on_validation_epoch_end(self) -> None:
        errors = {k: torch.cat(v) for k, v in self._val.items()}
        self._val = {}
        if self.trainer.world_size > 1:  # every rank saw a part of the rows
            errors = {k: self.all_gather(v).reshape(-1) for k, v in errors.items()}
        if self.trainer.sanity_checking or not errors:
            return
        score = 0.0
        for k, unit in (("position", "mm"), ("orientation", "deg")):
            if k not in errors:
                continue
            stats = error_stats(errors[k])
            base = float(self._base_val[k].mean())
            self.log(f"val/{k}_{unit}_mean", stats.mean, sync_dist=False, prog_bar=True)
            self.log(f"val/{k}_{unit}_p95", stats.p95, sync_dist=False)
            score += stats.mean / max(base, 1e-12)
            self._keep_best(k, stats.mean)
        self.log("val/score", score, sync_dist=False)
        self._log_histograms(errors)

    def _keep_best(self, name: str, value: float) -> None:
        """Keep every stage's ``name`` networks at the epoch of the lowest validation
        error of the whole model in that quantity."""
        best = self._best.get(name)
        if best is None or value < best[0]:
            heads = [getattr(stage, name) for stage in self.hybrid.stages]
            states = [None if h is None else copy.deepcopy(h.state_dict()) for h in heads]
            self._best[name] = (value, states)

    def on_train_end(self) -> None:
        # on_train_end, not on_fit_end: callbacks' on_fit_end (WriteModelFile) run
        # before the module's, and must see the restored networks.
        for name, (_, states) in self._best.items():
            for stage, state in zip(self.hybrid.stages, states, strict=True):
                if state is not None:
                    getattr(stage, name).load_state_dict(state)
        dm = self.trainer.datamodule
        if self.figure_at_end and self.trainer.is_global_zero and dm is not None:
            log_error_figure(self, dm.val_targets)

    # ------------------------------------------------------------------ checkpoints
    def on_save_checkpoint(self, checkpoint: dict) -> None:
        """The run's record (:mod:`~hybrid_pk.training.resume`): its data, epochs,
        schedule and processes, each network's best state so far and the random state
        (the next epoch's shuffle is drawn from it)."""
        checkpoint[RECORD] = {
            **self._record,
            "max_epochs": int(self.trainer.max_epochs),
            "world_size": int(self.trainer.world_size),
            "best": self._best,
            "rng": torch.get_rng_state(),
        }

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """Go on from ``checkpoint``: the best states so far and the random state; a
        run whose schedule ends before ``max_epochs`` is refused (one line)."""
        record = checkpoint.get(RECORD)
        if record is None:
            return
        trainer = self._trainer  # None when loaded outside a fit (the property raises)
        if trainer is not None and trainer.max_epochs is not None:
            done = {**record, "epochs_done": int(checkpoint.get("epoch", -1)) + 1}
            why = schedule_conflict(done, int(trainer.max_epochs), "max_epochs")
            if why:
                raise HybridPKError(f"cannot resume from this checkpoint: {why}")
        self._best = record["best"]
        torch.set_rng_state(record["rng"])

    # ------------------------------------------------------------------ logging
    def _tensorboard(self):
        from torch.utils.tensorboard import SummaryWriter

        writer = getattr(self.logger, "experiment", None)
        return writer if isinstance(writer, SummaryWriter) else None

    def _log_histograms(self, errors: dict[str, Tensor]) -> None:
        every = self.hparams.histogram_every
        writer = self._tensorboard()
        if writer is None or not every or not self.trainer.is_global_zero:
            return
        epoch = self.current_epoch
        if epoch % every and epoch + 1 != self.trainer.max_epochs:
            return
        for k, unit in (("position", "mm"), ("orientation", "deg")):
            if k in errors:
                writer.add_histogram(f"val/{k}_error_{unit}", errors[k].float(), self.global_step)

    def best_metrics(self) -> dict[str, float]:
        """Best validation mean error of each network (``position_mm``, ``orientation_deg``)."""
        return {_KEYS[k]: v for k, (v, _) in self._best.items() if math.isfinite(v)}

    def base_metrics(self) -> dict[str, float]:
        """Validation mean errors of the base model alone, same keys."""
        return {_KEYS[k]: float(v.mean()) for k, v in self._base_val.items()}
