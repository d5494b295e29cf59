"""The real-data walkthrough, end to end: the IPA UR10 laser-tracker campaign with a
workspace region held out (issue 6; ``experiments/walkthrough_ur10.md`` explains each step).

Every model is made by the public command line (``hybrid-pk import / diagnose /
calibrate / train / evaluate``, called in-process through ``hybrid_pk.cli.main``; the
equivalent shell command is printed before each). Steps:

1. ``hybrid-pk import ipa`` both series (Series A grid, Series B joint configurations).
2. Two hold-out splits, each series split on its own (``--frames-per-file``: every
   series keeps its own tracker and tool frame):

   - ``region``: the top ``--holdout`` of each series' workspace by height
     (``region_split(axis="z", side="high")`` on the nominal flange positions in the
     robot root frame). A Cartesian block mostly lies *inside* the per-joint range of
     the fit rows, so the networks' fade-out rarely applies there;
   - ``joint``: the rows whose ``--range-joint`` (default shoulder lift) lies above the
     ``1 - --holdout`` quantile over both series (``joint_box_split`` with an explicit
     one-joint box). Every held-out row is then outside the networks' training joint
     box: this is the split that tests "outside the training range".

3. ``hybrid-pk diagnose`` on the fit rows of the region split (JSON + report).
4. Per split: ``calibrate --effects none`` (nominal + frames) and ``calibrate --effects
   diagnosis.json`` (the diagnosed causes; the diagnosis is not run a second time;
   the joint split fits the region split's causes unless ``--diagnose-each-split``).
5. ``hybrid-pk train`` the residual networks on the extended model.
6. ``hybrid-pk evaluate`` all three models on the held-out rows (``--frames-per-file``),
   and per-row errors of the held-out rows inside / outside the networks' training
   joint box (read from the hybrid model file).

Writes ``OUT/results.json`` and ``OUT/results.md``. Run from the repository root::

    nice -n 10 python experiments/real_ur10.py --out /tmp/ur10_real            # full data
    python experiments/real_ur10.py --out /tmp/ur10_thin --thin 20 --epochs 3  # a quick look
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from hybrid_pk import Robot
from hybrid_pk.cli.main import main as hybrid_pk
from hybrid_pk.data import MeasuredData, read_table_for, write_table
from hybrid_pk.effects import conditions_from_data
from hybrid_pk.evaluation.metrics import error_stats, row_errors
from hybrid_pk.evaluation.splits import Split, joint_box_split, region_split
from hybrid_pk.io.hybrid_file import predict_poses
from hybrid_pk.io.model_file import load_model

REPO = Path(__file__).resolve().parents[1]
SERIES = {
    "A": ("Series_A/measurements_grid.csv", "measurements_grid"),
    "B": ("Series_B/measurements_joint_configurations.csv", "measurements_joint_configurations"),
}
MODELS = (
    ("nominal_frames", "nominal + frames"),
    ("extended", "extended (physics)"),
    ("hybrid", "hybrid (extended + networks)"),
)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--data",
        type=Path,
        default=REPO.parent / "shared" / "data" / "ipa-ur10",
        help="IPA UR10 data set (Series_A/, Series_B/) (default: ../shared/data/ipa-ur10)",
    )
    p.add_argument("--out", type=Path, required=True, help="output directory (created)")
    p.add_argument("--thin", type=int, default=1, metavar="K", help="keep every K-th row")
    p.add_argument("--epochs", type=int, default=None, help="training epochs (default: preset)")
    p.add_argument("--seed", type=int, default=0, help="seed of diagnosis and training")
    p.add_argument("--holdout", type=float, default=0.2, help="held-out fraction per split")
    p.add_argument(
        "--range-joint",
        default="shoulder_lift_joint",
        help="joint whose upper range the 'joint' split holds out",
    )
    p.add_argument(
        "--splits",
        default="region,joint",
        help="comma-separated splits to run: region, joint (default: both)",
    )
    p.add_argument(
        "--diagnose-each-split",
        action="store_true",
        help="diagnose the fit rows of every split (default: only the region split's, "
        "whose causes the joint split's extended model reuses)",
    )
    p.add_argument("--preset", default="fast", help="training preset (fast, paper)")
    p.add_argument(
        "--evaluate-only",
        action="store_true",
        help="evaluate the models of an earlier run in OUT again (no fitting)",
    )
    return p.parse_args(argv)


def run(argv: list[str], log: dict) -> None:
    """One ``hybrid-pk`` command in-process; fails loudly; records its wall time."""
    print("\n$ hybrid-pk " + " ".join(shlex.quote(str(a)) for a in argv), flush=True)
    t = time.perf_counter()
    rc = hybrid_pk([str(a) for a in argv])
    dt = time.perf_counter() - t
    sys.stdout.flush()
    log.setdefault("commands", []).append(
        {"argv": ["hybrid-pk", *map(str, argv)], "seconds": round(dt, 1), "rc": rc}
    )
    print(f"  [{dt:.1f} s]", flush=True)
    if rc != 0:
        raise SystemExit(f"hybrid-pk {argv[0]} failed (exit {rc})")


def read_series(path: Path, robot: Robot) -> MeasuredData:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Series B's std_* extra columns are not read
        return read_table_for(str(path), robot)


def make_splits(
    series: dict[str, MeasuredData], robot: Robot, args: argparse.Namespace
) -> dict[str, dict[str, Split]]:
    splits: dict[str, dict[str, Split]] = {}
    wanted = [s.strip() for s in args.splits.split(",") if s.strip()]
    if "region" in wanted:
        splits["region"] = {
            k: region_split(d, robot, holdout=args.holdout, axis="z", side="high")
            for k, d in series.items()
        }
    if "joint" in wanted:
        j = list(robot.joint_names).index(args.range_joint)
        q = torch.cat([d.q[:, j] for d in series.values()]).numpy()
        threshold = float(np.quantile(q, 1 - args.holdout))
        splits["joint"] = {
            k: joint_box_split(d, box={args.range_joint: (threshold, float("inf"))})
            for k, d in series.items()
        }
    return splits


def write_split(
    split_dir: Path, series: dict[str, MeasuredData], split: dict[str, Split]
) -> tuple[list[Path], list[Path]]:
    fit_files, hold_files = [], []
    for key, data in series.items():
        fit_rows, hold_rows = split[key].apply(data)
        name = SERIES[key][1]
        for part, rows, files in (("fit", fit_rows, fit_files), ("holdout", hold_rows, hold_files)):
            (split_dir / part).mkdir(parents=True, exist_ok=True)
            files.append(write_table(split_dir / part / f"{name}.parquet", rows))
    return fit_files, hold_files


def stats(x: torch.Tensor | None) -> dict | None:
    if x is None or x.numel() == 0:
        return None
    return error_stats(x).to_dict()


def subset_errors(models: dict[str, Path], hold_files: list[Path], robot: Robot) -> dict:
    """Per-row errors of every model on the held-out rows, grouped by where the rows lie
    relative to the hybrid's training joint box (weight w of its corrections)."""
    hybrid = load_model(models["hybrid"])
    box = hybrid.networks["input"]
    lo, hi = box["trust_lower"].double(), box["trust_upper"].double()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        data = read_table_for([str(f) for f in hold_files], robot)
    cond = conditions_from_data(data, True)
    q = data.q.double()
    inside = ((q >= lo) & (q <= hi)).all(-1)
    width = float(box["fade"])
    # distance outside the box in fade widths, as HybridFK's trust computes it
    beyond = (torch.relu(lo - q) + torch.relu(q - hi)) / (width * (hi - lo)).clamp_min(1e-9)
    faded = beyond.square().sum(-1) >= 1  # networks off entirely (w = 0)
    groups = {
        "all": torch.ones_like(inside),
        "inside_box": inside,
        "outside_box": ~inside,
        "outside_fading": ~inside & ~faded,
        "outside_faded": faded,
    }
    out = {
        "box": {
            "joints": list(robot.joint_names),
            "trust_lower": lo.tolist(),
            "trust_upper": hi.tolist(),
            "fade": width,
        },
        "counts": {g: int(m.sum()) for g, m in groups.items()},
        "counts_per_series": {
            g: [int((m & (data.file_index == i)).sum()) for i in range(len(hold_files))]
            for g, m in groups.items()
        },
        "models": {},
    }
    for key, path in models.items():
        loaded = hybrid if key == "hybrid" else load_model(path)
        T = predict_poses(loaded, data, cond)
        pos, ori = row_errors(T, data)
        out["models"][key] = {
            g: {
                "n": int(m.sum()),
                "position_mm": stats(pos[m]),
                "orientation_deg": None if ori is None else stats(ori[m]),
            }
            for g, m in groups.items()
        }
    return out


