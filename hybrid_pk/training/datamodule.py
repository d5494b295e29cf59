"""`HybridDataModule`: measured rows -> residual targets of a base model -> batches.

The base model is evaluated once (:func:`~hybrid_pk.hybrid.residual_targets`); the
rows are split into training and validation sets by a seeded permutation. Built
either from files (LightningCLI: ``data`` and ``model`` paths) or from objects
already in memory (:meth:`HybridDataModule.from_measured`).
"""

from __future__ import annotations

import lightning as L
import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from hybrid_pk.data import MeasuredData, read_table_for
from hybrid_pk.effects import Conditions, ExtendedModel, conditions_from_data
from hybrid_pk.errors import HybridPKError
from hybrid_pk.hybrid.losses import ResidualTargets, residual_targets
from hybrid_pk.io.model_file import load_model

__all__ = ["HybridDataModule", "TargetDataset", "keep_batch"]


class TargetDataset(Dataset):
    """Rows of :class:`ResidualTargets` as dict items (``q``, ``position``, ``lever``,
    and ``rotation`` with orientation data), plus any ``extra`` columns of as many rows
    (e.g. the networks' encoded inputs)."""

    def __init__(self, targets: ResidualTargets, extra: dict[str, Tensor] | None = None) -> None:
        self.columns = {**targets.tensors(), **(extra or {})}
        self.n = targets.n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, index: int) -> dict[str, Tensor]:
        return {k: v[index] for k, v in self.columns.items()}

    def __getitems__(self, indices: list[int]) -> dict[str, Tensor]:
        """A whole batch by one index per column (what the DataLoader fetches; row by
        row and stacking costs more than the small networks' step)."""
        index = torch.as_tensor(indices, dtype=torch.long)
        return {k: v[index] for k, v in self.columns.items()}


def keep_batch(batch: dict[str, Tensor]) -> dict[str, Tensor]:
    """Collate function for :meth:`TargetDataset.__getitems__`: the batch is ready."""
    return batch


class HybridDataModule(L.LightningDataModule):
    """Training/validation batches of what a base model leaves unexplained.

    Args:
        data: measured pose table(s) (contract section 1).
        model: the base model file (from ``calibrate``) or ``nominal:ROBOT``.
        val_fraction: share of the rows held out for validation/early stopping.
        batch_size: training rows per step.
        val_batch_size: validation rows per step.
        seed: seed of the train/validation split.
        frames_per_file: rows of each file use that file's base/tool frame set.
    """

    def __init__(
        self,
        data: list[str] | None = None,
        model: str | None = None,
        val_fraction: float = 0.1,
        batch_size: int = 128,
        val_batch_size: int = 8192,
        seed: int = 0,
        frames_per_file: bool = False,
    ) -> None:
        super().__init__()
        if not 0.0 < val_fraction < 1.0:
            raise HybridPKError(f"val_fraction must lie in (0, 1), got {val_fraction}")
        self.paths, self.model_path = data, model
        self.val_fraction = val_fraction
        self.batch_size, self.val_batch_size = int(batch_size), int(val_batch_size)
        self.seed, self.frames_per_file = int(seed), frames_per_file
        self.base: ExtendedModel | None = None
        self.train_targets: ResidualTargets | None = None
        self.val_targets: ResidualTargets | None = None
        self.extra: dict[str, dict[str, Tensor]] = {"train": {}, "val": {}}
        # file index of the training / validation rows when they come from several files
        self.files: tuple[Tensor | None, Tensor | None] = (None, None)

    @classmethod
    def from_measured(
        cls,
        data: MeasuredData,
        base: ExtendedModel,
        cond: Conditions | None = None,
        **kwargs,
    ) -> HybridDataModule:
        """From rows and a base model in memory (``kwargs``: the other arguments)."""
        dm = cls(**kwargs)
        dm.prepare(data, base, cond)
        return dm

    def prepare(self, data: MeasuredData, base: ExtendedModel, cond: Conditions | None) -> None:
        """Evaluate ``base`` on ``data`` and split the residual targets."""
        n_val = round(self.val_fraction * data.n)
        if n_val < 1 or data.n - n_val < 1:
            raise HybridPKError(
                f"{data.n} rows cannot be split into training and validation rows "
                f"(val_fraction {self.val_fraction})"
            )
        base.requires_grad_(False)
        cond = cond if cond is not None else conditions_from_data(data, self.frames_per_file)
        targets = residual_targets(base, data, cond)
        perm = torch.randperm(data.n, generator=torch.Generator().manual_seed(self.seed))
        self.base = base
        val, train = perm[:n_val].sort().values, perm[n_val:].sort().values
        self.val_targets = targets.subset(val)
        self.train_targets = targets.subset(train)
        if len(data.sources) > 1:
            self.files = (data.file_index[train], data.file_index[val])

    def setup(self, stage: str | None = None) -> None:
        if self.train_targets is not None:
            return
        if not self.paths or self.model_path is None:
            raise HybridPKError("HybridDataModule needs data (table files) and model (a file)")
        loaded = load_model(self.model_path)
        robot = loaded.model.robot
        robot.requires_grad_(False)
        data = read_table_for(list(self.paths), robot, n_params=1)
        self.prepare(data, loaded.model, None)

    def add_columns(self, train: dict[str, Tensor], val: dict[str, Tensor]) -> None:
        """Extra per-row columns of the training and validation batches (the module
        encodes its network inputs once instead of at every step)."""
        self.extra = {"train": dict(train), "val": dict(val)}

    @property
    def has_orientation(self) -> bool:
        return self.train_targets is not None and self.train_targets.rotation is not None

    def train_dataloader(self) -> DataLoader:
        # The global RNG is seeded (seed_everything): the shuffle order is deterministic.
        return DataLoader(
            TargetDataset(self.train_targets, self.extra["train"]),
            batch_size=self.batch_size,
            shuffle=True,
            collate_fn=keep_batch,
        )

    def val_dataloader(self) -> DataLoader:
        return DataLoader(
            TargetDataset(self.val_targets, self.extra["val"]),
            batch_size=self.val_batch_size,
            collate_fn=keep_batch,
        )
