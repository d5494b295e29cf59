"""``hybrid-pk import ipa`` given the data set's folder instead of its files."""

from __future__ import annotations

from hybrid_pk.cli.main import main


def test_a_folder_names_the_measurement_files_in_it(tmp_path, capsys):
    # before: "hybrid-pk import: error: DATA: no such file" for a folder that exists
    for series in ("Series_A", "Series_B"):
        (tmp_path / series).mkdir()
        (tmp_path / series / f"measurements_{series[-1]}.csv").write_text("x\n")
    code = main(["import", "ipa", str(tmp_path), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1
    assert "is a folder; give its IPA measurement files: " in err[0]
    assert str(tmp_path / "Series_A" / "measurements_A.csv") in err[0]
    assert str(tmp_path / "Series_B" / "measurements_B.csv") in err[0]
    assert "no such file" not in err[0]
