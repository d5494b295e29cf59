"""An interrupted training continues from its last checkpoint (``hybrid-pk train
--resume``, :mod:`hybrid_pk.training.resume`)."""

from __future__ import annotations

import itertools
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from hybrid_pk.cli.main import main
from hybrid_pk.data import write_table
from hybrid_pk.effects import ExtendedModel
from hybrid_pk.errors import HybridPKError, TrainingInterrupted
from hybrid_pk.io.model_file import load_model, save_model
from hybrid_pk.simulate import simulate_campaign
from hybrid_pk.training import HybridDataModule, HybridLitModule, make_trainer, preset, train_hybrid
from hybrid_pk.training.presets import full_model_settings
from tests.helpers import default_sigint

REPO = Path(__file__).resolve().parents[1]
NETS = {
    "position_net": "mlp:16x2",
    "orientation_net": "mlp:16x2",
    "refine_net": "mlp:8x2",
    "local_net": "mlp:8x1",
}
EPOCHS = 6


@pytest.fixture(scope="module")
def campaign(rx160):
    data, _ = simulate_campaign(
        rx160, 200, "joint_offset:joint_2=8e-4; gear_ratio:joint_3=3e-4", noise_mm=0.01,
        known_frames=True, seed=4,
    )  # fmt: skip
    return data


def _train(data, robot, logdir, **kwargs):
    kwargs = {"model": NETS, "datamodule": {"batch_size": 32}, "seed": 1, **kwargs}
    return train_hybrid(data, ExtendedModel(robot), logdir=logdir, **kwargs)


def _interrupt_after(epoch: int | None, line: str | None = None):
    """A progress callable that presses Ctrl-C (raises KeyboardInterrupt, as Python's
    SIGINT handler does) when epoch ``epoch`` ends, before its checkpoint, or at the
    progress ``line`` starting so."""

    def say(text: str) -> None:
        if text.startswith(line or f"epoch {epoch}/"):
            raise KeyboardInterrupt

    return say


def _scalars(logdir, tag: str) -> dict[int, float]:
    events = EventAccumulator(str(logdir), size_guidance={"scalars": 0, "images": 0})
    events.Reload()
    return {e.step: e.value for e in events.Scalars(tag)}


@pytest.fixture(scope="module")
def runs(campaign, rx160, tmp_path_factory):
    """One uninterrupted run, and one interrupted in epoch 3 and resumed."""
    full = _train(
        campaign, rx160, tmp_path_factory.mktemp("full"), max_epochs=EPOCHS, progress=False
    )
    cut = tmp_path_factory.mktemp("cut")
    with pytest.raises(TrainingInterrupted) as stopped:
        _train(campaign, rx160, cut, max_epochs=EPOCHS, progress=_interrupt_after(3))
    lines: list[str] = []
    resumed = _train(campaign, rx160, cut, resume=True, progress=lines.append)
    return full, stopped.value, resumed, lines, cut


def test_ctrl_c_keeps_the_last_epochs_checkpoint_and_says_how_to_resume(runs):
    _, stopped, _, _, cut = runs
    last = cut / "version_0" / "checkpoints" / "last.ckpt"
    assert stopped.exit_code == 130
    assert str(stopped) == (
        f"interrupted (Ctrl-C) in epoch 3/{EPOCHS}; kept {last} (2 of {EPOCHS} epochs done): "
        "rerun the same command with --resume to continue"
    )


def test_a_resumed_run_ends_where_an_uninterrupted_one_does(runs):
    # before: no resume; Lightning's ckpt_path restored neither the networks' best
    # states nor the random state of the next epoch's shuffle
    full, _, resumed, lines, cut = runs
    assert lines[0] == f"resuming {cut}/version_0/checkpoints/last.ckpt: 2 of {EPOCHS} epochs done"
    assert [t.split(",")[0] for t in lines if t.startswith("epoch ")] == [
        f"epoch {k}/{EPOCHS}" for k in range(3, EPOCHS + 1)
    ]
    assert resumed.epochs == full.epochs == EPOCHS
    assert resumed.resumed == (f"{cut}/version_0/checkpoints/last.ckpt", 2)
    assert resumed.best == full.best
    assert resumed.final == full.final
    a, b = full.hybrid.state_dict(), resumed.hybrid.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    # the curves go on in the same version folder, epoch by epoch as the full run's
    assert resumed.logdir == str(cut / "version_0")
    events = EventAccumulator(str(resumed.logdir), size_guidance={"scalars": 0})
    events.Reload()
    # epoch 3, logged before the Ctrl-C and run again, counts once (TensorBoard's purge)
    logged = [(e.step, e.value) for e in events.Scalars("val/position_mm_mean")]
    assert logged == list(_scalars(full.logdir, "val/position_mm_mean").items())


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"max_epochs": EPOCHS + 2}, "one-cycle learning rate was built for 6 epochs"),
        ({"seed": 2}, "belongs to a run on other rows or another base model"),
        ({"model": {**NETS, "lr": 0.01}}, "other settings: lr 0.003 (this run 0.01)"),
        ({"datamodule": {"batch_size": 16}}, "batches of 32 rows in 1 process(es), this run 16"),
    ],
)
def test_resume_refuses_a_checkpoint_of_another_run(runs, campaign, rx160, change, words):
    with pytest.raises(HybridPKError, match="--resume: ") as refused:
        _train(campaign, rx160, runs[4], resume=True, progress=False, **change)
    assert words in str(refused.value)
    assert "\n" not in str(refused.value)


