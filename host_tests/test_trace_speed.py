"""Issue 17, speed: the pieces that replaced finite differences and Python loops give the
same numbers.

* effects.first_order / lag_filter (vectorised first-order recursion, chunked so its
  factors stay in float64's range) equal the plain loop of the flight chain's lag_kernel,
  on irregular time steps with gaps, repeated stamps and time constants from far below
  to far above the step. Tolerance: the vectorised sum carries round-off of about
  eps * k * max|x| after k samples (the docstring's bound), k <= 4000 here, so 1e-11 of
  the series' scale;
* lag_filter_dtau (the derivative's own recursion) equals central differences of the
  loop; the central difference of relative step 1e-5 is off by ~1e-10 (curvature) and
  1e-16 / 1e-5 (round-off) of the column's scale: 1e-6 bounds both (plus the
  round-off floor eps |x| / h where the derivative itself is ~0);
* the analytic columns of a model with the SET/RESET rotation stage (B + c w x B after M)
  equal forward differences (every column is linear in its own parameter there, so
  forward differences are exact to round-off; tolerance as test_trace_jacobian).
"""

from __future__ import annotations

import numpy as np
import pytest

from generator.trace import effects as fx
from generator.trace import tracer as tr

from test_trace_jacobian import REL_TOL, samples


def loop(t, x, tau):
    dt = np.maximum(np.diff(t), 0.0)
    a = dt / (tau + dt)
    out = np.empty(len(x))
    y = out[0] = x[0]
    for k in range(1, len(x)):
        y = y + a[k - 1] * (x[k] - y)
        out[k] = y
    return out


@pytest.mark.parametrize("n", [1, 2, 5, 400, 4000])
def test_lag_filter_equals_the_loop(n):
    rng = np.random.default_rng(n)
    t = np.cumsum(rng.choice([5.0, 5.0, 0.1, 605.0, 0.0], size=n))
    x = 20.0 + np.cumsum(rng.normal(size=n))
    for tau in (1e-9, 0.01, 0.7, 6.0, 90.0, 1e4, 1e8):
        ref = loop(t, x, tau)
        got = fx.lag_filter(t, x, tau)
        assert np.max(np.abs(got - ref)) <= 1e-11 * np.max(np.abs(ref)), (n, tau)
        if n > 2 and tau >= 0.01:
            h = 1e-5 * tau
            fd = (loop(t, x, tau + h) - loop(t, x, tau - h)) / (2 * h)
            g = fx.lag_filter_dtau(t, x, tau)
            floor = 1e-9 * np.max(np.abs(x)) / tau    # the difference's round-off, eps |x| / h
            assert np.max(np.abs(g - fd)) <= 1e-6 * np.max(np.abs(fd)) + floor, (n, tau)


def test_analytic_columns_through_the_set_reset_stage(tmp_path):
    cs, S = samples(tmp_path, "vec")
    rng = np.random.default_rng(5)
    S.rate_frame_dps = rng.normal(scale=3.0, size=(S.n, 3))
    base = tr.base_from_coefficients(cs, "mmc1", 2)
    m = tr.SensorModel.for_samples(base, S)
    e = fx.SetResetRotation(1.0 / (3.0 * 5e4))
    ch = fx.ChannelBias("heater_A", 0.5)
    S.channels["heater_A"] = np.sin(S.time_s / 300.0)
    m = m.with_effect(ch, ch.init_params()).with_effect(e, e.init_params())
    th = m.theta + rng.normal(scale=2.0, size=m.P)
    r0, done = m._analytic_columns(th, S, np.arange(m.P))
    assert set(done) == set(range(m.P))     # nothing left to finite differences
    cols = np.arange(m.P)
    J_fd = m._fd_columns(th, S, cols, r0)
    for k, c in enumerate(cols):
        scale = max(np.max(np.abs(J_fd[:, k])), 1e-12)
        assert np.max(np.abs(done[c] - J_fd[:, k])) <= REL_TOL * scale + 1e-9, c
