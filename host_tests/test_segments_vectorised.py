"""The settled-part search of the segment finder tests all (start, stop) pairs at once
(generator.fit.segments._longest_settled, issue 20 item 3: it was half of the thermal
fit's time as a loop over starts). It must pick exactly what the loop picked: the oracle
below is that loop as it was at 5335ede (one start at a time, a stop kept only when
strictly longer than the best so far). Inputs: holds with approach and departure ramps,
quantised readings dithering between codes, noise, spikes, uneven sampling, runs shorter
and longer than the 200-point grid."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from generator.fit.segments import (_longest_settled, _RangeExtreme, _SettleLimits,
                                    find_segments)


def _oracle(ts, x, lim, n_block, min_duration_s):
    """The scan over starts of 5335ede (its range queries one start at a time)."""
    n = len(x)
    if n < 2 * n_block:
        return None
    g = max(1, n // 200)
    tc = ts - ts[0]
    P = [np.concatenate([[0.0], np.cumsum(v)]) for v in (tc, x, tc * tc, tc * x)]
    hi, lo = _RangeExtreme(x, np.maximum), _RangeExtreme(x, np.minimum)
    best = None
    for i in range(0, n - 2 * n_block + 1, g):
        js = np.unique(np.concatenate([np.arange(i + 2 * n_block, n + 1, g), [n]]))
        js = js[js - i >= 2 * n_block]
        dur = ts[js - 1] - ts[i]
        keep = dur >= min_duration_s
        if best is not None:
            keep &= dur > best[3]
        if not keep.any():
            continue
        js, dur = js[keep], dur[keep]
        k = js - i
        ii = np.full(len(js), i)
        span = hi.query(ii, js) - lo.query(ii, js)
        N = k.astype(float)
        St, Sx, Stt, Stx = (p[js] - p[i] for p in P)
        den = N * Stt - St * St
        slope = np.where(den > 0, (N * Stx - St * Sx) / np.where(den > 0, den, 1.0), 0.0)
        drift = slope * (ts[js - 1] - ts[i])
        mean = Sx / N
        first = (P[1][i + n_block] - P[1][i]) / n_block
        last = (P[1][js] - P[1][js - n_block]) / n_block
        ok = ((span <= lim.width_C * (1 + 1e-9))
              & (np.abs(drift) <= lim.drift_C(N))
              & (np.abs(first - mean) <= lim.block_C(n_block, N))
              & (np.abs(last - mean) <= lim.block_C(n_block, N)))
        if ok.any():
            m = int(np.argmax(np.where(ok, dur, -1.0)))
            best = (i, int(js[m]), float(drift[m]), float(dur[m]))
    return None if best is None else best[:3]


def _reading(rng, n, q_C, noise_C, kind):
    """A board's reading around one hold: an approach, the hold, a departure (kind 0), a
    random walk (1) or flat with spikes (2); quantised to q_C when q_C > 0."""
    u = np.linspace(0.0, 1.0, n)
    if kind == 0:
        level = rng.uniform(-20, 50)
        x = level + rng.uniform(-8, 8) * np.exp(-u / rng.uniform(0.03, 0.3))
        x += np.where(u > rng.uniform(0.6, 1.0), rng.uniform(-20, 20) * (u - 0.8), 0.0)
    elif kind == 1:
        x = rng.uniform(-20, 50) + np.cumsum(rng.normal(0, rng.uniform(0.001, 0.05), n))
    else:
        x = np.full(n, rng.uniform(-20, 50))
        hit = rng.random(n) < 0.02
        x[hit] += rng.normal(0, 3, hit.sum())
    x = x + rng.normal(0, noise_C, n)
    return np.round(x / q_C) * q_C if q_C > 0 else x


@settings(max_examples=120, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(5, 900),
       q_C=st.sampled_from([0.0, 0.0625, 0.7]), noise_C=st.sampled_from([0.0, 0.02, 0.3]),
       kind=st.integers(0, 2), min_frac=st.floats(0.0, 0.9),
       n_block=st.integers(3, 40), uneven=st.booleans())
def test_same_pick_as_the_scan_over_starts(seed, n, q_C, noise_C, kind, min_frac, n_block,
                                           uneven):
    rng = np.random.default_rng(seed)
    steps = rng.uniform(20, 100, n) if uneven else np.full(n, 60.0)
    ts = 1e5 + np.cumsum(steps)
    x = _reading(rng, n, q_C, noise_C, kind)
    lim = _SettleLimits(width_C=max(1.2, 2 * q_C), q_C=q_C, sigma_w_C=0.5 * noise_C,
                        min_band_C=0.5)
    min_duration_s = min_frac * (ts[-1] - ts[0])
    got = _longest_settled(ts, x, lim, n_block, min_duration_s, 60.0)
    want = _oracle(ts, x, lim, n_block, min_duration_s)
    assert got == want


def test_ties_take_the_first_start_then_the_first_stop():
    # a flat reading: every pair passes and the longest (the whole run) is unique; with
    # two equally long flat stretches split by a jump, both are candidates of equal length
    # and the scan kept the first
    ts = np.arange(100) * 60.0
    x = np.concatenate([np.zeros(40), np.full(20, 9.0), np.zeros(40)])
    lim = _SettleLimits(width_C=1.2, q_C=0.0, sigma_w_C=0.0, min_band_C=0.5)
    got = _longest_settled(ts, x, lim, 5, 600.0, 60.0)
    assert got == _oracle(ts, x, lim, 5, 600.0)
    assert got[:2] == (0, 40)


def test_find_segments_of_a_thermal_hold_profile():
    # end to end through find_segments: three holds on two positions, quantised at 0.7
    # degC (the MMC5883MA) with the board lagging the set-points
    rng = np.random.default_rng(3)
    t = np.arange(0, 6 * 3600.0, 30.0)
    setp = np.select([t < 7200, t < 14400], [-10.0, 20.0], 45.0)
    board = np.empty_like(t)
    board[0] = setp[0]
    for k in range(1, len(t)):      # first-order lag, 15 min
        board[k] = board[k - 1] + (setp[k] - board[k - 1]) * (1 - np.exp(-30.0 / 900.0))
    T = np.round((board + rng.normal(0, 0.1, len(t))) / 0.7) * 0.7
    pos = np.where((t // 3600) % 2 == 0, 1, 2)
    segs = find_segments(t, T, pos, temp_lsb_C=0.7)
    assert segs, "the holds are settled for an hour each"
    for s in segs:      # every segment is one hold's settled end, at its set-point
        assert abs(s.temp_C - setp[s.index[0]]) < 1.5
