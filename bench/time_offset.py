"""Time offsets of simulated stream pairs: how often the estimate is off by more than a
robot sample, and how often ``import streams`` says the offset is not determined.

    python bench/time_offset.py                       # seeds 100-109, 0.3-12 s (~4 min)
    python bench/time_offset.py --seeds 1 2 --durations 0.5 12

Each stream pair is ``tests/test_streams.py``'s simulation: a slow UR10 path, a 110 Hz
joint stream, a 3 kHz tracker stream with 0.02 mm of noise, an offset drawn in ±0.3 s,
and a 0.3 mrad joint offset that the nominal model lacks. Each is estimated with and
without the tracker's orientations, the search as wide as the streams allow (at most
1 s). Per duration: estimates, those off by more than one robot sample ("wrong"), those
that warn (``OffsetEstimate.determined`` false), and the wrong ones that do not warn,
which should be none.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hybrid_pk import Robot
from hybrid_pk.data.streams import estimate_time_offset
from tests.test_streams import simulate_streams


def run(durations: list[float], seeds: list[int]) -> list[tuple]:
    """``(duration, estimates, wrong, told, wrong and not told)`` per duration."""
    robot = Robot.from_urdf("ur10")
    robot.requires_grad_(False)
    rows = []
    for duration in durations:
        n = wrong = told = silent = 0
        for seed in seeds:
            offset = float(np.random.default_rng(seed).uniform(-0.3, 0.3))
            t_r, q, t_m, pos, quat, _ = simulate_streams(
                robot, offset, duration=duration, seed=seed
            )
            reach = max(abs(t_m[0] - t_r[-1]), abs(t_m[-1] - t_r[0]))
            for orientation in (None, quat):
                est = estimate_time_offset(
                    t_r, q, t_m, pos, robot, quat=orientation, max_offset=min(1.0, 0.7 * reach)
                )
                off = abs(est.offset - offset) > est.sample_s
                n, wrong, told = n + 1, wrong + off, told + (not est.determined)
                silent += off and est.determined
        rows.append((duration, n, wrong, told, silent))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(100, 110)))
    parser.add_argument(
        "--durations", type=float, nargs="+", default=[0.3, 0.5, 1.0, 2.0, 3.0, 12.0]
    )
    args = parser.parse_args()
    start = time.perf_counter()
    rows = run(args.durations, args.seeds)
    print("| stream | estimates | wrong (> 1 robot sample) | told | wrong and not told |")
    print("|---|---|---|---|---|")
    for duration, n, wrong, told, silent in rows:
        print(f"| {duration:g} s | {n} | {wrong} | {told} | {silent} |")
    print(f"({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
