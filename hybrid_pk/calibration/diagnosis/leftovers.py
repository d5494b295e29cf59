"""What a diagnosis leaves: the rows beyond the noise (outliers, the robust fit's
down-weighted rows) and the error no cause explains (its size, whether it is smooth,
what it varies along)."""

from __future__ import annotations

from hybrid_pk.calibration.diagnosis.noise import NoiseEstimate, beyond_noise
from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.calibration.diagnosis.statistics import (
    along_joints,
    in_link_1,
    neighbour_structure,
    residual_vectors,
)
from hybrid_pk.calibration.fit import FitResult, model_errors
from hybrid_pk.calibration.robust import OUTLIER_K, down_weighted, list_outliers
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import ExtendedModel, conditions_from_data

__all__ = ["left_verdict", "outliers_json", "robust_json", "structured_text", "unexplained_json"]


def outliers_json(model: ExtendedModel, data: MeasuredData, per_file: bool, res: FitResult):
    """Rows of ``data`` (fit and hold-out) beyond ``OUTLIER_K`` sigma of the final fit."""
    pos, ori = model_errors(model, data, conditions_from_data(data, per_file))
    return list_outliers(data, pos, ori, res.sigma_pos_mm, res.sigma_rot_rad)


def robust_json(res: FitResult, data: MeasuredData, split: Split) -> dict | None:
    """What a robust diagnosis down-weighted (rows of the fit set)."""
    if res.robust is None:
        return None
    return {
        "loss": res.robust,
        "outlier_k": OUTLIER_K,
        "down_weighted": down_weighted(data, res.weights, split.fit_rows),
    }


def unexplained_json(
    model: ExtendedModel, split: Split, errors: tuple, noise: NoiseEstimate | None = None
) -> dict:
    """RMS of what the model leaves on the hold-out rows, whether it is structured
    (neighbouring rows share it, or it is larger than the measurement ``noise``), and
    how much of it varies along each joint."""
    pos1, ori1 = errors
    residual_hold = residual_vectors(model, split.test, split.cond_hold)
    lower, upper = model.robot.joint_limits
    smooth, nn_corr = neighbour_structure(residual_hold, split.test.q, lower, upper)
    beyond = beyond_noise(residual_hold[:, :3], noise)
    return {
        "position_mm_rms": float(pos1.pow(2).mean().sqrt()),
        "orientation_deg_rms": None if ori1 is None else float(ori1.pow(2).mean().sqrt()),
        "structured": smooth or bool(beyond and beyond["beyond"]),
        "neighbour_correlation": nn_corr,
        "smooth": smooth,
        "beyond_noise": beyond,
        "along_joints": along_joints(
            in_link_1(model, split.test, split.cond_hold, residual_hold),
            split.test.q,
            model.robot.joint_names,
        ),
    }


def left_verdict(un: dict) -> str:
    """Why the left error (:func:`unexplained_json`) is structured: ``"smooth"``
    (neighbouring rows share it), ``"beyond_noise"`` (larger than the noise), or
    ``"noise"`` (neither)."""
    if un.get("smooth", un.get("structured")):
        return "smooth"
    return "beyond_noise" if (un.get("beyond_noise") or {}).get("beyond") else "noise"


def structured_text(un: dict) -> str:
    """The verdict on the left error (:func:`left_verdict`) in words."""
    beyond, verdict = un.get("beyond_noise") or {}, left_verdict(un)
    if verdict == "smooth":
        return "yes (a smooth error is left that no cause explains)"
    if verdict == "beyond_noise":
        return (
            f"yes (it is {beyond['ratio']:.3g} times the measurement noise, where noise "
            f"alone stays below {beyond['limit']:.3g}; the hold-out poses are too far "
            "apart for neighbours to show its shape)"
        )
    if "pair_distance_mm" not in beyond:
        return (
            "no sign of it (no smooth error; its size is not compared with the noise: "
            "too few hold-out rows, or no model-free noise estimate)"
        )
    if beyond["pair_distance_mm"] == 0:
        return "no (within the measurement noise, as estimated from repeated poses)"
    return (
        "no (within the measurement noise, as estimated from pairs of poses up to "
        f"{beyond['pair_distance_mm']:.3g} mm apart: an error that varies over less than "
        "that is not told from noise)"
    )
