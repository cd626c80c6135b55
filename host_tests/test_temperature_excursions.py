"""Temperature screen, excursions (fit/samples.py TEMP_SPAN_C, BOARD_TAU_MIN_S): a block of
readings a board cannot reach and leave in its time steps is rejected and counted; real
changes -- chamber steps, ramps, holds recorded across logging gaps, a thermal shock at
1 Hz -- are kept."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from generator.fit.samples import (BOARD_TAU_MIN_S, TEMP_SPAN_C, _possible_change_C,
                                   screen_temperatures)


def _ramp(n, dt_s, rng, rate_C_per_s=0.001, start_C=-20.0):
    time_s = np.arange(n) * dt_s
    return time_s, np.round(start_C + rate_C_per_s * time_s + rng.normal(0, 0.05, n), 2)


def test_possible_change_is_the_first_order_lag():
    dt = np.array([0.0, 1.0, 60.0, 3600.0])
    want = TEMP_SPAN_C * (1 - np.exp(-dt / BOARD_TAU_MIN_S))
    assert np.allclose(_possible_change_C(dt), want)
    assert np.isinf(_possible_change_C(np.array([np.nan, -1.0]))).all()


@pytest.mark.parametrize("dt_s", [1.0, 10.0, 60.0])
def test_block_of_corrupt_readings_rejected(dt_s):
    """20 rows at 120 degC inside a slow ramp near 0 degC (the reviewer's case, at 60 s)."""
    time_s, t = _ramp(3000, dt_s, np.random.default_rng(1), rate_C_per_s=0.02 / dt_s)
    t[1500:1520] = 120.0
    ok, counts = screen_temperatures(t, None, time_s)
    assert counts == {"impossible": 0, "outlying": 20}
    assert not ok[1500:1520].any() and ok.sum() == len(t) - 20
    # without the times only the running-median spike test runs: the block stays
    assert screen_temperatures(t)[1]["outlying"] == 0


def test_holds_recorded_across_gaps_kept():
    """A chamber logged only at its holds: 25, 85 (short), 25 degC, an hour apart."""
    rng = np.random.default_rng(2)
    t = np.concatenate([np.full(300, 25.0), np.full(50, 85.0), np.full(300, 25.0)])
    t = t + rng.normal(0, 0.05, len(t))
    time_s = np.concatenate([np.arange(300), 3600 + np.arange(50), 7200 + np.arange(300)])
    assert screen_temperatures(t, None, time_s.astype(float))[1]["outlying"] == 0
    # the same readings one second apart cannot be a board's
    assert screen_temperatures(t, None, np.arange(len(t), dtype=float))[1]["outlying"] == 50


def test_thermal_shock_at_one_hertz_kept():
    """A board (tau 5 min) moved between -40 and +85 degC chambers, 20 min dwells, sampled
    at 1 Hz: every change is one the board makes, nothing is rejected."""
    from generator.campaign.board_thermal import first_order_lag
    time_s = np.arange(4 * 1200, dtype=float)
    chamber = np.where((time_s // 1200) % 2 == 0, -40.0, 85.0)
    t = np.round(first_order_lag(time_s, chamber, BOARD_TAU_MIN_S), 2)
    assert screen_temperatures(t, None, time_s)[1] == {"impossible": 0, "outlying": 0}


def test_step_without_return_between_equal_stretches_kept():
    """One impossible jump between stretches of the same length: which side is wrong is
    unknown, nothing is rejected."""
    t = np.concatenate([np.full(400, 25.0), np.full(400, -20.0)])
    t = t + np.random.default_rng(3).normal(0, 0.05, len(t))
    assert screen_temperatures(t, None, np.arange(800, dtype=float))[1]["outlying"] == 0


@pytest.mark.parametrize("rows", [1, 3, 20])
@pytest.mark.parametrize("where", ["start", "end"])
@pytest.mark.parametrize("value_C", [85.0, 120.0, -70.0])
def test_block_at_a_file_edge_rejected(rows, where, value_C):
    """A power-on value in the first rows, a block in the last: a jump on one side, the
    file's edge on the other, shorter than the stretch across the jump."""
    time_s, t = _ramp(3000, 60.0, np.random.default_rng(4), rate_C_per_s=0.005 / 60.0,
                      start_C=-5.0)                     # -5 .. 10 degC over 50 h
    sl = slice(0, rows) if where == "start" else slice(len(t) - rows, len(t))
    t[sl] = value_C
    ok, counts = screen_temperatures(t, None, time_s)
    assert counts["outlying"] == rows and not ok[sl].any()


@pytest.mark.parametrize("rows", [1, 3, 20])
def test_block_right_after_a_gap_rejected(rows):
    """Logging stops for 960 s, resumes with a few rows at 85 degC, then drops back to the
    ramp within 60 s: the way out is a jump the board cannot make, the way in crosses the
    gap; the block is shorter than what follows."""
    rng = np.random.default_rng(5)
    time_s = np.concatenate([np.arange(1000) * 60.0, 1000 * 60.0 + 960 + np.arange(1000) * 60.0])
    t = np.round(-5.0 + 0.0003 * time_s + rng.normal(0, 0.05, len(time_s)), 2)
    t[1000:1000 + rows] = 85.0
    ok, counts = screen_temperatures(t, None, time_s)
    assert counts["outlying"] == rows and not ok[1000:1000 + rows].any()


@settings(max_examples=40, deadline=None)
@given(n=st.integers(200, 2000), dt_s=st.sampled_from([0.1, 1.0, 10.0, 60.0]),
       rate=st.floats(-0.01, 0.01), seed=st.integers(0, 2 ** 16))
def test_clean_ramps_never_rejected(n, dt_s, rate, seed):
    """Clean slow ramps (|rate| <= 0.01 degC/s, a chamber's; inside -40..85 degC) at any
    sampling: no rejection."""
    rng = np.random.default_rng(seed)
    rate = float(np.clip(rate, -60.0 / (n * dt_s), 60.0 / (n * dt_s)))
    time_s, t = _ramp(n, dt_s, rng, rate_C_per_s=rate, start_C=rng.uniform(-20, 20))
    assert screen_temperatures(t, None, time_s)[1] == {"impossible": 0, "outlying": 0}


def test_fit_counts_the_excursion(tmp_path):
    """Through the fit: a 20-row block of one sensor's temperature at 120 degC is counted as
    outlying and does not move the calibrated range."""
    from generator.fit.thermal import fit_unit
    from generator.io.telemetry_csv import read_telemetry
    from generator.io.unitfile import load_unit
    from pathlib import Path
    shared = Path(__file__).resolve().parents[2] / "shared" / "data" / "samsat_fm1"
    if not (shared / "rotation.csv").exists():
        pytest.skip("shared data not present")
    unit = load_unit(shared / "unit.toml")
    lines = (shared / "rotation.csv").read_text().splitlines()
    head = next(i for i, ln in enumerate(lines) if ln and not ln.startswith("#"))
    cols = lines[head].split(",")
    tcol = next(i for i, c in enumerate(cols) if c.endswith("temp_C"))
    name = cols[tcol][: -len("_temp_C")]
    mid = head + 1 + (len(lines) - head - 1) // 2
    for k in range(mid, mid + 20):
        cells = lines[k].split(",")
        cells[tcol] = "120.0"
        lines[k] = ",".join(cells)
    bad = tmp_path / "rotation_block.csv"
    bad.write_text("\n".join(lines) + "\n")
    base = fit_unit(unit, [read_telemetry(shared / "rotation.csv", unit)])
    cals = fit_unit(unit, [read_telemetry(bad, unit)])
    sensor = next(s.name for s in unit.sensors if s.name in cals and name.startswith(s.name))
    st_bad, st0 = cals[sensor].stats, base[sensor].stats
    assert st_bad["files"][0]["temperature_rejected"]["outlying"] == 20
    assert st_bad["calibrated_range_C"] == st0["calibrated_range_C"]


def test_constant_level_block_needs_the_parts_step():
    """A temperature that never moves but for a corrupt block: the data alone give no
    reporting step (their only changes are the block's jumps), the part's stated step does."""
    t = np.full(1000, 23.7)
    t[500:520] = 120.0
    time_s = np.arange(1000, dtype=float)
    assert screen_temperatures(t, None, time_s, temp_lsb_C=0.7)[1]["outlying"] == 20
    assert screen_temperatures(t, None, time_s)[1]["outlying"] == 0
