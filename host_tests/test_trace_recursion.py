"""Issue 20 F5 (review 20e): the trace's first-order recursion (trace.effects.first_order,
under lag_filter / lag_filter_dtau: the thermal lag's element temperature and the lagged
channels) at C speed, with the SAME float64 results bit for bit as before.

Two changes, both claimed exact (compared as bit patterns, no tolerance):
* the short-memory branch's per-row Python loop now runs compiled (trace.recursion,
  -ffp-contract=off): the same subtraction, product and sum per row, in the same order;
* the vectorised branch finds each chunk's end in doubling windows (effects._span_end)
  instead of over the rest of the stretch (quadratic in the rows with many chunks).

The oracle is the code as it was (`old_first_order` below, copied from
generator/trace/effects.py at d1d6bb7, its plain loop included), on the real files (the
shared flight_6h temperatures, the four PX4 office magnetometers' chip temperatures with
their real, jittery time stamps), on gaps and repeated or backward stamps, and on random
irregular steps (hypothesis).
"""

from __future__ import annotations

import csv

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from generator.trace import effects as fx
from generator.trace import recursion

LOG_SPAN = 500.0


def old_first_order(a, x, y0) -> np.ndarray:
    """generator.trace.effects.first_order at d1d6bb7, verbatim but for its name."""
    x = np.asarray(x, float)
    n = len(x)
    out = np.empty(n)
    if n == 0:
        return out
    out[0] = y0
    if n == 1:
        return out
    a = np.asarray(a, float)
    ax = a * x[1:]
    with np.errstate(divide="ignore"):
        lq = np.log1p(-a)
    hard = ~np.isfinite(lq) | (lq < -LOG_SPAN)
    lq = np.where(hard, 0.0, lq)
    L = np.cumsum(lq)
    if (len(np.nonzero(hard)[0]) - L[-1] / LOG_SPAN) * 100 > n:
        y = float(y0)
        al, xl = a.tolist(), x.tolist()
        for k in range(1, n):
            y = y + al[k - 1] * (xl[k] - y)
            out[k] = y
        return out
    k, y = 0, float(y0)
    cut = np.nonzero(hard)[0]
    ci = 0
    while k < n - 1:
        while ci < len(cut) and cut[ci] < k:
            ci += 1
        stop = cut[ci] if ci < len(cut) else n - 1
        if stop == k:
            y = x[k + 1]
            out[k + 1] = y
            k += 1
            continue
        Lk = L[k - 1] if k > 0 else 0.0
        e = int(np.searchsorted(-(L[k:stop] - Lk), LOG_SPAN, side="right")) + k
        e = max(e, k + 1)
        rel = L[k:e] - Lk
        csum = np.cumsum(ax[k:e] * np.exp(-rel))
        seg = np.exp(rel) * (y + csum)
        out[k + 1:e + 1] = seg
        y = float(seg[-1])
        k = e
    return out


def old_branch(a, n) -> str:
    """Which branch old_first_order takes ("loop" or "chunks")."""
    a = np.asarray(a, float)
    with np.errstate(divide="ignore"):
        lq = np.log1p(-a)
    hard = ~np.isfinite(lq) | (lq < -LOG_SPAN)
    L = np.cumsum(np.where(hard, 0.0, lq))
    return "loop" if (len(np.nonzero(hard)[0]) - L[-1] / LOG_SPAN) * 100 > n else "chunks"


def old_lag_filter(t, T, tau_s):
    t, T = np.asarray(t, float), np.asarray(T, float)
    if len(T) == 0:
        return np.empty_like(T)
    if tau_s <= 0:
        return T.copy()
    dt = np.maximum(np.diff(t), 0.0)
    return old_first_order(dt / (tau_s + dt), T, T[0])


def old_lag_filter_dtau(t, T, tau_s):
    t, T = np.asarray(t, float), np.asarray(T, float)
    if len(T) < 2 or tau_s <= 0:
        return np.zeros(len(T))
    el = old_lag_filter(t, T, tau_s)
    dt = np.maximum(np.diff(t), 0.0)
    u = np.concatenate([[0.0], -(T[1:] - el[:-1]) / (tau_s + dt)])
    return old_first_order(dt / (tau_s + dt), u, 0.0)