def test_the_last_checkpoint_is_the_last_epochs_even_without_a_gain(rx160, tmp_path):
    # before: Lightning's save_last wrote last.ckpt only when val/score improved, so a
    # resume went back to the last improving epoch (docs' run: 2 epochs, "resumed after 1")
    # noise alone: the networks learn nothing that carries to the validation rows
    noise, _ = simulate_campaign(rx160, 200, "", noise_mm=0.02, known_frames=True, seed=4)
    result = _train(noise, rx160, tmp_path, max_epochs=EPOCHS, progress=False)
    score = list(_scalars(result.logdir, "val/score").values())
    assert any(b >= a for a, b in itertools.pairwise(score))  # an epoch without gain
    last = torch.load(Path(result.logdir, "checkpoints", "last.ckpt"), weights_only=False)
    assert last["epoch"] + 1 == EPOCHS


def test_lightning_ckpt_path_with_more_epochs_is_refused_in_one_line(runs, campaign, rx160):
    # before: Lightning's own resume (LightningCLI fit --ckpt_path) with a larger
    # max_epochs failed in OneCycleLR ("Tried to step 37 times. The specified number of
    # total steps is 36")
    dm = HybridDataModule.from_measured(
        campaign, ExtendedModel(rx160), seed=1, batch_size=32, val_fraction=0.1
    )
    module = HybridLitModule(**full_model_settings({**preset("fast")["model"], **NETS}))
    trainer = make_trainer(max_epochs=EPOCHS + 2, progress=False)
    last = runs[4] / "version_0" / "checkpoints" / "last.ckpt"
    with pytest.raises(HybridPKError, match=r"built for 6 epochs .* resume with max_epochs 6"):
        trainer.fit(module, datamodule=dm, ckpt_path=last)


def test_a_checkpoint_loads_into_a_module_outside_a_fit(runs):
    # before: on_load_checkpoint asked self.trainer, which raises outside a fit
    last = torch.load(runs[4] / "version_0" / "checkpoints" / "last.ckpt", weights_only=False)
    module = HybridLitModule(**last["hyper_parameters"])
    module.on_load_checkpoint(last)
    assert set(module.best_metrics()) == {"position_mm", "orientation_deg"}


def test_resume_with_nothing_to_resume_is_one_line(campaign, rx160, tmp_path):
    with pytest.raises(HybridPKError, match=r"nothing to resume in .*: run without --resume"):
        _train(campaign, rx160, tmp_path, resume=True, progress=False)
    with pytest.raises(HybridPKError, match="--resume needs the --logdir DIR"):
        _train(campaign, rx160, None, resume=True, progress=False)


def test_resume_takes_the_newest_run_not_an_older_one(runs, campaign, rx160, tmp_path):
    # before: the newest run with a checkpoint, here the older one (version_0), was
    # resumed when the newest (version_1) stopped before its first epoch ended
    logdir = tmp_path / "logs"
    shutil.copytree(runs[4], logdir)
    (logdir / "version_1").mkdir()
    with pytest.raises(HybridPKError, match=r"nothing to resume in .*version_1, the newest run"):
        _train(campaign, rx160, logdir, resume=True, progress=False)


def test_without_a_schedule_a_resumed_run_may_train_longer(campaign, rx160, tmp_path):
    model = {**NETS, "optimizer": "adam", "scheduler": "none"}
    first = _train(campaign, rx160, tmp_path, model=model, max_epochs=2, progress=False)
    longer = _train(
        campaign, rx160, tmp_path, model=model, max_epochs=4, resume=True, progress=False
    )
    assert (first.epochs, longer.epochs, longer.resumed[1]) == (2, 4, 2)
    assert len(_scalars(longer.logdir, "val/position_mm_mean")) == 4


