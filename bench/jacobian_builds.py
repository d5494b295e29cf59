"""Every Jacobian a diagnosis builds, by the step of the diagnosis that asked for it,
against those of the plain fit of the model it found (``bench/diagnose.py``'s peer).

A Jacobian build is one pass of ``Problem.augmented_chunks``: ``[J r]`` of every fit
row at one model point. It is the largest single cost of a diagnosis and of a fit
alike, so the table shows where the diagnosis' time goes beyond the plain fit's, and
which part of it the search's rule needs (one linearisation with every candidate per
step, one exact Jacobian at each accepted refit's optimum). One thread, as the fits
run by default.

    python bench/jacobian_builds.py                 # the two UR10 series (~45 s)
    python bench/jacobian_builds.py --case rx160    # any case of bench/diagnose.py
"""

from __future__ import annotations

import argparse
import sys
import time
import traceback
from collections import defaultdict
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import diagnose as bench

from hybrid_pk.calibration import diagnose
from hybrid_pk.calibration.problem import Problem

DIAGNOSIS = "/calibration/diagnosis/"
# helpers that several steps call: a build is put down to the step that called them
SHARED = {"carryover.linearise", "swaps._swapped", "swaps.best_swap"}


def _asker() -> str:
    """The innermost step of the diagnosis (``module.function``, not a shared helper)
    on the stack; ``plain fit`` outside a diagnosis."""
    for f in reversed(traceback.extract_stack()[:-3]):
        name = f"{Path(f.filename).stem}.{f.name}"
        if DIAGNOSIS in f.filename.replace("\\", "/") and name not in SHARED:
            return name
    return "plain fit"


def counted(log: list) -> None:
    """Wrap ``Problem.augmented_chunks`` so that each full pass is logged as
    ``(asker, columns, seconds)``; the time is the pass's own (what the caller does
    with each chunk between them included, as the caller pays it)."""
    original = Problem.augmented_chunks

    def augmented_chunks(self, theta):
        asker, start = _asker(), time.perf_counter()
        yield from original(self, theta)
        log.append((asker, self.x0.numel(), time.perf_counter() - start))

    Problem.augmented_chunks = augmented_chunks


def table(log: list, title: str) -> float:
    """Print builds per asker; returns their total seconds."""
    by = defaultdict(lambda: [0, 0, 0.0])
    for asker, cols, seconds in log:
        entry = by[asker]
        entry[0] += 1
        entry[1] += cols
        entry[2] += seconds
    total = sum(e[2] for e in by.values())
    print(f"\n{title}: {len(log)} Jacobian builds, {total:.1f} s")
    print(f"  {'asked by':46s} {'builds':>6s} {'mean cols':>9s} {'seconds':>8s}")
    for asker, (n, cols, seconds) in sorted(by.items(), key=lambda kv: -kv[1][2]):
        print(f"  {asker:46s} {n:6d} {cols / n:9.0f} {seconds:8.2f}")
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--case", default="ur10", choices=bench.CASES)
    parser.add_argument("--ipa", type=Path, default=bench.IPA, help="the UR10 series' folder")
    args = parser.parse_args()
    torch.set_num_threads(1)
    robot, data, frames_per_file, _ = bench._case_data(args.case, args.ipa)
    robot.requires_grad_(False)
    bench.warm_up(robot, data, frames_per_file)
    log: list = []
    counted(log)
    start = time.perf_counter()
    diag = diagnose(robot, data, frames_per_file=frames_per_file)
    t_diag = time.perf_counter() - start
    diag_log, log[:] = list(log), []
    labels = [bench._label(c) for c in diag.causes]
    t_fit = bench.plain_fit(robot, data, labels, frames_per_file)
    print(f"{args.case}: {data.n} rows, {len(labels)} causes; diagnose {t_diag:.1f} s, "
          f"plain fit {t_fit:.1f} s ({t_diag / t_fit:.1f}x)")  # fmt: skip
    builds_diag = table(diag_log, "diagnose")
    builds_fit = table(log, "plain fit")
    needed = sum(
        s for a, _, s in diag_log if a in ("selection.score_candidates", "selection.try_candidate")
    )  # fmt: skip
    print(
        f"\nJacobian builds: diagnose {builds_diag:.1f} s of {t_diag:.1f}, plain fit "
        f"{builds_fit:.1f} s of {t_fit:.1f}.\nThe search's scorings and its refits' exact "
        f"Jacobians alone: {needed:.1f} s = {needed / t_fit:.1f}x the plain fit."
    )


if __name__ == "__main__":
    main()
