"""``hybrid-pk train`` refuses bad settings and unusable output paths in one line,
before any data is read or any network trained (a robotics user's tour, 2026-12-05)."""

from __future__ import annotations

import pytest
import torch

from hybrid_pk.cli import train_cmd
from hybrid_pk.cli.main import main
from hybrid_pk.data import write_table
from hybrid_pk.effects import ExtendedModel
from hybrid_pk.errors import HybridPKError
from hybrid_pk.io.hybrid_file import load_hybrid
from hybrid_pk.io.model_file import save_model
from hybrid_pk.simulate import simulate_campaign
from hybrid_pk.training import train_hybrid


@pytest.fixture(scope="module")
def files(rx160, tmp_path_factory):
    # the base model is the truth: what is left is the tracker noise
    data, _ = simulate_campaign(rx160, 40, "none", noise_mm=0.02, known_frames=True, seed=2)
    folder = tmp_path_factory.mktemp("train_checks")
    table = folder / "campaign.csv"
    write_table(table, data)
    return data, table, save_model(folder / "base.pt", ExtendedModel(rx160))


@pytest.fixture
def no_training(monkeypatch):
    """A training that is reached fails the test: the checks come first."""

    def refuse(*args, **kwargs):
        raise AssertionError("trained although the input was bad")

    monkeypatch.setattr(train_cmd, "train_job", refuse)


@pytest.mark.parametrize(
    ("flags", "named"),
    [
        (["--epochs", "0"], "--epochs"),  # before: 0 epochs, untrained networks written
        (["--epochs", "-1"], "--epochs"),  # before: OverflowError, an 'internal error'
        (["--batch-size", "0"], "--batch-size"),  # before: ZeroDivisionError
        (["--patience", "-2"], "--patience"),  # before: accepted without a word
        (["--lr", "0"], "--lr"),  # before: accepted, the networks never moved
        (["--devices", "0"], "--devices"),  # before: ZeroDivisionError
        # before: refused after the data was read, without the flag's name
        (["--val-fraction", "1.5"], "--val-fraction"),
        (["--strategy", "foo"], "--strategy"),  # before: Lightning's error, after the data
    ],
)
def test_out_of_range_flags_are_one_line_usage_errors(files, tmp_path, capsys, flags, named):
    _, table, base = files
    out = tmp_path / "h.pt"
    with pytest.raises(SystemExit) as stop:  # argparse's usage error
        main(["train", str(table), "--model", str(base), "--out", str(out), *flags])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert stop.value.code == 2
    assert err.startswith("hybrid-pk train: error: argument " + named), err
    assert "internal error" not in err
    assert not out.exists()


def test_a_yaml_with_zero_epochs_is_refused(files, tmp_path, capsys, no_training):
    _, table, base = files
    config = tmp_path / "zero.yaml"
    config.write_text("trainer:\n  max_epochs: 0\n", encoding="utf-8")
    args = ["train", str(table), "--model", str(base), "--config", str(config)]
    code = main([*args, "--out", str(tmp_path / "h.pt")])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert code == 2
    assert "--epochs (epochs): expected at least 1, got 0" in err


def test_train_hybrid_refuses_zero_epochs(files, rx160):
    data, _, _ = files
    with pytest.raises(HybridPKError, match="max_epochs must be at least 1, got 0"):
        train_hybrid(data, ExtendedModel(rx160), max_epochs=0, progress=False)


@pytest.mark.parametrize("flag", ["--out", "--logdir"])
def test_an_output_under_a_file_is_refused_before_training(
    files, tmp_path, capsys, flag, no_training
):
    _, table, base = files
    paths = {"--out": str(tmp_path / "h.pt"), "--logdir": None}
    paths[flag] = str(table / "sub")  # the table is a file: nothing can be made under it
    args = ["train", str(table), "--model", str(base), "--out", paths["--out"]]
    code = main(args + (["--logdir", paths["--logdir"]] if paths["--logdir"] else []))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1
    assert (
        err[0] == f"hybrid-pk train: error: {flag} {table / 'sub'}: {table} is a file, not a folder"
    )


