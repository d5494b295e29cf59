"""Whether a hybrid's networks carry over to a new set-up, decided on the rows its frames
are re-fitted on (issue 27: the hybrid is never worse than the physics out of coverage).

A model file with residual networks moved to a new set-up (``calibrate --model HYBRID
--refit frames``, :func:`~hybrid_pk.pipelines.refit.refit`) brings N rows of that set-up:
the only evidence there is of whether the networks' correction holds there (a robot's
own error does; one of the old set-up, its tracker or its workspace, does not). So both
the extended model (the physics) and the hybrid get their frames fitted on those rows
by the same fitter (:mod:`~hybrid_pk.pipelines.flange_frames`), and every row is
predicted with frames fitted without it (leave one out; folds beyond ``MAX_FOLDS`` rows).
The comparison is then out of sample for the frames, as it already is for the effects
and the networks (fitted on the other set-up); no other row of the new set-up is read.

The networks are kept only if the hybrid beats the physics on those held-out rows by
the tuning's ``freeing_z`` standard errors of the mean paired difference
(:func:`~hybrid_pk.hybrid.blocked_trust.beats`, the rule that frees a stage on blocked
hold-out), per row on the validation's score (position error over the physics' mean,
plus the orientation error over its mean where measured). Otherwise the file keeps
them but marks them unused (``networks["transfer"]``), and every command uses the
extended model (:func:`~hybrid_pk.io.hybrid_file.forward_model`) and says so.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from hybrid_pk.calibration.fit import DEFAULT_SIGMA_POS_MM, DEFAULT_SIGMA_ROT_RAD, FitResult
from hybrid_pk.calibration.frames import FramePriors
from hybrid_pk.data import MeasuredData
from hybrid_pk.distributions import norm_isf, norm_sf
from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.evaluation.metrics import row_errors
from hybrid_pk.geometry import quat_to_matrix
from hybrid_pk.hybrid import HybridFK
from hybrid_pk.hybrid.blocked_trust import beats
from hybrid_pk.hybrid.tuning import hybrid_tuning
from hybrid_pk.pipelines.calibration import FRAME_LABELS
from hybrid_pk.pipelines.flange_frames import (
    FlangeRows,
    fit_flange_frames,
    fold_of_rows,
    held_out_errors,
)

__all__ = ["NetworkVerdict", "carried_networks", "network_rule", "second_look_z", "verdict_line"]

# Looks at the same re-fit rows: the networks as stored, then with their gates lifted
# (Bonferroni: each look at the one-sided level of freeing_z divided by this).
LOOKS = 2


@dataclass(frozen=True)
class NetworkVerdict:
    """The rule's outcome on the re-fit rows: mean held-out errors of the physics and
    the hybrid, the mean paired gains (physics minus hybrid; positive: the networks
    help) with their standard errors, and whether the networks are used."""

    used: bool
    rows: int
    folds: int
    z: float
    physics_mm: float
    hybrid_mm: float
    gain_mm: float
    se_mm: float
    gain_deg: float | None
    se_deg: float | None
    score_gain: float
    score_se: float
    reached: int | None = None  # re-fit rows where any stage's networks act (trust > 0)
    carried: bool = False  # used with the stages' joint gates lifted (second look)
    lifted: dict | None = None  # the second look's numbers when it did not decide

    @property
    def rule(self) -> str:
        held = "leave one out" if self.folds == self.rows else f"{self.folds} folds"
        return (
            f"networks used only if, on the {self.rows} rows the frames are re-fitted on, "
            f"each predicted with frames fitted without it ({held}), the hybrid's error "
            "(position over the physics' mean, plus orientation over its mean where "
            f"measured) is lower than the extended model's by at least {self.z:g} standard "
            "errors of the mean paired difference"
        )

    def to_json(self) -> dict:
        out = {"used": self.used, "rule": self.rule}
        for key in ("z", "rows", "folds", "physics_mm", "hybrid_mm", "gain_mm", "se_mm"):
            out[key] = getattr(self, key)
        for key in ("gain_deg", "se_deg", "score_gain", "score_se", "reached", "carried", "lifted"):
            out[key] = getattr(self, key)
        return out

    def line(self) -> str:
        """One line for the command's output."""
        return verdict_line(self.to_json())


