"""Review 20b of `magcal trace` above its cap (generator.trace.subsample): the cap holds
however the telemetry is cut into files (F3), a cap just under the data keeps about the
cap (F10), a cap below one block is refused (F7). Small synthetic files, no trace run
except for the command-line refusal."""

from __future__ import annotations

import numpy as np
import pytest

from generator.errors import InputError
from generator.io.telemetry import Telemetry
from generator.trace import subsample as sub

from conftest import FM1


SAMSAT = FM1                 # rotation.csv: 4,001 rows


def _file(name, n, t0=0.0):
    ts = t0 + np.arange(n, dtype=float)
    return Telemetry(name, {"time_s": ts, "x": 2.0 * ts}, np.arange(2, n + 2))


def _kept(t) -> int:
    """The rows of a kept file that are samples (its drawn blocks)."""
    return int(t.sample_rows.sum())


def _first(t) -> float:
    return float(t.time_s[t.sample_rows][0])


def _passes(k, n, prefix="p"):
    """k files of n rows at 1 Hz, one after the other in time (passes of one recording)."""
    return [_file(f"{prefix}{i:03d}.csv", n, t0=i * (n + 100.0)) for i in range(k)]


def test_many_short_files_keep_the_cap():
    files = _passes(150, 1_000)
    cap = 20_000
    kept, _, info = sub.subsample_files(files, [], cap)
    L = info["block_rows"]
    assert L == 1_000 and info["samples"] == 150_000
    assert info["traced"] == sum(_kept(t) for t in kept) <= cap
    assert info["blocks"] == cap // L                       # as close to the cap as blocks go
    assert info["files_left_out"] == 150 - len(kept) > 0    # files with no block left out
    assert f"{info['files_left_out']} of 150 files had no block drawn" in info["text"]
    assert all(_kept(t) > 0 for t in kept)
    # one systematic draw over the blocks in order: spread over the whole recording
    starts = np.array([_first(t) for t in kept])
    assert starts.min() < 0.1 * files[-1].time_s[-1] and starts.max() > 0.9 * files[-1].time_s[-1]
    # independent of the files' names
    renamed = [Telemetry(f"q/{i}.csv", t.columns, t.line_numbers) for i, t in enumerate(files)]
    again, _, _ = sub.subsample_files(renamed, [], cap)
    assert [_first(t) for t in again] == list(starts)


def test_kept_blocks_of_a_file_stay_one_file():
    files = _passes(3, 40_000)
    kept, _, info = sub.subsample_files(files, [], 30_000)
    assert len(kept) == 3 and [t.path for t in kept] == [t.path for t in files]
    assert info["traced"] <= 30_000 and info["blocks"] == 30_000 // info["block_rows"]


def test_cap_just_under_the_data_keeps_about_the_cap():
    t = _file("long.csv", 150_000)
    (kept,), _, info = sub.subsample_files([t], [], 149_999)
    L = info["block_rows"]
    # floor(cap / L) whole blocks: within one block of the cap, never above it
    assert 149_999 - L < _kept(kept) <= 149_999, (_kept(kept), L)


def test_holdout_blocks_are_drawn_apart_and_kept():
    data, hold = _passes(4, 30_000), _passes(1, 5_000, prefix="h")
    kd, kh, info = sub.subsample_files(data, hold, 40_000)
    assert len(kh) == 1 and _kept(kh[0]) > 0
    assert info["traced"] <= 40_000


@pytest.mark.parametrize("cap", [1, 999])
def test_cap_below_one_block_is_refused(cap):
    with pytest.raises(InputError, match="--max-samples") as e:
        sub.subsample_files([_file("a.csv", 5_000)], [], cap)
    assert "at least 1,000" in str(e.value)


def test_cap_below_min_blocks_is_said():
    (kept,), _, info = sub.subsample_files([_file("a.csv", 20_000)], [], 5_000)
    assert info["blocks"] == 5 and _kept(kept) == 5_000
    assert f"fewer than the {sub.MIN_BLOCKS}" in info["text"]


