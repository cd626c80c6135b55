"""Constant-temperature segments in a reported temperature (seed 000 sec. 5), and their
grouping across positions into temperature levels.

Public: Segment, find_segments, group_levels, temperature_quantum, temperature_noise,
segment_band_C, step_and_white_noise_C.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Segment:
    index: np.ndarray          # sample indices (into the arrays given to find_segments)
    temp_C: float              # mean reported temperature
    temp_range_C: float        # max - min of the (spike-filtered) temperature
    t_start_s: float
    t_stop_s: float
    position: int = 0          # static position (0: none given)
    drift_C: float = 0.0       # fitted linear drift of the reading over the segment (end - start)

    @property
    def duration_s(self) -> float:
        return self.t_stop_s - self.t_start_s


def temperature_quantum(temp_C) -> float:
    """Reporting step of a temperature channel (median spacing of its distinct values)."""
    return quantum_of_values(np.unique(np.asarray(temp_C, float)[np.isfinite(temp_C)]))


def quantum_of_values(values) -> float:
    """temperature_quantum from the channel's distinct finite values, sorted."""
    return float(np.median(np.diff(values))) if len(values) > 1 else 0.0


def temperature_noise(temp_C) -> float:
    """Robust 1-sigma of a temperature channel's sample-to-sample noise, from its second
    differences d2 (white noise: var d2 = 6 sigma^2; a ramp cancels): the RMS of d2,
    winsorised at 3 of its own value and iterated to convergence, so that spikes and the
    jumps at recording gaps are clipped. Unlike a median, the RMS counts the discrete d2
    of a quantised channel as they are: a hold dithering between two codes has d2 of 0 and
    +-1 or 2 steps, and its median is either 0 or a whole step (a 0.7 degC MMC5883 step
    gave 0.42 degC where the dither was 0.2 degC), its RMS is the dither's size."""
    t = np.asarray(temp_C, float)
    t = t[np.isfinite(t)]
    if len(t) < 3:
        return 0.0
    d2 = t[2:] - 2 * t[1:-1] + t[:-2]
    s = float(np.sqrt(np.mean(d2 ** 2)))
    for _ in range(100):
        if s == 0.0:
            break
        c = WINSOR_SIGMAS * s
        s_new = float(np.sqrt(np.mean(np.minimum(d2 ** 2, c * c))))
        if s_new >= s * (1 - 1e-6):
            s = s_new
            break
        s = s_new
    return s / np.sqrt(6.0) / WINSOR_CONSISTENCY


# Winsorising at 3 of its own value: the iteration s <- sqrt(mean(min(d2^2, (3 s)^2)))
# settles on normal noise at s = c sigma with c^2 = E[min(x^2, 9 c^2)], x standard normal:
# c = 0.99744 (solved numerically); spikes are clipped while white noise keeps its size.
# It needs a spike fraction f with f 3^2 < 1 (under 11 % of the second differences).
WINSOR_SIGMAS = 3.0
WINSOR_CONSISTENCY = 0.99744


def segment_band_C(temp_C, *, temp_lsb_C=None, min_band_C=0.5) -> float:
    """The band a constant temperature's 5-sample median-filtered reading stays within
    (find_segments tests windows of the filtered reading): max(min_band_C, 6 sigma_f)
    with sigma_f the filtered reading's error about the true temperature, made of

    * white noise sigma_n, which the median of 5 shrinks to MEDIAN5_SD sigma_n;
    * quantisation with step q (the larger of the part's temperature LSB and the step seen
      in the data): an error uniform over one step, sd q / sqrt(12), that no filter
      removes (a hold dithering between two codes still spans one step q);

    independent, so sigma_f^2 = (MEDIAN5_SD sigma_n)^2 + q^2 / 12, and the band is at least
    6 q / sqrt(12) = 1.73 q: a hold dithering between two codes is inside it with 0.73 q
    to spare. sigma_n: temperature_noise measures the raw reading, quantisation included
    (sigma_tot^2 = sigma_n^2 + q^2/12 where the dither exceeds about q/2; below, the
    quantisation error is not white and the floor q/sqrt(12) holds)."""
    return _band_C(*step_and_white_noise_C(temp_C, temp_lsb_C), min_band_C)


