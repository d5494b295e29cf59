"""Lightning training of the residual networks.

A thin layer: the networks, losses and the hybrid model are plain modules of
:mod:`hybrid_pk.hybrid`; here they meet Lightning (module, datamodule, trainer,
TensorBoard). ``train/`` holds the LightningCLI entry point, its YAML configs and the
paper-reproduction script.
"""

from hybrid_pk.training.datamodule import HybridDataModule as HybridDataModule
from hybrid_pk.training.lightning_module import HybridLitModule as HybridLitModule
from hybrid_pk.training.presets import PRESETS as PRESETS
from hybrid_pk.training.presets import preset as preset
from hybrid_pk.training.run import TrainResult as TrainResult
from hybrid_pk.training.run import make_trainer as make_trainer
from hybrid_pk.training.run import quiet_lightning as quiet_lightning
from hybrid_pk.training.run import train_hybrid as train_hybrid

__all__ = [
    "PRESETS",
    "HybridDataModule",
    "HybridLitModule",
    "TrainResult",
    "make_trainer",
    "preset",
    "quiet_lightning",
    "train_hybrid",
]
