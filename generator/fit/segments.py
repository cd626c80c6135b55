"""Constant-temperature segments in a reported temperature (seed 000 sec. 5), and their
grouping across positions into temperature levels.

Public: Segment, find_segments, group_levels, temperature_quantum, temperature_noise,
segment_band_C.
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

    @property
    def duration_s(self) -> float:
        return self.t_stop_s - self.t_start_s


def temperature_quantum(temp_C) -> float:
    """Reporting step of a temperature channel (median spacing of its distinct values)."""
    u = np.unique(np.asarray(temp_C, float)[np.isfinite(temp_C)])
    return float(np.median(np.diff(u))) if len(u) > 1 else 0.0


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
    T = np.asarray(temp_C, float)
    T = T[np.isfinite(T)]
    q = temperature_step_C(T, temp_lsb_C)
    sigma_n2 = max(0.0, temperature_noise(T) ** 2 - q * q / 12.0)
    sigma_f = np.sqrt(MEDIAN5_SD ** 2 * sigma_n2 + q * q / 12.0)
    return float(max(min_band_C, 6.0 * sigma_f))


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
    (5-sample median filtered) temperature within `band_C`. A settled run is split into
    plateaus: the longest stretch of consecutive samples that stays inside one interval
    of width band_C is a plateau, and what is left before and after it is split the same
    way (a run that joins two holds by a slow transition, or a hold and the tail of the
    board's approach to it, gives a plateau per hold). Neighbouring pieces of one hold
    are joined again (a glitch, or a hold whose true temperature crosses one code
    boundary while it dithers, cuts a hold into pieces): less than min_duration_s apart,
    together within max(band_C, 2 q) and their means within max(min_band_C, 1.5 q), q the
    reporting step. What lasts `min_duration_s` is a segment. The boards lag the chamber,
    so nothing about the chamber profile is assumed.

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
    if band_C is None:
        band_C = segment_band_C(T[ok], temp_lsb_C=temp_lsb_C, min_band_C=min_band_C)
    # pieces of one hold -- cut by a glitch, or by a true temperature that crosses one
    # code boundary while it dithers (three codes, 2 q: more than the band) -- are joined
    # again: neighbours less than min_duration_s apart that together span at most
    # max(band, 2 q) and whose means differ by at most max(min_band_C, 1.5 q). Two pieces
    # of one hold share their middle code, so their means differ by about one step; two
    # holds 2 degC apart read at least two codes apart at 0.7 degC steps (2 q = 1.4 degC),
    # span four codes or more together with their dither, and their means differ by more
    # than 1.5 q (the 0.5 q between leaves room for a piece that holds the end of the
    # board's approach)
    q = temperature_step_C(T[ok], temp_lsb_C)
    join_C = (max(band_C, 2.0 * q), max(min_band_C, 1.5 * q))
    dt = np.diff(t[ok])
    dt_med = float(np.median(dt[dt > 0])) if np.any(dt > 0) else 1.0
    # runs of constant position, split at time gaps
    brk = np.zeros(n, bool)
    brk[1:] = (pos[1:] != pos[:-1]) | (np.diff(t) > 10 * dt_med)
    run_id = np.cumsum(brk)
    segs = []
    for rid in np.unique(run_id[ok & (pos > 0)]):
        idx = np.nonzero((run_id == rid) & ok)[0]
        segs.extend(_segments_in_run(idx, t, T, int(pos[idx[0]]), dt_med, window_s,
                                     min_duration_s, band_C, join_C))
    return segs


# ranges of quantised values are compared with this relative slack (11.8 - 9.7 is
# 2.1000000000000014 in binary; a span of whole steps must not miss by rounding)
_SLACK = 1e-9


def _plateaus(Tf, a, b, width_C, out):
    """Split Tf[a:b] into plateaus (see find_segments): appends (start, stop) to out, in
    time order.

    The plateau is the longest stretch of consecutive samples whose values stay inside
    one interval [v, v + width_C]; v runs over a grid from the smallest value in steps of
    width_C / 20 (a quantised reading's codes lie on its step, and the grid meets each
    code within width_C / 20). What is left before and after it is split the same way
    (iteratively: a run of many small pieces must not exhaust the call stack)."""
    found = []
    todo = [(a, b)]
    while todo:
        a, b = todo.pop()
        if b - a <= 0:
            continue
        seg = Tf[a:b]
        lo, hi = float(seg.min()), float(seg.max())
        edges = lo + np.arange(int((hi - lo) / (width_C / 20.0)) + 1) * (width_C / 20.0)
        best = (0, 0, 0)
        for v in edges:
            inside = (seg >= v - _SLACK * width_C) & (seg <= v + width_C * (1 + _SLACK))
            for s0, e0 in _runs(inside):
                if e0 - s0 > best[0]:
                    best = (int(e0 - s0), int(s0), int(e0))
        _, s, e = best
        found.append((a + s, a + e))
        todo += [(a, a + s), (a + e, b)]
    out.extend(sorted(found))


def _segments_in_run(idx, t, T, position, dt_med, window_s, min_duration_s, band_C,
                     join_C):
    n_w = max(3, int(round(window_s / dt_med)))
    if len(idx) < n_w:
        return []
    from scipy.ndimage import median_filter    # here: scipy.ndimage costs 0.2 s to import

    Tf = median_filter(T[idx], size=5, mode="nearest") if len(idx) >= 5 else T[idx]
    win = np.lib.stride_tricks.sliding_window_view(Tf, n_w)
    quiet = (win.max(axis=1) - win.min(axis=1)) <= band_C * (1 + _SLACK)
    cover = np.zeros(len(idx) + 1, int)
    starts = np.nonzero(quiet)[0]
    np.add.at(cover, starts, 1)
    np.add.at(cover, starts + n_w, -1)
    settled = np.cumsum(cover)[:-1] > 0
    out = []
    for a, b in _runs(settled):
        _plateaus(Tf, int(a), int(b), band_C, out)
    # join neighbouring pieces of one hold (find_segments: join_C), short ones too (the
    # last minutes of a hold that dithers onto a third code are such a piece), then keep
    # what lasts min_duration_s
    joined = []
    for a, b in out:
        keep = np.arange(a, b)
        if joined:
            union = np.concatenate([joined[-1], keep])
            if (np.ptp(Tf[union]) <= join_C[0] * (1 + _SLACK)
                    and abs(np.mean(Tf[keep]) - np.mean(Tf[joined[-1]])) <= join_C[1]
                    and t[idx[a]] - t[idx[joined[-1][-1]]] < min_duration_s):
                joined[-1] = union
                continue
        joined.append(keep)
    segs = [k for k in joined if t[idx[k[-1]]] - t[idx[k[0]]] + dt_med >= min_duration_s]
    result = []
    for keep in segs:
        ii = idx[keep]
        result.append(Segment(index=ii, temp_C=float(np.mean(T[ii])),
                              temp_range_C=float(np.ptp(Tf[keep])), t_start_s=float(t[ii[0]]),
                              t_stop_s=float(t[ii[-1]]), position=position))
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
