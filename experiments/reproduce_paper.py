"""Reproduce the paper's virtual experiment (Ojer et al. 2024, 4.1: Table I, Fig. 5)
and run the acceptance experiment of the hybrid model, sized for 2 CPU cores.

    nice -n 10 python experiments/reproduce_paper.py --out reproduce --nominal-mlp   # full run
    python experiments/reproduce_paper.py --quick --out /tmp/reproduce    # smoke test, minutes
    python experiments/reproduce_paper.py --estimate                      # time of the full run

The parts can run as parallel processes and be joined (same seed):

    python experiments/reproduce_paper.py --out a --skip table fig5
    python experiments/reproduce_paper.py --out a2 --skip acceptance table fig5 --nominal-mlp \
        --effects LIST
    python experiments/reproduce_paper.py --out bc --skip acceptance --effects LIST
    python experiments/reproduce_paper.py --merge a a2 bc --out reproduce

Ground truth: a noise-free virtual RX160 with a 20 kg payload whose joint stiffness is
*partly nonlinear*: the paper's linear torsional springs (``joint_compliance`` on
joints 2, 3, 5, at 0.75 x the ``paper`` preset) plus a hardening term — near zero
torque the joint is twice as compliant, as in harmonic drives (stiffness K1 < K2 <
K3): ``theta_true = theta - c tau - c tau0 tanh(tau / tau0)``, ``tau0`` = 0.4 x the
joint's RMS gravity torque. No effect of our vocabulary explains it exactly. The
measurement frame (a tracker) and the tool frame are unknown and fitted.

Experiments (markdown table and JSON in ``--out``):

A. Acceptance: 20,000 training rows (10 % of them held out for validation), 10,000
   random test rows. *Ours*: calibrate (effects diagnosed on 2,000 of the rows —
   ``--effects LIST`` names them instead — and fitted on all) + two MLPs (joints
   preset). *Paper*: nominal model + fitted frames + D4w (position) / Rw
   (orientation) with the paper's settings, epochs capped by a compute budget (the
   paper trained 400,000 rows for up to 300 epochs on a GPU). With ``--nominal-mlp``
   also our networks and schedule on the nominal model + frames (equal training).
B. Table I: every architecture (B1-B4, D1, D4, D4w, D4W, Rw, Rd) on 2,000 training
   rows with the paper's settings, once on the nominal model + frames (paper) and
   once on the calibrated model (ours); each training gets the same compute budget
   (floating-point operations, default 2e11), at most 100 epochs, early stopping.
C. Fig. 5: error vs number of training rows, paper vs ours, with the joints preset.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch
from torch import Tensor

from hybrid_pk import Robot
from hybrid_pk.calibration.diagnosis.search import diagnose
from hybrid_pk.calibration.settings import DiagnosisSettings
from hybrid_pk.data import MeasuredData
from hybrid_pk.effects import Effect, ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.evaluation.metrics import error_stats, pose_error
from hybrid_pk.hybrid import build_net, count_parameters
from hybrid_pk.pipelines import calibrate, refit_frames
from hybrid_pk.pipelines.calibration import cause_labels
from hybrid_pk.simulate import simulate_campaign
from hybrid_pk.simulate.effect_specs import paper_effects
from hybrid_pk.simulate.unmodelled import HardeningCompliance, rms_gravity_torques
from hybrid_pk.training import train_hybrid
from hybrid_pk.training.run import auto_threads

PAYLOAD = 20.0  # [kg]
LINEAR_SHARE = 0.75  # linear springs at this share of the `paper` preset
TAU0_SHARE = 0.4  # tanh knee at this share of the joint's RMS gravity torque
TABLE_ARCHS = ("B1", "B2", "B3", "B4", "D1", "D4", "D4w", "D4W", "Rw", "Rd")
# Ojer et al. 2024, Table I (400,000 training rows): mean position [mm], orientation [deg].
PAPER_TABLE_I = {
    "B1": (0.0485, 0.0648),
    "B2": (0.1796, 0.0876),
    "B3": (0.2703, 0.9496),
    "B4": (0.3367, 1.1860),
    "D1": (0.1502, 0.1015),
    "D4": (0.0357, 0.0565),
    "D4w": (0.0226, 0.0605),
    "D4W": (0.0246, 0.0567),
    "Rw": (0.0661, 0.0368),
    "Rd": (0.1034, 0.0378),
}
TARGET_MM, TARGET_DEG = 0.010, 0.010


@dataclass(frozen=True)
class Plan:
    """Sizes and budgets of one run."""

    n_train: int = 20_000
    n_test: int = 10_000
    n_diagnose: int = 2_000
    ours_arch: str = "mlp"
    ours_epochs: int = 200
    paper_flops: float = 1.0e13  # acceptance, paper method (D4w + Rw)
    table_rows: int = 2_000
    table_flops: float = 2.0e11  # per Table I training
    table_max_epochs: int = 100
    fig5_sizes: tuple[int, ...] = (1_000, 2_000, 5_000, 10_000, 20_000)
    fig5_arch: str = "mlp:128x3"
    fig5_epochs: int = 30


QUICK = Plan(
    n_train=1_500,
    n_test=500,
    n_diagnose=400,
    ours_arch="mlp:64x2",
    ours_epochs=15,
    paper_flops=2e11,
    table_rows=300,
    table_flops=1e10,
    table_max_epochs=3,
    fig5_sizes=(300, 600),
    fig5_arch="mlp:32x2",
    fig5_epochs=5,
)


# ----------------------------------------------------------------------------- ground truth


def ground_truth(robot: Robot) -> list[Effect]:
    """Linear springs of the paper's generator (scaled) + hardening on the same joints."""
    rms = rms_gravity_torques(robot, PAYLOAD, torch.Generator().manual_seed(0))
    effects: list[Effect] = []
    for e in paper_effects(robot):
        c = LINEAR_SHARE * float(e.value.detach())
        effects.append(make_effect(robot, e.label, c))
        tau0 = TAU0_SHARE * float(rms[e.joint_index])
        effects.append(HardeningCompliance(robot, e.joint, c, tau0))
    return effects


