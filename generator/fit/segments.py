"""Constant-temperature segments in a reported temperature (seed 000 sec. 5), and their
grouping across positions into temperature levels.

Public: Segment, find_segments, group_levels, temperature_quantum, temperature_noise.
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
    """Robust 1-sigma noise of a temperature channel from second differences."""
    t = np.asarray(temp_C, float)
    t = t[np.isfinite(t)]
    if len(t) < 3:
        return 0.0
    d2 = t[2:] - 2 * t[1:-1] + t[:-2]
    return float(1.4826 * np.median(np.abs(d2)) / np.sqrt(6.0))


def _runs(mask):
    """(start, stop) of the runs of True in a boolean array."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(np.int8))
    return list(zip(np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]))


def find_segments(time_s, temp_C, position=None, usable=None, *, window_s=600.0,
                  min_duration_s=600.0, band_C=None, min_band_C=0.5):
    """Constant-temperature segments, found in the reported temperature itself.

    A sample is settled when some window of `window_s` that contains it keeps the
    (5-sample median filtered) temperature within `band_C`, i.e. the slope stays below
    band_C / window_s for at least that long. Settled runs of at least `min_duration_s`
    are segments; a run drifting more than 2 band_C is cut; neighbouring segments of the
    same position within band_C of each other and less than min_duration_s apart are
    merged (a glitch does not split a plateau). The boards lag the chamber, so nothing
    about the chamber profile is assumed.

    band_C defaults to max(min_band_C, 1.5 x reporting quantum, 6 x noise sigma), so a
    quantised channel (MMC5883: ~0.7 degC steps) toggling between two levels is settled.
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
        band_C = max(min_band_C, 1.5 * temperature_quantum(T[ok]),
                     6.0 * temperature_noise(T[ok]))
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
                                     min_duration_s, band_C))
    return segs


def _segments_in_run(idx, t, T, position, dt_med, window_s, min_duration_s, band_C):
    n_w = max(3, int(round(window_s / dt_med)))
    if len(idx) < n_w:
        return []
    from scipy.ndimage import median_filter    # here: scipy.ndimage costs 0.2 s to import

    Tf = median_filter(T[idx], size=5, mode="nearest") if len(idx) >= 5 else T[idx]
    win = np.lib.stride_tricks.sliding_window_view(Tf, n_w)
    quiet = (win.max(axis=1) - win.min(axis=1)) <= band_C
    cover = np.zeros(len(idx) + 1, int)
    starts = np.nonzero(quiet)[0]
    np.add.at(cover, starts, 1)
    np.add.at(cover, starts + n_w, -1)
    settled = np.cumsum(cover)[:-1] > 0
    out = []
    for a, b in _runs(settled):
        # cut a run that drifts by more than 2 band_C in all
        while a < b:
            seg = Tf[a:b]
            rng = np.maximum.accumulate(seg) - np.minimum.accumulate(seg)
            over = np.nonzero(rng > 2 * band_C)[0]
            c = a + (over[0] if len(over) else b - a)
            out.append((a, c))
            a = c
    segs = []
    for a, b in out:
        if t[idx[b - 1]] - t[idx[a]] + dt_med < min_duration_s:
            continue
        if segs and (abs(np.mean(Tf[a:b]) - segs[-1][2]) < band_C
                     and t[idx[a]] - t[idx[segs[-1][1] - 1]] < min_duration_s):
            a0 = segs[-1][0]
            keep = np.concatenate([np.arange(a0, segs[-1][1]), np.arange(a, b)])
            segs[-1] = (a0, b, float(np.mean(Tf[keep])), keep)
            continue
        segs.append((a, b, float(np.mean(Tf[a:b])), np.arange(a, b)))
    result = []
    for a, b, _, keep in segs:
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
