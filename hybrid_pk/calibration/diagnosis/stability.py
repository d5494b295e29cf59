"""Whether a diagnosis would name the same causes again: the same rows diagnosed with
other seeds (``diagnose --stability N``).

The seed draws the random hold-out rows and the blocks (k-means regions) the causes
must carry over to. Where the data hold two near-equivalent explanations (on the
shared UR10 series: an elbow link length with a shoulder-lift compliance, or a tilt of
the base bearing under the arm's moment), which one the search names depends on those
draws, and one diagnosis cannot show it. Running it again with the next seeds can:
a cause named in every run is supported by these rows whatever the draw, one named in
some runs is one of several stories the rows do not tell apart. The first run (the
user's seed) stays the diagnosis; the others only report.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

from hybrid_pk.calibration.diagnosis.result import Diagnosis, cause_labels
from hybrid_pk.calibration.diagnosis.search import diagnose
from hybrid_pk.data import MeasuredData
from hybrid_pk.robot import Robot

__all__ = ["seed_stability", "stability_lines"]


def seed_stability(
    robot: Robot,
    data: MeasuredData,
    first: Diagnosis,
    runs: int,
    keywords: dict,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """The ``stability`` entry of the diagnosis JSON: ``first`` (the diagnosis of
    ``keywords``, a :func:`diagnose` call's keywords with its ``seed``) and ``runs - 1``
    more diagnoses of the same rows with the seeds after it.

    Returns:
        ``{"seeds", "runs" (the causes of each run), "named" ({cause: runs naming
        it}, most first), "in_every_run", "in_some_runs"}``.
    """
    say = progress or (lambda _m: None)
    seed = int(keywords.get("seed", 0))
    named = [cause_labels(first)]
    for k in range(1, runs):
        say(f"stability: diagnosis {k + 1} of {runs} (seed {seed + k})")
        again = diagnose(robot, data, **{**keywords, "seed": seed + k})
        named.append(cause_labels(again))
    counts = Counter(label for run in named for label in run)
    order = sorted(counts, key=lambda label: (-counts[label], label))
    return {
        "seeds": [seed + k for k in range(runs)],
        "runs": named,
        "named": {label: counts[label] for label in order},
        "in_every_run": [label for label in order if counts[label] == runs],
        "in_some_runs": [label for label in order if counts[label] < runs],
    }


def stability_lines(stability: dict) -> list[str]:
    """What ``diagnose --stability N`` prints."""
    runs, seeds, named = len(stability["runs"]), stability["seeds"], stability["named"]
    every = ", ".join(stability["in_every_run"]) or "none"
    lines = [
        f"stability over seeds {seeds[0]}-{seeds[-1]} ({runs} diagnoses of the same rows):",
        f"  named in every run: {every}",
    ]
    some = [f"{label} ({named[label]} of {runs})" for label in stability["in_some_runs"]]
    if some:
        lines.append("  named in some runs only (the rows do not tell them apart): "
                     + ", ".join(some))  # fmt: skip
    return lines
