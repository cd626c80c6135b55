"""The segment finder (generator.fit.segments.find_segments) made faster for issue 20
item 3 must find exactly the segments it found before: the oracle below is its code at
c6ef128 (find_segments, _segments_in_run, _longest_settled as they were; the helpers they
call are unchanged and imported). Every Segment field is compared bit for bit (index,
temp_C, temp_range_C, t_start_s, t_stop_s, position, drift_C) on the shared campaign's
thermal file (as the fit and the campaign check call it), on the real PX4 office log's
four chip temperatures (/work/shared/realdata, skipped where absent) and on generated
profiles: holds with lagged approaches, ramps, quantised and dithering readings, noise,
spikes, gaps, positions, unusable samples."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from generator.fit.segments import (Segment, _band_C, _RangeExtreme, _runs, _SettleLimits,
                                    find_segments, step_and_white_noise_C)

FM1 = Path("/work/shared/data/samsat_fm1")
PX4 = Path("/work/shared/realdata/px4_ecl_office")
FIELDS = ("temp_C", "temp_range_C", "t_start_s", "t_stop_s", "position", "drift_C")


# ---- the oracle: c6ef128's code ------------------------------------------------------
_SLACK = 1e-9
_DURATION_BANDS = (0.99, 0.95, 0.85, 0.6)

def old_find_segments(time_s, temp_C, position=None, usable=None, *, window_s=600.0,
                  min_duration_s=600.0, band_C=None, min_band_C=0.5, temp_lsb_C=None):
    t = np.asarray(time_s, float)
    T = np.asarray(temp_C, float)
    n = len(t)
    ok = np.isfinite(T) & np.isfinite(t)
    if usable is not None:
        ok &= np.asarray(usable, bool)
    pos = np.zeros(n, int) if position is None else np.nan_to_num(
        np.asarray(position, float), nan=0).astype(int)
    if position is None:
        pos[:] = 1
    q, sigma_w = step_and_white_noise_C(T[ok], temp_lsb_C)
    if band_C is None:          # segment_band_C of the same samples, from the same figures
        band_C = _band_C(q, sigma_w, min_band_C)
    limits = _SettleLimits(width_C=max(band_C, 2.0 * q), q_C=q, sigma_w_C=sigma_w,
                           min_band_C=min_band_C)
    dt = np.diff(t[ok])
    dt_med = float(np.median(dt[dt > 0])) if np.any(dt > 0) else 1.0
    # runs of constant position, split at time gaps
    brk = np.zeros(n, bool)
    brk[1:] = (pos[1:] != pos[:-1]) | (np.diff(t) > 10 * dt_med)
    run_id = np.cumsum(brk)
    segs = []
    for rid in np.unique(run_id[ok & (pos > 0)]):
        idx = np.nonzero((run_id == rid) & ok)[0]
        segs.extend(_old_segments_in_run(idx, t, T, int(pos[idx[0]]), dt_med, window_s,
                                     min_duration_s, band_C, limits))
    return segs


def _old_longest_settled(ts, x, lim, n_block, min_duration_s, dt_med, extremes=None):
    n = len(x)
    if n < 2 * n_block:
        return None
    g = max(1, n // 200)
    starts = np.arange(0, n - 2 * n_block + 1, g)
    stops = np.unique(np.concatenate([np.arange(2 * n_block, n + 1, g), [n]]))
    # every start's stops: those on the grid at least 2 n_block after it (a start is a
    # multiple of g, so its own grid i + 2 n_block + m g is the common one from there).
    # A segment lasts min_duration_s from its first sample to its last (what
    # Segment.duration_s and the report show), not one sample period less
    t_i, t_j = ts[starts], ts[stops - 1]
    # a bound on the longest pair's duration (the bands are fractions of it)
    longest = float(t_j.max() - t_i.min())
    if longest < min_duration_s:
        return None
    tc = ts - ts[0]
    P = [np.concatenate([[0.0], np.cumsum(v)]) for v in (tc, x, tc * tc, tc * x)]
    if extremes is None:
        hi, lo, off = _RangeExtreme(x, np.maximum), _RangeExtreme(x, np.minimum), 0
    else:
        hi, lo, off = extremes
    above = np.inf
    for band in (*_DURATION_BANDS, None):
        below, above = above, (-np.inf if band is None else band * longest)
        # the starts and stops that can make a pair lasting `above` (a sub-grid: its pairs
        # in (start, stop) order, so argmax takes the first of equal durations); a
        # difference rounds monotonically, so the row's longest is against the last stop
        rows = np.nonzero(t_j.max() - t_i >= above)[0]
        cols = np.nonzero(t_j - t_i.min() >= above)[0]
        dur2 = t_j[cols][None, :] - t_i[rows][:, None]
        cand = ((stops[cols][None, :] - starts[rows][:, None] >= 2 * n_block)
                & (dur2 >= min_duration_s) & (dur2 >= above) & (dur2 < below))
        I, J = np.nonzero(cand)
        if not len(I):
            continue
        dur = dur2[I, J]
        I, J = rows[I], cols[J]
        i, j = starts[I], stops[J]
        span = hi.query(i + off, j + off) - lo.query(i + off, j + off)
        N = (j - i).astype(float)
        St, Sx, Stt, Stx = (p[j] - p[i] for p in P)
        den = N * Stt - St * St
        slope = np.where(den > 0, (N * Stx - St * Sx) / np.where(den > 0, den, 1.0), 0.0)
        drift = slope * (ts[j - 1] - ts[i])
        mean = Sx / N
        first = (P[1][i + n_block] - P[1][i]) / n_block
        last = (P[1][j] - P[1][j - n_block]) / n_block
        ok = ((span <= lim.width_C * (1 + _SLACK))
              & (np.abs(drift) <= lim.drift_C(N))
              & (np.abs(first - mean) <= lim.block_C(n_block, N))
              & (np.abs(last - mean) <= lim.block_C(n_block, N)))
        if ok.any():
            m = int(np.argmax(np.where(ok, dur, -np.inf)))
            return int(i[m]), int(j[m]), float(drift[m])
    return None


def _old_segments_in_run(idx, t, T, position, dt_med, window_s, min_duration_s, band_C, lim):
    n_w = max(3, int(round(window_s / dt_med)))
    if len(idx) < n_w:
        return []
    from generator.fit.special import running_median

    Tf = running_median(T[idx], 5) if len(idx) >= 5 else T[idx]
    ts = t[idx]
    # every window's span from range tables (exact: the same max and min as the windows'
    # own, in O(n log n) rather than O(n n_w)); the tables serve _longest_settled too
    hi, lo = _RangeExtreme(Tf, np.maximum), _RangeExtreme(Tf, np.minimum)
    w0 = np.arange(len(idx) - n_w + 1)
    quiet = (hi.query(w0, w0 + n_w) - lo.query(w0, w0 + n_w)) <= band_C * (1 + _SLACK)
    cover = np.zeros(len(idx) + 1, int)
    starts = np.nonzero(quiet)[0]
    np.add.at(cover, starts, 1)
    np.add.at(cover, starts + n_w, -1)
    settled = np.cumsum(cover)[:-1] > 0
    n_block = max(3, n_w // 4)
    found = []
    for a, b in _runs(settled):
        means, found_run = [], []
        todo = [(int(a), int(b))]
        while todo:
            a0, b0 = todo.pop()
            if b0 - a0 < 2 or ts[b0 - 1] - ts[a0] < min_duration_s:
                continue
            got = _old_longest_settled(ts[a0:b0], Tf[a0:b0], lim, n_block, min_duration_s,
                                   dt_med, extremes=(hi, lo, a0))
            if got is None:
                continue
            s, e, drift = got
            todo += [(a0, a0 + s), (a0 + e, b0)]
            m = float(np.mean(Tf[a0 + s:a0 + e]))
            if any(abs(m - mm) <= lim.level_gap_C for mm in means):
                continue
            # the board's approach to a segment found before (this piece earlier, drifting
            # towards it by more than half the drift limit): not a hold of its own. (A
            # piece after a segment drifting away from it may be the next hold reached
            # through a slow transition; the departure at a ramp is short, its drift grows.)
            later = [(ss, mm) for (ss, _, _), mm in zip(found_run, means) if ss >= a0 + e]
            if later:
                ss, mm = min(later)
                if drift * np.sign(mm - m) > 0.5 * lim.drift_C(e - s):
                    continue
            means.append(m)
            found_run.append((a0 + s, a0 + e, drift))
            found.append((a0 + s, a0 + e, drift))
    result = []
    for a, b, drift in sorted(found):
        ii = idx[a:b]
        result.append(Segment(index=ii, temp_C=float(np.mean(T[ii])),
                              temp_range_C=float(np.ptp(Tf[a:b])), t_start_s=float(t[ii[0]]),
                              t_stop_s=float(t[ii[-1]]), position=position, drift_C=drift))
    return result


# ---- the comparison ------------------------------------------------------------------
def _same(new, old):
    assert len(new) == len(old)
    for a, b in zip(new, old):
        assert isinstance(a, Segment)
        assert np.array_equal(a.index, b.index)
        for f in FIELDS:
            assert np.float64(getattr(a, f)).tobytes() == np.float64(getattr(b, f)).tobytes(), f


def _both(*a, **k):
    new, old = find_segments(*a, **k), old_find_segments(*a, **k)
    _same(new, old)
    return new


@pytest.mark.skipif(not (FM1 / "thermal_12pos.csv").exists(), reason="shared data absent")
def test_the_campaign_as_the_fit_and_the_check_call_it():
    from generator.campaign.check import gather_samples
    from generator.io.unitfile import load_unit
    from generator.io.telemetry_csv import read_telemetry
    from generator.fit import samples as fit_samples
    from generator.campaign import check

    unit = load_unit(FM1 / "unit.toml")
    tel = read_telemetry(FM1 / "thermal_12pos.csv", unit)
    calls = []
    orig = check.find_segments

    def record(*a, **k):
        calls.append((a, k))
        return orig(*a, **k)

    check.find_segments = record
    try:
        gather_samples(unit, [tel])
    finally:
        check.find_segments = orig
    assert len(calls) == len(unit.sensors)
    n = sum(len(_both(*a, **k)) for a, k in calls)
    assert n >= 12 * 6 * len(unit.sensors)      # 12 positions x 6 levels, each sensor
    assert fit_samples.find_segments is find_segments   # the fit calls the same function


def _px4(i):
    a = np.genfromtxt(PX4 / f"sensor_mag_{i}.csv", delimiter=",", names=True)
    return a["timestamp"] * 1e-6, a["temperature"]


@pytest.mark.skipif(not PX4.exists(), reason="realdata absent")
@pytest.mark.parametrize("i", range(4))
def test_real_chip_temperatures(i):
    t, T = _px4(i)
    # the log is 329 s long (chips warming by 5-7 degC): short windows find its holds
    for w in (20.0, 40.0, 80.0):
        _both(t, T, window_s=w, min_duration_s=w)
        _both(t, T, window_s=w, min_duration_s=w / 2, min_band_C=0.1)
    # positions and an unusable stretch
    pos = (np.arange(len(t)) * 4 // len(t)) + 1
    usable = np.ones(len(t), bool)
    usable[len(t) // 3:len(t) // 3 + 500] = False
    _both(t, T, pos, usable, window_s=30.0, min_duration_s=30.0)


def _profile(rng, n_holds, hold_s, dt_s, q_C, noise_C, tau_s, spikes):
    """Set-points with first-order lagged readings between them, quantised, noisy."""
    levels = rng.uniform(-30, 60, n_holds)
    t = np.arange(0, n_holds * hold_s, dt_s)
    t = t + rng.uniform(0, 0.2 * dt_s, len(t))         # uneven sampling
    set_pt = levels[np.minimum((t // hold_s).astype(int), n_holds - 1)]
    T = np.empty(len(t))
    T[0] = set_pt[0]
    a = 1 - np.exp(-dt_s / tau_s)
    for k in range(1, len(t)):
        T[k] = T[k - 1] + a * (set_pt[k] - T[k - 1])
    T = T + rng.normal(0, noise_C, len(t))
    if q_C:
        T = np.round(T / q_C) * q_C
    if spikes:
        k = rng.integers(0, len(t), spikes)
        T[k] += rng.choice([-5.0, 5.0], spikes)
    return t, T


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_holds=st.integers(1, 6),
       hold_s=st.sampled_from([300.0, 900.0, 1500.0, 2400.0]),
       dt_s=st.sampled_from([1.0, 2.0, 5.0]), q_C=st.sampled_from([0.0, 0.0625, 0.25, 0.7]),
       noise_C=st.sampled_from([0.0, 0.02, 0.1, 0.3]), tau_s=st.sampled_from([30.0, 200.0, 600.0]),
       spikes=st.integers(0, 5), positions=st.booleans(), gap=st.booleans(),
       lsb=st.sampled_from([None, 0.125, 0.7]))
def test_generated_profiles(seed, n_holds, hold_s, dt_s, q_C, noise_C, tau_s, spikes,
                            positions, gap, lsb):
    rng = np.random.default_rng(seed)
    t, T = _profile(rng, n_holds, hold_s, dt_s, q_C, noise_C, tau_s, spikes)
    if gap and len(t) > 100:                # a recording gap
        t = t.copy()
        t[len(t) // 2:] += 50 * dt_s
    pos = None
    usable = None
    if positions:
        pos = (np.floor(t / hold_s) % 3).astype(float)     # position 0: moving
        usable = rng.random(len(t)) > 0.02
        T = T.copy()
        T[rng.integers(0, len(t), 3)] = np.nan
    _both(t, T, pos, usable, temp_lsb_C=lsb)
    _both(t, T, pos, usable, window_s=300.0, min_duration_s=200.0, temp_lsb_C=lsb)
