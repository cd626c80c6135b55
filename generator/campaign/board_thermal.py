"""A board's temperature as a first-order lag of the chamber (or of any driving temperature)."""

from __future__ import annotations

import numpy as np


def first_order_lag(time_s, input_value, tau_s, initial=None) -> np.ndarray:
    """Output of dy/dt = (u - y) / tau sampled at time_s, exact for u linear between
    samples. initial: y at time_s[0] (default u[0])."""
    t = np.asarray(time_s, dtype=float)
    u = np.asarray(input_value, dtype=float)
    y = np.empty_like(u)
    y[0] = u[0] if initial is None else initial
    if tau_s <= 0:
        y[:] = u
        return y
    h = np.diff(t)
    a = np.exp(-h / tau_s)
    slope_tau = np.divide(u[1:] - u[:-1], h, out=np.zeros_like(h), where=h > 0) * tau_s
    for n in range(len(h)):
        y[n + 1] = u[n + 1] - slope_tau[n] + (y[n] - u[n] + slope_tau[n]) * a[n]
    return y
