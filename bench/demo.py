"""``hybrid-pk demo`` over seeds: wall time against seed 7 in the same run, whether each
names its injected effects, and the longest stretch without a progress update.

    python bench/demo.py                         # seed 7, then seeds 1-10, full demos
    python bench/demo.py --seeds 1 2 3 --n 1200 --epochs 5   # a quick look

Each demo runs as its own ``hybrid-pk demo`` process, one after the other; seed 7 runs
first and again last, and the faster of the two is the reference (a load that drifts
cannot flatter the ratios). The progress stream (stderr, one
line per stage and inner step when not a terminal) is read as it comes: the longest
stretch between two lines, measured by this script's clock, is the longest time the
user saw nothing move. Acceptance (issue 18): every seed <= 3 x seed 7's time, every
injected vocabulary effect named within 5 %, no silent stretch over 10 s. The stretch
before the first line (Python importing torch and the rest) is reported on its own;
each demo's stream is kept in its folder as progress.log (arrival time, line).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REFERENCE_SEED = 7
MAX_RATIO = 3.0
MAX_SILENCE_S = 10.0
VALUE_TOL = 0.05


def absorbed_direction(robot, effect: str, joint: str | None):
    """The direction of a link-length error that no data can tell from the tool frame:
    along the last joint's axis (a translation along an axis commutes with the rotation
    about it), in the frame the error is expressed in. None for every other effect."""
    import torch

    from hybrid_pk.effects import make_effect
    from hybrid_pk.geometry import so3_exp

    if effect != "link_length" or joint != robot.joint_names[-1]:
        return None
    k = make_effect(robot, f"{effect}:{joint}").joint_index
    axis = torch.as_tensor(robot.spec.axes[k], dtype=torch.float64)
    return (so3_exp(robot.origin_rotvec[k].detach().double()) @ axis).tolist()


def named_within(truth: dict, diagnosis: dict, robot, tol: float = VALUE_TOL) -> list[dict]:
    """Per injected vocabulary effect: the found value's relative error (vector norm, on
    the part the data determines), None when the diagnosis did not name it."""
    found = {(c["effect"], c.get("joint")): c for c in diagnosis["causes"]}
    rows = []
    for e in truth["effects"]:
        c = found.get((e["effect"], e.get("joint")))
        rel, note = None, ""
        if c is not None:
            got = c.get("components") or c["value"]
            want = e["value"]
            got, want = (x if isinstance(x, list) else [x] for x in (got, want))
            d = absorbed_direction(robot, e["effect"], e.get("joint"))
            if d is not None:  # compare what the data determines
                got, want = (_reject(x, d) for x in (got, want))
                note = " (along-axis part: the tool frame's)"
            err = math.sqrt(sum((a - b) ** 2 for a, b in zip(got, want, strict=True)))
            rel = err / max(math.sqrt(sum(b * b for b in want)), 1e-300)
        label = f"{e['effect']}:{e.get('joint')}{note}"
        rows.append({"effect": label, "relative_error": rel, "ok": rel is not None and rel <= tol})
    return rows


def _reject(x: list[float], d: list[float]) -> list[float]:
    dot = sum(a * b for a, b in zip(x, d, strict=True))
    return [a - dot * b for a, b in zip(x, d, strict=True)]


def _read_progress(stream, lines: list) -> None:
    for line in iter(stream.readline, ""):
        lines.append((time.perf_counter(), line.rstrip("\n")))


def run_demo(seed: int, out: Path, extra: list[str], robot) -> dict:
    """One demo process; its time, the progress lines with arrival times, its outputs."""
    cmd = [sys.executable, "-m", "hybrid_pk.cli.main", "demo", "--seed", str(seed)]
    cmd += ["--out", str(out), *extra]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    start = time.perf_counter()
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, bufsize=1
    )
    lines: list[tuple[float, str]] = []
    out_lines: list[tuple[float, str]] = []
    readers = [
        threading.Thread(target=_read_progress, args=(stream, into), daemon=True)
        for stream, into in ((proc.stderr, lines), (proc.stdout, out_lines))
    ]
    for reader in readers:
        reader.start()
    proc.wait()
    for reader in readers:
        reader.join()
    end = time.perf_counter()
    stdout = "\n".join(text for _, text in out_lines)
    if proc.returncode != 0:
        tail = "\n".join(text for _, text in lines[-20:])
        raise SystemExit(f"demo --seed {seed} failed (exit {proc.returncode}):\n{tail}")
    # Progress lines on stderr; the summary on stdout shows the user the run is done.
    progress = [(t, text) for t, text in lines if text.startswith("demo [")]
    progress = sorted(progress + [(t, f"(summary) {text}") for t, text in out_lines[:1]])
    with open(out / "progress.log", "w", encoding="utf-8") as log:  # arrival time, line
        log.writelines(f"{t - start:8.2f}  {text}\n" for t, text in lines)
    stamps = [start, *(t for t, _ in progress), end]
    gaps = [(b - a, i) for i, (a, b) in enumerate(itertools.pairwise(stamps))]
    # Before the first line: Python and the libraries (torch, ...) loading.
    startup = gaps[0][0]
    silence, where = max(gaps[1:], default=(0.0, 0))
    after = progress[where - 1][1]
    truth = json.loads((out / "campaign.csv.truth.json").read_text())
    diagnosis = json.loads((out / "diagnosis.json").read_text())
    stages = next((x for x in stdout.splitlines() if x.strip().startswith("report:")), "")
    return {
        "seed": seed,
        "seconds": end - start,
        "startup": startup,
        "silence": silence,
        "silent_after": after,
        "progress_lines": len(progress),
        "named": named_within(truth, diagnosis, robot),
        "stages": stages.split("(", 1)[-1].rstrip(")") if stages else "",
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(1, 11)))
    ap.add_argument("--n", type=int, help="measured poses (default: the demo's)")
    ap.add_argument("--epochs", type=int, help="training epochs (default: the demo's)")
    ap.add_argument("--out", help="keep the demos' folders here (default: a temporary one)")
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args(argv)
    extra = [] if args.n is None else ["--n", str(args.n)]
    extra += [] if args.epochs is None else ["--epochs", str(args.epochs)]
    from hybrid_pk.robot import Robot

    robot = Robot.from_urdf("rx160")
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.out or tmp)
        results = {}
        for seed in [REFERENCE_SEED, *[s for s in args.seeds if s != REFERENCE_SEED]]:
            res = run_demo(seed, root / f"seed_{seed}", extra, robot)
            results[seed] = res
            _print_row(res, results[REFERENCE_SEED]["seconds"])
        # Seed 7 again at the end: the machine's load drifts. The reference is the
        # faster of its two runs, so a loaded first run cannot flatter the ratios.
        again = run_demo(REFERENCE_SEED, root / f"seed_{REFERENCE_SEED}_again", extra, robot)
        first = results[REFERENCE_SEED]["seconds"]
        print(f"seed {REFERENCE_SEED} again: {again['seconds']:.1f} s (first run {first:.1f} s)")
        if again["seconds"] < first:
            results[REFERENCE_SEED] = again
    ok = _print_verdict(results)
    if args.json:
        Path(args.json).write_text(json.dumps(list(results.values()), indent=2))
    return 0 if ok else 1


def _print_row(res: dict, reference: float) -> None:
    named = ", ".join(
        f"{r['effect']} "
        + ("NOT NAMED" if r["relative_error"] is None else f"{100 * r['relative_error']:.2g} %")
        for r in res["named"]
    )
    print(
        f"seed {res['seed']:>2}: {res['seconds']:6.1f} s = {res['seconds'] / reference:4.2f} x "
        f"seed {REFERENCE_SEED}; start-up {res['startup']:4.1f} s, then longest silence "
        f"{res['silence']:4.1f} s (after {res['silent_after']!r}); named: {named}",
        flush=True,
    )
    print(f"         stages: {res['stages']}", flush=True)


def _print_verdict(results: dict) -> bool:
    reference = results[REFERENCE_SEED]["seconds"]
    print(f"reference: seed {REFERENCE_SEED}, the faster of its two runs, {reference:.1f} s")
    worst_ratio = max(r["seconds"] / reference for r in results.values())
    worst_silence = max(r["silence"] for r in results.values())
    worst_startup = max(r["startup"] for r in results.values())
    missed = [
        f"seed {r['seed']} {n['effect']}"
        for r in results.values()
        for n in r["named"]
        if not n["ok"]
    ]
    print(
        f"largest ratio {worst_ratio:.2f} x (limit {MAX_RATIO:g}); longest silence after the "
        f"first progress line {worst_silence:.1f} s (limit {MAX_SILENCE_S:g} s), before it "
        f"(loading Python and the libraries) {worst_startup:.1f} s; effects not named within "
        f"{100 * VALUE_TOL:g} %: {', '.join(missed) or 'none'}"
    )
    silent = max(worst_silence, worst_startup)
    return worst_ratio <= MAX_RATIO and silent <= MAX_SILENCE_S and not missed


if __name__ == "__main__":
    sys.exit(main())