def same_bits(got, want) -> bool:
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    return got.shape == want.shape and np.array_equal(got.view(np.uint64),
                                                      want.view(np.uint64))


def check_all(t, T, taus) -> set:
    """lag_filter and lag_filter_dtau equal the old ones bit for bit at every tau; the
    branches the old code took."""
    branches = set()
    dt = np.maximum(np.diff(np.asarray(t, float)), 0.0)
    for tau in taus:
        assert same_bits(fx.lag_filter(t, T, tau), old_lag_filter(t, T, tau)), tau
        assert same_bits(fx.lag_filter_dtau(t, T, tau), old_lag_filter_dtau(t, T, tau)), tau
        if len(T) > 1:
            branches.add(old_branch(dt / (tau + dt), len(T)))
    return branches


def scan_taus(t, n=12):
    """Time constants over ThermalLag's scan range (2 steps .. a quarter of the span),
    and beyond it on both sides."""
    t = np.asarray(t, float)
    dt = float(np.median(np.diff(t)))
    lo, hi = max(2 * dt, 0.05), max(0.25 * float(np.ptp(t)), 8 * dt)
    return [1e-9, 0.1 * dt] + list(np.geomspace(lo, hi, n)) + [1e3 * float(np.ptp(t))]


# ---- the compiled loop is the Python loop ----------------------------------------------

def test_the_loop_is_compiled():
    # the machine has a C compiler (the host build needs it): the fast path is tested
    assert recursion.compiled()


@settings(max_examples=200, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.floats(0.0, 1.0), st.floats(-1e6, 1e6)), min_size=1,
                max_size=300),
       st.floats(-1e6, 1e6))
def test_compiled_loop_equals_the_python_loop(pairs, y0):
    a = np.array([p[0] for p in pairs[1:]])
    x = np.array([p[1] for p in pairs])
    got, want = np.empty(len(x)), np.empty(len(x))
    recursion.first_order_loop(a, x, y0, got)
    recursion.python_loop(a, x, y0, want)
    assert same_bits(got, want)


# ---- real files ----------------------------------------------------------------------