def test_out_an_existing_folder_is_refused_before_training(files, tmp_path, capsys, no_training):
    # before: the whole training ran, then "[Errno 21] Is a directory: '.../.x.abc' -> 'x'"
    _, table, base = files
    code = main(["train", str(table), "--model", str(base), "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err == [f"hybrid-pk train: error: --out {tmp_path} is a folder; give a file name"]


def test_logdir_an_existing_file_is_refused_before_training(files, capsys, no_training):
    _, table, base = files
    code = main(
        ["train", str(table), "--model", str(base), "--out", "x.pt", "--logdir", str(table)]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert (
        err
        == f"hybrid-pk train: error: --logdir {table} is a file; give a folder (it holds several)"
    )


def test_networks_no_epoch_improves_end_at_the_base_model(files, rx160, tmp_path, capsys):
    # The base model is the truth (rows with noise only): every step of a huge learning rate
    # only makes the networks worse. Before: they were kept at their least bad epoch,
    # worse than the base model on the validation rows the summary reports.
    data, table, base = files
    flags = ["--preset", "joints", "--position-net", "mlp:16x2", "--orientation-net", "mlp:16x2"]
    args = ["train", str(table), "--model", str(base), "--out", str(tmp_path / "h.pt")]
    assert main([*args, *flags, "--lr", "50", "--epochs", "2", "--batch-size", "8"]) == 0
    hybrid = load_hybrid(str(tmp_path / "h.pt"))
    with torch.no_grad():
        dp, dw = hybrid.corrections(data.q)
    # zero output layers: nothing left but rounding (1e-12 m is a picometre)
    assert float(dp.abs().max()) < 1e-12
    assert float(dw.abs().max()) < 1e-12
    out = capsys.readouterr().out
    assert "note: no epoch of the position networks beat the base model" in out


@pytest.mark.parametrize(
    ("fade", "said"),
    [
        ("0", "(the base model beyond it)"),  # before: "(fading out beyond it)", with no fade
        ("0.1", "(fading out within 0.1 x its size beyond it, then the base model)"),
    ],
)
def test_the_box_line_says_what_lies_beyond_the_box(files, tmp_path, capsys, fade, said):
    _, table, base = files
    args = ["train", str(table), "--model", str(base), "--out", str(tmp_path / "h.pt")]
    nets = ["--preset", "joints", "--position-net", "mlp:8x1", "--orientation-net", "none"]
    assert main([*args, *nets, "--epochs", "1", "--fade", fade]) == 0
    assert f"networks trusted inside the training box {said}: " in capsys.readouterr().out


def test_paper_networks_worse_than_the_base_are_not_said_kept_at_zero(files, tmp_path, capsys):
    # the paper preset starts from random output layers: the base model is no candidate.
    # Before: its summary said such networks were "kept at zero", which they are not
    _, table, base = files
    args = ["train", str(table), "--model", str(base), "--out", str(tmp_path / "h.pt")]
    nets = ["--preset", "paper", "--position-net", "mlp:8x1", "--orientation-net", "none"]
    assert main([*args, *nets, "--epochs", "1", "--seed", "3"]) == 0
    out = capsys.readouterr().out
    assert "warning: the position networks end worse than the base model on the validation" in out
    assert "kept at zero" not in out


def test_an_unknown_key_of_a_yaml_section_is_refused(files, tmp_path, capsys, no_training):
    # before: "internal error: TypeError: HybridLitModule.__init__() got an unexpected
    # keyword argument 'bogus'" after the data were read
    _, table, base = files
    config = tmp_path / "bad.yaml"
    config.write_text("model:\n  lr: 0.01\n  bogus: 3\n", encoding="utf-8")
    args = ["train", str(table), "--model", str(base), "--config", str(config)]
    assert main([*args, "--out", str(tmp_path / "h.pt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert f"error: config {config}: unknown model key(s) bogus; known: position_net," in err[0]


def test_a_gated_stage_says_the_physics_applies_beyond_its_joints(rx160, files, tmp_path, capsys):
    # before: "local+q1: gated (gated); ..." and "1 epochs in"
    _, _, base = files
    data, _ = simulate_campaign(rx160, 200, "none", noise_mm=0.02, known_frames=True, seed=6)
    table = write_table(tmp_path / "rows.csv", data)  # enough rows for the probe fits
    args = ["train", str(table), "--model", str(base), "--out", str(tmp_path / "h.pt")]
    nets = ["--position-net", "mlp:8x1", "--orientation-net", "none", "--local-net", "mlp:4x1"]
    assert main([*args, *nets, "--refine-net", "mlp:4x1", "--epochs", "1"]) == 0
    out = capsys.readouterr().out
    assert "(gated)" not in out
    assert ": gated (the physics beyond its training joints); gated " in out
    assert " 1 epoch in " in out
