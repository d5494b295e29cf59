"""How far one linearisation carries the diagnosis' search (issue 30's ``<= 5x``).

``diagnose`` linearises the model afresh at every step of its forward selection: one
Jacobian of every candidate, a score test and a blocked gain each, the best refitted,
then the next step at the refitted model (16 steps on the shared UR10 series). Its
scorings and refits are most of its time. This experiment asks what a search that
re-linearises only between *rounds* would choose:

1. at the current model, one exact scoring of every candidate (the search's own
   :func:`~hybrid_pk.calibration.diagnosis.selection.score_candidates`, after its cyclic
   screen);
2. forward selection on that linearisation alone: each candidate's score test is taken
   conditional on the causes the round has chosen (their columns projected off as the
   model's), its blocked gain with them re-fitted per block, and the search's entry
   rule applies (Bonferroni-significant, gaining the practical margin and its own
   standard error); the best by BIC gain enters, until none does;
3. one nonlinear refit of the model with the round's causes; the next round from there,
   until a round adds nothing.

Backward elimination, the order checks of cyclic errors and every stage after the
search are left out: the question is only how many linearisations the forward steps
need and whether they pick the same causes. It prints each round (causes, seconds)
and compares the final set with a diagnosis JSON (``--reference``).

    python experiments/linear_rounds.py --reference DIAG.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.diagnosis.ambiguity import projector_residual
from hybrid_pk.calibration.diagnosis.carryover import Carry
from hybrid_pk.calibration.diagnosis.cyclic_screen import screen_cyclic
from hybrid_pk.calibration.diagnosis.noise import measurement_noise
from hybrid_pk.calibration.diagnosis.regions import make_folds
from hybrid_pk.calibration.diagnosis.selection import (
    RANK_TOLERANCE,
    candidate_labels,
    gauss_newton_start,
    score_candidates,
)
from hybrid_pk.calibration.diagnosis.settle import rival_advantages
from hybrid_pk.calibration.diagnosis.split import split_campaign
from hybrid_pk.calibration.diagnosis.variants import shift_parameters, with_effects
from hybrid_pk.calibration.fit import fit
from hybrid_pk.calibration.known_frames import initialise_with_priors
from hybrid_pk.calibration.settings import DiagnosisSettings
from hybrid_pk.distributions import f_sf
from hybrid_pk.effects import ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.effects.joint import CYCLIC_PREFIX

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ipa_series import add_data, import_series, read_rows


def ur10_series(data: Path):
    """The UR10 robot and both IPA series (``hybrid-pk import ipa``, :mod:`ipa_series`)."""
    robot = hpk.Robot.from_urdf("ur10")
    paths = import_series(Path(tempfile.mkdtemp(prefix="linear_rounds_")), data, {})
    return robot, read_rows(list(paths.values()), robot)


def columns(scores) -> dict[str, torch.Tensor]:
    """Column indices of every block of a scoring's factor, by label."""
    out, start = {}, 0
    for b in scores.blocks:
        out[b.label] = torch.arange(start, start + b.size)
        start += b.size
    return out


def conditional_scores(scores, cols, base: list[str], open_: list[str]) -> dict:
    """Score test of each ``open_`` candidate given the model's columns and ``base``'s
    (causes chosen this round): ``{label: (p, bic_gain)}``."""
    R = scores.R
    n = R.shape[1] - 1
    keep = torch.cat([torch.arange(scores.n_current)] + [cols[b] for b in base])
    Q = torch.linalg.qr(R[:, keep])[0]
    r = R[:, n]
    r_off = r - Q @ (Q.T @ r)
    ssr, m, n_cur = float(r_off @ r_off), scores.m, keep.numel()
    out = {}
    for label in open_:
        Jc = R[:, cols[label]]
        U, S, _ = torch.linalg.svd(projector_residual(Jc, Q), full_matrices=False)
        k = int((S > RANK_TOLERANCE * float(Jc.norm())).sum())
        if k == 0:
            continue
        drop = min(float((U[:, :k].T @ r_off).pow(2).sum()), ssr)
        dof = max(m - n_cur - k, 1)
        F = (drop / k) / max((ssr - drop) / dof, 1e-300)
        out[label] = (f_sf(F, k, dof), -(drop - k * math.log(m)))
    return out


