"""Start-up bench: how long ``hybrid-pk`` takes before it does any work.

Each command line runs in a fresh process, the lines interleaved round by round so
that the machine's load falls on all alike; reported: the median wall time and its
ratio to the peer measured in the same run, ``python -c "import torch"`` (what every
command that computes must load; a ratio near 1 is the floor).

- ``hybrid-pk --help``: imports no command and no torch;
- ``hybrid-pk COMMAND --help``: that command's module and what it imports (its flags
  come from settings classes that import torch), not the other commands'.

    python bench/startup.py                   # every command, 5 rounds
    python bench/startup.py --rounds 3 --commands diagnose ik
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

from hybrid_pk.cli.main import COMMANDS


def _seconds(argv: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--commands", nargs="+", default=list(COMMANDS), choices=list(COMMANDS))
    args = ap.parse_args()
    cli = [sys.executable, "-m", "hybrid_pk.cli.main"]
    lines = {"python -c 'import torch' (peer)": [sys.executable, "-c", "import torch"]}
    lines["hybrid-pk --help"] = [*cli, "--help"]
    for name in args.commands:
        lines[f"hybrid-pk {name} --help"] = [*cli, name, "--help"]
    times: dict[str, list[float]] = {k: [] for k in lines}
    for _ in range(args.rounds):
        for label, argv in lines.items():
            times[label].append(_seconds(argv))
    peer = statistics.median(next(iter(times.values())))
    print(f"{args.rounds} rounds, fresh process each, median wall time; ratio to the peer")
    for label, values in times.items():
        t = statistics.median(values)
        print(f"  {label:<42} {t:6.2f} s  {t / peer:5.2f}x")


if __name__ == "__main__":
    main()
