"""Issue 15's acceptance on a virtual RX160: planned vs random poses, then compensation.

The robot hides two effects drawn by the simulator's own generator (``random:2`` at
``--effects-seed``, 0.2-1 mm each), independent of the planner. Every model is made by
the public command line (``hybrid-pk simulate / diagnose / plan / calibrate /
compensate``, called in-process; each command is printed before it runs):

0. a pilot campaign of ``--n`` random poses and ``diagnose --json``: the causes the
   planner plans for and every calibration fits (``--effects DIAG.json``);
1. per seed K (``--seeds``): ``--n`` random poses (``simulate --trajectory random``) and
   ``--n`` planned poses (``plan --effects DIAG.json --seed K``, then ``simulate
   --poses``), same hidden effects, same tracker, tool and noise stream (``simulate
   --seed 1000+K``), noise ``--noise-mm`` / ``--noise-deg``; ``calibrate --effects
   DIAG.json`` on each;
2. test error: the calibrated model against the noise-free true robot on ``--test``
   random joint configurations (their own generator), mean position error [mm];
3. predicted std (``plan --json``) against the spread of the estimates around the
   truth over the seeds: per effect parameter, and pooled as ``sqrt(mean z^2)`` with
   ``z = (estimate - truth) / predicted std`` (1 when the prediction is right); three
   seeds say little, so the first seed's planned poses are also measured ``--spread``
   more times (other noise, tracker and tool; in-process fits with the same effects);
4. ``compensate`` a program of ``--program`` random joint targets with the planned
   model of each seed; the true robot at the corrected joints against the intended
   pose (the nominal flange pose in the calibrated base frame, at the calibrated tool
   point; and, for reference, in the true frames), against the uncompensated program.

Writes ``OUT/results.json`` and ``OUT/results.md``. Run from the repository root::

    python experiments/plan_compensate.py --out /tmp/plan_compensate          # ~1 min
    python experiments/plan_compensate.py --out /tmp/pc --seeds 1 --candidates 300 --test 200

``--position-only`` measures points only (a tracker with a plain reflector): every
campaign, the plan and the repeats.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import time
from pathlib import Path

import torch

from hybrid_pk import Robot
from hybrid_pk.calibration.fit import fit, initialise_frames
from hybrid_pk.cli.main import main as hybrid_pk
from hybrid_pk.data.joint_table import read_joint_table, write_joint_table
from hybrid_pk.effects import (
    Conditions,
    ExtendedModel,
    approach_direction,
    conditions_from_data,
    make_effect,
)
from hybrid_pk.evaluation.metrics import pose_error
from hybrid_pk.io.model_file import load_model
from hybrid_pk.simulate import simulate_campaign
from hybrid_pk.simulate.effect_specs import effects_from_file
from hybrid_pk.simulate.trajectories import joint_box

F64 = torch.float64
CAMPAIGN_SEED = 1000  # campaigns of seed K are simulated with seed 1000 + K


def run(*argv: str) -> None:
    """One ``hybrid-pk`` command, printed first; stop on failure."""
    print("$ hybrid-pk " + " ".join(shlex.quote(a) for a in argv), flush=True)
    code = hybrid_pk([*argv, "--no-progress"] if argv[0] in _PROGRESS else list(argv))
    if code:
        sys.exit(f"hybrid-pk {argv[0]} failed with exit code {code}")


_PROGRESS = ("plan", "compensate")


def _points(args) -> list[str]:
    """``--position-only`` for every command when the campaign measures points only."""
    return ["--position-only"] if args.position_only else []


def true_model(robot: Robot, truth_file: Path) -> ExtendedModel:
    truth = json.loads(truth_file.read_text())
    model = ExtendedModel(
        robot,
        effects_from_file(robot, truth_file),
        base=torch.tensor(truth["base_frame"], dtype=F64),
        tool=torch.tensor(truth["tool_frame"], dtype=F64),
    )
    model.requires_grad_(False)
    return model


def random_joints(robot: Robot, n: int, seed: int, margin: float = 0.02) -> torch.Tensor:
    lo, hi = joint_box(robot, margin)
    gen = torch.Generator().manual_seed(seed)
    return lo + torch.rand(n, robot.dof, generator=gen, dtype=F64) * (hi - lo)


def test_error(model, truth: ExtendedModel, q: torch.Tensor) -> float:
    """Mean position error [mm] of ``model`` against the true robot at ``q`` (no noise)."""
    cond = Conditions(payload=torch.zeros(q.shape[0], dtype=F64), direction=approach_direction(q))
    with torch.no_grad():
        return float(pose_error(truth(q, cond), model(q, cond)).position_mm.mean())


def estimates(model: ExtendedModel, truth: ExtendedModel) -> dict[str, float]:
    """Estimate - truth of every effect parameter, by label (``label[k]`` for vectors)."""
    out = {}
    labels = {e.label for e in truth.effects}
    for e in model.effects:
        true = truth.effect(e.label).value if e.label in labels else 0 * e.value
        diff = (e.value - true).detach().reshape(-1)
        for k, d in enumerate(diff.tolist()):
            out[e.label if diff.numel() == 1 else f"{e.label}[{k}]"] = d
    return out


def compensation(robot, model_file: Path, truth: ExtendedModel, program: Path, out: Path):
    run("compensate", str(model_file), str(program), "--out", str(out))
    q_nom, _ = read_joint_table(program, robot)
    q_comp, rest = read_joint_table(out, robot)
    ok = torch.tensor((rest["status"] == "ok").to_numpy())
    model = load_model(model_file).model
    with torch.no_grad():
        B, X = model.base.matrix()[0], model.tool.matrix()[0]
        B_true, X_true = truth.base.matrix()[0], truth.tool.matrix()[0]
        g = robot.fk(q_nom)
    # the real robot approaches each row in program order (backlash)
    cond = Conditions(payload=torch.zeros(q_nom.shape[0], dtype=F64))
    cond_c = Conditions(payload=cond.payload, direction=approach_direction(q_comp))
    cond_n = Conditions(payload=cond.payload, direction=approach_direction(q_nom))
    with torch.no_grad():
        after, before = truth(q_comp, cond_c), truth(q_nom, cond_n)
    rows = {}
    for name, T_int in (("model frames", B @ g @ X), ("true frames", B_true @ g @ X_true)):
        e_after, e_before = pose_error(T_int, after), pose_error(T_int, before)
        rows[name] = {
            "compensated_mm": float(e_after.position_mm[ok].mean()),
            "compensated_deg": float(e_after.orientation_deg[ok].mean()),
            "uncompensated_mm": float(e_before.position_mm[ok].mean()),
            "uncompensated_deg": float(e_before.orientation_deg[ok].mean()),
        }
    rows["ok_rows"] = int(ok.sum())
    rows["rows"] = int(ok.numel())
    rows["statuses"] = rest["status"].value_counts().to_dict()
    return rows


def seed_run(args, robot, work: Path, diag: Path, effects_file: Path, seed: int) -> dict:
    common = ["--effects", str(effects_file), "--noise-mm", str(args.noise_mm)]
    # the campaign's own seed (tracker, tool, noise), unrelated to the plan's seed K
    campaign_seed = str(CAMPAIGN_SEED + seed)
    common += ["--noise-deg", str(args.noise_deg), "--no-temperature", "--seed", campaign_seed]
    common += _points(args)
    d = work / f"seed{seed}"
    d.mkdir(parents=True, exist_ok=True)
    run("plan", "rx160", "--n", str(args.n), "--effects", str(diag), "--candidates",
        str(args.candidates), "--criterion", args.criterion, "--noise-mm", str(args.noise_mm),
        "--noise-deg", str(args.noise_deg), "--seed", str(seed), "--out", str(d / "poses.csv"),
        "--json", str(d / "plan.json"), *_points(args))  # fmt: skip
    run(
        "simulate",
        "rx160",
        "--poses",
        str(d / "poses.csv"),
        *common,
        "--out",
        str(d / "planned.csv"),
    )
    run("simulate", "rx160", "--n", str(args.n), *common, "--out", str(d / "random.csv"))
    for kind in ("planned", "random"):
        run("calibrate", str(d / f"{kind}.csv"), "--robot", "rx160", "--effects", str(diag),
            "--out", str(d / f"{kind}.pt"))  # fmt: skip
    truth = true_model(robot, d / "planned.csv.truth.json")
    q_test = random_joints(robot, args.test, 10_000 + seed)
    result = {"seed": seed, "plan": json.loads((d / "plan.json").read_text())}
    for kind in ("planned", "random"):
        model = load_model(d / f"{kind}.pt").model
        model.requires_grad_(False)
        result[kind] = {
            "test_mm": test_error(model, truth, q_test),
            "error": estimates(model, truth),
        }
    program = write_joint_table(
        d / "program.csv",
        random_joints(robot, args.program, 20_000 + seed, 0.05),
        robot.joint_names,
    )
    result["compensation"] = compensation(
        robot, d / "planned.pt", truth, program, d / "corrected.csv"
    )
    result["compensation"]["model_test_mm"] = result["planned"]["test_mm"]
    return result


def spread(results: list[dict], kind: str, std_key: str) -> tuple[dict, float]:
    """Per effect parameter: observed RMS error over seeds / mean predicted std; and the
    pooled ``sqrt(mean z^2)``."""
    names = list(results[0][kind]["error"])
    predicted = {
        p["name"]: [r["plan"]["parameters"][i][std_key] for r in results]
        for i, p in enumerate(results[0]["plan"]["parameters"])
    }
    ratios, z2 = {}, []
    for name in names:
        errs = [r[kind]["error"][name] for r in results]
        stds = predicted[name]
        ratios[name] = math.sqrt(sum(e * e for e in errs) / len(errs)) / (sum(stds) / len(stds))
        z2 += [(e / s) ** 2 for e, s in zip(errs, stds, strict=True)]
    return ratios, math.sqrt(sum(z2) / len(z2))


def repeat_spread(args, robot, work: Path, diag_labels: list[str], effects_file: Path) -> dict:
    """The planned poses of the first seed measured ``--spread`` more times (other noise,
    tracker and tool): observed spread of the effect estimates / predicted std."""
    first = work / f"seed{args.seeds[0]}"
    q, _ = read_joint_table(first / "poses.csv", robot)
    predicted = {
        p["name"]: p["planned_std"]
        for p in json.loads((first / "plan.json").read_text())["parameters"]
    }
    effects = effects_from_file(robot, effects_file)
    errors: dict[str, list[float]] = {}
    for k in range(args.spread):
        data, _ = simulate_campaign(
            robot, None, effects, poses=q, noise_mm=args.noise_mm, noise_deg=args.noise_deg,
            temperature_range=None, seed=50_000 + k, position_only=args.position_only,
        )  # fmt: skip
        model = ExtendedModel(robot, [make_effect(robot, label) for label in diag_labels])
        cond = conditions_from_data(data)
        initialise_frames(model, data, cond)
        fit(model, data, cond=cond)
        truth = ExtendedModel(robot, effects)
        for name, d in estimates(model, truth).items():
            errors.setdefault(name, []).append(d)
    ratios = {
        n: math.sqrt(sum(e * e for e in v) / len(v)) / predicted[n] for n, v in errors.items()
    }
    z2 = [(e / predicted[n]) ** 2 for n, v in errors.items() for e in v]
    return {"repeats": args.spread, "ratios": ratios, "pooled": math.sqrt(sum(z2) / len(z2))}


def report(
    args, results: list[dict], diag_labels: list[str], hidden: list[str], spread_doc: dict
) -> str:
    mean = lambda xs: sum(xs) / len(xs)  # noqa: E731
    planned = mean([r["planned"]["test_mm"] for r in results])
    rand = mean([r["random"]["test_mm"] for r in results])
    lines = [
        f"# Planned vs random poses, and compensation (virtual RX160, {len(results)} seed(s))",
        "",
        f"hidden effects: {', '.join(hidden)}; diagnosed on the pilot: {', '.join(diag_labels)}",
        f"{args.n} poses per campaign"
        + (", points only" if args.position_only else "")
        + f", noise {args.noise_mm} mm / {args.noise_deg} deg, "
        f"plan: {args.candidates} candidates, criterion {args.criterion}; test: "
        f"{args.test} random rows against the noise-free truth",
        "",
        "| seed | test error, planned [mm] | test error, random [mm] | planned / random "
        "| predicted RMS, planned [mm] | predicted RMS, random [mm] | predicted ratio |",
        "|---|---|---|---|---|---|---|",
    ]
    predicted = []
    for r in results:
        p, q = r["planned"]["test_mm"], r["random"]["test_mm"]
        rms = r["plan"]["position_rms_mm"]
        predicted.append(rms["planned"] / rms["random"])
        lines.append(
            f"| {r['seed']} | {p:.5f} | {q:.5f} | {p / q:.3f} | {rms['planned']:.5f} "
            f"| {rms['random']:.5f} | {predicted[-1]:.3f} |"
        )
    lines += [
        f"| mean | {planned:.5f} | {rand:.5f} | {planned / rand:.3f} | | | {mean(predicted):.3f} |",
        "",
        "(predicted: the plan's RMS position error over the joint box from the fit's own "
        "covariance, against the plan's own random poses)",
        "",
    ]
    lines.append(f"planned poses lower the mean test error by {100 * (1 - planned / rand):.1f} %")
    lines.append(f"the plan predicted {100 * (1 - mean(predicted)):.1f} % (its RMS over the box)")
    # Cramer-Rao: the base and tool translations enter every position row with an
    # orthonormal Jacobian (identity, and the flange rotation), so no N poses know either
    # better than sigma / sqrt(N) per coordinate; their share of the RMS is a floor.
    floor = args.noise_mm * math.sqrt(6 / args.n)
    rand_rms = mean([r["plan"]["position_rms_mm"]["random"] for r in results])
    lines.append(
        f"floor of any design (base and tool translations, sigma sqrt(6 / N)): {floor:.5f} mm "
        f"RMS, {100 * (1 - floor / rand_rms):.1f} % below the random poses' predicted RMS"
    )
    for kind, key in (("planned", "planned_std"), ("random", "random_std")):
        ratios, pooled = spread(results, kind, key)
        lines += ["", f"{kind} poses: observed spread / predicted std (1 = right)", ""]
        lines += [f"- {name}: {v:.2f}" for name, v in ratios.items()]
        lines.append(
            f"- pooled sqrt(mean z^2) over {len(ratios)} parameter(s) x {len(results)} "
            f"seed(s): {pooled:.2f}"
        )
    head = ["seed", "frames", "compensated [mm]", "uncompensated [mm]", "ratio"]
    head += ["model test error [mm]", "compensated / test error", "compensated [deg]"]
    head += ["uncompensated [deg]", "ok rows"]
    if spread_doc:
        lines += ["", f"planned poses of seed {args.seeds[0]} measured {spread_doc['repeats']} "
                  "more times: observed spread / predicted std", ""]  # fmt: skip
        lines += [f"- {name}: {v:.2f}" for name, v in spread_doc["ratios"].items()]
        lines.append(f"- pooled sqrt(mean z^2): {spread_doc['pooled']:.2f}")
    lines += ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results:
        c = r["compensation"]
        for frames in ("model frames", "true frames"):
            e = c[frames]
            lines.append(
                f"| {r['seed']} | {frames} | {e['compensated_mm']:.5f} | "
                f"{e['uncompensated_mm']:.4f} | "
                f"{e['uncompensated_mm'] / e['compensated_mm']:.0f}x | {c['model_test_mm']:.5f} | "
                f"{e['compensated_mm'] / c['model_test_mm']:.2f} | {e['compensated_deg']:.6f} | "
                f"{e['uncompensated_deg']:.4f} | {c['ok_rows']}/{c['rows']} |"
            )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--n", type=int, default=60)
    p.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    p.add_argument("--effects-seed", type=int, default=100)
    p.add_argument("--candidates", type=int, default=2000)
    p.add_argument("--criterion", default="d")
    p.add_argument("--test", type=int, default=2000)
    p.add_argument("--program", type=int, default=500)
    p.add_argument("--noise-mm", type=float, default=0.02)
    p.add_argument("--noise-deg", type=float, default=0.002)
    p.add_argument("--spread", type=int, default=20, help="repeats of the first plan (0: none)")
    p.add_argument(
        "--position-only",
        action="store_true",
        help="the instrument measures points only (a tracker with a plain reflector)",
    )
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    work = args.out
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    robot = Robot.from_urdf("rx160")
    robot.requires_grad_(False)
    pilot = work / "pilot.csv"
    run("simulate", "rx160", "--n", str(args.n), "--effects", "random:2", "--noise-mm",
        str(args.noise_mm), "--noise-deg", str(args.noise_deg), "--no-temperature", "--seed",
        str(args.effects_seed), "--out", str(pilot),
        *_points(args))  # fmt: skip
    effects_file = Path(f"{pilot}.truth.json")
    hidden = [f"{e['effect']}:{e['joint']}" if "joint" in e else e["effect"]
              for e in json.loads(effects_file.read_text())["effects"]]  # fmt: skip
    diag = work / "diagnosis.json"
    run("diagnose", str(pilot), "--robot", "rx160", "--json", str(diag))
    doc = json.loads(diag.read_text())
    diag_labels = [
        c["effect"] + (f":{c['joint']}" if c.get("joint") else "") for c in doc["causes"]
    ]
    results = [seed_run(args, robot, work, diag, effects_file, s) for s in args.seeds]
    spread_doc = repeat_spread(args, robot, work, diag_labels, effects_file) if args.spread else {}
    text = report(args, results, diag_labels, hidden, spread_doc)
    text += f"\n{time.time() - t0:.0f} s in all\n"
    doc = {"seeds": results, "repeat_spread": spread_doc}
    (work / "results.json").write_text(json.dumps(doc, indent=2) + "\n")
    (work / "results.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
