"""What the diagnosis names when a tilted mounting is left out (tour 5): the lifting-column
arm on an 8° tilted base, measured by a levelled total station (positions only), hiding
``restation.py``'s effects (a soft joint, a joint offset, a hardening spring) under the
tilted gravity, diagnosed once with the default upright gravity and once with
``--gravity level-tracker``. Prints per seed the causes named beyond the injected
vocabulary effects and the spring's stand-in (a linear compliance of its joint), and
whether the summary's mounting note fires. Run from the repository root, e.g.::

    python experiments/tilt_left_out.py --seeds 1-5
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

import hybrid_pk as hpk
from experiments.restation import column_arm, hidden_effects, seed_list
from hybrid_pk.cli.common import gravity_note
from hybrid_pk.effects import Gravity
from hybrid_pk.simulate import simulate_campaign
from hybrid_pk.simulate.mounting import parse_mount


def one_seed(seed: int, tilt: str, noise_mm: float, rows: int, scale: float) -> list[str]:
    """The table cells of one seed: for each gravity, the extra causes and the note."""
    robot = column_arm()
    mount = parse_mount(tilt)
    effects, what = hidden_effects(
        robot, np.random.default_rng(seed), mount.gravity_root.tolist(), scale
    )
    data, _ = simulate_campaign(
        robot, rows, effects, noise_mm=noise_mm, position_only=True, temperature_range=None,
        mount=mount, seed=seed,
    )  # fmt: skip
    spring = what.rsplit("spring ", 1)[1]
    expected = {e.label for e in effects[:2]} | {f"joint_compliance:{spring}"}
    cells = []
    for gravity in (Gravity(), Gravity.level_tracker()):
        diagnosis = hpk.diagnose(robot, data, gravity=gravity)
        extra = [_cause(c) for c in diagnosis.causes if f"{c.effect}:{c.joint}" not in expected]
        note = gravity_note(diagnosis.model) is not None
        cells += ["; ".join(extra) or "none", "yes" if note else "no"]
    return [str(seed), *cells, what]


def _cause(c) -> str:
    """``label size unit (blocked hold-out gain)``."""
    size = float(np.linalg.norm(np.atleast_1d(c.value)))
    gain = c.blocked_holdout_gain_mm
    return f"{c.effect}:{c.joint} {size:.3g} {c.unit} ({'-' if gain is None else f'{gain:.2f}'} mm)"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", default="1-5", help="seeds, 'A-B' or 'A,B,...'")
    p.add_argument("--tilt", default="tilt:8", help="the mounting (simulate --mount)")
    p.add_argument("--noise", type=float, default=0.75, help="position noise [mm]")
    p.add_argument("--rows", type=int, default=444, help="rows of the campaign")
    p.add_argument("--scale", type=float, default=4.0, help="hidden effects times this")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    print(
        "| seed | extra causes, default gravity (blocked gain) | note | extra causes, "
        "level-tracker | note | hidden |"
    )
    print("|---|---|---|---|---|---|")
    for seed in seed_list(args.seeds):
        cells = one_seed(seed, args.tilt, args.noise, args.rows, args.scale)
        print("| " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
