"""Callbacks for LightningCLI runs (``train/cli.py``)."""

from __future__ import annotations

from pathlib import Path

import lightning as L

from hybrid_pk.io.hybrid_file import save_hybrid

__all__ = ["WriteModelFile"]


class WriteModelFile(L.Callback):
    """At the end of the fit, write the hybrid model (base model + networks) to ``path``.

    Runs on the first process only; the networks are at their best validation state
    (restored by the module when training ends).

    Args:
        path: the model file to write (read by ``evaluate``, ``ik``, ``calibrate --refit``).
    """

    def __init__(self, path: str = "hybrid_model.pt") -> None:
        super().__init__()
        self.path = Path(path)

    def on_fit_end(self, trainer: L.Trainer, pl_module) -> None:
        if not trainer.is_global_zero:
            return
        training = {
            "hparams": dict(pl_module.hparams),
            "best_validation": pl_module.best_metrics(),
            "base_validation": pl_module.base_metrics(),
            "epochs": int(trainer.current_epoch),
        }
        save_hybrid(self.path, pl_module.hybrid, metadata={"command": "train"}, training=training)
