"""What a second thread buys each kind of work: a fit, a diagnosis and batched FK, each
timed on 1 and on 2 torch threads in the same process, alternating (machines here are
noisy: compare the ratio of one run, not times across runs).

The thread policy (hybrid_pk.threads) gives the fits and the diagnosis
``FIT_THREADS`` threads and batched kinematics every usable core; this bench is the
measurement that rule stands on. Simulated UR10 campaigns (three effects, 5 kg payload)
of ``--rows`` sizes:

    fit        calibrate's fit of frames and the three effects
    diagnose   the diagnosis (``--diagnose-rows``; slow: minutes per size)
    fk         the extended model's forward kinematics of every row, float64

    python bench/threads.py                          # ~3 min on a quiet 2-core machine
    python bench/threads.py --rows 13406,50000 --repeats 3
"""

from __future__ import annotations

import argparse
import os
import time

# waiting threads sleep, as in every hybrid-pk command (set before torch loads OpenMP)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch

import hybrid_pk as hpk
from hybrid_pk.calibration import diagnose
from hybrid_pk.calibration.fit import fit, initialise_frames
from hybrid_pk.effects import ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.simulate import simulate_campaign

EFFECTS = (
    "joint_compliance:shoulder_lift_joint=8e-6; joint_offset:elbow_joint=5e-4; "
    "link_length:wrist_1_joint=0,0,4e-4"
)
LABELS = [
    "joint_compliance:shoulder_lift_joint",
    "joint_offset:elbow_joint",
    "link_length:wrist_1_joint",
]


def _campaign(robot, rows: int):
    data, _ = simulate_campaign(
        robot, rows, EFFECTS, noise_mm=0.02, noise_deg=0.002, payload=5.0, seed=2
    )
    return data


def _fit(robot, data) -> None:
    cond = conditions_from_data(data)
    model = ExtendedModel(robot, [make_effect(robot, lbl) for lbl in LABELS])
    initialise_frames(model, data, cond)
    fit(model, data, cond=cond)


def _fk(robot, data) -> None:
    model = ExtendedModel(robot, [make_effect(robot, lbl) for lbl in LABELS])
    with torch.no_grad():
        model(data.q, conditions_from_data(data))


def _diagnose(robot, data) -> None:
    diagnose(robot, data)


def _timed(work, robot, data, threads: int) -> float:
    """Seconds of ``work`` on ``threads`` torch threads (``--threads N`` as a user fixes
    it: the policy's own choice is bypassed)."""
    os.environ[hpk.threads.ENV] = str(threads)
    torch.set_num_threads(threads)
    start = time.perf_counter()
    work(robot, data)
    return time.perf_counter() - start


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rows", default="13406,50000", help="campaign sizes (fit and fk)")
    p.add_argument("--diagnose-rows", default="", help="sizes for the diagnosis (slow)")
    p.add_argument("--repeats", type=int, default=2, help="alternations per size")
    args = p.parse_args(argv)
    robot = hpk.Robot.from_urdf("ur10")
    robot.requires_grad_(False)
    jobs = [("fit", _fit, r) for r in args.rows.split(",") if r]
    jobs += [("fk", _fk, r) for r in args.rows.split(",") if r]
    jobs += [("diagnose", _diagnose, r) for r in args.diagnose_rows.split(",") if r]
    print(f"load {os.getloadavg()[0]:.1f}; usable cores {hpk.threads.usable_cores()}")
    for name, work, rows in jobs:
        data = _campaign(robot, int(rows))
        work(robot, data)  # warm-up: first-call costs out of the timings
        times = {1: [], 2: []}
        for _ in range(args.repeats):
            for n in (1, 2):
                times[n].append(_timed(work, robot, data, n))
        one, two = min(times[1]), min(times[2])
        print(
            f"{name:<9} {int(rows):>7} rows: 1 thread {one:7.2f} s, 2 threads {two:7.2f} s, "
            f"speed-up {one / two:.2f}x (best of {args.repeats}; load {os.getloadavg()[0]:.1f})"
        )


if __name__ == "__main__":
    main()
