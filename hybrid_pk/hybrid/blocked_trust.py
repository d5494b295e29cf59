"""Whether a stage's networks carry over beyond their training rows: decided on blocked
hold-out of those rows (issue 27).

A stage on physics inputs (:class:`~hybrid_pk.hybrid.features.PhysicsFeatures`,
:class:`~hybrid_pk.hybrid.local.LocalFeatures`) assumes invariances: its correction
turns with joint 1 (equivariance), and depends on the arm's posture only through its
own inputs (the static load). Where they hold it extrapolates, e.g. to angles of joint
1 never measured; where they do not, its coverage (in its own input space) still
calls such rows "inside" and the correction is wrong there.

So every such stage first gets a :class:`JointGate`, the coverage of its training
rows in *joint* space (the joint box times the distance to the training joints, as
the networks on every joint have): the stage is used only near where it was trained,
the physics beyond. The gate is lifted (``free``: only joint 1's trained range stays,
see :meth:`JointGate.trust`) only if the stage beats the physics on **blocked**
hold-out: contiguous regions of its training rows (end quarters of
joint 1 and of the joint that moves the flange point most, whole files when there are
several) left out of a probe fit of the same networks (:mod:`~hybrid_pk.training.blocked`).
For a freed stage with a :class:`~hybrid_pk.hybrid.spread.TargetSpread` the same test
decides whether it is shrunk there (``shrunk``) or kept in full (``free``); a gated
stage drops its spread.

:func:`decide` frees a stage, in cascade order, only if it beats ``gated`` on the
blocked score (per row: hybrid / physics mean error, position plus orientation, as the
validation score) of every family of blocks (each invariance: joint 1's ends, the other
joint's ends, the files) by at least two standard errors: a measured gain on each.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn

from hybrid_pk.hybrid.coverage import Coverage
from hybrid_pk.hybrid.inputs import InputBox
from hybrid_pk.hybrid.tuning import hybrid_tuning

__all__ = ["MODES", "JointGate", "beats", "decide", "verdict"]

MODES = ("gated", "free", "shrunk")


class JointGate(nn.Module):
    """Trust of a stage in joint space: the training rows' joint box times the coverage
    of their joints (normalised over that box).

    Args:
        box: the training rows' joint box (fade 0: nothing outside it).
        coverage: coverage of the normalised training joints.
        free: the stage earned its use away from the training joints: only joint 1's
            trained range remains (see :meth:`trust`).
        carried: rows of a new set-up showed the stage carries beyond its training
            joints, joint 1's range included (``calibrate --refit``,
            :mod:`~hybrid_pk.pipelines.network_rule`): the gate is open everywhere and
            the stage's own coverage (in its inputs) alone limits it.
    """

    def __init__(
        self, box: InputBox, coverage: Coverage, free: bool = False, carried: bool = False
    ) -> None:
        super().__init__()
        self.box = box
        self.coverage = coverage
        self.free = bool(free)
        self.carried = bool(carried)

    @classmethod
    def fit(cls, q_train: Tensor, q_val: Tensor | None, quantile: float, ratio: float) -> JointGate:
        """Gate of training joints ``q_train (N, dof)``, its full-trust radius set by
        the held-out rows ``q_val`` of the same region (see
        :meth:`Coverage.from_inputs`)."""
        box = InputBox.from_data(q_train.detach().to(torch.float64), None, 0.0)
        val = None if q_val is None else box.normalise(q_val.detach().to(torch.float64))
        cov = Coverage.from_inputs(
            box.normalise(q_train.detach().to(torch.float64)), val, quantile=quantile, ratio=ratio
        )
        return cls(box, cov)

    def trust(self, q: Tensor) -> Tensor:
        """``(*B,)`` weight in [0, 1] at joints ``q (*B, dof)``: the box times the
        coverage, or (:attr:`free`) joint 1's trained range alone. Even a
        freed stage is not carried to angles of joint 1 never trained on: blocked
        hold-out inside the trained range cannot tell an error that turns with joint 1
        from one symmetric about the middle of that range (the test of a sin q1 field
        trained on [0, pi]: the stages gained 8-18 % on joint 1's end quarters and were
        1.6 x worse than the physics on [-pi, 0])."""
        if self.carried:
            return torch.ones(q.shape[:-1], dtype=q.dtype, device=q.device)
        if self.free:
            lo, hi = self.box.trust_lower[0].to(q.dtype), self.box.trust_upper[0].to(q.dtype)
            return ((q[..., 0] >= lo) & (q[..., 0] <= hi)).to(q.dtype)
        return self.box.trust(q) * self.coverage.trust(self.box.normalise(q))

    def state(self) -> dict:
        """Plain data for a model file."""
        out = {"input": self.box.state(), "coverage": self.coverage.state(), "free": self.free}
        return out | ({"carried": True} if self.carried else {})

    @classmethod
    def from_state(cls, state: dict) -> JointGate:
        """Inverse of :meth:`state`."""
        return cls(
            InputBox.from_state(state["input"]),
            Coverage.from_state(state["coverage"]),
            bool(state.get("free", False)),
            bool(state.get("carried", False)),
        )


Scorer = Callable[[dict[int, str]], tuple[dict[str, Tensor], dict[str, float]]]


def beats(candidate: Tensor, reference: Tensor) -> bool:
    """Whether per-row scores ``candidate (n,)`` are lower than ``reference (n,)`` (the
    same rows) by at least the tuning's ``freeing_z`` standard errors of the mean difference."""
    return verdict(candidate, reference)["beats"]