def _band_C(q, sigma_w, min_band_C) -> float:
    """segment_band_C from the step and white noise (step_and_white_noise_C)."""
    sigma_f = np.sqrt(sigma_w ** 2 + q * q / 12.0)
    return float(max(min_band_C, 6.0 * sigma_f))


def step_and_white_noise_C(temp_C, temp_lsb_C=None):
    """(q, sigma_w): the reporting step and the white noise of the 5-sample median
    filtered reading (MEDIAN5_SD sigma_n, sigma_n the raw noise less quantisation; see
    segment_band_C)."""
    T = np.asarray(temp_C, float)
    T = T[np.isfinite(T)]
    q = temperature_step_C(T, temp_lsb_C)
    sigma_n2 = max(0.0, temperature_noise(T) ** 2 - q * q / 12.0)
    return q, float(MEDIAN5_SD * np.sqrt(sigma_n2))


def temperature_step_C(temp_C, temp_lsb_C=None) -> float:
    """The reporting step of a temperature channel: the larger of the part's temperature
    LSB (where known) and the step seen in the data (temperature_quantum)."""
    return max(float(temp_lsb_C or 0.0), temperature_quantum(temp_C))


# sd of the median of 5 independent standard normal values (its variance is 0.2868)
MEDIAN5_SD = 0.5355