# ----------------------------------------------------------------------------- models


def stats(T: Tensor, data: MeasuredData) -> dict:
    """Mean / p95 / max position [mm] and orientation [deg] errors of poses ``T``."""
    err = pose_error(data.T_measured(), T)
    p, o = error_stats(err.position_mm), error_stats(err.orientation_deg)
    return {
        "position_mm": {"mean": p.mean, "p95": p.p95, "max": p.max},
        "orientation_deg": {"mean": o.mean, "p95": o.p95, "max": o.max},
    }


@torch.no_grad()
def evaluate(model, data: MeasuredData) -> dict:
    return stats(model(data.q, conditions_from_data(data)), data)


# The fits' and the diagnosis' settings: hybrid-pk calibrate's defaults (its seed the run's).
SETTINGS = DiagnosisSettings()


def frames_only(robot: Robot, data: MeasuredData) -> ExtendedModel:
    """The paper's mathematical model: the robot as it is, base and tool frames fitted."""
    model = ExtendedModel(robot, gravity=SETTINGS.mounting())
    cond = conditions_from_data(data)
    refit_frames(model, data, cond, priors=SETTINGS.priors(), robust=SETTINGS.loss())
    return model


def diagnosed_effects(robot: Robot, data: MeasuredData, seed: int) -> list[str]:
    """``calibrate --effects auto``'s choice: the causes the diagnosis names."""
    return cause_labels(diagnose(robot, data, **replace(SETTINGS, seed=seed).keywords()))


def calibrated(robot: Robot, data: MeasuredData, labels: list[str]) -> ExtendedModel:
    """Frames + the ``labels`` effects fitted to ``data`` (``calibrate``'s workflow)."""
    return calibrate(robot, data, labels, settings=SETTINGS).model