def verdict_line(verdict: dict) -> str:
    """One line on a file's networks from their ``transfer`` verdict (the JSON of a
    :class:`NetworkVerdict`)."""
    reached, lifted = verdict.get("reached"), verdict.get("lifted")
    second = ""
    if lifted is not None:
        second = (
            f"; with their joint gates lifted they act on {lifted['reached']} rows and gain "
            f"{lifted['gain_mm']:.3g} ± {lifted['se_mm']:.2g} mm (needs {lifted['z']:.3g} "
            "standard errors)"
        )
    if reached == 0:
        return (
            f"residual networks NOT used: as stored they act on none of the {verdict['rows']} "
            "re-fit rows (every row lies beyond where a stage is trusted: the joints they "
            f"were trained on, joint 1's trained range){second}; the extended model "
            "(physics) instead"
        )
    if verdict.get("used", True) and verdict.get("carried"):
        what = (
            "residual networks used beyond the joints they were trained on (their joint "
            "gates lifted: as stored they did not beat the physics here, lifted they do, "
            "at the stricter z of a second look)"
        )
    elif verdict.get("used", True):
        what = "residual networks used"
    else:
        what = "residual networks NOT used, the extended model (physics) instead"
    if reached is not None and reached < verdict["rows"]:
        what += f" (they act on {reached} of the {verdict['rows']} re-fit rows)"
    z = f"{verdict['z']:g}"
    return (
        f"{what} (held out on the {verdict['rows']} re-fit rows: hybrid "
        f"{verdict['hybrid_mm']:.4g} mm vs physics {verdict['physics_mm']:.4g} mm, gain "
        f"{verdict['gain_mm']:.3g} ± {verdict['se_mm']:.2g} mm; needs {z} standard errors)" + second
    )


def network_rule(
    nets: dict,
    model: ExtendedModel,
    data: MeasuredData,
    cond: Conditions,
    which: str,
    fit: FitResult,
) -> tuple[NetworkVerdict, tuple[Tensor, Tensor] | None, dict]:
    """The verdict on the networks of a model whose ``which`` frames were just
    re-fitted on ``data`` (``model``: the extended model with those frames, the start of
    every fit here), the hybrid's own frames ``(B, X)`` ``(G, 4, 4)`` on all rows
    when the networks are used (None otherwise), and the networks entry to keep.

    Networks that do not beat the physics as stored get a second look with their
    stages' joint gates lifted (:func:`carried_networks`): a stage gated to its
    training joints, or to joint 1's trained range, may still carry to the new rows (an
    error that turns with the arm, where the rows lie at new angles of joint 1), and
    these rows are the only evidence there is. They are then kept, lifted, only at
    :func:`second_look_z` (the one-sided level of ``freeing_z`` halved: two looks).

    Args:
        nets: the model file's networks entry.
        which: the re-fitted frames (``"base"``, ``"tool"``, ``"frames"``).
        fit: the re-fit of ``model`` (a :class:`~hybrid_pk.calibration.fit.FitResult`):
            its noise levels and robust row weights (``--robust``) weigh the residuals;
            the components its priors fix (known frames) are not fitted here either.
    """
    fixed = (fit.priors or FramePriors()).fixed_labels()
    free = tuple(b for b in FRAME_LABELS[which] if b not in fixed)
    with torch.no_grad():
        B0, X0 = model.base.matrix().detach(), model.tool.matrix().detach()
    group = cond.group if model.base.sets > 1 else None
    sig = (fit.sigma_pos_mm or DEFAULT_SIGMA_POS_MM, fit.sigma_rot_rad or DEFAULT_SIGMA_ROT_RAD)
    R_meas = None if data.quat is None else quat_to_matrix(data.quat)

    def held_out(flange: Tensor) -> tuple[FlangeRows, tuple]:
        rows = FlangeRows(flange, data.position, R_meas, *sig, fit.weights)
        return rows, row_errors(held_out_errors(rows, B0, X0, free, group), data)

    with torch.no_grad():
        physics = held_out(model.end_pose(data.q, cond))[1]

    def judged(state: dict, z: float | None) -> tuple[NetworkVerdict, FlangeRows]:
        hybrid = HybridFK.from_state(model, state)
        with torch.no_grad():
            rows, errors = held_out(hybrid.end_pose(data.q, cond))
        v = _verdict({"physics": physics, "hybrid": errors}, data.n, fold_of_rows(data.n)[1], z)
        return dataclasses.replace(v, reached=_reached(hybrid, data.q)), rows

    verdict, hybrid_rows = judged(nets, None)
    lifted = None if verdict.used else carried_networks(nets)
    if lifted is not None:
        second, rows2 = judged(lifted, second_look_z())
        if second.used:
            verdict, hybrid_rows, nets = dataclasses.replace(second, carried=True), rows2, lifted
        else:
            keys = ("reached", "gain_mm", "se_mm", "score_gain", "score_se", "z")
            verdict = dataclasses.replace(verdict, lifted={k: getattr(second, k) for k in keys})
    if not verdict.used:
        return verdict, None, nets
    frames = [
        fit_flange_frames(hybrid_rows, B0[g], X0[g], free, None if group is None else group == g)
        for g in range(B0.shape[0])
    ]
    return verdict, (torch.stack([f[0] for f in frames]), torch.stack([f[1] for f in frames])), nets