def fit_split(
    split_dir: Path, fit_files: list[Path], effects: str, args: argparse.Namespace, log: dict
) -> None:
    """Nominal + frames, extended (the diagnosed effects) and hybrid models of a split."""
    models = {k: split_dir / f"{k}.pt" for k, _ in MODELS}
    calibrate = ["calibrate", *fit_files, "--robot", "ur10", "--frames-per-file"]
    run([*calibrate, "--effects", "none", "--out", models["nominal_frames"], "--no-urdf"], log)
    run([*calibrate, "--effects", effects, "--out", models["extended"]], log)
    train = ["train", *fit_files, "--frames-per-file", "--model", models["extended"]]
    train += ["--out", models["hybrid"], "--preset", args.preset, "--seed", str(args.seed)]
    train += ["--logdir", split_dir / "runs", "--no-progress"]
    if args.epochs is not None:
        train += ["--epochs", str(args.epochs)]
    run(train, log)


def evaluate_split(split_dir: Path, hold_files: list[Path], robot: Robot, log: dict) -> dict:
    """``hybrid-pk evaluate`` of the three models on the held-out rows, and per-row errors
    inside / outside the hybrid's training joint box."""
    models = {k: split_dir / f"{k}.pt" for k, _ in MODELS}
    evaluations = {}
    for key, _ in MODELS:
        target = split_dir / f"eval_{key}.json"
        run(["evaluate", models[key], *hold_files, "--frames-per-file", "--json", target], log)
        evaluations[key] = json.loads(target.read_text())
    extended_meta = load_model(models["extended"]).metadata
    return {
        "effects": ",".join(e["effect"] for e in extended_meta.get("effects", [])) or "none",
        "effects_requested": extended_meta.get("effects_requested", ""),
        "fitted_effects": extended_meta.get("effects"),
        "evaluate": evaluations,
        "by_box": subset_errors(models, hold_files, robot),
    }