def epochs_for(archs: tuple[str, str], rows: int, flops: float, cap: int, dof: int) -> int:
    """Epochs that spend ``flops`` (forward + backward ~ 6 x parameters per row)."""
    params = sum(count_parameters(build_net(a, dof)) for a in archs)
    return int(min(cap, max(1, flops // (6 * params * rows))))


def train(base, data, archs, preset, epochs, seed, logdir=None, patience="preset") -> tuple:
    """Train both networks on ``data`` over ``base``; (hybrid, seconds, epochs run)."""
    result = train_hybrid(
        data,
        base,
        preset_name=preset,
        model={"position_net": archs[0], "orientation_net": archs[1]},
        max_epochs=epochs,
        patience=patience,
        seed=seed,
        logdir=logdir,
        progress=False,
    )
    return result.hybrid, result.seconds, result.epochs


# ----------------------------------------------------------------------------- experiments


def log(msg: str) -> None:
    print(msg, flush=True)


def effect_labels(robot, train_rows, plan, seed, effects: str) -> list[str]:
    """The effects to calibrate: diagnosed on the first rows, or the listed ones."""
    if effects == "auto":
        return diagnosed_effects(robot, train_rows.subset(slice(0, plan.n_diagnose)), seed)
    return [lb.strip() for lb in effects.split(",") if lb.strip()]


def merge(dirs: list[str], out: Path) -> int:
    """Join the parts (A, B, C) of runs with the same seed and sizes into one report."""
    parts = [json.loads((Path(d) / "results.json").read_text(encoding="utf-8")) for d in dirs]
    results = dict(parts[0])
    for part in parts[1:]:
        for key in ("seed", "n_train", "n_test", "table_rows", "mode"):
            if part[key] != results[key]:
                raise SystemExit(f"cannot merge: {key} differs ({part[key]} vs {results[key]})")
        for key in ("acceptance", "nominal_mlp", "table_one", "figure_five", "plan", "fig5_arch"):
            if part.get(key):
                results[key] = part[key]
    results["seconds"] = sum(p["seconds"] for p in parts)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n", encoding="utf-8")
    (out / "reproduce_paper.md").write_text(markdown(results), encoding="utf-8")
    if results.get("figure_five"):
        figure(results, out / "figure5.png")
    log(f"wrote {out / 'reproduce_paper.md'}")
    return 0


def acceptance(robot, train_rows, test_rows, plan, seed, out, effects) -> tuple[dict, list[str]]:
    res: dict = {}
    t0 = time.perf_counter()
    nominal = frames_only(robot, train_rows)
    res["nominal_frames"] = evaluate(nominal, test_rows)
    labels = effect_labels(robot, train_rows, plan, seed, effects)
    ext = calibrated(robot, train_rows, labels)
    res["calibrated"] = evaluate(ext, test_rows)
    res["calibrated"]["effects"] = {e.label: e.report_value() for e in ext.effects}
    res["calibration_seconds"] = time.perf_counter() - t0
    log(f"  calibrated in {res['calibration_seconds']:.0f} s: {res['calibrated']['effects']}")

    archs = (plan.ours_arch, plan.ours_arch)
    logs = out / "logs_ours"
    hybrid, sec, ep = train(ext, train_rows, archs, "joints", plan.ours_epochs, seed, logs)
    res["ours"] = {**evaluate(hybrid, test_rows), "seconds": sec, "epochs": ep, "archs": archs}
    log(f"  ours: {_short(res['ours'])} ({ep} epochs, {sec:.0f} s)")

    archs = ("D4w", "Rw")
    epochs = epochs_for(archs, train_rows.n, plan.paper_flops, 300, robot.dof)
    hybrid, sec, ep = train(nominal, train_rows, archs, "paper", epochs, seed, out / "logs_paper")
    res["paper"] = {**evaluate(hybrid, test_rows), "seconds": sec, "epochs": ep, "archs": archs}
    log(f"  paper method: {_short(res['paper'])} ({ep} epochs, {sec:.0f} s)")
    return res, labels


def table_one(robot, rows, labels, test_rows, plan, seed) -> dict:
    nominal, ext = frames_only(robot, rows), calibrated(robot, rows, labels)
    out = {}
    for arch in TABLE_ARCHS:
        epochs = epochs_for((arch, arch), rows.n, plan.table_flops, plan.table_max_epochs, 6)
        row = {"parameters": count_parameters(build_net(arch, robot.dof)), "budget_epochs": epochs}
        for name, base in (("paper", nominal), ("ours", ext)):
            hybrid, sec, ep = train(base, rows, (arch, arch), "paper", epochs, seed)
            row[name] = {**evaluate(hybrid, test_rows), "seconds": sec, "epochs": ep}
        log(f"  {arch:>4}: paper {_short(row['paper'])} | ours {_short(row['ours'])}")
        out[arch] = row
    return out


def figure_five(robot, train_rows, labels, test_rows, plan, seed) -> dict:
    out = {}
    archs = (plan.fig5_arch, plan.fig5_arch)
    for n in plan.fig5_sizes:
        rows = train_rows.subset(slice(0, min(n, train_rows.n)))
        nominal, ext = frames_only(robot, rows), calibrated(robot, rows, labels)
        entry = {}
        for name, base in (("paper", nominal), ("ours", ext)):
            hybrid, sec, ep = train(base, rows, archs, "joints", plan.fig5_epochs, seed)
            entry[name] = {**evaluate(hybrid, test_rows), "seconds": sec, "epochs": ep}
        log(f"  n={n:>6}: paper {_short(entry['paper'])} | ours {_short(entry['ours'])}")
        out[str(n)] = entry
    return out


def _short(r: dict) -> str:
    return f"{r['position_mm']['mean']:.4f} mm / {r['orientation_deg']['mean']:.4f} deg"


# ----------------------------------------------------------------------------- report


def _pm(r: dict) -> str:
    return f"{r['position_mm']['mean']:.4f} / {r['orientation_deg']['mean']:.4f}"


def markdown(results: dict) -> str:
    lines = [
        "# Hybrid kinematics on a virtual RX160 with partly nonlinear joint stiffness",
        "",
        f"{results['setup']} Run: {results['mode']}, {results['seconds'] / 60:.1f} min, "
        f"{results['threads']} thread(s), seed {results['seed']}.",
        "",
    ]
    if results.get("acceptance"):
        lines += _acceptance_lines(results)
    if results.get("table_one"):
        lines += _table_one_lines(results)
    if results.get("figure_five"):
        lines += _figure_five_lines(results)
    return "\n".join(lines) + "\n"


def _acceptance_lines(results: dict) -> list[str]:
    a = results["acceptance"]
    ours = a["ours"]
    ok = ours["position_mm"]["mean"] <= TARGET_MM and ours["orientation_deg"]["mean"] <= TARGET_DEG
    lines = [
        f"## A. Acceptance ({results['n_train']:,} training rows, "
        f"{results['n_test']:,} random test rows)",
        "",
        "Mean (p95) test errors.",
        "",
        "| model | position [mm] | orientation [deg] | training |",
        "|---|---|---|---|",
        f"| dataset error (nominal, true frames) | {results['dataset_error'][0]:.4f} | "
        f"{results['dataset_error'][1]:.4f} | |",
    ]
    rows = [
        ("nominal_frames", "nominal model + fitted frames"),
        ("calibrated", "calibrated extended model (physics)"),
        ("paper", "paper: nominal + frames + D4w / Rw"),
        ("nominal_mlp", "nominal + frames + our MLPs, our training"),
        ("ours", "ours: calibrated + MLPs"),
    ]
    a = {**a, "nominal_mlp": results.get("nominal_mlp")}
    for key, label in rows:
        r = a[key]
        if r is None:
            continue
        train = f"{r['epochs']} epochs, {r['seconds']:.0f} s" if "epochs" in r else ""
        lines.append(
            f"| {label} | {r['position_mm']['mean']:.4f} ({r['position_mm']['p95']:.4f}) | "
            f"{r['orientation_deg']['mean']:.4f} ({r['orientation_deg']['p95']:.4f}) | {train} |"
        )
    lines += [
        "",
        f"Target {TARGET_MM} mm / {TARGET_DEG} deg mean: **{'met' if ok else 'not met'}**. "
        f"Calibrated effects: {a['calibrated']['effects']}.",
        "",
    ]
    return lines


def _table_one_lines(results: dict) -> list[str]:
    lines = [
        f"## B. Table I ({results['table_rows']:,} training rows, paper settings, "
        "equal compute per training"
        + (
            f": {results['plan']['table_flops']:.0e} FLOPs, at most "
            f"{results['plan']['table_max_epochs']} epochs)"
            if "plan" in results
            else ")"
        ),
        "",
        "Mean test errors, position [mm] / orientation [deg].",
        "",
        "| net | parameters | epochs (budget) | paper: nominal + net | ours: physics + net "
        "| paper's Table I (400k rows) |",
        "|---|---:|---:|---|---|---|",
    ]
    for arch, row in results["table_one"].items():
        ref = PAPER_TABLE_I[arch]
        lines.append(
            f"| {arch} | {row['parameters']:,} | {row['paper']['epochs']} / "
            f"{row['ours']['epochs']} ({row['budget_epochs']}) | {_pm(row['paper'])} | "
            f"{_pm(row['ours'])} | {ref[0]} / {ref[1]} |"
        )
    return [*lines, ""]


def _figure_five_lines(results: dict) -> list[str]:
    lines = [
        f"## C. Fig. 5: error vs training rows (joints preset, {results['fig5_arch']})",
        "",
        "| training rows | paper: nominal + net | ours: physics + net |",
        "|---:|---|---|",
    ]
    for n, entry in results["figure_five"].items():
        lines.append(f"| {int(n):,} | {_pm(entry['paper'])} | {_pm(entry['ours'])} |")
    return [*lines, ""]


def figure(results: dict, path: Path) -> None:
    try:
        from hybrid_pk.evaluation.plots import new_figure, save_figure
    except Exception as exc:  # matplotlib is optional
        log(f"no figure: {exc}")
        return
    sizes = [int(n) for n in results["figure_five"]]
    fig = new_figure(10, 4)
    for ax, (key, unit) in zip(
        fig.subplots(1, 2), (("position_mm", "mm"), ("orientation_deg", "deg")), strict=True
    ):
        for name, color in (("paper", "#d95f02"), ("ours", "#1b9e77")):
            ys = [results["figure_five"][str(n)][name][key]["mean"] for n in sizes]
            ax.plot(sizes, ys, "o-", color=color, label=name)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("training rows")
        ax.set_ylabel(f"mean test error [{unit}]")
        ax.legend()
    save_figure(fig, path)


# ----------------------------------------------------------------------------- timing


def estimate(plan: Plan, threads: int) -> float:
    """Seconds the full run would take, from timed training steps of every network pair
    (upper bound: early stopping shortens the Table I runs). Meaningful on an idle
    machine only: other processes on the same cores inflate every step."""

    def step_seconds(archs, batch):
        nets = [build_net(a, 6) for a in archs]
        torch.set_num_threads(1 if auto_threads(list(archs)) else threads)
        opt = torch.optim.Adagrad([p for n in nets for p in n.parameters()], lr=1e-3)
        x = torch.rand(batch, 6)
        times = []
        for _ in range(7):
            t0 = time.perf_counter()
            opt.zero_grad()
            sum(n(x).square().mean() for n in nets).backward()
            opt.step()
            times.append(time.perf_counter() - t0)
        return sorted(times[2:])[2] + 3e-3  # median after warm-up + Lightning's overhead

    n_fit = int(0.9 * plan.n_train)
    parts = {"simulation + diagnosis + calibrations (measured)": 300.0}
    steps = plan.ours_epochs * math.ceil(n_fit / 256)
    parts["A ours"] = steps * step_seconds((plan.ours_arch,) * 2, 256)
    ep = epochs_for(("D4w", "Rw"), plan.n_train, plan.paper_flops, 300, 6)
    parts["A paper"] = ep * math.ceil(0.8 * plan.n_train / 128) * step_seconds(("D4w", "Rw"), 128)
    parts["B Table I"] = 0.0
    for arch in TABLE_ARCHS:
        ep = epochs_for((arch, arch), plan.table_rows, plan.table_flops, plan.table_max_epochs, 6)
        steps = ep * math.ceil(0.8 * plan.table_rows / 128)
        parts["B Table I"] += 2 * steps * step_seconds((arch, arch), 128)
    steps = sum(plan.fig5_epochs * math.ceil(0.9 * n / 256) for n in plan.fig5_sizes)
    parts["C Fig. 5"] = 2 * steps * step_seconds((plan.fig5_arch,) * 2, 256)
    for name, sec in parts.items():
        log(f"  {name}: {sec / 60:.1f} min")
    return sum(parts.values())


# ----------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="reproduce", help="output folder (default: reproduce)")
    parser.add_argument("--quick", action="store_true", help="tiny sizes: a smoke test")
    parser.add_argument("--estimate", action="store_true", help="only predict the run time")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--effects",
        default="auto",
        help="effects to calibrate: auto (diagnosed, default) or a comma-separated list",
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=2,
        help="torch threads for networks of 1M+ parameters (default: 2; smaller ones use 1)",
    )
    parser.add_argument(
        "--skip",
        nargs="*",
        default=(),
        choices=("acceptance", "table", "fig5"),
        help="leave out A, B or C (parts can run in parallel processes; --merge joins them)",
    )
    parser.add_argument(
        "--nominal-mlp",
        action="store_true",
        help="also train our networks and schedule (A) on the nominal model + frames: "
        "the physics' share at equal training",
    )
    parser.add_argument(
        "--table-flops", type=float, help="compute budget per Table I training (default 2e11)"
    )
    parser.add_argument(
        "--table-max-epochs", type=int, help="epoch cap of Table I trainings (default 100)"
    )
    parser.add_argument(
        "--fig5-sizes", type=int, nargs="+", help="training rows of Fig. 5 (default 1k-20k)"
    )
    parser.add_argument("--fig5-epochs", type=int, help="epochs per Fig. 5 training (default 30)")
    parser.add_argument(
        "--merge",
        nargs="+",
        metavar="DIR",
        help="only join the results.json of earlier runs (same seed) into --out",
    )
    args = parser.parse_args(argv)
    plan = QUICK if args.quick else Plan()
    overrides = {
        "table_flops": args.table_flops,
        "table_max_epochs": args.table_max_epochs,
        "fig5_sizes": None if args.fig5_sizes is None else tuple(args.fig5_sizes),
        "fig5_epochs": args.fig5_epochs,
    }
    plan = replace(plan, **{k: v for k, v in overrides.items() if v is not None})
    if args.merge:
        return merge(args.merge, Path(args.out))
    if args.estimate:
        seconds = estimate(plan, args.threads)
        log(f"estimated run time: {seconds / 60:.0f} min on {args.threads} thread(s)")
        return 0
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    robot = Robot.from_urdf("rx160")
    robot.requires_grad_(False)
    truth = ground_truth(robot)
    n = plan.n_train + plan.n_test
    data, info = simulate_campaign(robot, n, truth, noise_mm=0.0, payload=PAYLOAD, seed=args.seed)
    train_rows, test_rows = data.subset(slice(0, plan.n_train)), data.subset(slice(plan.n_train, n))
    dataset = info["dataset_error"]
    log(
        f"campaign: {n} rows, dataset error {dataset['position_mm']['mean']:.3f} mm / "
        f"{dataset['orientation_deg']['mean']:.3f} deg"
    )
    results: dict = {
        "mode": "quick" if args.quick else "full",
        "seed": args.seed,
        "threads": args.threads,
        "n_train": plan.n_train,
        "n_test": plan.n_test,
        "table_rows": plan.table_rows,
        "fig5_arch": plan.fig5_arch,
        "plan": asdict(plan),
        "dataset_error": (dataset["position_mm"]["mean"], dataset["orientation_deg"]["mean"]),
        "setup": (
            f"RX160, {PAYLOAD:g} kg payload, noise-free, unknown tracker and tool frames; joint "
            f"springs of joints 2, 3, 5 at {LINEAR_SHARE} x the paper preset plus hardening "
            f"(twice as compliant near zero torque, knee at {TAU0_SHARE} x RMS torque)."
        ),
    }
    if "acceptance" in args.skip:
        labels = effect_labels(robot, train_rows, plan, args.seed, args.effects)
    else:
        log("A. acceptance")
        results["acceptance"], labels = acceptance(
            robot, train_rows, test_rows, plan, args.seed, out, args.effects
        )
    if args.nominal_mlp:
        log("A'. our networks on the nominal model + frames")
        archs = (plan.ours_arch, plan.ours_arch)
        nominal = frames_only(robot, train_rows)
        hybrid, sec, ep = train(nominal, train_rows, archs, "joints", plan.ours_epochs, args.seed)
        results["nominal_mlp"] = {
            **evaluate(hybrid, test_rows),
            "seconds": sec,
            "epochs": ep,
            "archs": archs,
        }
        log(f"  nominal + MLPs: {_short(results['nominal_mlp'])} ({ep} epochs, {sec:.0f} s)")
    # B and C fit the effects named in A to their own (fewer) rows, frames included.
    results["table_one"] = {}
    if "table" not in args.skip:
        log("B. Table I")
        rows = train_rows.subset(slice(0, plan.table_rows))
        results["table_one"] = table_one(robot, rows, labels, test_rows, plan, args.seed)
    results["figure_five"] = {}
    if "fig5" not in args.skip:
        log("C. Fig. 5")
        results["figure_five"] = figure_five(robot, train_rows, labels, test_rows, plan, args.seed)
        figure(results, out / "figure5.png")
    results["seconds"] = time.perf_counter() - start
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n", encoding="utf-8")
    (out / "reproduce_paper.md").write_text(markdown(results), encoding="utf-8")
    log(f"wrote {out / 'reproduce_paper.md'} in {results['seconds'] / 60:.1f} min")
    return 0


if __name__ == "__main__":
    sys.exit(main())
