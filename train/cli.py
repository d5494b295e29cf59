"""LightningCLI entry point for the residual networks of a hybrid model.

    python train/cli.py fit --config train/configs/fast.yaml \
        --data.data '[campaign.csv]' --data.model calibrated.pt

``--data.model`` is a model file from ``hybrid-pk calibrate`` (or ``nominal:ROBOT``
when the data is the flange measured in the robot's base frame). The fit writes the
hybrid model file named by the ``WriteModelFile`` callback of the config, TensorBoard
logs and checkpoints. ``hybrid-pk train`` runs the same module and datamodule with a
progress bar and a summary; prefer it unless you need LightningCLI's overrides.
"""

from __future__ import annotations

from lightning.pytorch.cli import LightningCLI

from hybrid_pk.training import HybridDataModule, HybridLitModule


def main(args: list[str] | None = None) -> None:
    LightningCLI(
        HybridLitModule, HybridDataModule, args=args, save_config_kwargs={"overwrite": True}
    )


if __name__ == "__main__":
    main()
