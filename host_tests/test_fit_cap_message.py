"""A fit refused on its subsample names the cap (review 20e F9b): `--max-samples 13` gave
"reference fit: 13 samples for 48 unknowns", blaming the file. The message now says the
fit took a subsample of the sensor's usable samples and that a larger --max-samples (or 0)
gives it more; a fit of every sample keeps its message as it was."""

from __future__ import annotations

import os

import pytest

from generator.cli import main

FM1 = "/work/shared/data/samsat_fm1"


def _err(capsys, argv):
    rc = main(argv + ["-q"])
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    return rc, lines


def test_a_cap_too_small_is_named(tmp_path, capsys):
    unit, data = os.path.join(FM1, "unit.toml"), os.path.join(FM1, "thermal_12pos.csv")
    if not os.path.exists(data):
        pytest.skip("no shared data")
    rc, lines = _err(capsys, ["fit", unit, data, "-o", str(tmp_path / "o"), "--no-report",
                              "--max-samples", "13"])
    assert rc == 2 and len(lines) == 1, lines
    assert "reference fit: 13 samples for 48 unknowns (sensor 'mmc1' was fitted on a " \
           "subsample of 13 of its 36,000 usable samples, --max-samples 13" in lines[0]
    assert not (tmp_path / "o").exists()


def test_a_fit_of_every_sample_keeps_its_message(tmp_path, capsys):
    """Too few samples in the file itself: the message does not mention a cap."""
    data = os.path.join(FM1, "thermal_12pos.csv")
    if not os.path.exists(data):
        pytest.skip("no shared data")
    lines = open(data).read().splitlines(True)
    head = [ln for ln in lines if ln.startswith("#") or ln.startswith("time_s")]
    short = tmp_path / "short.csv"
    short.write_text("".join(head + lines[len(head):len(head) + 10]))
    rc, err = _err(capsys, ["fit", os.path.join(FM1, "unit.toml"), str(short), "-o",
                            str(tmp_path / "o"), "--no-report"])
    assert rc == 2 and len(err) == 1, err
    assert "--max-samples" not in err[0] and "subsample" not in err[0]