def carried_networks(nets: dict) -> dict | None:
    """``nets`` (a model file's networks entry) with every stage's joint gate lifted
    (``carried``), or None when no stage has one."""
    stages = [nets, *nets.get("stages", [])]
    if all(st.get("gate") is None for st in stages):
        return None
    out = copy.deepcopy(nets)
    for st in [out, *out.get("stages", [])]:
        if st.get("gate") is not None:
            st["gate"]["carried"] = True
    return out


def second_look_z() -> float:
    """The z of the lifted gates' look: the one-sided level of ``freeing_z`` halved
    (Bonferroni over the two looks at the same rows)."""
    return norm_isf(norm_sf(hybrid_tuning().freeing_z) / LOOKS)


def _verdict(errors: dict, n: int, folds: int, z: float | None = None) -> NetworkVerdict:
    """The rule on the held-out errors ``{"physics", "hybrid"}: (position, orientation)``
    (``z``: the standard errors the gain needs; None: the tuning's ``freeing_z``)."""
    (p_pos, p_ori), (h_pos, h_ori) = errors["physics"], errors["hybrid"]
    score = {"physics": p_pos / _scale(p_pos), "hybrid": h_pos / _scale(p_pos)}
    deg = (None, None)
    if p_ori is not None:
        score["physics"] = score["physics"] + p_ori / _scale(p_ori)
        score["hybrid"] = score["hybrid"] + h_ori / _scale(p_ori)
        deg = _mean_se(p_ori - h_ori)
    means = (float(p_pos.mean()), float(h_pos.mean()))
    mm, scores = _mean_se(p_pos - h_pos), _mean_se(score["physics"] - score["hybrid"])
    if z is None:
        z, used = hybrid_tuning().freeing_z, beats(score["hybrid"], score["physics"])
    else:
        used = n > 1 and scores[0] > z * scores[1]
    return NetworkVerdict(used, n, folds, z, *means, *mm, *deg, *scores)


@torch.no_grad()
def _reached(hybrid: HybridFK, q: Tensor) -> int:
    """Rows of joints ``q`` where any stage's networks have a weight above zero."""
    acts = torch.zeros(q.shape[0], dtype=torch.bool)
    for w in hybrid.weights(q):
        acts |= (w.reshape(q.shape[0], -1) > 0).any(1)
    return int(acts.sum())


def _scale(err: Tensor) -> Tensor:
    """The mean error a score divides by; 1e-12 [mm, deg] only keeps exact rows finite."""
    return err.mean().clamp_min(1e-12)


def _mean_se(d: Tensor) -> tuple[float, float]:
    """Mean of paired differences and its standard error (NaN for one row)."""
    d = d.to(torch.float64)
    se = float(d.std() / d.numel() ** 0.5) if d.numel() > 1 else float("nan")
    return float(d.mean()), se
