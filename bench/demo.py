"""``hybrid-pk demo`` over seeds: wall time against seed 7 in the same run, whether each
names its injected effects, and the longest stretch without a progress update.

    python bench/demo.py                         # seed 7, then seeds 1-10, full demos
    python bench/demo.py --seeds 1 2 3 --n 1200 --epochs 5   # a quick look

Each demo runs as its own ``hybrid-pk demo`` process, one after the other (same
machine, same load as far as the bench can make it). The progress stream (stderr, one
line per stage and inner step when not a terminal) is read as it comes: the longest
stretch between two lines, measured by this script's clock, is the longest time the
user saw nothing move. Acceptance (issue 18): every seed <= 3 x seed 7's time, every
injected vocabulary effect named within 5 %, no silent stretch over 10 s.
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


def named_within(truth: dict, diagnosis: dict, tol: float = VALUE_TOL) -> list[dict]:
    """Per injected vocabulary effect: the found value's relative error (vector norm),
    None when the diagnosis did not name it."""
    found = {(c["effect"], c.get("joint")): c for c in diagnosis["causes"]}
    rows = []
    for e in truth["effects"]:
        c = found.get((e["effect"], e.get("joint")))
        rel = None
        if c is not None:
            got = c.get("components") or c["value"]
            want = e["value"]
            got, want = (x if isinstance(x, list) else [x] for x in (got, want))
            err = math.sqrt(sum((a - b) ** 2 for a, b in zip(got, want, strict=True)))
            rel = err / max(math.sqrt(sum(b * b for b in want)), 1e-300)
        label = f"{e['effect']}:{e.get('joint')}"
        rows.append({"effect": label, "relative_error": rel, "ok": rel is not None and rel <= tol})
    return rows


def _read_progress(stream, lines: list) -> None:
    for line in iter(stream.readline, ""):
        lines.append((time.perf_counter(), line.rstrip("\n")))


def run_demo(seed: int, out: Path, extra: list[str]) -> dict:
    """One demo process; its time, the progress lines with arrival times, its outputs."""
    cmd = [sys.executable, "-m", "hybrid_pk.cli.main", "demo", "--seed", str(seed)]
    cmd += ["--out", str(out), *extra]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    start = time.perf_counter()
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, bufsize=1
    )
    lines: list[tuple[float, str]] = []
    reader = threading.Thread(target=_read_progress, args=(proc.stderr, lines), daemon=True)
    reader.start()
    stdout = proc.stdout.read()
    proc.wait()
    reader.join()
    end = time.perf_counter()
    if proc.returncode != 0:
        tail = "\n".join(text for _, text in lines[-20:])
        raise SystemExit(f"demo --seed {seed} failed (exit {proc.returncode}):\n{tail}")
    progress = [(t, text) for t, text in lines if text.startswith("demo [")]
    stamps = [start, *(t for t, _ in progress), end]
    gaps = [(b - a, i) for i, (a, b) in enumerate(itertools.pairwise(stamps))]
    silence, where = max(gaps)
    after = "start" if where == 0 else progress[where - 1][1]
    truth = json.loads((out / "campaign.csv.truth.json").read_text())
    diagnosis = json.loads((out / "diagnosis.json").read_text())
    stages = next((x for x in stdout.splitlines() if x.strip().startswith("report:")), "")
    return {
        "seed": seed,
        "seconds": end - start,
        "silence": silence,
        "silent_after": after,
        "progress_lines": len(progress),
        "named": named_within(truth, diagnosis),
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
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.out or tmp)
        results = {}
        for seed in [REFERENCE_SEED, *[s for s in args.seeds if s != REFERENCE_SEED]]:
            res = run_demo(seed, root / f"seed_{seed}", extra)
            results[seed] = res
            _print_row(res, results[REFERENCE_SEED]["seconds"])
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
        f"seed {REFERENCE_SEED}; longest silence {res['silence']:4.1f} s (after "
        f"{res['silent_after']!r}); named: {named}",
        flush=True,
    )
    print(f"         stages: {res['stages']}", flush=True)


def _print_verdict(results: dict) -> bool:
    reference = results[REFERENCE_SEED]["seconds"]
    worst_ratio = max(r["seconds"] / reference for r in results.values())
    worst_silence = max(r["silence"] for r in results.values())
    missed = [
        f"seed {r['seed']} {n['effect']}"
        for r in results.values()
        for n in r["named"]
        if not n["ok"]
    ]
    print(
        f"largest ratio {worst_ratio:.2f} x (limit {MAX_RATIO:g}); longest silence "
        f"{worst_silence:.1f} s (limit {MAX_SILENCE_S:g} s); effects not named within "
        f"{100 * VALUE_TOL:g} %: {', '.join(missed) or 'none'}"
    )
    return worst_ratio <= MAX_RATIO and worst_silence <= MAX_SILENCE_S and not missed


if __name__ == "__main__":
    sys.exit(main())
