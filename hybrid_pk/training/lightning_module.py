"""`HybridLitModule`: Lightning glue around :class:`~hybrid_pk.hybrid.HybridFK`.

The networks are built in :meth:`HybridLitModule.setup` from the datamodule (base
model, joint range and residual sizes of the training rows), so a LightningCLI YAML
only names architectures and optimiser settings.

Logged (TensorBoard): ``train/loss``, ``train/position_mm``, ``train/orientation_deg``
(epoch means of the losses), ``val/position_mm_{mean,p95}``,
``val/orientation_deg_{mean,p95}``, ``val/score`` (hybrid / base mean error, summed
over position and orientation: what early stopping watches); histograms of
the validation errors; at the end of the fit a Fig.-4-like figure (base model vs
hybrid error distributions, :func:`~hybrid_pk.training.figures.log_error_figure`).

Each network keeps its own best state (lowest validation mean error of its quantity)
and both are restored at the end of the fit: the paper trains the two networks as
separate models with their own early stopping.
"""

from __future__ import annotations

import copy
import math

import lightning as L
import torch
from torch import Tensor

from hybrid_pk.evaluation.metrics import error_stats
from hybrid_pk.hybrid.coverage import DEFAULT_QUANTILE, DEFAULT_RATIO, Coverage
from hybrid_pk.hybrid.features import PhysicsFeatures
from hybrid_pk.hybrid.hybrid_fk import HybridFK
from hybrid_pk.hybrid.inputs import DEFAULT_FADE, InputBox, parse_inputs
from hybrid_pk.hybrid.local import LocalFeatures, LocalSpec
from hybrid_pk.hybrid.losses import (
    LOSSES,
    corrected_orientation_errors_deg,
    corrected_position_errors_mm,
    reduce_errors,
)
from hybrid_pk.hybrid.nets import parse_arch
from hybrid_pk.training.figures import log_error_figure

__all__ = [
    "OPTIMIZERS",
    "SCHEDULERS",
    "TRUSTS",
    "HybridLitModule",
    "network_inputs",
]

