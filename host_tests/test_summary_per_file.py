"""The summary's verdict holds for every file, not only the RMS over all of them, and a
file the calibration makes worse is a warning (issue 19 review: a campaign doubled in
error under an overall MEETS)."""
from generator.report.summary import verdict


def _fig(after_all, files):
    return {"norm_after_nT": after_all, "per_file": [
        {"file": f"/d/{n}.csv", "n": 100, "norm_before_nT": b, "norm_after_nT": a}
        for n, b, a in files]}


def test_one_file_beyond_the_requirement_fails_the_sensor():
    fig = _fig(90.0, [("thermal", 500.0, 40.0), ("rotation", 300.0, 180.0)])
    v, why = verdict(fig, {"field_error_nT": 150.0})
    assert v == "FAILS" and any("rotation.csv" in w for w in why), why


def test_every_file_within_meets():
    fig = _fig(90.0, [("thermal", 500.0, 40.0), ("rotation", 300.0, 120.0)])
    assert verdict(fig, {"field_error_nT": 150.0}) == ("MEETS", [])