# ----------------------------------------------------------------------------- report


def _row(label: str, n: int, e: dict | None) -> str:
    def four(s: dict | None) -> str:
        if s is None:
            return "–"
        return " / ".join(f"{s[k]:.3f}" for k in ("mean", "rms", "p95", "max"))

    if e is None or not n:
        return f"| {label} | 0 | – | – |"
    return f"| {label} | {n} | {four(e['position_mm'])} | {four(e['orientation_deg'])} |"


def _fmt_value(v) -> str:
    if isinstance(v, list):
        return "(" + ", ".join(f"{x:.3g}" for x in v) + ")"
    if isinstance(v, dict):
        return json.dumps(v)
    return f"{v:.4g}"


def write_markdown(results: dict, path: Path) -> None:
    thin = results["thin"]
    rows = f"every {thin}-th row" if thin > 1 else "full data"
    lines = [
        "# IPA UR10, region-held-out evaluation",
        "",
        f"Command: `{results['command']}`  ",
        f"Rows: {results['rows']} ({rows}); "
        f"total wall time {results['seconds_total'] / 60:.1f} min.",
        "",
        "Errors on the held-out rows: position [mm] and orientation [deg], each "
        "mean / RMS / p95 / max.",
    ]
    for name, res in results["splits"].items():
        box = res["by_box"]
        lines += ["", f"## Split `{name}`", ""]
        for key, rule in res["rules"].items():
            lines.append(f"- Series {key}: {rule}")
        lines += [
            "",
            f"Extended model effects: `{res['effects']}`",
            "",
            "| model / rows | n | position mm mean / RMS / p95 / max | "
            "orientation deg mean / RMS / p95 / max |",
            "|---|---|---|---|",
        ]
        for key, label in MODELS:
            ev = res["evaluate"][key]
            lines.append(_row(f"{label}, all held-out (evaluate)", ev["n"], ev))
        for group, words in (
            ("inside_box", "inside the training joint box"),
            ("outside_box", "outside the training joint box"),
            ("outside_fading", "outside the box, in the fade-out zone"),
            ("outside_faded", "beyond the fade-out (networks off)"),
        ):
            for key, label in MODELS:
                e = box["models"][key][group]
                lines.append(_row(f"{label}, {words}", e["n"], e))
        per = box["counts_per_series"]
        lines += [
            "",
            f"Held-out rows inside / outside the networks' training joint box: "
            f"{box['counts']['inside_box']} / {box['counts']['outside_box']} "
            f"(per series {per['inside_box']} / {per['outside_box']}); "
            f"{box['counts']['outside_fading']} of the outside rows in the fade-out zone "
            f"(networks partly on), {box['counts']['outside_faded']} beyond it.",
        ]
    diag = results.get("diagnosis")
    if diag:
        lines += [
            "",
            "## Diagnosis (fit rows of the region split)",
            "",
            f"`hybrid-pk diagnose` on {diag['n_samples']} rows ({diag['n_holdout']} of them "
            "its own random hold-out); hold-out mean position error "
            f"{diag['nominal']['position_mm']['mean']:.3f} mm nominal -> "
            f"{diag['extended']['position_mm']['mean']:.3f} mm extended.",
            "",
            "| cause | value | ± std (1σ) | unit | gain mm | gain deg | evidence |",
            "|---|---|---|---|---|---|---|",
        ]
        for c in diag["causes"]:
            label = c["effect"] + (f":{c['joint']}" if c.get("joint") else "")
            ev = " ".join(str(c.get("evidence", "")).split()).replace("|", "/")
            lines.append(
                f"| {label} | {_fmt_value(c['value'])} | {_fmt_value(c['std'])} | {c['unit']} | "
                f"{c['position_gain_mm']:.3f} | {c['orientation_gain_deg']:.4f} | {ev} |"
            )
        for a in diag.get("ambiguous", []):
            lines.append(f"\nAmbiguous: {' / '.join(a['effects'])}: {a.get('why', '')}")
        lines.append(f"\nUnexplained: `{json.dumps(diag.get('unexplained'))}`")
        for w in diag.get("warnings", []):
            lines.append(f"\nWarning: `{json.dumps(w)}`")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def main(argv=None) -> int:
    args = parse_args(argv)
    t_start = time.perf_counter()
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(args.seed)
    robot = Robot.from_urdf("ur10")
    log: dict = {}
    results: dict = {
        "command": "python " + " ".join(shlex.quote(a) for a in sys.argv),
        "data": str(args.data),
        "thin": args.thin,
        "seed": args.seed,
        "splits": {},
    }

    if args.evaluate_only:  # models of an earlier run in OUT: evaluate them again
        previous = json.loads((out / "results.json").read_text())
        results.update({k: previous[k] for k in ("rows", "thin", "diagnosis") if k in previous})
        results["reevaluated_by"] = results["command"]
        results["command"] = previous["command"].split("  (re-evaluated")[0]
        for name, res in previous["splits"].items():
            hold = [out / name / "holdout" / f"{SERIES[k][1]}.parquet" for k in SERIES]
            results["splits"][name] = {**evaluate_split(out / name, hold, robot, log)}
            results["splits"][name]["rules"] = res["rules"]
        results["log"] = previous.get("log", {})
        results["seconds_total"] = previous.get("seconds_total", 0.0)
        write_results(results, out)
        return 0

    # 1. import both series
    sources = [args.data / SERIES[k][0] for k in SERIES]
    run(["import", "ipa", *sources, "--out", out / "series", "--format", "parquet"], log)
    series = {}
    for key, (_, name) in SERIES.items():
        data = read_series(out / "series" / f"{name}.parquet", robot)
        if args.thin > 1:
            data = data.subset(slice(0, None, args.thin))
        series[key] = data
    results["rows"] = {k: d.n for k, d in series.items()}

    # 2. splits, each series on its own
    splits = make_splits(series, robot, args)
    files = {}
    for name, split in splits.items():
        files[name] = write_split(out / name, series, split)
        for key, s in split.items():
            print(f"split {name}, series {key}: {s.rule}")

    # 3. diagnose (fit rows only)
    effects = {}
    for name in splits:
        if name != "region" and not args.diagnose_each_split and "region" in effects:
            effects[name] = effects["region"]
            continue
        target = out / name / "diagnosis.json"
        diagnose = ["diagnose", *files[name][0], "--robot", "ur10", "--frames-per-file"]
        diagnose += ["--seed", str(args.seed), "--json", target, "--report", out / name / "report"]
        run(diagnose, log)
        diag = json.loads(target.read_text())
        effects[name] = str(target)  # calibrate --effects DIAGNOSIS.json: its causes
        if name == "region" or "diagnosis" not in results:
            results["diagnosis"] = diag
        results.setdefault("diagnoses", {})[name] = diag

    # 4.-6. calibrate, train, evaluate per split
    for name, split in splits.items():
        fit_split(out / name, files[name][0], effects[name], args, log)
        res = evaluate_split(out / name, files[name][1], robot, log)
        res["rules"] = {k: s.rule for k, s in split.items()}
        results["splits"][name] = res
        results["seconds_total"] = time.perf_counter() - t_start
        results["log"] = log
        write_results(results, out)
    return 0


def write_results(results: dict, out: Path) -> None:
    (out / "results.json").write_text(json.dumps(results, indent=1, default=str) + "\n")
    write_markdown(results, out / "results.md")
    print(f"\nwrote {out / 'results.json'} and {out / 'results.md'}")
    print((out / "results.md").read_text(), flush=True)


if __name__ == "__main__":
    sys.exit(main())
