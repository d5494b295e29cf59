"""Wall time of ``diagnose`` on a simulated campaign (target: < 60 s for 4,000 rows on
2 cores), with what it found, so a fast-but-wrong run cannot pass for a fast one.

    python bench/diagnose.py                       # RX160, 4,000 rows, 2 hidden effects
    python bench/diagnose.py --robot ur10 --n 4000 --effects random:3 --repeat 3
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.diagnosis import diagnose
from hybrid_pk.simulate import simulate_campaign


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--robot", default="rx160")
    ap.add_argument("--n", type=int, default=4000, help="rows")
    ap.add_argument(
        "--effects", default="joint_compliance:joint_2=1.5e-6; joint_offset:joint_3=4e-4"
    )
    ap.add_argument("--noise-mm", type=float, default=0.02)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    robot = hpk.Robot.from_urdf(args.robot)
    robot.requires_grad_(False)
    data, truth = simulate_campaign(
        robot,
        args.n,
        args.effects,
        noise_mm=args.noise_mm,
        noise_deg=args.noise_mm / 10,
        payload=20.0,
        seed=1,
    )
    times = []
    for _ in range(args.repeat):
        start = time.perf_counter()
        diag = diagnose(robot, data)
        times.append(time.perf_counter() - start)
    print(
        f"diagnose {robot.name}, {data.n} rows, {torch.get_num_threads()} torch threads: "
        f"median {statistics.median(times):.1f} s over {len(times)} run(s) "
        f"(target < 60 s)"
    )
    print("injected:", [(e["effect"], e.get("joint"), e["value"]) for e in truth["effects"]])
    print("found:   ", [(c.effect, c.joint, c.value) for c in diag.causes])
    print(
        f"hold-out mean position error: nominal {diag.nominal['position_mm']['mean']:.4f} mm"
        f" -> extended {diag.extended['position_mm']['mean']:.4f} mm"
    )


if __name__ == "__main__":
    main()
