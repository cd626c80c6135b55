"""The settling analysis `magcal fit` runs (campaign.check.settling_warnings, via
check_campaign(cells_only=True)) skips what it does not read (issue 20 item 3): the cells
and the settling it returns must be the full check's, on a campaign that settles (the
shared thermal campaign) and on one whose holds are too short for the boards (not settled
cells, a settling warning). And settled_segments' look-back before a segment, taken as a
slice of a time-ordered file, must see the samples the mask saw."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from generator.campaign import check as C

FM1 = Path("/work/shared/data/samsat_fm1")


def _cells(result):
    """The cells without what cells_only leaves out (saturated counts; the gaps' mark)."""
    return [{**{k: v for k, v in c.items() if k != "reported_with_level"},
             "sensors": {n: {k: v for k, v in b.items() if k != "saturated"}
                         for n, b in c["sensors"].items()}} for c in result["cells"]]


def _same_as_full(unit, paths, tels):
    full = C.check_campaign(unit, paths, tels=tels)
    lean = C.check_campaign(unit, paths, tels=tels, cells_only=True)
    assert lean["cells"] and repr(_cells(lean)) == repr(_cells(full))
    assert lean["settling"] == full["settling"] and lean["plan"] == full["plan"]
    assert all("saturated" not in b for c in lean["cells"] for b in c["sensors"].values())
    assert all("saturated" in b for c in full["cells"] for b in c["sensors"].values())
    return full, lean


def _same_look_back(samples):
    """Every segment's look-back samples (_approach_temps) are the mask's, in order."""
    n = 0
    for S in samples.values():
        spans = C._sorted_file_spans(S)
        for sg in S.segments:
            i0 = sg.index[0]
            t0 = S.time_s[i0]
            want = S.T[(S.file == S.file[i0]) & (S.time_s < t0)
                       & (S.time_s >= t0 - C.APPROACH_LOOKBACK_S)]
            got = C._approach_temps(S, spans, i0)
            assert np.array_equal(got, want)
            n += len(want) > 0
    return n


def _mask_look_back(monkeypatch, unit, samples, nearest, tol):
    """settled_segments with every file left to the mask (no time-ordered slices)."""
    monkeypatch.setattr(C, "_sorted_file_spans", lambda S: {})
    try:
        return C.settled_segments(unit, samples, nearest, tol)
    finally:
        monkeypatch.undo()


@pytest.mark.skipif(not (FM1 / "thermal_12pos.csv").exists(), reason="shared data absent")
def test_the_shared_campaign(monkeypatch):
    from generator.io.telemetry_csv import read_telemetry
    from generator.io.unitfile import load_unit

    unit = load_unit(FM1 / "unit.toml")
    paths = [FM1 / "thermal_12pos.csv", FM1 / "rotation.csv"]
    tels = [read_telemetry(p, unit) for p in paths]
    full, _ = _same_as_full(unit, paths, tels)
    assert {c["status"] for c in full["cells"]} == {"ok"}
    samples = C.gather_samples(unit, tels)
    assert all(C._sorted_file_spans(S) for S in samples.values())   # the slices are used
    levels = full["plan"]["levels_C"]

    def nearest(t):
        k = int(np.argmin([abs(t - L) for L in levels]))
        return levels[k] if abs(t - levels[k]) <= 3.0 else None

    assert _same_look_back(samples) > 100     # segments with samples before them
    fast = C.settled_segments(unit, samples, nearest, 1.0)
    assert fast == _mask_look_back(monkeypatch, unit, samples, nearest, 1.0)
    assert sum(s["settled"] for d in fast.values() for s in d["segments"]) > 100


def test_holds_too_short_for_the_boards(tmp_path, monkeypatch):
    from generator.campaign.simulate import make_example_unit, random_truth, simulate_campaign
    from generator.io.telemetry_csv import read_telemetry

    unit = make_example_unit()
    truth = random_truth(unit, np.random.default_rng(3))
    tau_scale = 240.0 / max(truth.board_tau_s.values())
    path, _ = simulate_campaign("thermal_12pos", unit, truth, np.random.default_rng(4),
                                tmp_path, name="short", levels_C=(-20.0, 25.0, 55.0),
                                hold_s=360.0, sample_period_s=20.0,
                                board_tau_scale=3 * tau_scale)
    tels = [read_telemetry(path, unit)]
    full, lean = _same_as_full(unit, [path], tels)
    assert "not settled" in {c["status"] for c in lean["cells"]}
    assert C.settling_warnings(unit, [path], tels=tels)         # a level never settled
    S = C.gather_samples(unit, tels)
    _same_look_back(S)

    def nearest(x):
        return min((-20.0, 25.0, 55.0), key=lambda L: abs(x - L))

    assert C.settled_segments(unit, S, nearest, 1.0) == \
        _mask_look_back(monkeypatch, unit, S, nearest, 1.0)
    # a file out of time order: the look-back falls back to the mask, same figures
    name = next(iter(S))
    t = S[name].time_s.copy()
    t[[5, 6]] = t[[6, 5]]
    S[name].time_s = t
    assert name not in [n for n in S if C._sorted_file_spans(S[n])]
    assert C.settled_segments(unit, S, nearest, 1.0) == \
        _mask_look_back(monkeypatch, unit, S, nearest, 1.0)
