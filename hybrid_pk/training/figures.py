"""Fig.-4-like figure for TensorBoard: base model vs hybrid error distributions."""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path

import torch

from hybrid_pk.hybrid.losses import (
    ResidualTargets,
    corrected_orientation_errors_deg,
    corrected_position_errors_mm,
)

__all__ = ["FIGURE_TAG", "log_error_figure"]

FIGURE_TAG = "val/error_distribution"


@torch.no_grad()
def log_error_figure(module, rows: ResidualTargets) -> Path | None:
    """Draw the error distributions of the base model and of the hybrid on ``rows``
    (paper Fig. 4), save ``error_distribution.png`` in the logger's folder and add it
    to TensorBoard as the image ``val/error_distribution``.

    Args:
        module: a fitted :class:`~hybrid_pk.training.HybridLitModule` with a
            TensorBoard logger.
        rows: validation rows.

    Returns:
        The PNG written, or None without a TensorBoard logger or matplotlib.
    """
    writer = module._tensorboard()
    if writer is None:
        return None
    try:
        from matplotlib.image import imread

        from hybrid_pk.evaluation.plots import error_histograms
    except Exception as exc:  # matplotlib missing: the figure is optional
        warnings.warn(f"no error-distribution figure: {exc}", stacklevel=2)
        return None
    hybrid = module.hybrid
    was_training = hybrid.training
    hybrid.eval()
    dp, dw = hybrid.corrections(rows.q)
    hybrid.train(was_training)
    zero = torch.zeros_like(dp)
    base = [corrected_position_errors_mm(rows.position, rows.lever, zero, zero), None]
    after = [corrected_position_errors_mm(rows.position, rows.lever, dp, dw), None]
    if rows.rotation is not None:
        base[1] = corrected_orientation_errors_deg(rows.rotation, zero)
        after[1] = corrected_orientation_errors_deg(rows.rotation, dw)
    folder = Path(module.logger.log_dir or tempfile.mkdtemp(prefix="hybrid_pk_fig_"))
    path = error_histograms(
        base,
        after,
        ("base model", "hybrid"),
        folder / "error_distribution.png",
        # the networks restored to their best state, not those of the last epoch
        title=f"validation rows (n = {rows.n}), networks at their best of "
        f"{module.current_epoch} epochs",
    )
    writer.add_image(FIGURE_TAG, imread(path)[..., :3], module.global_step, dataformats="HWC")
    writer.flush()
    return path
