"""The demo pipeline: the whole job on a simulated campaign, from hidden effects to IK.

simulate a laser-tracker campaign with hidden effects -> diagnose (name the causes,
show the evidence) -> calibrate -> train the residual networks -> evaluate on rows no
fit saw -> IK with every solution -> report. The injected effects are revealed only at
the end, next to what the diagnosis found, so the run shows that the tool finds them by
itself.

Besides effects of the vocabulary, the campaign carries by default one effect that no
calibration can fit: a hardening joint spring (softer near zero torque, as harmonic
drives are) on a gravity-loaded joint. The physics explains what it can of it; the
residual networks learn the rest.

``hybrid-pk demo`` is a thin wrapper of :func:`run_demo`.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch

from hybrid_pk.calibration.diagnosis import Diagnosis, diagnose
from hybrid_pk.calibration.diagnosis.unseen import mark_unseen
from hybrid_pk.calibration.settings import DiagnosisSettings
from hybrid_pk.data import MeasuredData, write_table
from hybrid_pk.data.table import write_frame
from hybrid_pk.effects import Conditions, Effect, ExtendedModel, conditions_from_data
from hybrid_pk.ik import solve_ik_two_stage
from hybrid_pk.io.hybrid_file import save_hybrid
from hybrid_pk.io.model_file import save_model
from hybrid_pk.output_file import write_text
from hybrid_pk.pipelines.calibration import calibrate, cause_labels
from hybrid_pk.pipelines.demo_report import write_demo_report
from hybrid_pk.report.diagnosis_report import write_diagnosis_report
from hybrid_pk.report.evaluation_report import write_evaluation_report
from hybrid_pk.robot import Robot
from hybrid_pk.simulate import simulate_campaign
from hybrid_pk.simulate.effect_specs import effect_entry, parse_effects
from hybrid_pk.simulate.unmodelled import HardeningCompliance, rms_gravity_torques

__all__ = [
    "DEFAULT_ROBOT",
    "IK_TARGETS",
    "STAGES",
    "UNMODELLED_DEFLECTION",
    "UNMODELLED_KNEE",
    "DemoResult",
    "hidden_effects",
    "run_demo",
]

DEFAULT_ROBOT = "rx160"
UNMODELLED_DEFLECTION = 2e-4  # [rad] of the hardening spring's saturated extra deflection
UNMODELLED_KNEE = 0.4  # knee torque tau0, share of the joint's RMS gravity torque
IK_TARGETS = 4
# The stages in order: (short name: DemoResult.stage_seconds and the report, what the
# progress callback shows).
STAGES = (
    ("simulate", "simulating the measurement campaign"),
    ("diagnose", "diagnosing: which effects explain the errors?"),
    ("calibrate", "calibrating frames + named effects on the calibration rows"),
    ("train", "training the residual networks (Lightning)"),
    ("evaluate", "evaluating on held-out rows"),
    ("ik", "inverse kinematics on the hybrid model: every solution"),
    ("report", "writing the report"),
)

Progress = Callable[[str, str | None], None]


@dataclass
class DemoResult:
    """What :func:`run_demo` wrote and measured.

    Attributes:
        out: output folder; ``report`` is ``out/report.md``.
        robot: name of the robot.
        n_rows, n_test: simulated rows, and the held-out last quarter of them.
        truth: the campaign's truth (``effects``: the injected vocabulary effects,
            ``unmodelled``: the hardening spring, if any).
        diagnosis: the diagnosis of the calibration rows.
        evaluation: held-out errors per model (``position_mm`` / ``orientation_deg``
            statistics).
        ik: IK summary (targets, solutions, per target, failed, largest errors).
        stage_seconds: wall time per stage [s], by the short names of :data:`STAGES`.
        seconds: total wall time [s].
    """

    out: Path
    report: Path
    robot: str
    n_rows: int
    n_test: int
    truth: dict
    diagnosis: Diagnosis
    evaluation: dict
    ik: dict
    stage_seconds: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0


def hidden_effects(
    robot: Robot, effects: str, *, seed: int, payload: float, unmodelled: bool = True
) -> tuple[list[Effect], list[Effect]]:
    """The vocabulary effects of ``effects`` (simulate's ``--effects`` syntax) and the
    unmodelled hardening spring on joint 2 or 3 (drawn from ``seed``), if asked for.

    The spring goes to the other of the two joints when the drawn one carries a
    joint-space vocabulary effect, or to joint 5 (a wrist gearbox) when both do: its
    linear part is a compliance of that joint, and would otherwise bias what the
    diagnosis can say of an injected compliance, gear ratio or offset there."""
    vocabulary = parse_effects(robot, effects, seed=seed, payload=payload)
    extra: list[Effect] = []
    if unmodelled:
        gen = torch.Generator().manual_seed(seed + 1)
        index = 1 + int(torch.randint(2, (1,), generator=gen))  # joint 2 or 3
        taken = {e.joint for e in vocabulary if e.stage in ("joint", "compliance")}
        for choice in (index, 3 - index, 4):  # drawn, the other of 2 and 3, joint 5
            if choice < robot.dof - 1 and robot.joint_names[choice] not in taken:
                index = choice
                break
        tau0 = UNMODELLED_KNEE * float(rms_gravity_torques(robot, payload, gen)[index])
        extra.append(
            HardeningCompliance(robot, robot.joint_names[index], UNMODELLED_DEFLECTION / tau0, tau0)
        )
    return vocabulary, extra


class _Stages:
    """Names the stage to the progress callback and times each stage."""

    def __init__(self, progress: Progress | None) -> None:
        self.progress = progress or (lambda _stage, _step: None)
        self.seconds: dict[str, float] = {}
        self.current: str | None = None
        self.started = time.perf_counter()

    def start(self, index: int) -> Callable[[str], None]:
        """Start stage ``index`` of :data:`STAGES`; returns the callback of its steps."""
        self.finish()
        self.current, text = STAGES[index]
        self.started = time.perf_counter()
        self.progress(text, None)
        return lambda step: self.progress(text, step)

    def finish(self) -> None:
        if self.current is not None:
            self.seconds[self.current] = time.perf_counter() - self.started
            self.current = None


def run_demo(
    out: str | Path,
    *,
    robot: str = DEFAULT_ROBOT,
    n: int = 3000,
    effects: str = "random:3",
    unmodelled: bool = True,
    noise_mm: float = 0.02,
    noise_deg: float = 0.002,
    payload: float = 20.0,
    epochs: int = 100,
    seed: int = 7,
    progress: Progress | None = None,
) -> DemoResult:
    """Run the demo and write its files and ``out/report.md``.

    Args:
        out: output folder (created).
        robot: shipped robot name or URDF path.
        n: simulated measured poses; the last quarter is held out of every step.
        effects: hidden vocabulary effects (simulate's ``--effects`` syntax).
        unmodelled: add the hardening spring no vocabulary effect can fit.
        noise_mm, noise_deg: measurement noise std [mm], [deg].
        payload: mass at the flange [kg].
        epochs: training epochs of the residual networks.
        seed: seed of the campaign (effects, poses, noise, frames), the diagnosis split
            and the training.
        progress: called as ``progress(stage, step)``: ``step`` None when ``stage`` (the
            text of one of :data:`STAGES`) starts, else the inner step under way.
    """
    started = time.perf_counter()
    out = Path(out)  # made once the campaign is drawn: a refused input leaves no folder
    nominal_robot = Robot.from_urdf(robot)
    nominal_robot.requires_grad_(False)
    stages = _Stages(progress)

    stages.start(0)
    hidden = hidden_effects(
        nominal_robot, effects, seed=seed, payload=payload, unmodelled=unmodelled
    )
    sim = {"noise_mm": noise_mm, "noise_deg": noise_deg, "payload": payload, "seed": seed}
    data, truth = _simulate(out, nominal_robot, n, hidden, sim)
    split = _Split(data)
    settings = DiagnosisSettings(seed=seed)  # hybrid-pk diagnose / calibrate's defaults
    diag, diag_report = _diagnose(out, nominal_robot, split, settings, stages.start(1))
    truth["effects"] = mark_unseen(diag.nominal_model, split.calib, split.cond, truth["effects"])
    model, nominal = _calibrate(out, nominal_robot, diag, split, settings, stages.start(2))
    trained = _train(out, model, split, epochs, seed, stages.start(3))
    stages.start(4)
    evaluation_report, results = _evaluate(out, nominal, model, trained.hybrid, split)
    stages.start(5)
    ik = _ik(out, nominal_robot, model, trained.hybrid, split.test, split.test_cond)
    stages.start(6)
    report = write_demo_report(
        out, truth, diag, results, ik, diag_report, evaluation_report, trained,
        dict(stages.seconds), time.perf_counter() - started,
    )  # fmt: skip
    stages.finish()
    return DemoResult(
        out=out,
        report=report,
        robot=nominal_robot.name,
        n_rows=data.n,
        n_test=split.test.n,
        truth=truth,
        diagnosis=diag,
        evaluation=results,
        ik={k: v for k, v in ik.items() if k != "frame"},
        stage_seconds=stages.seconds,
        seconds=time.perf_counter() - started,
    )


def _simulate(out: Path, robot: Robot, n: int, hidden, sim: dict):
    """The campaign, its table and its truth JSON (effects revealed only at the end)."""
    vocabulary, unmodelled = hidden
    data, truth = simulate_campaign(robot, n, vocabulary + unmodelled, **sim)
    truth["effects"] = [effect_entry(e) for e in vocabulary]
    truth["unmodelled"] = [{**effect_entry(e), "tau0_Nm": e.tau0} for e in unmodelled]
    out.mkdir(parents=True, exist_ok=True)
    write_table(out / "campaign.csv", data)
    write_text(out / "campaign.csv.truth.json", json.dumps(truth, indent=2))
    return data, truth


class _Split:
    """Calibration rows (first three quarters) and held-out rows (last quarter), never
    seen by diagnosis, calibration or training."""

    def __init__(self, data: MeasuredData) -> None:
        n_test = data.n // 4
        calib_rows = torch.arange(0, data.n - n_test)
        test_rows = torch.arange(data.n - n_test, data.n)
        cond = conditions_from_data(data)
        self.calib, self.test = data.subset(calib_rows), data.subset(test_rows)
        self.cond, self.test_cond = cond.subset(calib_rows), cond.subset(test_rows)


def _diagnose(out: Path, robot: Robot, split: _Split, settings: DiagnosisSettings, say):
    """The diagnosis of the calibration rows, its JSON and its report with the plots."""
    diag = diagnose(robot, split.calib, progress=say, **settings.keywords())
    write_text(out / "diagnosis.json", json.dumps(diag.to_json(), indent=2, default=str))
    say("writing the diagnosis report")
    return diag, write_diagnosis_report(diag, split.calib, robot, out / "diagnosis", say)


def _calibrate(out: Path, robot: Robot, diag: Diagnosis, split: _Split, settings, say):
    """The extended model of the named causes and the nominal model, frames and
    effects fitted on the calibration rows with the diagnosis' ``settings``."""
    labels = cause_labels(diag)
    say(f"frames + {len(labels)} effect(s): {', '.join(labels) or 'none'}; nominal: frames only")
    result = calibrate(robot, split.calib, labels, settings=settings)  # hybrid-pk calibrate's
    model, nominal = result.model, result.nominal
    model.requires_grad_(False)
    save_model(out / "model.pt", model, metadata={"source": "hybrid-pk demo"})
    nominal.requires_grad_(False)
    return model, nominal


def _train(out: Path, model: ExtendedModel, split: _Split, epochs: int, seed: int, say):
    from hybrid_pk.training import train_hybrid  # Lightning: imported when needed

    trained = train_hybrid(
        split.calib,
        model,
        split.cond,
        preset_name="joints",  # its random rows cover the workspace: MLPs on every joint
        max_epochs=epochs,
        seed=seed,
        datamodule={"batch_size": 128},  # more steps on a small campaign
        logdir=out / "tensorboard",
        progress=say,
    )
    save_hybrid(out / "hybrid.pt", trained.hybrid, metadata={"source": "hybrid-pk demo"})
    return trained


def _evaluate(out: Path, nominal, model, hybrid, split: _Split):
    test, cond = split.test, split.test_cond
    with torch.no_grad():
        predictions = {
            "nominal + frames": nominal(test.q, cond),
            "extended (physics)": model(test.q, cond),
            "hybrid (physics + networks)": hybrid(test.q, cond),
        }
    report, results = write_evaluation_report(
        out / "evaluation",
        test,
        predictions,
        title="Held-out evaluation",
        intro=f"{test.n} rows of the campaign that no diagnosis, calibration or training step saw.",
        joint_types=model.robot.joint_types,
    )
    write_text(out / "evaluation.json", json.dumps(results, indent=2))
    return report, results


def _ik(out: Path, robot: Robot, model, hybrid, test: MeasuredData, cond: Conditions) -> dict:
    """All IK solutions on the hybrid model for the first held-out measured poses."""
    rows = torch.arange(min(IK_TARGETS, test.n))
    targets = test.T_measured()[rows]
    write_table(out / "ik_targets.csv", test.subset(rows))
    cheap = ExtendedModel(robot, [], base=model.base.matrix()[0], tool=model.tool.matrix()[0])
    cheap.requires_grad_(False)
    started = time.perf_counter()
    result = solve_ik_two_stage(
        cheap, hybrid, targets, seeds=64, cond=cond.subset(rows), robot=robot
    )
    seconds = time.perf_counter() - started
    frame = result.to_frame()
    write_frame(out / "ik_solutions.csv", frame)
    valid = result.valid
    return {
        "targets": int(rows.numel()),
        "solutions": int(valid.sum()),
        "per_target": [int(c) for c in result.counts.reshape(-1)],
        "failed": int(result.n_failed),
        "max_position_mm": float(result.position_error_mm[valid].max()) if valid.any() else 0.0,
        "max_orientation_deg": (
            float(result.orientation_error_deg[valid].max()) if valid.any() else 0.0
        ),
        "seconds": seconds,
        "frame": frame,
    }
