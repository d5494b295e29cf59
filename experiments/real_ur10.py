"""The real-data walkthrough, end to end: the IPA UR10 laser-tracker campaign with parts
of it held out (issues 6 and 13; ``experiments/walkthrough_ur10.md`` explains each step).

Every model is made by the public command line (``hybrid-pk import / diagnose /
calibrate / train / evaluate``, called in-process through ``hybrid_pk.cli.main``; the
equivalent shell command is printed before each). Steps:

1. ``hybrid-pk import ipa`` both series (Series A grid, Series B joint configurations).
2. Hold-out splits, each series keeping its own tracker and tool frame
   (``--frames-per-file``):

   - ``pan``: the rows whose shoulder pan angle lies in the lowest ``--pan-share`` of
     both series together (one threshold: the networks are shared). Joint 1 is
     turned where no training row was;
   - ``region``: the top ``--holdout`` of each series' workspace by height
     (``region_split(axis="z", side="high")`` on the nominal flange positions);
   - ``random``: a random ``--holdout`` of each series (accuracy inside the region);
   - ``joint`` (on request): the rows above the ``1 - --holdout`` quantile of
     ``--range-joint``.

3. ``hybrid-pk diagnose`` on each split's own fit rows (``--diagnose-on each``, the
   default: which causes a split's models carry is chosen without its held-out rows,
   as for a user whose robot later works elsewhere), or once on the region split's fit
   rows for all (``--diagnose-on region``), or ``--diagnosis FILE`` of an earlier run;
   the split's extended model fits those causes (``calibrate --effects diagnosis.json``).
4. Per split: ``calibrate --effects none`` (nominal + frames) and ``--effects
   DIAGNOSIS`` (extended).
5. ``hybrid-pk train`` twice on the extended model: ``--preset joints`` (the paper's
   inputs: MLPs on every joint, the base model outside their joint box) and
   ``--preset fast`` (the default: stages whose frames and inputs the physics chooses).
6. ``hybrid-pk evaluate`` the four models on the held-out rows, and per-row errors on
   subsets: each series, and every window of ``--window`` consecutive held-out rows
   ordered by each joint (where the hybrid must not be worse than the extended model).

Model files already in OUT are kept (``--evaluate-only``: fit nothing). Writes
``OUT/results.json`` and ``OUT/results.md``. Run from the repository root::

    nice -n 10 python experiments/real_ur10.py --out /tmp/ur10_real              # ~15 min
    python experiments/real_ur10.py --out /tmp/ur10_quick --epochs 40 --splits region
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch

from hybrid_pk import Robot
from hybrid_pk.data import MeasuredData, write_table
from hybrid_pk.effects import conditions_from_data
from hybrid_pk.evaluation.metrics import error_stats, row_errors
from hybrid_pk.evaluation.splits import Split, joint_box_split, random_split, region_split
from hybrid_pk.io.hybrid_file import forward_model
from hybrid_pk.io.model_file import load_model

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ipa_series import SERIES, add_data, import_series, read_rows, run, series_paths
from real_ur10_report import write_markdown

MODELS = (
    ("nominal_frames", "nominal + frames"),
    ("extended", "extended (physics)"),
    ("hybrid_joints", "hybrid, networks on the joints (--preset joints)"),
    ("hybrid", "hybrid, physics-chosen stages (--preset fast)"),
)
SPLITS = ("pan", "region", "random", "joint")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_data(p)
    p.add_argument("--out", type=Path, required=True, help="output directory (created)")
    p.add_argument("--thin", type=int, default=1, metavar="K", help="keep every K-th row")
    p.add_argument(
        "--epochs", type=int, default=150, help="training epochs (default 150, the presets')"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of splits, diagnosis, training")
    p.add_argument("--holdout", type=float, default=0.2, help="region/random/joint share")
    p.add_argument("--pan-share", type=float, default=0.25, help="pan split: lowest share")
    p.add_argument("--range-joint", default="shoulder_lift_joint", help="joint split's joint")
    p.add_argument("--splits", default="pan,region,random", help=f"from {', '.join(SPLITS)}")
    p.add_argument("--window", type=int, default=100, help="rows per held-out subset")
    p.add_argument("--diagnosis", type=Path, help="diagnosis JSON of an earlier run (reused)")
    p.add_argument(
        "--diagnose-on",
        choices=("each", "region"),
        default="each",
        help="diagnose each split's own fit rows (default), or the region split's for all",
    )
    p.add_argument(
        "--effects",
        help="effects of the extended models as calibrate --effects LIST (no diagnosis)",
    )
    p.add_argument(
        "--evaluate-only",
        action="store_true",
        help="fit nothing: evaluate the model files of an earlier run in OUT",
    )
    return p.parse_args(argv)


def make_splits(series: dict[str, MeasuredData], robot: Robot, args) -> dict[str, dict]:
    wanted = [s.strip() for s in args.splits.split(",") if s.strip()]
    unknown = set(wanted) - set(SPLITS)
    if unknown:
        raise SystemExit(f"unknown split(s) {sorted(unknown)}; choose from {', '.join(SPLITS)}")

    def threshold(joint: str, share: float) -> float:
        j = list(robot.joint_names).index(joint)
        return float(np.quantile(torch.cat([d.q[:, j] for d in series.values()]).numpy(), share))

    splits: dict[str, dict[str, Split]] = {}
    for name in wanted:
        out = {}
        for key, d in series.items():
            if name == "pan":
                pan = threshold("shoulder_pan_joint", args.pan_share)
                out[key] = joint_box_split(d, box={"shoulder_pan_joint": (-np.inf, pan)})
            elif name == "region":
                out[key] = region_split(d, robot, holdout=args.holdout, axis="z", side="high")
            elif name == "random":
                out[key] = random_split(d, holdout=args.holdout, seed=args.seed)
            else:
                high = threshold(args.range_joint, 1 - args.holdout)
                out[key] = joint_box_split(d, box={args.range_joint: (high, np.inf)})
        splits[name] = out
    return splits


def write_split(split_dir: Path, series: dict, split: dict) -> tuple[list[Path], list[Path]]:
    files: tuple[list[Path], list[Path]] = ([], [])
    for key, data in series.items():
        for part, rows, into in zip(("fit", "holdout"), split[key].apply(data), files, strict=True):
            (split_dir / part).mkdir(parents=True, exist_ok=True)
            into.append(write_table(split_dir / part / f"{SERIES[key][1]}.parquet", rows))
    return files


def split_files(split_dir: Path) -> tuple[list[Path], list[Path]]:
    return tuple(
        [split_dir / part / f"{SERIES[k][1]}.parquet" for k in SERIES]
        for part in ("fit", "holdout")
    )


def fit_split(split_dir: Path, fit_files: list[Path], effects, args, log: dict) -> None:
    """The four models of a split; a model file already there is kept."""
    m = {k: split_dir / f"{k}.pt" for k, _ in MODELS}
    calibrate = ["calibrate", *fit_files, "--robot", "ur10", "--frames-per-file", "--no-urdf"]
    if not m["nominal_frames"].exists():
        run([*calibrate, "--effects", "none", "--out", m["nominal_frames"]], log)
    if not m["extended"].exists():
        run([*calibrate, "--effects", effects, "--out", m["extended"]], log)
    for key, preset in (("hybrid_joints", "joints"), ("hybrid", "fast")):
        if m[key].exists():
            continue
        train = ["train", *fit_files, "--frames-per-file", "--model", m["extended"]]
        train += ["--out", m[key], "--preset", preset, "--seed", args.seed]
        train += ["--epochs", args.epochs, "--logdir", split_dir / f"runs_{key}", "--no-progress"]
        run(train, log)


def _stats(x: torch.Tensor) -> dict | None:
    return None if x.numel() == 0 else error_stats(x).to_dict()


def subsets(data: MeasuredData, robot: Robot, window: int) -> dict[str, torch.Tensor]:
    """Row masks of the held-out subsets: each series, and every window of ``window``
    consecutive rows ordered by each joint (half-overlapping)."""
    out = {f"series {k}": data.file_index == i for i, k in enumerate(SERIES)}
    for j, name in enumerate(robot.joint_names):
        order = data.q[:, j].argsort()
        for start in range(0, max(data.n - window, 0) + 1, max(window // 2, 1)):
            mask = torch.zeros(data.n, dtype=torch.bool)
            mask[order[start : start + window]] = True
            lo, hi = data.q[order[start], j], data.q[order[min(start + window, data.n) - 1], j]
            out[f"{name} in [{lo:.2f}, {hi:.2f}]"] = mask
    return out


def evaluate_split(split_dir: Path, hold_files: list[Path], robot: Robot, args, log) -> dict:
    """``hybrid-pk evaluate`` of the four models, per-row errors on the subsets, and
    where the networks applied."""
    res: dict = {"evaluate": {}, "models": {}}
    for key, _ in MODELS:
        target = split_dir / f"eval_{key}.json"
        run(
            [
                "evaluate",
                split_dir / f"{key}.pt",
                *hold_files,
                "--frames-per-file",
                "--json",
                target,
            ],
            log,
        )
        res["evaluate"][key] = json.loads(target.read_text())
    data = read_rows(hold_files, robot)
    cond = conditions_from_data(data, True)
    masks = subsets(data, robot, args.window)
    errors = {}
    for key, _ in MODELS:
        loaded = load_model(split_dir / f"{key}.pt")
        model = forward_model(loaded)
        with torch.no_grad():
            errors[key] = row_errors(model(data.q, cond), data)
            if key.startswith("hybrid"):
                weights = [w.reshape(data.n, -1).mean(-1) for w in model.weights(data.q)]
                res[f"{key}_stage_weights"] = {
                    s.label: float(w.mean()) for s, w in zip(model.stages, weights, strict=True)
                }
        res["models"][key] = {"position_mm": _stats(errors[key][0])}
        if errors[key][1] is not None:
            res["models"][key]["orientation_deg"] = _stats(errors[key][1])
    ext = errors["extended"][0]
    for key in ("hybrid_joints", "hybrid"):
        pos = errors[key][0]
        ratios = {n: float(pos[m].mean() / ext[m].mean()) for n, m in masks.items() if m.any()}
        worst = max(ratios, key=ratios.get)
        res[f"{key}_vs_extended"] = {
            "mean_ratio": float(pos.mean() / ext.mean()),
            "worst_subset": worst,
            "worst_subset_ratio": ratios[worst],
            "series_ratios": {n: r for n, r in ratios.items() if n.startswith("series")},
        }
    res["effects"] = load_model(split_dir / "extended.pt").metadata.get("effects")
    return res


def diagnosis_for(out: Path, name: str, args, log: dict, results: dict) -> Path | str:
    """What split ``name``'s extended model fits: ``--effects``, the diagnosis JSON
    ``--diagnosis``, or a diagnosis (made here unless already in OUT) of the split's own
    fit rows (``--diagnose-on each``) or of the region split's (``region``)."""
    if args.effects:
        return args.effects
    if args.diagnosis:
        results["diagnosis"] = json.loads(args.diagnosis.read_text())
        results["diagnosis_rows"] = f"{args.diagnosis}, given with --diagnosis"
        return args.diagnosis.resolve()
    source = name if args.diagnose_on == "each" else "region"
    target = out / source / "diagnosis.json"
    if not target.exists():
        if args.evaluate_only:
            raise SystemExit(f"--evaluate-only: no {target}")
        fit_files = split_files(out / source)[0]
        if not fit_files[0].exists():
            raise SystemExit(f"the diagnosis needs the {source} split's fit rows: add {source}")
        run(["diagnose", *fit_files, "--robot", "ur10", "--frames-per-file", "--seed",
             args.seed, "--json", target, "--report", out / source / "report"], log)  # fmt: skip
    diagnosis = json.loads(target.read_text())
    if args.diagnose_on == "each":
        results["splits"][name]["diagnosis"] = diagnosis
    else:
        results["diagnosis"] = diagnosis
    return target


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
        "thin": args.thin,
        "epochs": args.epochs,
        "seed": args.seed,
        "splits": {},
    }
    paths = series_paths(out) if args.evaluate_only else import_series(out, args.data, log)
    series = {}
    for key, path in paths.items():
        data = read_rows([path], robot)
        series[key] = data.subset(slice(0, None, args.thin)) if args.thin > 1 else data
    results["rows"] = {k: d.n for k, d in series.items()}
    splits = make_splits(series, robot, args)
    for name, split in splits.items():
        if not args.evaluate_only:
            write_split(out / name, series, split)
        results["splits"][name] = {"rules": {k: s.rule for k, s in split.items()}}
        print(f"split {name}: " + "; ".join(s.rule for s in split.values()), flush=True)
    if args.diagnose_on == "region" and "region" not in splits and not args.diagnosis:
        raise SystemExit("--diagnose-on region needs the region split: add it to --splits")
    for name in sorted(splits, key=lambda n: n != "region"):  # region first: its diagnosis
        fit_files, hold_files = split_files(out / name)
        effects = diagnosis_for(out, name, args, log, results)
        if not args.evaluate_only:
            fit_split(out / name, fit_files, effects, args, log)
        results["splits"][name].update(evaluate_split(out / name, hold_files, robot, args, log))
        results["seconds_total"] = time.perf_counter() - t_start
        results["log"] = log
        write_results(results, out)
    return 0


def write_results(results: dict, out: Path) -> None:
    (out / "results.json").write_text(json.dumps(results, indent=1, default=str) + "\n")
    write_markdown(results, MODELS, out / "results.md")
    print(f"\nwrote {out / 'results.json'} and {out / 'results.md'}")
    print((out / "results.md").read_text(), flush=True)


if __name__ == "__main__":
    sys.exit(main())
