"""Speed-ups of the fit that must not change a bit of what it computes (issue 20 item 3):
each rewritten helper against the code it replaced (as at 5335ede), on random inputs."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from generator.fit.reference import DIFF_CLIP_SIGMAS, difference_noise_var


def _difference_noise_var_5335ede(series):
    dd = []
    for a in series:
        a = np.asarray(a, float)
        a = a.reshape(len(a), -1)
        if len(a) >= 3:
            dd.append(a[2:] - 2.0 * a[1:-1] + a[:-2])
    if not dd or sum(len(a) for a in dd) < 3:
        return None
    d = np.concatenate(dd)
    keep = np.ones(d.shape, bool)
    for _ in range(5):
        mu = np.array([np.mean(d[keep[:, j], j]) for j in range(d.shape[1])])
        var = np.array([np.mean((d[keep[:, j], j] - mu[j]) ** 2) for j in range(d.shape[1])])
        new = np.abs(d - mu) <= DIFF_CLIP_SIGMAS * np.sqrt(var)
        if np.array_equal(new, keep):
            break
        keep = new
    return var / 6.0


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), sizes=st.lists(st.integers(1, 3000), min_size=1,
                                                      max_size=4),
       k=st.sampled_from([1, 3]), q=st.sampled_from([0.0, 1.0, 25.0]),
       spikes=st.floats(0.0, 0.05), flat=st.booleans())
def test_difference_noise_var_bit_for_bit(seed, sizes, k, q, spikes, flat):
    rng = np.random.default_rng(seed)
    series = []
    for n in sizes:
        a = np.cumsum(rng.normal(0, 30, (n, k)), axis=0) + rng.normal(0, 5, (n, k))
        hit = rng.random((n, k)) < spikes
        a[hit] += rng.normal(0, 1e4, hit.sum())
        if flat:
            a[:, 0] = 7.0
        if q:
            a = np.round(a / q) * q
        series.append(a if k == 3 or rng.random() < 0.5 else a[:, 0])
    got, want = difference_noise_var(series), _difference_noise_var_5335ede(series)
    if want is None:
        assert got is None
    else:
        assert np.array_equal(got.view(np.uint64), want.view(np.uint64))


# ---- the temperature reporting step's rows per bin (reference.temperature_error_rows) ---
# The per-bin sums now come from the bin's moments (sum w, sum w x, sum w x x^T) instead of
# a row per sample: the same sums in another order, equal to rounding. Bound: a recursive
# sum of N terms errs by at most N eps relative to the sum of their magnitudes (N <= 3000
# per bin here: 7e-13); y = x - b(T) with |b| < |x| / 10 loses at most a factor ~1.2 more
# in the moment form. 1e-10 of each bin row's magnitude covers both with margin, and a
# wrong term (a sign, a transposed M, a missing derivative) is off by O(1).
@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), degree=st.integers(1, 3), n=st.integers(5, 3000),
       n_files=st.integers(1, 3), clamp=st.booleans(), weighted=st.booleans())
def test_temperature_error_rows_match_the_rows_per_sample(seed, degree, n, n_files, clamp,
                                                         weighted):
    from generator.fit.reference import (_bin_sums, _powers, temperature_bins,
                                         temperature_derivative, temperature_error_rows,
                                         vector_gradient_rows)

    rng = np.random.default_rng(seed)
    K = degree + 1
    T = np.round(rng.uniform(-20, 60, n) / 0.7) * 0.7        # quantised: shared values
    grp = rng.integers(0, n_files, n)
    t_range = (-10.0, 50.0) if clamp else (float(T.min()), float(T.max()))
    tau = max(abs(t_range[0] - 25.0), abs(t_range[1] - 25.0), 1.0)
    P = _powers((np.clip(T, *t_range) - 25.0) / tau, degree)
    x = rng.normal(0, 30000, (n, 3))
    bp = rng.normal(0, 500, (K, 3)) / np.arange(1, K + 1)[:, None] ** 2
    Mp = np.eye(3)[None] * (np.arange(K) == 0)[:, None, None] + rng.normal(0, 0.02, (K, 3, 3))
    w = rng.uniform(0.5, 2.0, n_files)[grp] if weighted else None
    key, var_b, _ = temperature_bins(T, grp)
    got = temperature_error_rows(P, x, (bp, Mp), w, T, key, len(var_b), tau, t_range)
    D = temperature_derivative(P, x, (bp, Mp), T, tau, t_range)
    rows = vector_gradient_rows(P, x, (bp, Mp), w, D)
    want = _bin_sums(np.zeros((len(var_b), 12 * K)), key, rows)
    scale = _bin_sums(np.zeros((len(var_b), 12 * K)), key, np.abs(rows))
    assert np.all(np.abs(got - want) <= 1e-10 * scale.max(axis=1, keepdims=True))


# ---- b(T), M(T) once per reported temperature value (calibration.PerValue) -------------
@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 2000), q=st.sampled_from([0.0, 0.7]),
       h=st.sampled_from([0.0, 0.5, -0.5]))
def test_per_value_is_the_per_sample_arithmetic(seed, n, q, h):
    from generator.fit.calibration import SensorCalibration

    rng = np.random.default_rng(seed)
    T = rng.uniform(-30, 70, n)
    if q:
        T = np.round(T / q) * q
    cal = SensorCalibration("s", rng.normal(0, 300, (4, 3)),
                            np.eye(3) + rng.normal(0, 0.01, (4, 3, 3)), 25.0, -20.0, 60.0)
    x = rng.normal(0, 4e4, (n, 3))
    pv = cal.per_value(T)
    for got, want in ((pv.apply64(x, h), cal.apply64(x, T + h)), (pv.M_at(h), cal.M_at(T + h)),
                      (pv.b_at(h), cal.b_at(T + h))):
        assert np.array_equal(got.view(np.uint64), want.view(np.uint64))
