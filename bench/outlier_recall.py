"""Gross errors listed by the diagnosis (issue 28): recall and false listings.

RX160, two hidden effects (``random:2``), 20 kg payload, noise 0.05 mm / 0.005 deg;
2 % of the rows displaced by 2-10 mm in random directions. For each seed the diagnosis
(least squares, or ``--robust cauchy``) runs once; its ``outliers`` are scored, and so
is the rule before issue 28 (the fit's own noise levels, 4-sigma tail) on the same
model. Prints one JSON line per seed::

    python bench/outlier_recall.py --n 3000 --seeds 1,2,3,4,5
    python bench/outlier_recall.py --n 3000 --seeds 1,2,3,4,5 --robust cauchy
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from hybrid_pk.calibration.diagnosis import diagnose
from hybrid_pk.calibration.fit import model_errors
from hybrid_pk.calibration.robust import outlier_threshold
from hybrid_pk.effects import conditions_from_data
from hybrid_pk.robot import Robot
from hybrid_pk.simulate import displace_rows, simulate_campaign


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=3000)
    p.add_argument("--seeds", default="1,2,3,4,5")
    p.add_argument("--robust", default=None)
    args = p.parse_args()
    robot = Robot.from_urdf("rx160")
    robot.requires_grad_(False)
    for seed in (int(s) for s in args.seeds.split(",")):
        t = time.perf_counter()
        data, truth = simulate_campaign(
            robot, args.n, "random:2", noise_mm=0.05, noise_deg=0.005, seed=seed, payload=20.0
        )
        dirty, bad = displace_rows(data, 0.02, torch.Generator().manual_seed(seed + 1))
        diag = diagnose(robot, dirty, robust=args.robust)
        truly = {int(data.rows[i]) for i in bad}
        listed = {o["row"] for o in diag.outliers}
        pos, ori = model_errors(diag.model, dirty, conditions_from_data(dirty))
        noise = diag.identifiability["noise_estimate"]
        d2 = (pos / noise["position_mm"]) ** 2
        d2 = d2 + (torch.deg2rad(ori) / noise["orientation_rad"]) ** 2
        old = {int(dirty.rows[i]) for i in torch.nonzero(d2 > outlier_threshold(6)).reshape(-1)}
        out = {
            "seed": seed,
            "robust": args.robust,
            "recall": len(listed & truly) / len(truly),
            "false": len(listed - truly),
            "recall_before": len(old & truly) / len(truly),
            "false_before": len(old - truly),
            "causes": [f"{c.effect}:{c.joint}" for c in diag.causes],
            "truth": [f"{e['effect']}:{e.get('joint')}" for e in truth["effects"]],
            "seconds": round(time.perf_counter() - t),
        }
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