def test_ctrl_c_in_the_probe_fits_resumes_to_them_and_a_cut_checkpoint_is_one_line(
    campaign, rx160, tmp_path
):
    stop = _interrupt_after(None, "blocked hold-out 2/")
    with pytest.raises(TrainingInterrupted, match=r"in the blocked hold-out's probe fits") as cut:
        _train(campaign, rx160, tmp_path, max_epochs=2, progress=stop)
    assert "(2 of 2 epochs done): rerun the same command with --resume" in str(cut.value)
    lines: list[str] = []
    resumed = _train(campaign, rx160, tmp_path, resume=True, progress=lines.append)
    assert lines[0].endswith("last.ckpt: 2 of 2 epochs done")
    assert [t.split(":")[0] for t in lines[1:]] == ["blocked hold-out 1/2", "blocked hold-out 2/2"]
    assert resumed.blocked
    assert resumed.resumed[1] == 2
    last = tmp_path / "version_0" / "checkpoints" / "last.ckpt"
    last.write_bytes(last.read_bytes()[:1000])  # a job killed while writing it
    with pytest.raises(HybridPKError, match=r"last.ckpt cannot be read \(") as refused:
        _train(campaign, rx160, tmp_path, resume=True, progress=False)
    assert "\n" not in str(refused.value)
    assert len(str(refused.value)) < 400


def test_a_run_stopped_early_resumes_to_no_more_epochs(rx160, tmp_path):
    # before: the resumed run trained one epoch past the early stop (4 against 3)
    noise, _ = simulate_campaign(rx160, 200, "", noise_mm=0.02, known_frames=True, seed=4)
    model = {**NETS, "scheduler": "none", "blocked": False}
    kwargs = {"model": model, "max_epochs": 20, "patience": 2, "progress": False}
    first = _train(noise, rx160, tmp_path, **kwargs)
    assert first.epochs < 20  # stopped early
    resumed = _train(noise, rx160, tmp_path, resume=True, **kwargs)
    assert resumed.epochs == first.epochs
    assert resumed.best == first.best


def test_ctrl_c_without_logdir_says_nothing_was_kept(campaign, rx160):
    with pytest.raises(TrainingInterrupted, match=r"no checkpoint kept .*--logdir DIR"):
        _train(campaign, rx160, None, max_epochs=EPOCHS, progress=_interrupt_after(1))


class _CtrlCInDestructor:
    """Sends this process SIGINT from its ``__del__``, where Python drops the
    ``KeyboardInterrupt`` its handler raises ("Exception ignored in ...")."""

    def __del__(self) -> None:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.5)  # the handler runs in here (the signal cuts the sleep short)


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the drop itself
def test_ctrl_c_dropped_in_a_destructor_still_stops_the_training(campaign, rx160, tmp_path):
    # before: the interrupt raised inside a __del__ was dropped and the training ran on
    # to its end (a CI run of the CLI test below ended with exit code 0); and after an
    # interrupt Lightning left SIGINT ignored for the rest of the process
    def say(text: str) -> None:
        if text.startswith("epoch 2/"):
            _CtrlCInDestructor()  # dropped at once: its __del__ runs here

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal
    try:
        with pytest.raises(TrainingInterrupted, match=r"interrupted \(Ctrl-C\) in epoch 3/6"):
            _train(campaign, rx160, tmp_path, max_epochs=EPOCHS, progress=say)
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, previous)


# ----------------------------------------------------------------------------- CLI


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    env["OMP_NUM_THREADS"] = "1"
    return env


@pytest.mark.parametrize(
    ("sig", "code", "name"), [(signal.SIGINT, 130, "Ctrl-C"), (signal.SIGTERM, 143, "SIGTERM")]
)
def test_cli_interrupted_by_a_signal_resumes(campaign, rx160, tmp_path, capsys, sig, code, name):
    # before: Ctrl-C ended with "exit 1" and no word, SIGTERM with exit code 0 and no
    # model file; and there was no --resume
    table = tmp_path / "campaign.csv"
    write_table(table, campaign)
    base = save_model(tmp_path / "base.pt", ExtendedModel(rx160))
    out, logdir = tmp_path / "hybrid.pt", tmp_path / "logs"
    args = [
        "train", str(table), "--model", str(base), "--out", str(out), "--logdir", str(logdir),
        "--epochs", "40", "--batch-size", "32", "--seed", "1", "--no-blocked",
        *[f"--{k.replace('_', '-')}={v}" for k, v in NETS.items()],
    ]  # fmt: skip
    proc = subprocess.Popen(
        [sys.executable, "-m", "hybrid_pk.cli.main", *args], cwd=tmp_path, env=_env(),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=default_sigint,
    )  # fmt: skip
    epochs = 0
    for line in proc.stderr:  # the second epoch line: a checkpoint is written
        epochs += "| epoch " in line
        if epochs == 2:
            proc.send_signal(sig)
            break
    err = proc.stderr.read()
    assert proc.wait() == code, err
    assert not out.exists()
    message = err.strip().splitlines()[-1]
    assert message.startswith(f"hybrid-pk train: interrupted ({name}) in epoch "), err
    assert message.endswith("rerun the same command with --resume to continue"), err
    assert main([*args, "--resume", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "40 epochs, resumed after " in printed
    training = load_model(out).metadata["training"]
    assert training["epochs"] == 40
    assert training["resumed"]["epochs_done"] >= 1
