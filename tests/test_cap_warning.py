"""The capped-search warning counts the causes taken out after the cap, so a user who
reads "its limit of 8 causes" beside seven named causes sees why (steps as recorded in
the diagnosis JSON of both UR10 series, --frames-per-file, every 10th / 5th row)."""

from __future__ import annotations

from hybrid_pk.calibration.diagnosis.gains import cap_warnings


def _step(label: str, **extra) -> dict:
    return {"candidate": label, "score_F": 173.0, "score_p": 5.2e-74, "accepted": True, **extra}


def test_the_cap_warning_counts_causes_taken_out_after_it():
    named = [_step(f"link_length:joint_{i}") for i in range(8)]
    capped = _step("axis_misalignment:elbow_joint", accepted=False, capped=8)
    settled = {"candidate": "cyclic_error_20:shoulder_pan_joint", "removed": True}
    (warning,) = cap_warnings([*named, capped, settled])
    assert "its limit of 8 causes (1 of them taken out after it: 7 named):" in warning["why"]
    (plain,) = cap_warnings([*named, capped])
    assert "its limit of 8 causes: the data carry more" in plain["why"]
    # a cause taken out before the cap does not count against it
    (early,) = cap_warnings([settled, *named, capped])
    assert "taken out" not in early["why"]