def _runs(mask):
    """(start, stop) of the runs of True in a boolean array."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(np.int8))
    return list(zip(np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]))


def find_segments(time_s, temp_C, position=None, usable=None, *, window_s=600.0,
                  min_duration_s=600.0, band_C=None, min_band_C=0.5, temp_lsb_C=None):
    """Constant-temperature segments, found in the reported temperature itself.

    A sample is settled when some window of `window_s` that contains it keeps the
    (5-sample median filtered) temperature within `band_C`. In each settled stretch the
    segment is the settled part of the hold: the longest part that spans at most
    max(band_C, 2 q) (q the reporting step) and whose fitted drift and end blocks stay
    within the drift limit (_SettleLimits: min_band_C + q + 3 sd of noise), so the
    board's approach to its level and its departure at the next ramp are left out. What
    is left before and after is searched the same way; a part found there is another
    segment only if it reads another level (_SettleLimits.level_gap_C) and is not the
    approach to a segment after it. What lasts `min_duration_s` is a segment (one per
    hold; docs/segments.md). The boards lag the chamber, so nothing about the chamber
    profile is assumed.

    band_C defaults to segment_band_C (6 sigma of noise and quantisation: 1.21 degC for
    the MMC5883's 0.7 degC step, which a hold dithering between two codes stays within;
    0.5 degC at least). temp_lsb_C: the part's temperature step, where known (the data's
    own step is measured and the larger one used).
    position: split into runs of constant position; 0 (moving) is never a segment.
    Returns a list of Segment in time order.
    """
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
    # run_id does not decrease: a run's rows are one slice (found once, not by a scan of
    # every row per run, which made long files quadratic: review 20e F3)
    starts = np.flatnonzero(np.r_[True, brk[1:]])
    ends = np.r_[starts[1:], n]
    segs = []
    for rid in np.unique(run_id[ok & (pos > 0)]):
        a, b = starts[rid], ends[rid]
        idx = a + np.flatnonzero(ok[a:b])
        segs.extend(_segments_in_run(idx, t, T, int(pos[idx[0]]), dt_med, window_s,
                                     min_duration_s, band_C, limits))
    return segs


# ranges of quantised values are compared with this relative slack (11.8 - 9.7 is
# 2.1000000000000014 in binary; a span of whole steps must not miss by rounding)
_SLACK = 1e-9


@dataclass
class _SettleLimits:
    """What a settled stretch of a reading may show (find_segments).

    * width_C: its (median-filtered) values span at most max(band, 2 q): the band of a
      constant temperature, or three codes of a quantised one whose true temperature sits
      on a code boundary while it dithers (a span the band alone would cut);
    * drift: the fitted linear drift over the stretch (end - start) and the mean of its
      first and last blocks (window_s / 4) against the stretch's mean are within
      min_band_C + q + 3 sd: min_band_C the smallest true drift counted (the plan's
      default settling tolerance, 0.5 degC); q the reporting step, because a quantised
      reading errs by up to q/2 either way, so a difference of two readings (or of the
      dither fractions of two blocks: a 0.3 degC drift across a code boundary moves a
      dithering reading by nearly a whole step) is off by up to q; sd the white noise's
      contribution to the estimate (sigma_w sqrt(12 / N) for the drift of N samples,
      sigma_w sqrt(1/N_b + 1/N) for a block of N_b). A board still approaching its level
      (a first-order lag) or leaving it at the next ramp drifts monotonically beyond this:
      that part of the hold is not settled data.
    """
    width_C: float
    q_C: float
    sigma_w_C: float
    min_band_C: float

    def drift_C(self, n):
        return self.min_band_C + self.q_C + 3.0 * self.sigma_w_C * np.sqrt(
            12.0 / np.maximum(n, 1))

    def block_C(self, n_block, n):
        return self.min_band_C + self.q_C + 3.0 * self.sigma_w_C * np.sqrt(
            1.0 / n_block + 1.0 / np.maximum(n, 1))

    @property
    def level_gap_C(self):
        """Two settled stretches of one run read different holds when their means differ
        by more than this: the width, and at least twice the smallest drift counted."""
        return max(self.width_C, 2.0 * max(self.min_band_C, self.q_C))


class _RangeExtreme:
    """Maximum (or minimum) of x[i:j] for many (i, j) at once: a sparse table (level k
    holds the extreme of every 2^k consecutive values), so each query costs two lookups."""

    def __init__(self, x, fn):
        self.fn = fn
        self.levels = [np.asarray(x, float)]
        w = 1
        while 2 * w <= len(x):
            prev = self.levels[-1]
            self.levels.append(fn(prev[:-w], prev[w:]))
            w *= 2

    def query(self, i, j):
        """Extreme of x[i[m]:j[m]] for every m (i < j, equal-length integer arrays)."""
        k = np.floor(np.log2(j - i)).astype(int)
        out = np.empty(len(j))
        if not len(j):
            return out
        for kk in range(int(k.min()), int(k.max()) + 1):
            m = k == kk
            lv = self.levels[kk]
            out[m] = self.fn(lv[i[m]], lv[j[m] - (1 << kk)])
        return out


def _spans(hi, lo, i, j):
    """hi.query(i, j) - lo.query(i, j) (_RangeExtreme max and min tables of one array):
    the span of x[i[m]:j[m]] for every m, each table level's lookups done once for both."""
    out = np.empty(len(j))
    if not len(j):
        return out
    k = np.floor(np.log2(j - i)).astype(int)
    k0, k1 = int(k.min()), int(k.max())
    for kk in range(k0, k1 + 1):
        if k0 == k1:            # one level (a window's spans, or pairs of similar length)
            ii, jj, m = i, j - (1 << kk), slice(None)
        else:
            m = k == kk
            ii, jj = i[m], j[m] - (1 << kk)
        h, low = hi.levels[kk], lo.levels[kk]
        out[m] = np.maximum(h[ii], h[jj]) - np.minimum(low[ii], low[jj])
    return out


# the settled-part search tests the longest (start, stop) pairs first: those lasting at
# least these fractions of the longest candidate, then the rest (what it finds is the
# same whatever the fractions: a band is searched only when every longer pair failed)
_DURATION_BANDS = (0.99, 0.95, 0.85, 0.6)


