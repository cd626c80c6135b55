"""Two numerical helpers of the fit without scipy's heavy modules: the chi-square quantile
(scipy.stats imports in ~0.5-0.65 s of CPU, against ~0.15 s for scipy.special, on this
machine) and the running median (scipy.ndimage: ~0.2 s). `magcal fit` paid both imports
on every run, for a handful of quantiles and two 5-sample median filters.

Both give the values of the calls they replace bit for bit (host_tests/test_fit_special.py):

* chi2_quantile(p, dof) is what scipy.stats.chi2.ppf(p, dof) computes for 0 < p < 1 and
  dof > 0 (scipy 1.17: chi2_gen._ppf = 2 gammaincinv(dof / 2, p), times scale 1 plus
  loc 0, both exact);
* running_median(a, size) is scipy.ndimage.median_filter(a, size=size, mode="nearest")
  of a finite 1-D series with an odd size: the middle one of the `size` values around
  each sample (the ends repeated), an element of the series, not an interpolation; for
  sizes 3 and 5 by a network of minima and maxima on shifted views (a selection too).
  A series with a non-finite value or a negative zero goes to scipy.ndimage itself (its
  ordering of NaN is its own, and between 0.0 and -0.0, equal values, the one it picks).
"""

from __future__ import annotations

import numpy as np

# samples per block of running_median's (n, size) window copy: bounded memory whatever n
_MEDIAN_CHUNK = 1 << 16


def chi2_quantile(p: float, dof: float) -> float:
    """The p quantile of the chi-square distribution with dof degrees of freedom
    (scipy.stats.chi2.ppf(p, dof), bit for bit; 0 < p < 1, dof > 0)."""
    from scipy.special import gammaincinv

    return float(2.0 * gammaincinv(dof / 2.0, p))


def running_median(a, size: int) -> np.ndarray:
    """scipy.ndimage.median_filter(a, size=size, mode="nearest") of a 1-D series, size
    odd (module docstring)."""
    a = np.asarray(a, float)
    if (a.ndim != 1 or size % 2 != 1 or not np.isfinite(a).all()
            or np.any(np.signbit(a) & (a == 0))):
        from scipy.ndimage import median_filter

        return median_filter(a, size=size, mode="nearest")
    h = size // 2
    if h == 0 or len(a) == 0:
        return a.copy()
    padded = np.concatenate([np.full(h, a[0]), a, np.full(h, a[-1])])
    n = len(a)
    if size in (3, 5):
        v = [padded[i:i + n] for i in range(size)]
        if size == 5:       # median of 5: med3(e, max(min(a,b), min(c,d)), min(max(a,b), max(c,d)))
            lo = np.maximum(np.minimum(v[0], v[1]), np.minimum(v[2], v[3]))
            hi = np.minimum(np.maximum(v[0], v[1]), np.maximum(v[2], v[3]))
            v = [v[4], lo, hi]
        return np.maximum(np.minimum(v[0], v[1]), np.minimum(np.maximum(v[0], v[1]), v[2]))
    win = np.lib.stride_tricks.sliding_window_view(padded, size)
    out = np.empty_like(a)
    for s in range(0, len(a), _MEDIAN_CHUNK):
        out[s:s + _MEDIAN_CHUNK] = np.partition(win[s:s + _MEDIAN_CHUNK], h, axis=1)[:, h]
    return out
