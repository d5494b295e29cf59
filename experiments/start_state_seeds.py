"""Does keeping the start (the base model) as a candidate best state change what a
trained hybrid does on held-out rows? Over several seeds, two simulated RX160 cases:
``exact`` (the base model is the true physics: the networks can only learn noise) and
``missing`` (the base model lacks one injected effect: the networks have something to
learn). Each seed trains the default preset twice, with the start kept as a candidate
(the rule of ``HybridLitModule.keep_start``) and without it (the rule before), and
measures the mean position error of base and hybrid on the validation rows and on
independent test rows of the same campaign, and prints the blocked hold-out's decision
for each gated stage (its probe fits follow the same rule).

    OMP_NUM_THREADS=1 python experiments/start_state_seeds.py --seeds 0 1 2 3 4 5
"""

from __future__ import annotations

import argparse
import statistics

import torch

from hybrid_pk.effects import ExtendedModel, conditions_from_data
from hybrid_pk.evaluation.metrics import pose_error
from hybrid_pk.robot import Robot
from hybrid_pk.simulate import parse_effects, simulate_campaign
from hybrid_pk.training import HybridLitModule, quiet_lightning, train_hybrid

TRUE = "joint_offset:joint_2=5e-4; joint_compliance:joint_3=5e-5; gear_ratio:joint_3=3e-4"
BASES = {"exact": TRUE, "missing": "joint_offset:joint_2=5e-4; joint_compliance:joint_3=5e-5"}


def _test_mm(hybrid, test) -> tuple[float, float]:
    cond = conditions_from_data(test)
    with torch.no_grad():
        base = pose_error(test.T_measured(), hybrid.base(test.q, cond))
        hyb = pose_error(test.T_measured(), hybrid(test.q, cond))
    return float(base.position_mm.mean()), float(hyb.position_mm.mean())


def run(case: str, seed: int, n: int, epochs: int, keep: bool) -> dict:
    robot = Robot.from_urdf("rx160")
    data, _ = simulate_campaign(robot, 2 * n, TRUE, noise_mm=0.02, known_frames=True, seed=seed)
    train, test = data.subset(slice(0, n)), data.subset(slice(n, 2 * n))
    base = ExtendedModel(robot).with_effects(parse_effects(robot, BASES[case]))
    original = HybridLitModule.keep_start
    if not keep:
        HybridLitModule.keep_start = lambda self: None
    try:
        result = train_hybrid(train, base, max_epochs=epochs, seed=seed, progress=False)
    finally:
        HybridLitModule.keep_start = original
    test_base, test_hybrid = _test_mm(result.hybrid, test)
    return {
        "val_base": result.base["position_mm"],
        "val_hybrid": result.best["position_mm"],
        "test_base": test_base,
        "test_hybrid": test_hybrid,
        "modes": " ".join(r["mode"] for r in result.blocked.values()),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5])
    p.add_argument("--n", type=int, default=600, help="training rows (as many test rows)")
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--cases", nargs="+", default=list(BASES), choices=list(BASES))
    args = p.parse_args(argv)
    quiet_lightning()
    print("case     seed rule   val base -> hybrid [mm]   test base -> hybrid [mm]   blocked")
    for case in args.cases:
        ratios: dict[str, list[float]] = {"before": [], "start kept": []}
        for seed in args.seeds:
            for rule, keep in (("before", False), ("start kept", True)):
                r = run(case, seed, args.n, args.epochs, keep)
                ratios[rule].append(r["test_hybrid"] / r["test_base"])
                print(
                    f"{case:<8} {seed:>4} {rule:<10} {r['val_base']:.5f} -> {r['val_hybrid']:.5f}"
                    f"      {r['test_base']:.5f} -> {r['test_hybrid']:.5f}   {r['modes']}",
                    flush=True,
                )
        for rule, values in ratios.items():
            worse = sum(v > 1 for v in values)
            print(
                f"{case} {rule}: test hybrid / base mean {statistics.mean(values):.5f}, "
                f"max {max(values):.5f}, worse than the base on {worse} of {len(values)} seeds"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