def linear_round(model, scores, say, limit: int) -> list[str]:
    """The causes forward selection picks on ``scores``' linearisation alone."""
    cols, blocked = columns(scores), scores.blocked
    current = [e.label for e in model.effects]
    chosen: list[str] = []
    open_ = [sc.label for sc in scores.scored]
    while open_:
        tests = conditional_scores(scores, cols, chosen, open_)
        base = blocked.of(current + chosen)
        labels = [c for c in open_ if c in tests and tests[c][0] < scores.threshold]
        eligible = []
        for c, with_it in zip(labels, blocked.each(current + chosen, labels), strict=True):
            gain, se = blocked.gain_mm(base, with_it), blocked.gain_se_mm(base, with_it)
            if gain >= max(scores.margin, se):
                eligible.append((tests[c][1], c, gain))
        best = None
        for _, label, gain in sorted(eligible):
            if label not in open_:
                continue  # set aside with an order above it
            rivals = order_rivals(blocked, current + chosen, label, open_, scores.margin)
            if not rivals:
                best = (label, gain)
                break
            say(f"    ({label}: other orders predict as well: {', '.join(rivals)})")
            open_ = [c for c in open_ if c != label and c not in rivals]
        if best is None or len(current) + len(chosen) >= limit:
            break
        say(f"    + {best[0]} (blocked gain {best[1]:.4f} mm)")
        chosen.append(best[0])
        open_.remove(best[0])
    return chosen


def order_rivals(blocked, effects, label, open_, margin) -> list[str]:
    """The other open orders of a cyclic candidate's joint that predict the held-out
    blocks within ``margin`` of it (the search's entry check on the scored orders)."""
    if not label.startswith(CYCLIC_PREFIX):
        return []
    joint = label.partition(":")[2]
    alts = [
        c for c in open_
        if c != label and c.startswith(CYCLIC_PREFIX) and c.partition(":")[2] == joint
    ]  # fmt: skip
    adv = rival_advantages(blocked, effects, label, alts)
    return [a for a, v in adv.items() if v < margin]


def refit_with(model, res, scores, chosen, split):
    """The model with ``chosen`` added, started at the linearised optimum, refitted."""
    new = with_effects(model, [make_effect(model.robot, c) for c in chosen])
    steps: dict = {}
    for label in chosen:  # the Gauss-Newton start of each, with the model's blocks
        steps.update(gauss_newton_start(scores, label))
    shift_parameters(new, steps, split.position_only)
    sigmas = (res.sigma_pos_mm, res.sigma_rot_rad)
    near = scores.near  # the round's Jacobian: the refit steps with it (a chord)
    return new, fit(new, split.train, cond=split.cond_fit, initial_sigma=sigmas, near=near)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    add_data(ap)
    ap.add_argument("--reference", type=Path, help="a diagnosis JSON of the same rows")
    ap.add_argument("--rounds", type=int, default=6, help="at most this many rounds")
    args = ap.parse_args()
    torch.set_num_threads(1)
    robot, data = ur10_series(args.data)
    defaults = DiagnosisSettings()
    cond = conditions_from_data(data, True, robot)
    split = split_campaign(data, cond, defaults.holdout, defaults.seed)
    start = time.perf_counter()
    model = ExtendedModel(robot, frame_sets=len(data.sources))
    initialise_with_priors(model, split.train, split.cond_fit, None)
    res = fit(model, split.train, cond=split.cond_fit)
    noise = measurement_noise(model, data, cond)
    carry = Carry(make_folds(model, split, defaults.seed), None, noise)
    remaining = candidate_labels(robot, data)
    print(f"frames and folds: {time.perf_counter() - start:.1f} s")
    for k in range(args.rounds):
        t0 = time.perf_counter()
        pool, screened = screen_cyclic(
            model, split, remaining, res.weights, carry.folds, carry.margin(res)
        )
        scores = score_candidates(
            model, res, pool, split, defaults.alpha, False, screened=screened, carry=carry
        )
        t1 = time.perf_counter()
        print(f"round {k + 1}: {len(pool)} candidates scored in {t1 - t0:.1f} s")
        chosen = linear_round(model, scores, print, defaults.max_causes)
        t2 = time.perf_counter()
        if not chosen:
            print(f"  nothing enters ({t2 - t1:.1f} s)")
            break
        model, res = refit_with(model, res, scores, chosen, split)
        remaining = [c for c in remaining if c not in chosen]
        print(
            f"  {len(chosen)} causes: selection {t2 - t1:.1f} s, refit "
            f"{time.perf_counter() - t2:.1f} s; position sigma {res.sigma_pos_mm:.4f} mm"
        )
    named = [e.label for e in model.effects]
    print(f"search in rounds: {time.perf_counter() - start:.1f} s, {len(named)} causes")
    if args.reference:
        ref = {f"{c['effect']}:{c['joint']}" if c.get("joint") else c["effect"]
               for c in json.loads(args.reference.read_text())["causes"]}  # fmt: skip
        print(f"  also in the reference: {sorted(set(named) & ref)}")
        print(f"  only here: {sorted(set(named) - ref)}")
        print(f"  only in the reference: {sorted(ref - set(named))}")


if __name__ == "__main__":
    main()
