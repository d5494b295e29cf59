"""``hybrid-pk export`` of what a file holds besides the geometry: a thermal expansion
(the file holds the geometry at 20 °C, so the expansion away from it is listed as not
carried, with its size; without temperatures per kelvin, not a crash) and the mounting
(gravity: said, with the --gravity that gives it back)."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
import torch

from hybrid_pk.cli.main import main
from hybrid_pk.effects import Conditions, ExtendedModel, make_effect
from hybrid_pk.io.model_file import save_model

pytestmark = pytest.mark.usefixtures("one_thread")

ALPHA = 1.2e-5  # [1/K] steel


def _model(rx160, tmp_path: Path) -> tuple[ExtendedModel, Path]:
    effects = [
        make_effect(rx160, "thermal_expansion", ALPHA),
        make_effect(rx160, "joint_offset:joint_2", 5e-4),
    ]
    model = ExtendedModel(rx160, effects)
    model.requires_grad_(False)
    return model, save_model(tmp_path / "thermal.pt", model)


def _line(printed: str, label: str) -> str:
    return next(line for line in printed.splitlines() if line.strip().startswith(label))


def test_thermal_expansion_listed_at_the_data_temperatures(rx160, tmp_path, capsys):
    """With data at 28 °C: the expansion is listed, sized as the move of the full model
    without it at those rows; the file header says the geometry is written at 20 °C."""
    model, path = _model(rx160, tmp_path)
    q = rx160.sample_q(40, torch.Generator().manual_seed(2))
    with torch.no_grad():
        p = rx160.fk(q)[:, :3, 3].numpy()
    table = pd.DataFrame(q.numpy(), columns=rx160.joint_names)
    table[["x", "y", "z"]] = p
    table["temperature"] = 28.0
    data = tmp_path / "warm.csv"
    table.to_csv(data, index=False)
    out = tmp_path / "t.yaml"
    argv = ["export", str(path), "--format", "dh", "--data", str(data), "--out", str(out)]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    line = _line(printed, "thermal_expansion")
    assert "20 °C" in line, line
    temp = torch.full((40,), 28.0, dtype=torch.float64)
    cond = Conditions(temperature=temp)
    others = model.with_effects([e for e in model.effects if e.kind != "thermal_expansion"])
    with torch.no_grad():
        moved = (model(q, cond) - others(q, cond))[:, :3, 3].norm(dim=-1).max() * 1000
    assert float(moved) > 0.05  # 8 K x 1.2e-5 over a metre and more
    assert f"{float(moved):.4g} mm max" in line, line
    assert "thermal_expansion" in out.read_text(encoding="utf-8")


def test_thermal_expansion_without_temperatures_is_sized_per_kelvin(rx160, tmp_path, capsys):
    """No data found (the calibration files moved away): the export still writes the
    file (before: 'thermal_expansion needs the temperature of each row'), and sizes the
    expansion per kelvin from 20 °C."""
    _, path = _model(rx160, tmp_path)
    out = tmp_path / "t.yaml"
    assert main(["export", str(path), "--format", "mdh", "--out", str(out)]) == 0
    line = _line(capsys.readouterr().out, "thermal_expansion")
    assert "per K" in line, line
    assert out.is_file()


def test_a_mounted_model_says_its_mounting_is_not_in_the_file(rx160, tmp_path, capsys):
    """A ceiling-mounted model (gravity +z in the root frame): every format says the
    mounting is not carried and which --gravity gives it back (before: nothing, and the
    DH table's masses read back as an upright robot's statics); an upright model has no
    such line."""
    from hybrid_pk.effects import Gravity

    soft = [make_effect(rx160, "joint_compliance:joint_2", 2e-6)]
    for gravity, said in ((Gravity((0.0, 0.0, 9.81)), True), (None, False)):
        path = save_model(tmp_path / "m.pt", ExtendedModel(rx160, soft, gravity=gravity))
        for fmt, suffix in (("dh", "yaml"), ("urdf", "urdf")):
            out = tmp_path / f"t.{suffix}"
            assert main(["export", str(path), "--format", fmt, "--out", str(out)]) == 0
            printed = capsys.readouterr().out
            assert ("mounting not carried" in printed) == said, printed
            assert ("--gravity 0,0,9.81" in printed) == said


def test_calibration_data_not_found_is_named(rx160, tmp_path, capsys):
    """export run where the model's calibration data (recorded as given to calibrate)
    cannot be found: the summary names the file and --data (before: '(no data found)'
    though the model names its data)."""
    model = ExtendedModel(rx160, [make_effect(rx160, "joint_compliance:joint_2", 2e-6)])
    path = save_model(tmp_path / "m.pt", model, metadata={"data": ["gone/campaign.csv"]})
    assert main(["export", str(path), "--format", "dh", "--out", str(tmp_path / "t.yaml")]) == 0
    printed = capsys.readouterr().out
    assert "its calibration data gone/campaign.csv not found from here; --data" in printed
