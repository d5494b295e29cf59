"""``hybrid-pk diagnose DATA... --robot ROBOT --json OUT``: what the nominal model gets wrong."""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import TextIO

from hybrid_pk.errors import HybridPKError

_DESCRIPTION = """\
Diagnose a robot from measured poses: fit base and tool frames to the nominal URDF,
then name the physical effects (joint offsets, compliance, gear ratios, eccentricity,
backlash, link lengths, axis misalignments, thermal expansion, bearing tilt and link or
column bending under the static load) that explain its errors, with their values,
uncertainties and gains, tested on hold-out rows. A robot on a ceiling, a wall or a
tilted base: --gravity X,Y,Z or --gravity level-tracker.

Units: DATA tables have joints [rad, m for prismatic], x y z [m], optional
qw qx qy qz (unit quaternion), payload [kg], temperature [°C]. Errors are reported in
mm (position: point distance) and deg (orientation: rotation angle); each cause in the
unit of its effect (rad, rad/Nm, 1, m, 1/K, rad/Nm/m). --holdout is a fraction of the rows.
"""

# Width of the label column of the printed error table.
_LABEL_WIDTH = 26


def _fraction(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1), got {text!r}") from None
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(
            f"expected a fraction of the rows in (0, 1), got {value:g} (e.g. 0.2 for 20 %)"
        )
    return value


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``diagnose`` command."""
    p = subparsers.add_parser(
        "diagnose",
        help="name the physical causes of the nominal model's errors (JSON + report)",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "data",
        nargs="+",
        metavar="DATA",
        help="measured pose table(s), .csv or .parquet (several files: one campaign)",
    )
    p.add_argument("--robot", required=True, help="URDF path or shipped robot (rx160, ur10)")
    p.add_argument(
        "--holdout",
        type=_fraction,
        default=0.2,
        metavar="FRACTION",
        help="fraction of the rows (0-1) kept out of every fit to compare the models "
        "(default: 0.2)",
    )
    p.add_argument(
        "--json", required=True, metavar="OUT.json", help="write the diagnosis JSON here"
    )
    p.add_argument(
        "--report",
        metavar="DIR",
        help="write DIR/report.md with plots (PNG) of the evidence for each cause",
    )
    p.add_argument(
        "--frames-per-file",
        action="store_true",
        help="each DATA file gets its own base and tool frames (re-mounted tool, moved tracker)",
    )
    p.add_argument(
        "--seed", type=int, default=0, metavar="K", help="seed of the hold-out split (default: 0)"
    )
    p.add_argument("--end-link", metavar="NAME", help="end link (default: the URDF's leaf)")
    p.add_argument(
        "--candidates",
        metavar="LIST",
        help="comma-separated effects to consider, e.g. "
        "joint_offset:joint_2,joint_compliance:joint_3 (default: every effect the data "
        "could reveal)",
    )
    p.add_argument(
        "--alpha",
        type=float,
        default=1e-3,
        help="false-positive rate of the significance test per selection step (default: 1e-3)",
    )
    p.add_argument(
        "--max-causes", type=int, default=8, metavar="N", help="stop after N causes (default: 8)"
    )
    from hybrid_pk.cli.common import add_gravity_argument

    add_gravity_argument(p)
    p.set_defaults(func=_run)


class _Progress:
    """Stage and elapsed time on stderr while the diagnosis runs.

    On a terminal: one tqdm status line, redrawn every half second so the clock keeps
    moving during long fits. Otherwise (logs, pipes): one line per stage.
    """

    def __init__(self, stream: TextIO | None = None) -> None:
        # Looked up per call, not at import: a default of sys.stderr would pin whatever
        # stream was installed when the module was first imported.
        stream = sys.stderr if stream is None else stream
        self.stream = stream
        self.start = time.monotonic()
        self.bar = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if getattr(stream, "isatty", lambda: False)():
            from tqdm import tqdm

            # Some terminals report a 0 x 0 size, on which tqdm would draw nothing.
            width, height = shutil.get_terminal_size((100, 24))
            self.bar = tqdm(
                total=None,
                file=stream,
                ncols=width if width >= 40 else 100,
                nrows=height if height >= 2 else 24,
                bar_format="diagnose: {desc} [{elapsed}]",
                leave=False,  # the summary says how long it took
            )
            self._thread = threading.Thread(target=self._tick, daemon=True)
            self._thread.start()

    def _tick(self) -> None:
        while not self._stop.wait(0.5):
            self.bar.refresh()

    def __call__(self, message: str) -> None:
        if self.bar is not None:
            self.bar.set_description_str(message)
        else:
            print(f"diagnose [{self.elapsed():6.1f} s] {message}", file=self.stream, flush=True)

    def elapsed(self) -> float:
        return time.monotonic() - self.start

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self.bar is not None:
            self.bar.close()


def _finite(obj):
    """JSON-safe copy: non-finite floats become null (JSON has no NaN or inf)."""
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    if isinstance(obj, bool) or obj is None or isinstance(obj, int | str):
        return obj
    if hasattr(obj, "item"):  # numpy / torch scalars
        obj = obj.item()
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    return obj


def _num(x, digits: int = 4) -> str:
    return "-" if x is None else f"{x:.{digits}g}"


def _value(value, std, unit: str) -> str:
    if isinstance(value, list):
        vals = ", ".join(f"{v:.3g}" for v in value)
        stds = ", ".join(f"{s:.2g}" for s in std)
        return f"({vals}) ± ({stds}) {unit}"
    return f"{value:.4g} ± {std:.2g} {unit}"


def summary_lines(diagnosis, seconds: float | None = None) -> list[str]:
    """The short human summary ``diagnose`` prints (errors, causes, ambiguities, rest)."""
    took = "" if seconds is None else f" in {seconds:.1f} s"
    lines = [
        f"diagnosed {diagnosis.robot}: {diagnosis.n_samples} rows, "
        f"{diagnosis.n_holdout} hold-out{took}",
        f"{'hold-out error':<{_LABEL_WIDTH}}{'mean':>10}{'rms':>10}{'p95':>10}{'max':>10}",
    ]
    for key, name in (("position_mm", "position [mm]"), ("orientation_deg", "orientation [deg]")):
        for model in ("nominal", "extended"):
            stats = getattr(diagnosis, model).get(key)
            if stats is None:
                continue
            cells = "".join(f"{_num(stats[s]):>10}" for s in ("mean", "rms", "p95", "max"))
            lines.append(f"{model + ' ' + name:<{_LABEL_WIDTH}}{cells}")
    if diagnosis.causes:
        lines.append(f"causes ({len(diagnosis.causes)}, largest gain first):")
        for c in diagnosis.causes:
            where = f" {c.joint}" if c.joint else ""
            gain = f"gain {c.position_gain_mm:.4g} mm"
            if c.orientation_gain_deg is not None:
                gain += f", {c.orientation_gain_deg:.3g} deg"
            lines.append(f"  {c.effect}{where} = {_value(c.value, c.std, c.unit)}  ({gain})")
    else:
        lines.append("causes: none beyond measurement noise")
    if diagnosis.ambiguous:
        lines.append(f"ambiguous ({len(diagnosis.ambiguous)}):")
        lines += [f"  {' ~ '.join(a['effects'])}" for a in diagnosis.ambiguous]
    for w in diagnosis.warnings:
        lines.append(f"warning: {w['cause']}: {w['why']}")
    from hybrid_pk.cli.common import mounting_lines

    lines += mounting_lines(diagnosis.model)
    un = diagnosis.unexplained
    rest = f"unexplained: RMS {_num(un.get('position_mm_rms'))} mm"
    if un.get("orientation_deg_rms") is not None:
        rest += f", {_num(un['orientation_deg_rms'])} deg"
    rest += (
        "; structured: yes (a smooth error is left that no cause explains)"
        if un.get("structured")
        else "; structured: no (looks like measurement noise)"
    )
    lines.append(rest)
    return lines


def _read(paths: list[str], robot):
    from hybrid_pk.data import read_table_for

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        data = read_table_for(paths, robot)
    for w in caught:  # reader notes (ignored columns, …) as one line each
        print(f"hybrid-pk diagnose: note: {' '.join(str(w.message).split())}", file=sys.stderr)
    return data


def _run(args: argparse.Namespace) -> int:
    from hybrid_pk.calibration.diagnosis.search import diagnose
    from hybrid_pk.effects import make_effect, parse_gravity
    from hybrid_pk.robot import Robot

    for path in args.data:
        if not Path(path).is_file():
            raise FileNotFoundError(f"no such data file: {path}")
    robot = Robot.from_urdf(args.robot, end_link=args.end_link)
    candidates = None
    if args.candidates:
        candidates = [c.strip() for c in args.candidates.split(",") if c.strip()]
        for c in candidates:
            make_effect(robot, c)  # unknown effect or joint: a clear error now
    if args.max_causes < 1:
        raise HybridPKError(f"--max-causes must be at least 1, got {args.max_causes}")
    if not 0.0 < args.alpha < 1.0:
        raise HybridPKError(f"--alpha must lie in (0, 1), got {args.alpha:g}")
    gravity = parse_gravity(args.gravity)
    data = _read(args.data, robot)

    progress = _Progress()
    try:
        result = diagnose(
            robot,
            data,
            holdout=args.holdout,
            seed=args.seed,
            candidates=candidates,
            alpha=args.alpha,
            max_causes=args.max_causes,
            frames_per_file=args.frames_per_file,
            progress=progress,
            gravity=gravity,
        )
        if args.report:
            progress("writing the report")
            from hybrid_pk.report import write_diagnosis_report

            report = write_diagnosis_report(result, data, robot, args.report)
    finally:
        progress.close()
    seconds = progress.elapsed()

    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(_finite(result.to_json()), indent=2) + "\n", encoding="utf-8")
    print("\n".join(summary_lines(result, seconds)))
    print(f"wrote {out}" + (f" and {report}" if args.report else ""))
    return 0
