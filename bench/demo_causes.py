"""The demo's diagnosis over seeds, without the training: what it names against what
was injected, each value's error and what it names that was not injected.

    python bench/demo_causes.py                  # seeds 1-10, the demo's defaults
    python bench/demo_causes.py --seeds 7 8 --json out.json

Each seed builds the campaign ``hybrid-pk demo --seed N`` builds (the same hidden
effects, unmodelled spring, rows and noise) and diagnoses its calibration rows (the
first three quarters) with the demo's settings. Acceptance (issue 27): no cause that
was not injected is named as a finding (a stand-in for the unmodelled spring on the
spring's own joint is reported as such, as the demo's report does), and every injected
vocabulary effect is named within 5 % (on the part the data determine; see
``bench/demo.py``). The set-up never moves in these campaigns, so no set-up move may be
named either (``setup_moves``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from demo import named_within

from hybrid_pk.calibration.diagnosis import diagnose
from hybrid_pk.calibration.settings import DiagnosisSettings
from hybrid_pk.pipelines.demo import DEFAULT_ROBOT, hidden_effects
from hybrid_pk.pipelines.demo_report import found_table
from hybrid_pk.robot import Robot
from hybrid_pk.simulate import simulate_campaign
from hybrid_pk.simulate.effect_specs import effect_entry


def one_seed(seed: int, n: int = 3000) -> dict:
    """Diagnose the demo campaign of ``seed`` (the demo's defaults otherwise)."""
    robot = Robot.from_urdf(DEFAULT_ROBOT)
    robot.requires_grad_(False)
    vocabulary, unmodelled = hidden_effects(robot, "random:3", seed=seed, payload=20.0)
    sim = {"noise_mm": 0.02, "noise_deg": 0.002, "payload": 20.0, "seed": seed}
    data, truth = simulate_campaign(robot, n, vocabulary + unmodelled, **sim)
    truth["effects"] = [effect_entry(e) for e in vocabulary]
    truth["unmodelled"] = [{**effect_entry(e), "tau0_Nm": e.tau0} for e in unmodelled]
    calib = data.subset(torch.arange(0, data.n - data.n // 4))
    start = time.perf_counter()
    diag = diagnose(robot, calib, **DiagnosisSettings(seed=seed).keywords())  # the demo's
    seconds = time.perf_counter() - start
    rows = found_table(truth, diag)
    false = [r[0] for r in rows if r[-1] == "false positive"]  # the "named" column
    stand_ins = [r[0] for r in rows if str(r[-1]).startswith("stands in")]
    js = diag.to_json()
    return {
        "seed": seed,
        "seconds": seconds,
        "injected": named_within(truth, js, robot),
        "false_positives": false,
        "stand_ins": stand_ins,
        "causes": [
            {
                "label": f"{c['effect']}:{c.get('joint')}",
                "blocked_gain_mm": c.get("blocked_holdout_gain_mm"),
                "random_gain_mm": c.get("random_holdout_gain_mm"),
            }
            for c in js["causes"]
        ],
        "margin_mm": js["carry_over"]["min_gain_mm"],
        "ambiguous": [a["effects"] for a in js["ambiguous"]],
        "setup_moves": js["setup_moves"],
    }


def _pct(x: float | None) -> str:
    return "not named" if x is None else f"{x:.1%}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(1, 11)))
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args(argv)
    results, ok = [], True
    for seed in args.seeds:
        r = one_seed(seed)
        results.append(r)
        named = all(x["ok"] for x in r["injected"])
        ok = ok and named and not r["false_positives"] and not r["setup_moves"]
        moves = [f"{m['kind']} ({m['shift_mm']['mean']:.3g} mm)" for m in r["setup_moves"]]
        within = ", ".join(f"{x['effect']} {_pct(x['relative_error'])}" for x in r["injected"])
        print(
            f"seed {seed:2d} ({r['seconds']:.0f} s, margin {r['margin_mm']:.4f} mm): "
            f"injected {within}; false positives {r['false_positives'] or 'none'}; "
            f"stand-ins {r['stand_ins'] or 'none'}; set-up moves {moves or 'none'}",
            flush=True,
        )
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