def _longest_settled(ts, x, lim, n_block, min_duration_s, dt_med, extremes=None):
    """(start, stop, drift_C) of the longest stretch of x (times ts) meeting lim
    (_SettleLimits), lasting min_duration_s; None if there is none. Starts and stops are
    tried on a grid of about 200 points per run (every sample in runs up to 200 long):
    starts i = 0, g, 2 g, ..., stops j = 2 n_block + m g and n, with j - i >= 2 n_block.
    Of the longest pairs that pass, the first start, then the first stop (as a scan over
    starts keeping the first strictly longer one). The pairs are tested in bands of
    decreasing duration (_DURATION_BANDS), many at once, and the search stops at the first
    band where one passes: every longer pair was tested and failed.
    extremes: (hi, lo, offset): _RangeExtreme max and min tables of the whole run that x
    is x_run[offset:offset + len(x)] of (built once per run; a max or min is exact, so
    the same spans as tables of x itself); None: built here."""
    n = len(x)
    if n < 2 * n_block:
        return None
    g = max(1, n // 200)
    starts = np.arange(0, n - 2 * n_block + 1, g)
    stops = np.arange(2 * n_block, n + 1, g)          # and n, once
    if stops[-1] != n:
        stops = np.append(stops, n)
    # every start's stops: those on the grid at least 2 n_block after it (a start is a
    # multiple of g, so its own grid i + 2 n_block + m g is the common one from there).
    # A segment lasts min_duration_s from its first sample to its last (what
    # Segment.duration_s and the report show), not one sample period less
    t_i, t_j = ts[starts], ts[stops - 1]
    # a bound on the longest pair's duration (the bands are fractions of it)
    t_j_max, t_i_min = t_j.max(), t_i.min()
    longest = float(t_j_max - t_i_min)
    if longest < min_duration_s:
        return None
    tc = ts - ts[0]
    # the running sums of tc, x, tc^2, tc x from 0 (each row a sequential sum, as a 1-D
    # cumsum's)
    V = np.empty((4, n))
    V[0], V[1] = tc, x
    np.multiply(tc, tc, out=V[2])
    np.multiply(tc, x, out=V[3])
    P = np.empty((4, n + 1))
    P[:, 0] = 0.0
    np.cumsum(V, axis=1, out=P[:, 1:])
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
        rows = np.nonzero(t_j_max - t_i >= above)[0]
        cols = np.nonzero(t_j - t_i_min >= above)[0]
        dur2 = t_j[cols][None, :] - t_i[rows][:, None]
        cand = ((stops[cols][None, :] - starts[rows][:, None] >= 2 * n_block)
                & (dur2 >= min_duration_s) & (dur2 >= above) & (dur2 < below))
        I, J = np.nonzero(cand)
        if not len(I):
            continue
        dur = dur2[I, J]
        I, J = rows[I], cols[J]
        i, j = starts[I], stops[J]
        span = _spans(hi, lo, i + off, j + off)
        N = (j - i).astype(float)
        St, Sx, Stt, Stx = P[:, j] - P[:, i]
        den = N * Stt - St * St
        slope = np.where(den > 0, (N * Stx - St * Sx) / np.where(den > 0, den, 1.0), 0.0)
        drift = slope * (ts[j - 1] - ts[i])
        mean = Sx / N
        first = (P[1][i + n_block] - P[1][i]) / n_block
        last = (P[1][j] - P[1][j - n_block]) / n_block
        block = lim.block_C(n_block, N)
        ok = ((span <= lim.width_C * (1 + _SLACK))
              & (np.abs(drift) <= lim.drift_C(N))
              & (np.abs(first - mean) <= block)
              & (np.abs(last - mean) <= block))
        if ok.any():
            m = int(np.argmax(np.where(ok, dur, -np.inf)))
            return int(i[m]), int(j[m]), float(drift[m])
    return None


def _segments_in_run(idx, t, T, position, dt_med, window_s, min_duration_s, band_C, lim):
    """Segments of one run of constant position (find_segments): in each settled stretch
    (windows of window_s within band_C), the longest part meeting lim (_SettleLimits);
    what is left before and after it is searched the same way, and a part found there is
    another segment only if it reads another level (lim.level_gap_C away): the rest of the
    board's approach to a hold is not a segment of its own."""
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
    quiet = _spans(hi, lo, w0, w0 + n_w) <= band_C * (1 + _SLACK)
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
            got = _longest_settled(ts[a0:b0], Tf[a0:b0], lim, n_block, min_duration_s,
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


def group_levels(segments, tol_C):
    """Group segments (from all positions) into temperature levels: sorted by mean
    temperature, a new level starts where the gap to the previous one exceeds tol_C."""
    if not segments:
        return []
    order = sorted(segments, key=lambda s: s.temp_C)
    levels = [[order[0]]]
    for s in order[1:]:
        if s.temp_C - levels[-1][-1].temp_C > tol_C:
            levels.append([s])
        else:
            levels[-1].append(s)
    return levels
