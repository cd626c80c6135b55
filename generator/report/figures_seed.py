"""Figures of seed 000 drawn from the campaign's data (matplotlib, Agg): plain arrays in,
PNG out, as generator/report/figures.py (its figure, save and parallel helpers).

* projections_before_after: per-axis normalised projections of two magnetometers before
  and after the alignment H (seed 000 fig. 8-9);
* sphere_projections: raw and calibrated readings in the three coordinate planes against
  the reference magnitude's circle (fig. 14 rotation, fig. 16 twelve positions);
* temperature_profile: the recorded sensor temperatures with the constant-temperature
  segments marked and the positions (fig. 21 and 23);
* positions_timeline: raw and calibrated field components against time in some positions,
  with the reference (fig. 26);
* axis_rms_bars: per-axis vector RMS before and after, per sensor.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from generator.report.figures import (_AFTER, _AXIS_COLORS, _BEFORE, _axes_title, _deferrable,
                                      _figure, _save)
from generator.report.lean_axis import fixed_ticks as _fixed_ticks
from generator.report.lean_axis import lean_ticks as _lean_ticks

BAND = 0.35          # sphere_projections: points within 0.35 |B| of the plane (~20 deg)
MAX_POINTS = 3000    # points per scatter series: beyond this the drawing only gets slower


def _thin(n):
    return slice(None, None, max(1, n // MAX_POINTS))


def thinning_note(counts, what="samples") -> str:
    """The caption's statement of the decimation _thin applies to series of these lengths:
    "" when every point is drawn, else e.g. " Drawn: every 12th of the 36,000 samples"."""
    notes = sorted({(max(1, int(n) // MAX_POINTS), int(n)) for n in counts if int(n)})
    notes = [(k, n) for k, n in notes if k > 1]
    if not notes:
        return ""
    def nth(k):
        return f"{k}{'th' if 10 <= k % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(k % 10, 'th')}"
    return " Drawn: " + "; ".join(f"every {nth(k)} of the {n:,} {what}" for k, n in notes) + "."


@_deferrable(lambda path, *a, **k: Path(path))
def projections_before_after(path, title, time, u_ref, u_before, u_after, names,
                             time_label="time, s") -> Path:
    """Columns x, y, z; rows: the normalised projections B/|B| of the reference sensor and
    of the boom sensor before H, the same after H (seed 000 fig. 8-9), and their difference
    in % before (grey) and after (coloured), where a gap of a percent becomes visible."""
    fig = _figure(12.0, 7.6, constrained="fixed")
    axes = fig.subplots(3, 3, sharex=True)
    t = np.asarray(time, float)
    sl = _thin(len(t))
    for r, (label, ub) in enumerate((("before H", u_before), ("after H", u_after))):
        for c in range(3):
            ax = axes[r, c]
            ax.plot(t[sl], u_ref[sl, c], ".", ms=0.8, color="k", label=names[0], zorder=3)
            ax.plot(t[sl], ub[sl, c], ".", ms=1.2, color=_AXIS_COLORS[c], alpha=0.6,
                    label=names[1])
            _axes_title(ax, f"{'xyz'[c]} axis, {label}", fontsize=9)
            if c == 0:
                ax.set_ylabel("B/|B|", fontsize=8)
    for c in range(3):
        ax = axes[2, c]
        ax.plot(t[sl], 100 * (u_before[sl, c] - u_ref[sl, c]), ".", ms=1.2, color=_BEFORE,
                label="before H")
        ax.plot(t[sl], 100 * (u_after[sl, c] - u_ref[sl, c]), ".", ms=1.2,
                color=_AXIS_COLORS[c], label="after H")
        _axes_title(ax, f"{'xyz'[c]} axis: {names[1]} - {names[0]}", fontsize=9)
        ax.set_xlabel(time_label, fontsize=8)
        if c == 0:
            ax.set_ylabel("difference, %", fontsize=8)
        ax.legend(fontsize=6, markerscale=4)
    for ax in axes.ravel():
        ax.grid(alpha=0.3, lw=0.5)
        _lean_ticks(ax)
        ax.tick_params(labelsize=7)
    axes[0, 0].legend(fontsize=7, markerscale=5)
    fig.suptitle(title, fontsize=10)
    return _save(fig, path)


@_deferrable(lambda path, *a, **k: Path(path))
def sphere_projections(path, title, rows) -> Path:
    """One row per series (label, raw (N,3), calibrated (N,3), radius nT): the three planes
    xy, xz, yz, raw (grey) and calibrated (blue), the circle of the reference magnitude
    (seed 000 fig. 14 and 16). Each plane shows the points within BAND |B| of it (raw: of
    its median), so that a calibrated sensor draws the circle and not a filled disc."""
    n = len(rows)
    fig = _figure(11.0, 3.3 * n + 0.5, constrained="fixed")
    axes = np.atleast_2d(fig.subplots(n, 3, squeeze=False))
    phi = np.linspace(0, 2 * np.pi, 181)
    for r, (label, raw, cal, radius) in enumerate(rows):
        raw = np.asarray(raw, float)
        cal = np.asarray(cal, float)
        sl = _thin(len(raw))
        ms = 1.5 if len(raw) > 200 else 5
        for c, (i, j) in enumerate(((0, 1), (0, 2), (1, 2))):
            ax = axes[r, c]
            o = 3 - i - j          # the out-of-plane axis: a band about the plane only
            near_raw = np.abs(raw[:, o] - np.median(raw[:, o])) < BAND * radius
            near_cal = np.abs(cal[:, o]) < BAND * radius
            ax.plot(radius * np.cos(phi) / 1e3, radius * np.sin(phi) / 1e3, "-",
                    color="#2ca02c", lw=0.8, label=f"|B| = {radius / 1e3:.2f} µT")
            rr, cc = raw[near_raw][sl], cal[near_cal][sl]
            ax.plot(rr[:, i] / 1e3, rr[:, j] / 1e3, ".", ms=ms, color=_BEFORE, label="raw")
            ax.plot(cc[:, i] / 1e3, cc[:, j] / 1e3, ".", ms=ms, color=_AFTER,
                    label="calibrated")
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_xlabel(f"B{'xyz'[i]}, µT", fontsize=8)
            ax.set_ylabel(f"B{'xyz'[j]}, µT", fontsize=8)
            _axes_title(ax, f"{label}: {'xyz'[i]}{'xyz'[j]} plane", fontsize=9)
            _lean_ticks(ax, nx=5, ny=5)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3, lw=0.5)
        axes[r, 0].legend(fontsize=6, markerscale=3, loc="upper right")
    fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def _envelope(t, y, max_points=40000):
    """A long curve as the minimum and maximum of each of ~max_points / 2 consecutive
    pieces, in time order: every spike and dip of the curve stays in the drawing (a curve
    of at most max_points points is drawn whole)."""
    n = len(t)
    k = -(-n // (max_points // 2))
    if k <= 2:
        return t, y
    m = n // k * k
    tb, yb = t[:m].reshape(-1, k), y[:m].reshape(-1, k)
    filled = np.where(np.isnan(yb), np.inf, yb)
    lo = np.argmin(filled, axis=1)
    hi = np.argmax(np.where(np.isnan(yb), -np.inf, yb), axis=1)
    first, second = np.minimum(lo, hi), np.maximum(lo, hi)
    rows = np.arange(len(tb))
    idx = np.stack([first, second], axis=1)
    t_out = np.concatenate([tb[rows[:, None], idx].ravel(), t[m:]])
    y_out = np.concatenate([yb[rows[:, None], idx].ravel(), y[m:]])
    return t_out, y_out


@_deferrable(lambda path, *a, **k: Path(path))
def temperature_profile(path, title, series, segments, positions) -> Path:
    """series: [(sensor, time_h (N,), temp_C (N,))]; segments: [(sensor, t0_h, t1_h,
    temp_C)] drawn as thick bars on the sensor's curve; positions: [(number, t0_h, t1_h)]
    shaded alternately and numbered (seed 000 fig. 21 and 23)."""
    fig = _figure(12.0, 4.6, constrained="fixed")
    ax = fig.subplots()
    for k, (num, t0, t1) in enumerate(positions):
        if k % 2:
            ax.axvspan(t0, t1, color="#000000", alpha=0.04, lw=0)
    colors = {}
    for k, (name, t, T) in enumerate(series):
        colors[name] = f"C{k % 10}"
        t, T = _envelope(np.asarray(t, float), np.asarray(T, float))
        ax.plot(t, T, "-", lw=0.8, color=colors[name], label=name)
    first = True
    for name, t0, t1, temp in segments:
        ax.plot([t0, t1], [temp, temp], "-", lw=4, color=colors.get(name, "k"), alpha=0.5,
                solid_capstyle="butt", label="constant-temperature segment" if first else None)
        first = False
    lo, hi = ax.get_ylim()
    hi += 0.08 * (hi - lo)          # room for the position numbers above the curves
    ax.set_ylim(lo, hi)
    for num, t0, t1 in positions:
        ax.text((t0 + t1) / 2, hi, str(num), ha="center", va="top", fontsize=7)
    ax.set_xlabel("time, h (numbers: positions)", fontsize=8)
    ax.set_ylabel("sensor temperature, °C", fontsize=8)
    ax.grid(alpha=0.3, lw=0.5)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=7, ncol=min(6, len(series) + 1), loc="lower right")
    fig.suptitle(title, fontsize=10)
    return _save(fig, path)


@_deferrable(lambda path, *a, **k: Path(path))
def positions_timeline(path, title, rows) -> Path:
    """rows: [(label, time_h (N,), raw (N,3), cal (N,3), ref (N,3), bounds [(pos, t0, t1)])]:
    one row per sensor, columns x, y, z: raw and calibrated minus the reference, nT
    (seed 000 fig. 26; the difference, since the field itself hides the drift)."""
    n = len(rows)
    fig = _figure(12.0, 2.6 * n + 0.6, constrained="fixed")
    axes = np.atleast_2d(fig.subplots(n, 3, squeeze=False))
    for r, (label, t, raw, cal, ref, bounds) in enumerate(rows):
        t = np.asarray(t, float)
        sl = _thin(len(t))
        for c in range(3):
            ax = axes[r, c]
            ax.plot(t[sl], raw[sl, c] - ref[sl, c], ".", ms=1.5, color=_BEFORE, label="raw")
            ax.plot(t[sl], cal[sl, c] - ref[sl, c], ".", ms=1.5, color=_AFTER,
                    label="calibrated")
            ax.axhline(0.0, lw=0.8, color="#2ca02c", label="reference")
            if len(bounds):     # one collection of full-height lines, not a line each
                ax.vlines([t0 for _, t0, _ in bounds], 0, 1,
                          transform=ax.get_xaxis_transform(), color="#888888", lw=0.5,
                          ls=":")
            _axes_title(ax, f"{label}: B{'xyz'[c]} - reference", fontsize=9)
            _lean_ticks(ax, ny=5)   # few ticks: tick objects are most of the drawing time
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3, lw=0.5)
            if r == n - 1:
                ax.set_xlabel("time, h (dotted: next position)", fontsize=8)
            if c == 0:
                ax.set_ylabel("nT", fontsize=8)
    axes[0, 0].legend(fontsize=6, markerscale=4)
    fig.suptitle(title, fontsize=10)
    return _save(fig, path)


@_deferrable(lambda path, *a, **k: Path(path))
def axis_rms_bars(path, title, names, before, after) -> Path:
    """Per sensor (groups) and axis: RMS of the vector residual before (grey) and after
    (coloured by axis), log scale."""
    before = np.asarray(before, float)
    after = np.asarray(after, float)
    fig = _figure(max(6.0, 1.6 * len(names) + 2), 3.8, constrained="fixed")
    ax = fig.subplots()
    x = np.arange(len(names))
    w = 0.13
    for c in range(3):
        ax.bar(x + (2 * c - 2.5) * w, before[:, c], w, color=_BEFORE,
               edgecolor=_AXIS_COLORS[c], lw=0.8, label="before" if c == 0 else None)
        ax.bar(x + (2 * c - 1.5) * w, after[:, c], w, color=_AXIS_COLORS[c],
               label=f"after, {'xyz'[c]}")
    ax.set_yscale("log")
    _fixed_ticks(ax.xaxis, x, names, fontsize=8)
    ax.set_ylabel("vector residual RMS per axis, nT", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.grid(axis="y", alpha=0.3, lw=0.5)
    ax.legend(fontsize=7, ncol=4)
    fig.suptitle(title, fontsize=10)
    return _save(fig, path)
