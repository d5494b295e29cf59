"""The shape of the paper's Table IV on a *trained* hybrid RX160 model.

1. Simulate a campaign with physics the base model lacks (default: the paper's joint
   compliance under gravity with a 20 kg payload, plus a sinusoidal eccentricity of
   joints 2 and 3), fit the base/tool frames of the nominal robot (the base model),
   and train a HybridFK on top of it with ``train_hybrid`` (Lightning).
2. Targets: the trained hybrid's own FK at random joint values within the limits
   (every target is reachable; the hybrid FK is the reference, as in the paper's 5.1).
3. For each method, every returned solution's position [mm] and orientation [deg]
   error w.r.t. the hybrid FK (recomputed here), mean / std / max, the share of
   targets with a solution within ``--tol-mm`` / ``--tol-deg`` and the time per target
   (median of ``--rounds``, methods interleaved):

   (a) IK on the cheap model only (nominal kinematics + fitted frames),
   (b) Wang et al.'s one-shot target correction (the paper's comparison),
   (c) our two-stage solver (branches on the cheap model, refinement on the hybrid).

    python bench/ik_hybrid.py                                # ~3 min on 2 busy cores
    python bench/ik_hybrid.py --rows 2000 --epochs 40 --targets 100
    python bench/ik_hybrid.py --preset paper --epochs 300    # the paper's D4w / Rw
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.fit import fit, initialise_frames
from hybrid_pk.effects import ExtendedModel, conditions_from_data
from hybrid_pk.evaluation.metrics import pose_error
from hybrid_pk.ik import IKOptions, solve_ik, solve_ik_two_stage, wang_baseline
from hybrid_pk.simulate import simulate_campaign
from hybrid_pk.training import train_hybrid

EFFECTS = "paper; joint_eccentricity:joint_2=8e-4,-6e-4; joint_eccentricity:joint_3=-6e-4,4e-4"
# Ojer et al. 2024, Table IV (virtual RX160 data): mean / std [mm], mean / std [deg].
PAPER_TABLE_IV = {
    "Wang et al.": (4.52, 0.078, 0.397, 1.13),
    "two-stage": (6.02e-6, 1.25e-4, 4.85e-4, 0.011),
}


def _train(args) -> tuple[ExtendedModel, object, dict]:
    robot = hpk.Robot.from_urdf("rx160")
    robot.requires_grad_(False)
    t0 = time.perf_counter()
    data, _ = simulate_campaign(
        robot,
        args.rows,
        args.effects,
        noise_mm=args.noise_mm,
        noise_deg=args.noise_deg,
        payload=args.payload,
        temperature_range=None,
        seed=args.seed,
    )
    cond = conditions_from_data(data)
    base = ExtendedModel(robot)  # nominal kinematics + fitted frames: the cheap model
    initialise_frames(base, data, cond)
    fit(base, data, cond=cond, covariance=False)
    base.requires_grad_(False)
    model = {"lr": args.lr} if args.lr else {}
    if args.position_net:
        model["position_net"] = args.position_net
    if args.orientation_net:
        model["orientation_net"] = args.orientation_net
    data_args = {"batch_size": args.batch_size} if args.batch_size else {}
    result = train_hybrid(
        data,
        base,
        cond,
        preset_name=args.preset,
        model=model,
        datamodule=data_args,
        max_epochs=args.epochs,
        seed=args.seed,
        progress=args.progress,
        threads=args.threads,
    )
    hybrid = result.hybrid
    hybrid.requires_grad_(False)
    info = {
        "seconds": time.perf_counter() - t0,
        "fit_seconds": result.seconds,
        "epochs": result.epochs,
        "base": result.base,
        "best": result.best,
        "nets": (
            result.settings["model"]["position_net"],
            result.settings["model"]["orientation_net"],
        ),
    }
    return base, hybrid, info


def _stats(x: torch.Tensor) -> tuple[float, float, float]:
    if x.numel() == 0:
        return math.nan, math.nan, math.nan
    std = float(x.std()) if x.numel() > 1 else 0.0
    return float(x.mean()), std, float(x.max())


def _evaluate(robot, hybrid, result, T, args) -> dict:
    """Errors of every valid solution w.r.t. the hybrid FK, recomputed here."""
    valid = result.valid
    q = result.q[valid]
    with torch.no_grad():
        err = pose_error(T[:, None].expand(*valid.shape, 4, 4)[valid], hybrid(q))
    lo, hi = robot.joint_limits
    ok = (err.position_mm <= args.tol_mm) & (err.orientation_deg <= args.tol_deg)
    ok &= ((q >= lo) & (q <= hi)).all(-1)
    within = torch.zeros_like(valid)
    within[valid] = ok
    return {
        "pos": _stats(err.position_mm),
        "ori": _stats(err.orientation_deg),
        "solved": float(within.any(-1).double().mean()),
        "within": float(ok.double().mean()) if ok.numel() else math.nan,
        "returned": float(valid.any(-1).double().mean()),
        "per_target": float(valid.sum(-1).double().mean()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--targets", type=int, default=200, help="IK targets N")
    ap.add_argument("--seeds", type=int, default=64, help="first-stage seeds per target")
    ap.add_argument("--rounds", type=int, default=3, help="timing rounds (median)")
    ap.add_argument("--tol-mm", type=float, default=1e-3)
    ap.add_argument("--tol-deg", type=float, default=1e-3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--rows", type=int, default=10000, help="simulated training rows")
    ap.add_argument("--effects", default=EFFECTS, help="hidden effects (simulate --effects)")
    ap.add_argument("--payload", type=float, default=20.0, help="[kg]")
    ap.add_argument("--noise-mm", type=float, default=0.01)
    ap.add_argument("--noise-deg", type=float, default=1e-3)
    ap.add_argument("--preset", default="fast", choices=["fast", "paper"])
    ap.add_argument("--position-net", default="mlp:128x3", help="'' for the preset's")
    ap.add_argument("--orientation-net", default="mlp:128x3", help="'' for the preset's")
    ap.add_argument("--epochs", type=int, default=100)
    ap.add_argument("--batch-size", type=int, default=128)
    ap.add_argument("--lr", type=float, default=0.005, help="0 for the preset's")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--progress", action="store_true", help="Lightning's progress bar")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    base, hybrid, info = _train(args)
    robot = base.robot
    print(
        f"hybrid RX160: {args.rows} simulated rows ({args.effects}; payload {args.payload} kg, "
        f"noise {args.noise_mm} mm / {args.noise_deg} deg), nets {info['nets'][0]} / "
        f"{info['nets'][1]}, {info['epochs']} epochs, trained in {info['fit_seconds']:.0f} s "
        f"({info['seconds']:.0f} s with simulation and frame fit)"
    )
    b, h = info["base"], info["best"]
    print(
        f"validation mean error vs the simulated measurements: base model "
        f"{b['position_mm']:.3f} mm / {b['orientation_deg']:.4f} deg -> hybrid "
        f"{h['position_mm']:.3f} mm / {h['orientation_deg']:.4f} deg"
    )

    q = robot.sample_q(args.targets, torch.Generator().manual_seed(2024))
    with torch.no_grad():
        T = hybrid(q)
    options = IKOptions(tol_mm=args.tol_mm, tol_deg=args.tol_deg)
    methods = {
        "cheap model only": lambda: solve_ik(base, T, seeds=args.seeds, options=options),
        "Wang et al.": lambda: wang_baseline(
            base, hybrid, T, seeds=args.seeds, robot=robot, options=options
        ),
        "two-stage (ours)": lambda: solve_ik_two_stage(
            base, hybrid, T, seeds=args.seeds, robot=robot, options=options
        ),
    }
    times: dict[str, list[float]] = {k: [] for k in methods}
    results = {}
    for _ in range(args.rounds):
        for label, fn in methods.items():
            t0 = time.perf_counter()
            results[label] = fn()
            times[label].append(time.perf_counter() - t0)
    rows = {k: _evaluate(robot, hybrid, r, T, args) for k, r in results.items()}
    ms = {k: 1e3 * statistics.median(v) / args.targets for k, v in times.items()}
    fallback = results["two-stage (ours)"].info.get("fallback_targets", 0)

    print(
        f"\n{args.targets} targets (hybrid FK at random q), {args.seeds} seeds, tolerance "
        f"{args.tol_mm} mm / {args.tol_deg} deg, {args.threads} thread(s); errors w.r.t. the "
        "hybrid FK over every returned solution\n"
    )
    print(
        "| method | pos mean [mm] | pos std [mm] | pos max [mm] | ori mean [deg] "
        "| ori std [deg] | ori max [deg] | solved | sol./target | sol. within tol | ms/target |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for label, r in rows.items():
        p, o = r["pos"], r["ori"]
        print(
            f"| {label} | {p[0]:.3g} | {p[1]:.3g} | {p[2]:.3g} | {o[0]:.3g} | {o[1]:.3g} "
            f"| {o[2]:.3g} | {100 * r['solved']:.1f} % | {r['per_target']:.2f} "
            f"| {100 * r['within']:.1f} % | {ms[label]:.1f} |"
        )
    ours, wang, cheap = rows["two-stage (ours)"], rows["Wang et al."], rows["cheap model only"]
    print(
        f"\nsolved: targets with a solution within tolerance and the joint limits; sol. within "
        f"tol: share of the returned solutions; two-stage fell back to direct IK on the hybrid "
        f"for {fallback} target(s)"
    )
    print(
        f"ratio Wang / two-stage: position mean {wang['pos'][0] / ours['pos'][0]:.3g}x, "
        f"orientation mean {wang['ori'][0] / ours['ori'][0]:.3g}x"
    )
    print(
        f"ratio cheap-only / two-stage: position mean {cheap['pos'][0] / ours['pos'][0]:.3g}x, "
        f"orientation mean {cheap['ori'][0] / ours['ori'][0]:.3g}x"
    )
    print(
        f"time two-stage / Wang: {ms['two-stage (ours)'] / ms['Wang et al.']:.2f}x, "
        f"two-stage / cheap-only: {ms['two-stage (ours)'] / ms['cheap model only']:.2f}x"
    )
    print("\npaper, Table IV (virtual data): pos mean / std [mm], ori mean / std [deg]")
    for label, (pm, ps, om, os_) in PAPER_TABLE_IV.items():
        print(f"  {label:<12} {pm:9.3g} {ps:9.3g} {om:9.3g} {os_:9.3g}")


if __name__ == "__main__":
    main()
