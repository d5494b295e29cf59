"""Fig.-4-like figure for TensorBoard: base model vs hybrid error distributions, of
the model as written (after the blocked hold-out's decisions where they run)."""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path

import torch

from hybrid_pk.evaluation.metrics import error_stats
from hybrid_pk.hybrid.losses import (
    ResidualTargets,
    corrected_orientation_errors_deg,
    corrected_position_errors_mm,
)

__all__ = ["FIGURE_TAG", "WRITTEN_TAGS", "log_error_figure", "log_written_model"]

FIGURE_TAG = "val/error_distribution"
# scalars of the model as written, after the blocked hold-out (the val/ curves are the
# fit's, every stage gated to its training joints)
WRITTEN_TAGS = tuple(
    f"written/{q}_{s}" for q in ("position_mm", "orientation_deg") for s in ("mean", "p95")
)


@torch.no_grad()
def log_error_figure(module, rows: ResidualTargets, note: str = "") -> Path | None:
    """Draw the error distributions of the base model and of the hybrid on ``rows``
    (paper Fig. 4), save ``error_distribution.png`` in the logger's folder and add it
    to TensorBoard as the image ``val/error_distribution``.

    Args:
        module: a fitted :class:`~hybrid_pk.training.HybridLitModule` with a
            TensorBoard logger.
        rows: validation rows.
        note: added to the title (the blocked hold-out's decisions).

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
        f"{module.current_epoch} epochs{note}",
    )
    writer.add_image(FIGURE_TAG, imread(path)[..., :3], module.global_step, dataformats="HWC")
    writer.flush()
    return path


@torch.no_grad()
def log_written_model(module, rows: ResidualTargets, blocked: dict) -> Path | None:
    """After the blocked hold-out (``blocked``: its records, ``"<index>:<label>"`` ->
    record, applied to ``module.hybrid``): the figure of the model as written, its
    title naming each probed stage's mode, and its mean / p95 validation errors as the
    scalars :data:`WRITTEN_TAGS`. The figure of :func:`log_error_figure`, drawn once."""
    writer = module._tensorboard()
    if writer is None:
        return None
    hybrid = module.hybrid.eval()
    dp, dw = hybrid.corrections(rows.q)
    errors = {"position_mm": corrected_position_errors_mm(rows.position, rows.lever, dp, dw)}
    if rows.rotation is not None and hybrid.orientation is not None:
        errors["orientation_deg"] = corrected_orientation_errors_deg(rows.rotation, dw)
    for key, e in errors.items():
        stats = error_stats(e)
        writer.add_scalar(f"written/{key}_mean", stats.mean, module.global_step)
        writer.add_scalar(f"written/{key}_p95", stats.p95, module.global_step)
    modes = ", ".join(f"{k.split(':', 1)[1]} {r['mode']}" for k, r in blocked.items())
    return log_error_figure(module, rows, f";\nblocked hold-out: {modes}" if modes else "")
