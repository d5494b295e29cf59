"""Wall time of ``diagnose`` against a plain fit of the model it found, with what it
found, so that a fast-but-wrong run cannot pass for a fast one.

Each case runs in a fresh process (its peak RSS is its own) and times, in that
process, ``diagnose`` and then the plain fit that ``calibrate --effects DIAG.json``
makes of the diagnosed causes (frames of the nominal robot, then frames + causes, on
all rows). Printed per case: both wall times and their ratio, both CPU times and
theirs (on a shared machine the CPU time is the fairer measure of the work), peak RSS,
the load average before and after, the work of each (model evaluations of one row, as
the diagnosis budget counts them: a ratio that does not move with the machine's speed
or load; the linear algebra done on those rows is not in it), and where the diagnosis'
time went (its budget record: the main search, each optional stage, the rest), each
against the plain fit.

    python bench/diagnose.py                    # RX160, 4,000 rows, 2 hidden effects
    python bench/diagnose.py --case all         # every case below
    python bench/diagnose.py --case ur10 --reference DIAG.json
    python bench/diagnose.py --case ur10 --commands 2 --threads 1

``--commands K`` also times the two commands a user runs, each in a fresh process, in
K alternating rounds: ``hybrid-pk diagnose`` of the case's files and ``hybrid-pk
calibrate --effects DIAG.json`` of what it found (start-up, reading, the transfer check
and the written files included in both), and prints their medians and ratio.

Cases (targets of issue 12 in brackets):
    rx160     simulated RX160, 4,000 rows, compliance + offset        [< 60 s]
    arm7      simulated 7-axis arm, 444 rows, position only           [<= 20 s]
    ur10      the two shared UR10 series, 13,406 rows, --frames-per-file
                                                 [<= 120 s and <= 10x the plain fit]
    campaign  simulated UR10 continuous campaign, 250,000 rows, 3 effects
                                                 [<= 15 min, <= 6 GB peak RSS]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import torch

import hybrid_pk as hpk
from hybrid_pk.calibration import diagnose
from hybrid_pk.calibration.fit import fit, initialise_frames
from hybrid_pk.calibration.work import done as work_done
from hybrid_pk.effects import ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.simulate import simulate_campaign

REPO = Path(__file__).resolve().parents[1]
IPA = REPO.parent / "shared" / "data" / "ipa-ur10"
CASES = ("rx160", "arm7", "ur10", "campaign")
FRAME_BLOCKS = [
    "base_frame.translation",
    "base_frame.rotation",
    "tool_frame.translation",
    "tool_frame.rotation",
]
# rows of the warm-up diagnosis: enough for frames per file and a blocked hold-out
WARM_ROWS = 400
TARGETS = {"rx160": 60.0, "arm7": 20.0, "ur10": 120.0, "campaign": 900.0}


def import_ipa(ipa: Path, out: Path) -> list[Path]:
    """The two shared UR10 series imported into ``out`` (``hybrid-pk import ipa``, in a
    child process), as Parquet paths in the order Series A, Series B."""
    files = [
        ipa / "Series_A" / "measurements_grid.csv",
        ipa / "Series_B" / "measurements_joint_configurations.csv",
    ]
    cmd = _cli("import", "ipa", *map(str, files), "--out", str(out), "--format", "parquet")
    if subprocess.run(cmd, stdout=subprocess.DEVNULL).returncode != 0:
        raise SystemExit("hybrid-pk import ipa failed")
    return [out / f"{f.stem}.parquet" for f in files]


def _case_data(case: str, ipa: Path):
    """``(robot, data, frames_per_file, injected labels or None)`` of a case."""
    if case == "rx160":
        robot = hpk.Robot.from_urdf("rx160")
        effects = "joint_compliance:joint_2=1.5e-6; joint_offset:joint_3=4e-4"
        data, truth = simulate_campaign(
            robot, 4000, effects, noise_mm=0.02, noise_deg=0.002, payload=20.0, seed=1
        )
        return robot, data, False, truth
    if case == "arm7":
        robot = hpk.Robot.from_urdf(REPO / "tests" / "data" / "arm7_generic.urdf", end_link="tool0")
        effects = "backlash:j3=3.6e-3; axis_misalignment:j5=0,2e-3,1.4e-3"
        data, truth = simulate_campaign(
            robot, 444, effects, noise_mm=0.02, position_only=True, payload=5.0, seed=3
        )
        return robot, data, False, truth
    if case == "campaign":
        robot = hpk.Robot.from_urdf("ur10")
        effects = (
            "joint_compliance:shoulder_lift_joint=8e-6; joint_offset:elbow_joint=5e-4; "
            "link_length:wrist_1_joint=0,0,4e-4"
        )
        data, truth = simulate_campaign(
            robot,
            250_000,
            effects,
            noise_mm=0.02,
            noise_deg=0.002,
            trajectory="continuous",
            payload=5.0,
            seed=2,
        )
        return robot, data, False, truth
    if case == "ur10":
        robot = hpk.Robot.from_urdf("ur10")
        paths = import_ipa(ipa, Path(tempfile.mkdtemp(prefix="bench_ur10_")))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Series B's std_* columns are not read
            parts = [hpk.read_table_for(path, robot) for path in paths]
        return robot, hpk.MeasuredData.concat(parts), True, None
    raise SystemExit(f"unknown case {case!r}; one of {', '.join(CASES)}")


def plain_fit(robot, data, labels: list[str], frames_per_file: bool) -> float:
    """Seconds of what ``calibrate --effects DIAG.json`` fits: frames of the nominal
    robot, then frames and the diagnosed effects, on all rows."""
    start = time.perf_counter()
    cond = conditions_from_data(data, frames_per_file)
    sets = len(data.sources) if frames_per_file else 1
    nominal = ExtendedModel(robot, frame_sets=sets)
    initialise_frames(nominal, data, cond)
    fit(nominal, data, free=FRAME_BLOCKS, cond=cond)
    model = ExtendedModel(robot, [make_effect(robot, lbl) for lbl in labels], frame_sets=sets)
    initialise_frames(model, data, cond)
    fit(model, data, cond=cond)
    return time.perf_counter() - start


def warm_up(robot, data, frames_per_file: bool) -> None:
    """An untimed diagnosis of a few rows first: torch's one-time set-up (linear
    algebra libraries, functorch) is then paid by neither timed run. Without it the
    diagnosis, timed first, paid ~1 s of it and the plain fit after it none."""
    rows = torch.arange(0, data.n, max(data.n // WARM_ROWS, 1))[:WARM_ROWS]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        diagnose(robot, data.subset(rows), frames_per_file=frames_per_file, max_causes=1)


def _label(c) -> str:
    return c.effect if c.joint is None else f"{c.effect}:{c.joint}"


def run_case(case: str, ipa: Path, progress: bool) -> dict:
    """One case in this process: diagnosis, plain fit, peak RSS."""
    load0 = os.getloadavg()
    robot, data, frames_per_file, truth = _case_data(case, ipa)
    robot.requires_grad_(False)
    say = (lambda t: print(f"  [{case}] {t}", file=sys.stderr, flush=True)) if progress else None
    warm_up(robot, data, frames_per_file)
    start, cpu, work = time.perf_counter(), time.process_time(), work_done()
    diag = diagnose(robot, data, frames_per_file=frames_per_file, progress=say)
    t_diag, cpu_diag = time.perf_counter() - start, time.process_time() - cpu
    work_diag = work_done() - work
    labels = [_label(c) for c in diag.causes]
    cpu, work = time.process_time(), work_done()
    t_fit = plain_fit(robot, data, labels, frames_per_file)
    cpu_fit, work_fit = time.process_time() - cpu, work_done() - work
    injected = None
    if truth is not None:
        injected = [
            e["effect"] + (f":{e['joint']}" if e.get("joint") else "") for e in truth["effects"]
        ]
    return {
        "case": case,
        "rows": data.n,
        "threads": torch.get_num_threads(),
        "diagnose_s": t_diag,
        "plain_fit_s": t_fit,
        "diagnose_cpu_s": cpu_diag,
        "plain_fit_cpu_s": cpu_fit,
        "diagnose_work": work_diag,
        "plain_fit_work": work_fit,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "load": [load0[0], os.getloadavg()[0]],
        "found": labels,
        "injected": injected,
        "diagnosis": diag.to_json(),
    }


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "hybrid_pk.cli.main", *args]


def case_files(case: str, ipa: Path, out: Path) -> tuple[list[str], list[str]]:
    """The case's rows as files in ``out``, and the arguments that name its robot and
    its frame sets (what ``diagnose`` and ``calibrate`` are given)."""
    if case == "ur10":
        paths = import_ipa(ipa, out)
        return [str(path) for path in paths], ["--robot", "ur10", "--frames-per-file"]
    _, data, _, _ = _case_data(case, ipa)
    path = hpk.write_table(out / f"{case}.parquet", data)
    if case == "arm7":
        urdf = REPO / "tests" / "data" / "arm7_generic.urdf"
        return [str(path)], ["--robot", str(urdf), "--end-link", "tool0"]
    return [str(path)], ["--robot", "rx160" if case == "rx160" else "ur10"]


def command_times(case: str, ipa: Path, threads: int | None, rounds: int) -> dict:
    """Wall and CPU seconds of ``hybrid-pk diagnose`` and of ``hybrid-pk calibrate
    --effects DIAG.json``, each in a fresh process, alternated for ``rounds`` rounds."""
    out = Path(tempfile.mkdtemp(prefix=f"bench_cmd_{case}_"))
    files, robot = case_files(case, ipa, out)
    common = [*files, *robot, "--no-progress"]
    common += ["--threads", str(threads)] if threads else []
    diag_json, model = out / "diag.json", str(out / "model.pt")
    cmds = {
        "diagnose": _cli("diagnose", *common, "--json", str(diag_json)),
        "calibrate": _cli("calibrate", *common, "--effects", str(diag_json), "--out", model),
    }
    wall: dict[str, list[float]] = {k: [] for k in cmds}
    cpu: dict[str, list[float]] = {k: [] for k in cmds}
    for _ in range(rounds):
        for name, cmd in cmds.items():
            used0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            start = time.perf_counter()
            done = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
            wall[name].append(time.perf_counter() - start)
            used = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu[name].append(used.ru_utime + used.ru_stime - used0.ru_utime - used0.ru_stime)
            if done.returncode != 0:
                raise SystemExit(f"{case}: hybrid-pk {name} failed: {done.stderr.strip()[-300:]}")
    return {
        "case": case,
        "wall": {k: statistics.median(v) for k, v in wall.items()},
        "cpu": {k: statistics.median(v) for k, v in cpu.items()},
        "rounds": rounds,
    }


def report_commands(r: dict) -> None:
    w, c = r["wall"], r["cpu"]
    print(
        f"{r['case']:<9} commands (median of {r['rounds']}, fresh processes): hybrid-pk "
        f"diagnose {w['diagnose']:.1f} s, hybrid-pk calibrate --effects DIAG.json "
        f"{w['calibrate']:.1f} s, ratio {w['diagnose'] / w['calibrate']:.2f}x; CPU "
        f"{c['diagnose']:.1f} s / {c['calibrate']:.1f} s = {c['diagnose'] / c['calibrate']:.2f}x"
    )


def compare(found: dict, reference: dict) -> str:
    """Causes of two diagnoses and the largest value difference in units of std."""

    def by_label(d):
        return {c["effect"] + (f":{c['joint']}" if c.get("joint") else ""): c for c in d["causes"]}

    a, b = by_label(found), by_label(reference)
    worst = 0.0
    for label in set(a) & set(b):
        va, vb, s = (
            c if isinstance(c, list) else [c]
            for c in (a[label]["value"], b[label]["value"], b[label]["std"])
        )
        for x, y, e in zip(va, vb, s, strict=True):
            if e > 0:
                worst = max(worst, abs(x - y) / e)
    same = "same causes" if set(a) == set(b) else f"causes differ: {sorted(set(a) ^ set(b))}"
    return f"{same}; largest value difference {worst:.3f} std"


def report(r: dict, reference: dict | None) -> None:
    ratio = r["diagnose_s"] / max(r["plain_fit_s"], 1e-9)
    cpu_ratio = r["diagnose_cpu_s"] / max(r["plain_fit_cpu_s"], 1e-9)
    print(
        f"{r['case']:<9} {r['rows']:>7} rows, {r['threads']} torch thread(s): diagnose "
        f"{r['diagnose_s']:.1f} s (target <= {TARGETS[r['case']]:.0f} s), plain fit "
        f"{r['plain_fit_s']:.1f} s, ratio {ratio:.1f}x; CPU {r['diagnose_cpu_s']:.1f} s / "
        f"{r['plain_fit_cpu_s']:.1f} s = {cpu_ratio:.1f}x; peak RSS {r['peak_rss_mb']:.0f} MB; "
        f"load {r['load'][0]:.1f} -> {r['load'][1]:.1f}"
    )
    w_diag, w_fit = r["diagnose_work"], r["plain_fit_work"]
    print(
        f"          work (row evaluations, as the budget counts them): diagnose "
        f"{w_diag / 1e6:.1f} M, plain fit {w_fit / 1e6:.1f} M, ratio "
        f"{w_diag / max(w_fit, 1):.1f}x (the same on any machine, loaded or not)"
    )
    print(f"          found:    {r['found']}")
    if r["injected"] is not None:
        ok = "named" if set(r["found"]) == set(r["injected"]) else "NOT the injected set"
        print(f"          injected: {r['injected']} ({ok})")
    d = r["diagnosis"]
    print(
        f"          hold-out mean position error: nominal {d['nominal']['position_mm']['mean']:.4f}"
        f" mm -> extended {d['extended']['position_mm']['mean']:.4f} mm"
    )
    print(f"          {where(d, r['diagnose_s'], r['plain_fit_s'])}")
    if reference is not None:
        print(f"          vs reference: {compare(d, reference)}")


def where(d: dict, total: float, plain: float) -> str:
    """Where a diagnosis' wall time went, from its budget record: the main search (the
    frames and the forward selection), the optional stages, and the rest (settling,
    detection limits, exchanges, gains), each against the plain fit."""
    seconds = dict((d.get("budget") or {}).get("seconds") or {})
    main = seconds.pop("main search", float("nan"))
    optional = sum(seconds.values())
    stages = ", ".join(f"{k} {v:.1f}" for k, v in seconds.items())
    rest = total - main - optional
    return (
        f"time: main search {main:.1f} s ({main / plain:.1f}x the plain fit), optional "
        f"stages {optional:.1f} s ({stages}), the rest {rest:.1f} s ({rest / plain:.1f}x: "
        "settling, detection limits, exchanges, gains)"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--case", default="rx160", help=f"{', '.join(CASES)} or all")
    ap.add_argument("--threads", type=int, default=None, help="torch threads per case")
    ap.add_argument("--ipa", type=Path, default=IPA, help="IPA UR10 data (Series_A/, Series_B/)")
    ap.add_argument("--reference", type=Path, help="diagnosis JSON to compare the ur10 case with")
    ap.add_argument("--json", type=Path, help="write every case's result here")
    ap.add_argument("--progress", action="store_true", help="print the diagnosis's progress")
    ap.add_argument(
        "--commands", type=int, default=0, metavar="K",
        help="also time hybrid-pk diagnose and calibrate --effects DIAG.json, K rounds",
    )  # fmt: skip
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.child:  # one case, result as one JSON line
        print(json.dumps(run_case(args.case, args.ipa, args.progress)))
        return
    cases = CASES if args.case == "all" else tuple(args.case.split(","))
    reference = json.loads(args.reference.read_text()) if args.reference else None
    results = []
    for case in cases:
        cmd = [sys.executable, __file__, "--child", "--case", case, "--ipa", str(args.ipa)]
        cmd += ["--threads", str(args.threads)] if args.threads else []
        cmd += ["--progress"] if args.progress else []
        out = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, check=False)
        if out.returncode != 0:
            raise SystemExit(f"case {case} failed (exit {out.returncode})")
        results.append(json.loads(out.stdout.strip().splitlines()[-1]))
        report(results[-1], reference if case == "ur10" else None)
        if args.commands:
            results[-1]["commands"] = command_times(case, args.ipa, args.threads, args.commands)
            report_commands(results[-1]["commands"])
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