OPTIMIZERS = ("adagrad", "adam", "adamw")
SCHEDULERS = ("none", "cosine", "onecycle")
TRUSTS = ("auto", "box", "coverage", "none")
_KEYS = {"position": "position_mm", "orientation": "orientation_deg"}


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
        inputs: ``joints`` (the paper's: every joint, min-max normalised) or physics
            features ``frameK[+gravity][+torque|+full]``
            (:class:`~hybrid_pk.hybrid.features.FeatureSpec`).
        trust: where the networks apply: ``box`` (the training rows' joint box; joints
            inputs only), ``coverage`` (distance to the training rows in input space,
            :class:`~hybrid_pk.hybrid.coverage.Coverage`), ``none`` (everywhere), or
            ``auto``: ``box`` for the joints inputs, ``coverage`` for physics features.
        coverage_quantile: share of the validation rows inside the full-trust radius.
        coverage_ratio: radius where the networks are off / full-trust radius.
        zero_init: zero output layers (training starts from the base model).
        histogram_every: log error histograms every this many validation epochs (0: off).
    """

    def __init__(
        self,
        position_net: str = "mlp",
        orientation_net: str = "mlp",
        optimizer: str = "adam",
        lr: float = 3e-3,
        weight_decay: float = 0.0,
        scheduler: str = "onecycle",
        loss: str = "mse",
        input_range: str = "data",
        fade: float = DEFAULT_FADE,
        inputs: str = "joints",
        trust: str = "auto",
        coverage_quantile: float = DEFAULT_QUANTILE,
        coverage_ratio: float = DEFAULT_RATIO,
        zero_init: bool = True,
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
        for arch in (position_net, orientation_net):
            if arch != "none":
                parse_arch(arch)  # fail before any data is read
        if inputs != "joints":
            parse_inputs(inputs)
            if trust == "box":
                raise ValueError(f"trust 'box' needs the joints inputs; with {inputs!r}: coverage")
        self.trust_kind = trust if trust != "auto" else "box" if inputs == "joints" else "coverage"
        self.save_hyperparameters()
        self.hybrid: HybridFK | None = None
        self._val: dict[str, list[Tensor]] = {}
        self._train_sums: dict[str, float] = {}
        self._base_val: dict[str, Tensor] = {}
        self._best: dict[str, tuple[float, dict]] = {}

    # ------------------------------------------------------------------ construction
    def setup(self, stage: str) -> None:
        if self.hybrid is not None:
            return
        dm = self.trainer.datamodule
        hp = self.hparams
        train, val = dm.train_targets, dm.val_targets
        inputs = network_inputs(hp, self.trust_kind, dm.base.robot, train.q)
        pos_scale, rot_scale = train.scales()
        ori = hp.orientation_net if train.rotation is not None else "none"
        self.hybrid = HybridFK.build(
            dm.base,
            inputs,
            None if hp.position_net == "none" else hp.position_net,
            None if ori == "none" else ori,
            pos_scale,
            rot_scale,
            zero_init=hp.zero_init,
        )
        self._encode_once(dm)
        self.hybrid.base.requires_grad_(False)
        self.hybrid.train()  # a base model shared with an earlier (eval-mode) hybrid
        zero = torch.zeros_like(val.position)
        self._base_val["position"] = corrected_position_errors_mm(
            val.position, val.lever, zero, zero
        )
        if val.rotation is not None:
            self._base_val["orientation"] = corrected_orientation_errors_deg(val.rotation, zero)

    @torch.no_grad()
    def _encode_once(self, dm) -> None:
        """Encode the rows' network inputs once, fit the coverage on them, and hand them
        to the datamodule as batch columns (``u``, ``A``; ``w`` for validation)."""
        hybrid, hp = self.hybrid, self.hparams
        columns = {}
        for part, rows in (("train", dm.train_targets), ("val", dm.val_targets)):
            u, geo = hybrid.encode(rows.q)
            columns[part] = {"u": u, **{f"geo_{k}": v for k, v in geo.items()}}
        if self.trust_kind == "coverage":
            hybrid.coverage = Coverage.from_inputs(
                columns["train"]["u"],
                columns["val"]["u"],
                quantile=hp.coverage_quantile,
                ratio=hp.coverage_ratio,
            )
        columns["val"]["w"] = hybrid.weight(dm.val_targets.q, columns["val"]["u"])
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
        if hp.scheduler == "none" or steps < 4:  # a schedule needs a few steps
            return opt
        if hp.scheduler == "cosine":
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=steps)
        else:  # warm-up over 10 % of the steps (at least 2), then cosine annealing
            sched = torch.optim.lr_scheduler.OneCycleLR(
                opt, max_lr=hp.lr, total_steps=steps, pct_start=max(0.1, 2.5 / steps)
            )
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    # ------------------------------------------------------------------ steps
    def _errors(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """Per-row position [mm] and orientation [deg] errors of the hybrid model
        (training rows: the networks unweighted; validation rows: with their trust)."""
        if "u" in batch:
            geo = {k[4:]: v for k, v in batch.items() if k.startswith("geo_")}
            dp, dw = self.hybrid.predict(batch["u"], geo, batch.get("w"))
        else:
            dp, dw = self.hybrid.corrections(batch["q"])
        out = {"position": corrected_position_errors_mm(batch["position"], batch["lever"], dp, dw)}
        if "rotation" in batch and self.hybrid.orientation is not None:
            out["orientation"] = corrected_orientation_errors_deg(batch["rotation"], dw)
        return out

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        errors = self._errors(batch)
        losses = {k: reduce_errors(v, self.hparams.loss) for k, v in errors.items()}
        loss = sum(losses.values())
        # Epoch means are summed here and logged once per epoch: self.log costs more
        # per call than a step of the small networks.
        n = batch["q"].shape[0]
        sums = self._train_sums
        sums["rows"] = sums.get("rows", 0) + n
        sums["train/loss"] = sums.get("train/loss", 0.0) + float(loss) * n
        for k, v in errors.items():
            key = f"train/{_KEYS[k]}"
            sums[key] = sums.get(key, 0.0) + float(v.sum())
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
        best = self._best.get(name)
        if best is None or value < best[0]:
            head = getattr(self.hybrid, name)
            self._best[name] = (value, copy.deepcopy(head.state_dict()))

    def on_train_end(self) -> None:
        # on_train_end, not on_fit_end: callbacks' on_fit_end (WriteModelFile) run
        # before the module's, and must see the restored networks.
        for name, (_, state) in self._best.items():
            getattr(self.hybrid, name).load_state_dict(state)
        if self.trainer.is_global_zero and self.trainer.datamodule is not None:
            log_error_figure(self, self.trainer.datamodule.val_targets)

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


def network_inputs(hp, trust: str, robot, q: Tensor) -> InputBox | PhysicsFeatures | LocalFeatures:
    """The networks' inputs for module settings ``hp`` (``inputs``, ``input_range``,
    ``fade``), the trust kind and training joints ``q (N, dof)``."""
    if hp.inputs == "joints":
        if trust == "none":  # an unbounded box: the networks apply everywhere
            limits = robot.joint_limits if hp.input_range == "limits" else None
            box = InputBox.from_data(q, limits, 1.0)
            inf = torch.full_like(box.trust_lower, math.inf)
            return InputBox(box.lower, box.upper, -inf, inf, 1.0)
        limits = robot.joint_limits if hp.input_range == "limits" else None
        return InputBox.from_data(q, limits, hp.fade)
    spec = parse_inputs(hp.inputs)
    if isinstance(spec, LocalSpec):
        return LocalFeatures(spec, robot).fit_standardisation(robot, q)
    return PhysicsFeatures(spec, robot).fit_standardisation(robot, q)