def test_cli_cap_below_one_block_exits_2_one_line(tmp_path, capsys):
    from generator.cli import main
    rc = main(["trace", str(SAMSAT / "unit.toml"), str(SAMSAT / "rotation.csv"), "-o",
               str(tmp_path / "out"), "--max-samples", "999"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "--max-samples" in err, err
    assert not (tmp_path / "out").exists()


# --- F1 / F5: what every row says reaches the user -------------------------------------

def test_all_rows_warnings_statistics():
    """The thresholds: a rise of the traced set over the baseline, or of the model over
    every row above the blocks', warns only beyond Z_WARN standard errors."""
    ne = 5_000.0                               # relative s.e. of an RMS: 1 / sqrt(10^4) = 1 %
    same = {"m": {"baseline_rms_nT": 50.0, "traced_rms_nT": 50.0 * (1 + 2.9 / 100),
                  "model_rms_nT": 50.0, "n_eff": ne}}
    assert sub.all_rows_warnings(same, {"m": (50.0, 1e12)}) == {}
    worse = {"m": dict(same["m"], traced_rms_nT=50.0 * (1 + 3.1 / 100))}
    (w,) = sub.all_rows_warnings(worse)["m"]
    assert w.startswith("WARNING m:") and "WORSE than the baseline" in w
    hidden = {"m": dict(same["m"], model_rms_nT=50.0 * (1 + 3.1 / 100))}
    (w,) = sub.all_rows_warnings(hidden, {"m": (50.0, 1e12)})["m"]
    assert "blocks left out" in w
    # the blocks' own uncertainty counts: with as few effective rows there, no warning
    assert sub.all_rows_warnings(hidden, {"m": (50.0, ne)}) == {}


def test_something_only_in_dropped_blocks_is_warned(tmp_path):
    """A disturbance the blocks never see (a reference error in rows the draw leaves out):
    the blocks find nothing, every row says otherwise, and the warning reaches trace.json
    (warnings, notes first, the stop text) and coefficients.json (fit.trace.warnings)."""
    import json

    from generator.trace import tracer as tr
    from test_trace import make_case, sigma_field
    from test_trace_subsample import CAP, long_file
    case = make_case("channel_bias", 2, tmp_path)
    case.effects = []
    tel = long_file(case, tmp_path, "hidden")
    (kept,), _, _ = sub.subsample_files([tel], [], CAP)
    dropped = ~kept.sample_rows
    assert 0 < dropped.sum() < tel.n
    # 20 sigma of the noisiest sensor: far above any noise, invisible to the blocks
    a_nT = 20 * max(sigma_field(s) for s in case.unit.sensors)
    cols = {c: np.array(v, float) for c, v in tel.columns.items()}
    cols["ref_x_nT"][dropped] += a_nT * np.sin(2 * np.pi * cols["time_s"][dropped] / 300.0)
    cols["ref_norm_nT"] = np.sqrt(cols["ref_x_nT"] ** 2 + cols["ref_y_nT"] ** 2
                                  + cols["ref_z_nT"] ** 2)
    bad = Telemetry(tel.path, cols, tel.line_numbers, dict(tel.meta))
    res = tr.trace(case.unit, [bad], max_samples=CAP)
    assert res.warnings and all(w.startswith(sub.WARNING_PREFIX) for w in res.warnings)
    assert any("blocks left out" in w for w in res.warnings), res.warnings
    assert res.notes[:len(res.warnings)] == res.warnings
    d = json.loads(json.dumps(res.to_json(), default=tr._json_default))
    assert d["warnings"] == res.warnings == d["subsample"]["warnings"]
    assert res.coefficients.fit_info["trace"]["warnings"] == res.warnings
    warned = {w.split()[1].rstrip(":") for w in res.warnings}
    for n in warned:
        stop = d["final"][n]["stop"]
        assert not stop.startswith("nothing significant left:"), stop


def test_a_found_effect_is_not_warned(tmp_path):
    """The planted channel bias of test_trace_subsample, found on the blocks: the traced
    set is better over every row, nothing is warned (the warnings are not always on)."""

    from generator.trace import tracer as tr
    from test_trace import make_case
    from test_trace_subsample import CAP, long_file
    out = tmp_path
    case = make_case("channel_bias", 1, out)
    res = tr.trace(case.unit, [long_file(case, out, "planted")], max_samples=CAP)
    assert [n for n, _ in res.effects] == [case.sensor]
    assert res.warnings == [], res.warnings


# --- F2: the lag recursions run through the rows left out --------------------------------

def test_lag_recursion_runs_exactly_through_the_rows_left_out(tmp_path):
    """Above the cap a kept file is the whole file: the per-file series the lag
    recursions run over hold every usable row (bridge rows), the samples only the drawn
    blocks' rows; the element temperature at a sample is the one the recursion over the
    whole file gives (not one step across the gap), for a slow tau where one step is
    wrong."""
    from generator.trace.effects import element_temperature, lag_filter
    from generator.trace.samples import gather_samples
    from test_trace import make_case
    from test_trace_subsample import CAP, long_file
    case = make_case("channel_bias", 2, tmp_path)
    case.effects = []
    tel = long_file(case, tmp_path, "lagged")
    (kept,), _, _ = sub.subsample_files([tel], [], CAP)
    whole = gather_samples(case.unit, [tel], [0])
    blocks = gather_samples(case.unit, [kept], [0])
    tau_s = 4_000.0                      # slower than a block: the gap matters
    for s in case.unit.sensors:
        W, B = whole[s.name], blocks[s.name]
        assert 0 < B.n < W.n                              # samples: the blocks only
        assert np.array_equal(B.files[0].time_s, W.files[0].time_s)   # series: every row
        exact = lag_filter(W.files[0].time_s, W.files[0].temp_C, tau_s)
        got = element_temperature(B.files[0], tau_s)[B.file_row]
        assert np.array_equal(got, exact[B.file_row])
        # what one step across each gap gives instead differs (the test can fail)
        one_step = lag_filter(B.time_s, B.temp_C, tau_s)
        assert np.max(np.abs(one_step - got)) > 1e-3


def test_uncapped_trace_warns_when_the_written_set_is_worse(tmp_path, monkeypatch):
    """Every row traced (no cap): the same check of the written coefficient set against
    the baseline over every row runs for the sensors with an effect; a worse written set
    (as time_drift's refit gave on a drifting unit: 95 -> 170 nT) reaches the notes,
    trace.json and coefficients.json. The figures are forced here (the wiring); the
    statistics are test_all_rows_warnings_statistics'."""
    from generator.trace import tracer as tr
    from test_trace import make_case
    from test_trace_subsample import long_file
    case = make_case("channel_bias", 1, tmp_path)
    tel = long_file(case, tmp_path, "planted")
    seen = []

    def worse(base, cs, tels, sensors, *a, **k):
        seen.append(list(sensors))
        return {n: {"baseline_rms_nT": 50.0, "traced_rms_nT": 60.0, "samples": 1000,
                    "n_eff": 1000.0} for n in sensors}
    monkeypatch.setattr(tr, "all_rows_rms", worse)
    res = tr.trace(case.unit, [tel], max_samples=0)
    assert res.subsample is None and seen == [[case.sensor]]   # only sensors with an effect
    assert res.warnings and "WORSE than the baseline" in res.warnings[0]
    assert res.notes[0] == res.warnings[0]
    d = res.to_json()
    assert d["warnings"] == res.warnings and "subsample" not in d
    assert res.coefficients.fit_info["trace"]["warnings"] == res.warnings