def verdict(candidate: Tensor, reference: Tensor) -> dict:
    """The evidence :func:`beats` decides on: rows, the mean drop of the per-row score
    from ``reference`` to ``candidate`` (a share of the physics' error per channel,
    summed over the channels), its standard error, ``z`` (their ratio) and ``beats``."""
    d = (reference - candidate).to(torch.float64)
    if d.numel() < 2:
        return {"rows": int(d.numel()), "gain": 0.0, "se": 0.0, "z": 0.0, "beats": False}
    gain, se = float(d.mean()), float(d.std()) / d.numel() ** 0.5
    z = gain / max(se, 1e-300)  # finite for the JSON; no spread: the sign decides
    rows = int(d.numel())
    return {"rows": rows, "gain": gain, "se": se, "z": z, "beats": z > hybrid_tuning().freeing_z}


def decide(stages: list[int], spread: set[int], score: Scorer) -> dict[int, dict]:
    """Mode of each probed stage, greedily in cascade order.

    Args:
        stages: indices of the stages to decide (the others keep their own trust).
        spread: those of them that carry a target spread (``shrunk`` is tried too).
        score: ``{stage: mode}`` (every probed stage) -> the per-row blocked scores
            (lower is better) of each family of blocks (one per invariance: a joint's
            ends, the files) and the mean errors to report (``position_mm``, ...).

    Returns:
        ``{stage: {"mode": ..., "families": {family: verdict of free against gated},
        "<mode>": errors of that choice}}``. ``free`` is taken
        only if it :func:`beats` ``gated`` on every family (each invariance the stage
        assumes holds); a freed stage with a spread is ``shrunk`` if that beats
        ``free`` on all the blocked rows (the shrink alone never frees a stage: it only
        softens a correction that carries over).
    """
    modes = {i: "gated" for i in stages}
    out: dict[int, dict] = {}
    for i in stages:
        tried = {m: score({**modes, i: m}) for m in ("gated", "free")}
        gated, free = tried["gated"][0], tried["free"][0]
        families = {f: verdict(free[f], gated[f]) for f in gated}
        best = "free" if all(v["beats"] for v in families.values()) else "gated"
        if best == "free" and i in spread:
            tried["shrunk"] = score({**modes, i: "shrunk"})
            if beats(torch.cat(list(tried["shrunk"][0].values())), torch.cat(list(free.values()))):
                best = "shrunk"
        modes[i] = best
        out[i] = {"mode": best, "families": families}
        out[i].update({m: errors for m, (_, errors) in tried.items()})
    return out