def test_flight_6h_temperatures(fm1_dir):
    with open(fm1_dir / "flight_6h.csv") as f:
        rows = [r for r in csv.reader(line for line in f if not line.startswith("#"))]
    head, body = rows[0], rows[1:]
    t = np.array([float(r[head.index("time_s")]) for r in body])
    branches = set()
    for col in [c for c in head if c.endswith("_temp_C")]:
        T = np.array([float(r[head.index(col)]) for r in body])
        branches |= check_all(t, T, scan_taus(t))
        # the same with a telemetry gap of an hour cut in (the recursion's hard cuts)
        tg = np.where(np.arange(len(t)) >= len(t) // 2, t + 3600.0, t)
        branches |= check_all(tg, T, scan_taus(tg, 4))
    assert branches == {"loop", "chunks"}      # both of the old code's branches met


@pytest.mark.parametrize("k", [0, 1, 2, 3])
def test_px4_office_chip_temperatures(realdata_dir, k):
    path = realdata_dir / "px4_ecl_office" / f"sensor_mag_{k}.csv"
    with open(path) as f:
        r = csv.DictReader(f)
        rows = [(float(d["timestamp"]) * 1e-6, float(d["temperature"])) for d in r]
    t = np.array([p[0] for p in rows])
    T = np.array([p[1] for p in rows])
    assert len(T) > 1000 and np.ptp(T) > 1.0      # a real warm-up, real stamps
    branches = check_all(t, T, scan_taus(t))
    assert branches == {"loop", "chunks"}


# ---- gaps, repeated and backward stamps, irregular steps --------------------------------

def test_many_chunks_with_gaps():
    # the case of the review: short memory against the span, so many chunks (the old
    # search over the rest of each stretch was quadratic); gaps every few hundred rows
    rng = np.random.default_rng(20)
    n = 60_000
    steps = rng.choice([1.0, 1.0, 1.0, 0.0, 0.5, 7200.0], p=[.3, .3, .3, .04, .0595, .0005],
                       size=n - 1)
    t = np.concatenate([[0.0], np.cumsum(steps)])
    T = 20.0 + np.cumsum(rng.normal(scale=0.01, size=n))
    assert check_all(t, T, [0.005, 0.5, 3.0, 40.0, 800.0, 1e5]) == {"loop", "chunks"}


step_kinds = st.one_of(
    st.floats(0.0, 2.0),                          # jittery regular steps
    st.sampled_from([0.0, 0.0, 1.0, -0.5]),       # repeated and backward stamps
    st.floats(100.0, 1e5),                        # gaps
)


@settings(max_examples=150, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(step_kinds, min_size=0, max_size=2500),
       st.lists(st.floats(-50.0, 80.0), min_size=1, max_size=40),
       st.floats(1e-6, 1e7))
def test_irregular_steps(steps, levels, tau):
    t = np.concatenate([[0.0], np.cumsum(steps)])
    T = np.resize(np.array(levels), len(t)) + 1e-3 * np.arange(len(t))
    check_all(t, T, [tau, tau * 1e-3, tau * 1e3])


def test_span_end_equals_the_whole_stretch_search():
    # the windows start at _SPAN_WINDOW rows: chunks longer than it (long memory against
    # the step) need the doubling
    n = 5 * fx._SPAN_WINDOW
    rng = np.random.default_rng(3)
    lq = -rng.uniform(0.0, 0.2, size=n)
    L = np.cumsum(lq)
    for k in (0, 1, 17, 3000, n // 2):
        for stop in (k + 1, k + 50, n - 1):
            if stop <= k:
                continue
            Lk = L[k - 1] if k > 0 else 0.0
            want = int(np.searchsorted(-(L[k:stop] - Lk), LOG_SPAN, side="right")) + k
            assert fx._span_end(L, k, stop, Lk) == want, (k, stop)


# ---- memory: the recursion's temporaries -------------------------------------------------

@pytest.mark.parametrize("tau", [0.005, 50.0])       # the loop branch, the chunked branch
def test_recursion_temporaries(tau):
    # review 20e: ~160 B a row of peak growth on long files; the loop branch alone held
    # its inputs as Python float lists (2 x 32 B a row) besides 6-7 arrays. Now, besides
    # the caller's inputs, lag_filter_dtau holds at most: the output, the factors, the
    # forcing, the running log factor (8 B a row each) and the memoryless-step mask (1 B)
    # -- 33 B a row; the bound: 5 arrays of 8 B (the old code: 57-121 B a row, measured)
    import tracemalloc
    n = 200_000
    rng = np.random.default_rng(4)
    t = np.cumsum(rng.choice([1.0, 0.0, 0.5, 3600.0], p=[.6, .1, .2999, .0001], size=n))
    T = 20.0 + np.cumsum(rng.normal(scale=0.01, size=n))
    el = fx.lag_filter(t, T, tau)
    for f in (lambda: fx.lag_filter(t, T, tau), lambda: fx.lag_filter_dtau(t, T, tau, el)):
        tracemalloc.start()
        try:
            f()
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak <= 5 * 8 * n, f"{peak / n:.1f} B a row"


def test_without_a_compiler_the_python_loop_gives_the_same(monkeypatch):
    rng = np.random.default_rng(9)
    t = np.cumsum(rng.choice([1.0, 0.0, 0.5, 900.0], p=[.6, .1, .29, .01], size=3000))
    T = 20.0 + np.cumsum(rng.normal(scale=0.05, size=3000))
    dt = np.maximum(np.diff(t), 0.0)
    assert old_branch(dt / (1e-4 + dt), len(t)) == "loop"
    compiled = fx.lag_filter(t, T, 1e-4)
    monkeypatch.setattr(recursion, "_lib", False)        # as when the build failed
    assert not recursion.compiled()
    assert same_bits(fx.lag_filter(t, T, 1e-4), compiled)
    assert same_bits(fx.lag_filter(t, T, 1e-4), old_lag_filter(t, T, 1e-4))
