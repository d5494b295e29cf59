"""``hybrid-pk train DATA... --model MODEL --out MODEL2``: residual networks (Lightning)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from contextlib import contextmanager

import torch

from hybrid_pk.calibration.setups import FrameFit, check_one_setup
from hybrid_pk.cli.common import frame_parameter_count, frame_sets_for, read_data
from hybrid_pk.cli.gross import gross_warning
from hybrid_pk.cli.options import (
    add_data,
    add_fit_frames,
    add_model,
    add_out,
    add_seed,
)
from hybrid_pk.cli.progress import progress
from hybrid_pk.cli.settings_flags import add_settings_flags, given_values
from hybrid_pk.errors import HybridPKError, TrainingInterrupted
from hybrid_pk.evaluation.metrics import pose_error
from hybrid_pk.hybrid.tuning import hybrid_tuning
from hybrid_pk.io.model_file import NOMINAL_PREFIX, load_model, model_robot
from hybrid_pk.pipelines.training import (
    TrainSettings,
    base_for_training,
    is_main_process,
    train_job,
    train_settings,
    training_sections,
)

_DESCRIPTION = """\
Train the two residual networks of the hybrid model (Ojer et al. 2024) on top of MODEL
(a calibrated model file, or nominal:ROBOT with --fit-frames for the paper's
pure-network method) and write MODEL2: MODEL plus the networks, read by evaluate, ik
and calibrate --refit.

The position network corrects the flange position [m], the orientation network its
rotation [rad, axis-angle]; inputs are the joints normalised over the training rows'
range (--input-range data) or the joint limits (limits). Outside the joint box of the
training rows the model is the base model (--fade 0, the default), or the corrections
fade out within --fade x the box size (e.g. 0.1: they may help just outside the
data, or hurt: measure it on held-out rows outside the box).

--inputs gives the networks inputs chosen by the physics instead. frameK[+qI-J]
[+gravity][+torque|+full]: corrections in the frame of link K from the joints after K
(or only joints I..J), so they turn with joints 1..K and need no data over their range,
plus the gravity direction there and the gravity torque (torque) or full static wrench
(full) of each joint after K. local[+q1]: one small network per joint (--local-net)
from its angle and the static wrench there, its small motion carried to the flange by
the chain. Stages join with ',' (where the first is not trusted the next one
corrects, after the last the base model) and '/' (refines the stage before it). Such
networks apply where their inputs are covered by the training rows (--trust coverage,
their default: distance to the training inputs, the base model beyond
--coverage-ratio x the radius of the validation rows, a smooth blend between).
A stage on physics inputs is used away from its training joints only if it earns it:
probe fits of the same networks on blocked hold-out of the training rows (the end
quarters of joint 1 and of the joint that moves the flange point most, each file when
several) must show it beating the physics on each of these families of blocks; else
it stays gated to its training joints (joint box and coverage, the physics beyond).
For a freed stage refined by networks on every joint, the same test decides whether
its correction is shrunk where those are off, axis by axis, c^3 / (c^2 + s^2), by the
spread s^2 of its training targets among rows its inputs cannot tell apart. The
decision of each stage is in MODEL2 and printed (--no-blocked: no probe fits, every
such stage gated; --no-spread: never shrunk). qarm in frameK+qarm: the joints after K
up to the last one whose axis does not pass through the flange point.

