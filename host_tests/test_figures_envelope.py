"""The temperature profile of a long recording is drawn as the minimum and maximum of
consecutive pieces (figures_seed._envelope): a spike or a dip of a single sample stays
in the drawing, which an every-k-th thinning would drop without saying so."""

from __future__ import annotations

import numpy as np

from generator.report.figures_seed import _envelope


def test_single_sample_extremes_are_kept_in_time_order():
    t = np.arange(1_000_000.0)
    y = np.sin(t / 50_000.0)
    y[543_210], y[777_777] = 9.0, -7.0          # one-sample spike and dip
    y[123] = np.nan
    t_out, y_out = _envelope(t, y)
    assert len(t_out) <= 40_000 + 50            # bounded drawing
    assert y_out.max() == 9.0 and y_out.min() == -7.0
    assert 543_210.0 in t_out and 777_777.0 in t_out
    assert np.all(np.diff(t_out) >= 0)
    # an every-k-th thinning to the same size would have missed both
    k = len(t) // 40_000
    assert 9.0 not in y[::k] and -7.0 not in y[::k]


def test_short_curves_are_drawn_whole():
    t = np.arange(36_000.0)                     # the thermal campaign's length per sensor
    y = np.cos(t)
    t_out, y_out = _envelope(t, y)
    assert np.array_equal(t_out, t) and np.array_equal(y_out, y)
