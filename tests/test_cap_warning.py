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


def test_the_cap_warning_gives_the_gain_it_would_have_entered_on():
    """The next candidate's blocked gain, its standard error over the blocks and the
    margin (what the search's entry rule would have read), not only "the margin"."""
    named = [_step(f"link_length:joint_{i}") for i in range(8)]
    blocked = {"blocked_gain_mm": 0.0371, "blocked_gain_se_mm": 0.0284, "min_gain_mm": 0.00192}
    capped = _step("link_length:wrist_2_joint", accepted=False, capped=8, **blocked)
    (warning,) = cap_warnings([*named, capped])
    assert (
        "gaining 0.0371 ± 0.028 mm (margin 0.00192 mm) on the blocked hold-out" in (warning["why"])
    )