Presets: fast (ours: posture networks in link 1's frame refined by networks on every
joint, then local deformation networks: --inputs frame1+qarm+torque/joints,local+q1,
Adam + one-cycle, batch 256, 150 epochs, MSE), joints (ours before: 3 x 256 SiLU MLPs
on every joint, --inputs joints) and paper (D4w / Rw, Adagrad lr 0.005, batch 128,
<= 300 epochs, early stopping, mean-distance / mean-angle losses, limits
normalisation). --config reads the model / data / trainer sections of a LightningCLI
YAML (train/configs/*.yaml) over the preset. Networks: D1, D4, D4w, D4W, Rw, Rd,
B1-B4, mlp, mlp:WIDTHxDEPTH, or none.

--logdir DIR writes TensorBoard logs (losses, mean/p95 position [mm] and orientation
[deg] errors per epoch, error histograms; the model as written after the blocked
hold-out: written/* scalars and a Fig.-4-like figure) and a checkpoint after every
epoch. An interrupted run (Ctrl-C, SIGTERM) keeps the last one and says so; the same
command with --resume continues it in the same version_K folder. A one-cycle learning
rate ends at the epochs it was started for: --resume with other --epochs is refused
(--preset paper, no schedule, may be given more).
--strategy ddp --devices N trains in N processes (DDP; CPU: gloo).
"""


DESCRIPTION = _DESCRIPTION


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``hybrid-pk train``: the training's from :class:`TrainSettings`."""
    add_data(p)
    add_model(p, flag=True, help="base model file, or nominal:ROBOT (with --fit-frames)")
    add_out(p, metavar="MODEL2", help="output model file (.pt)")
    add_settings_flags(p, TrainSettings)
    p.add_argument(
        "--config",
        metavar="YAML",
        help="LightningCLI config over the preset (its values under the flags'); a "
        "top-level tuning: mapping sets the hybrid's tuning constants",
    )
    p.add_argument("--logdir", metavar="DIR", help="TensorBoard logs and checkpoints")
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the interrupted run whose checkpoints are in --logdir DIR (same DATA, "
        "--model, --seed and settings; its epochs unless --epochs)",
    )
    add_seed(p, what="seed of the split, the initialisation and the shuffling")
    p.add_argument("--strategy", default="auto", choices=("auto", "ddp"), help="Lightning strategy")
    p.add_argument(
        "--devices", type=_processes, default=1, metavar="N", help="processes (default: 1)"
    )
    add_fit_frames(
        p, help="first fit only the base and tool frames of MODEL to DATA (nominal:ROBOT)"
    )


def _processes(text: str) -> int:
    """``--devices``: a count of training processes, at least one."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected at least 1 process, got {value}")
    return value


def _prepare(args, loaded, robot, sets: int):
    """DATA read for the model's robot, its conditions, and the base model (frames
    fitted to DATA with --fit-frames)."""
    with progress("train: preparing", total=2 if args.fit_frames else 1) as bar:
        bar.stage("reading data")
        n_params = frame_parameter_count(sets, False) if args.fit_frames else None
        data = read_data(
            args.data, robot, n_params=n_params, skip_bad_rows=args.skip_bad_rows, args=args
        )
        if args.fit_frames:
            bar.stage("fitting base and tool frames")
        cond, base = base_for_training(loaded, data, sets, args.fit_frames)
    with torch.no_grad():
        mean_mm = float(pose_error(data.T_measured(), base(data.q, cond)).position_mm.mean())
    if args.fit_frames and sets == 1:  # files of separate set-ups with one frame set: refused
        check_one_setup(
            base.robot, (data, cond), (data, cond), mean_mm, FrameFit(None, None, base.gravity)
        )
    line = gross_warning(
        "the base model", mean_mm, args.fit_frames, "; the networks would learn that mismatch"
    )
    if line and is_main_process():
        print(line)
    return data, cond, base


@contextmanager
def _epoch_progress(args) -> Iterator[object]:
    """Lightning's epoch bar on a terminal; off one (a log, a pipe) one line per epoch as
    every other command's progress (the bar redrawn with carriage returns filled a log
    with a line per batch). Several processes (--devices) keep Lightning's bar."""
    if args.no_progress or sys.stderr.isatty() or args.devices > 1:
        yield not args.no_progress
        return
    with progress("train") as bar:
        bar.stage(f"{'resuming' if args.resume else 'training'} the residual networks")
        yield bar


def run(args: argparse.Namespace) -> int:
    try:
        from hybrid_pk.training import quiet_lightning
    except ImportError as exc:
        raise HybridPKError(
            f"training needs Lightning (a dependency of hybrid_pk): pip install lightning ({exc})"
        ) from exc
    quiet_lightning()  # after the import: Lightning sets its logger up when imported
    settings = train_settings(given_values(args, TrainSettings), args.config)
    training_sections(settings, args.config)  # checked before any data is read
    if args.resume and args.logdir is None:
        raise HybridPKError("--resume needs the --logdir DIR of the run to continue")
    loaded = load_model(args.model, robot_check=args.robot, end_link=args.end_link)
    robot = model_robot(loaded)
    robot.requires_grad_(False)
    sets = frame_sets_for(args, loaded.model.base.sets)
    data, cond, base = _prepare(args, loaded, robot, sets)
    if loaded.has_networks and is_main_process():
        print(f"note: {args.model} already has residual networks; they are replaced")
    try:
        with _epoch_progress(args) as shown:
            job = train_job(
                loaded, data, cond, base, model_label=args.model, out=args.out,
                settings=settings, config=args.config, fit_frames=args.fit_frames,
                seed=args.seed, logdir=args.logdir, progress=shown, strategy=args.strategy,
                devices=args.devices, resume=args.resume,
            )  # fmt: skip
    except TrainingInterrupted as exc:  # what was kept and how to go on, one line
        print(f"hybrid-pk train: {exc}", file=sys.stderr)
        return exc.exit_code
    if job.out is None:
        return 0
    _print_summary(args, robot, data, job.result)
    if not job.frames_fitted:
        print(
            "warning: base and tool frames are identity (nominal model without --fit-frames): "
            "the networks learned the frames too"
        )
    return 0


def _print_summary(args, robot, data, result) -> None:
    from hybrid_pk.hybrid.nets import count_parameters

    hybrid = result.hybrid
    for note in result.settings.get("notes", []):
        print(f"note: {note}")
    nets = []
    for stage in hybrid.stages:
        for name, head in stage.heads().items():
            where = "" if len(hybrid.stages) == 1 else f" [{stage.label}]"
            nets.append(f"{name}{where} {head.arch} ({count_parameters(head):,} parameters)")
    base = "nominal URDF" if args.model.startswith(NOMINAL_PREFIX) else args.model
    resumed = "" if result.resumed is None else f", resumed after {result.resumed[1]},"
    print(
        f"trained {', '.join(nets)} on {data.n} rows of {robot.name} over {base}: "
        f"{result.epochs} epoch{'' if result.epochs == 1 else 's'}{resumed} in "
        f"{result.seconds:.1f} s"
    )
    print("validation rows, mean error        base model ->   hybrid")
    for key, label in (("position_mm", "position [mm]"), ("orientation_deg", "orientation [deg]")):
        if key in result.best:
            print(f"  {label:<30} {result.base[key]:>12.5g} -> {result.final[key]:>8.5g}")
    for key, name in (("position_mm", "position"), ("orientation_deg", "orientation")):
        best, base_error = result.best.get(key), result.base.get(key)
        if best is None or best < base_error:
            continue
        if best == base_error:  # the start, zero output layers, was kept
            print(
                f"note: no epoch of the {name} networks beat the base model on the validation "
                f"rows: they are kept at zero (the base model's {name}); more rows or epochs "
                "may help"
            )
        else:
            print(
                f"warning: the {name} networks end worse than the base model on the "
                f"validation rows ({best:.5g} against {base_error:.5g} {key.split('_')[1]}): "
                "their output layers start random (as in --preset paper), so the base model "
                "was no candidate; more epochs or rows may help"
            )
    if len(hybrid.stages) > 1 or hybrid.coverage is not None:
        print(
            f"networks ({hybrid.input_label}) trusted near their training inputs (coverage), "
            "each stage falling back to the next, the last to the base model"
        )
    elif hybrid.box is not None and bool(hybrid.box.trust_lower.isfinite().all()):
        lo, hi = hybrid.box.trust_lower, hybrid.box.trust_upper
        box = ", ".join(
            f"{n} [{a:.3f}, {b:.3f}]" for n, a, b in zip(robot.joint_names, lo, hi, strict=True)
        )
        fade = hybrid.box.fade
        beyond = (
            f"fading out within {fade:g} x its size beyond it, then the base model"
            if fade > 0
            else "the base model beyond it"
        )
        print(f"networks trusted inside the training box ({beyond}): {box}")
    else:
        print(f"networks ({hybrid.input_label}) applied everywhere (--trust none)")
    _print_blocked(result.blocked)
    if result.logdir:
        print(f"TensorBoard logs: tensorboard --logdir {result.logdir}")
    print(f"wrote {args.out}")


def _print_blocked(blocked: dict) -> None:
    """One line per probed stage: its mode and its blocked hold-out errors."""
    if not blocked:
        return
    first = next(iter(blocked.values()))
    physics = first["physics"]
    print(
        f"blocked hold-out ({physics['rows']} held-out rows, a row counted once per family "
        f"of blocks holding it: {', '.join(first['blocks'])}), physics "
        f"{physics['position_mm']:.4g} mm:"
    )
    for name, record in blocked.items():
        tried = ", ".join(
            f"{m} {record[m]['position_mm']:.4g} mm"
            for m in ("gated", "free", "shrunk")
            if m in record
        )
        where = (
            "used beyond its training joints"
            if record["mode"] != "gated"
            else "the physics beyond its training joints"
        )
        print(f"  {name.split(':', 1)[1]}: {record['mode']} ({where}); {tried}")
        families = record.get("families") or {}
        if families:
            z = hybrid_tuning().freeing_z
            print(
                f"    free against gated, per family of blocks (z of the mean gain; frees at "
                f"> {z:g} on every family): "
                + ", ".join(
                    f"{f} z {v['z']:+.2g}" + ("" if v["beats"] else " (no)")
                    for f, v in families.items()
                )
            )
