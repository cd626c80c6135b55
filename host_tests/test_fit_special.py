"""fit.special replaces scipy.stats.chi2.ppf and scipy.ndimage.median_filter on the fit's
path (their imports cost more than the fit's use of them): the same values, bit for bit."""

from __future__ import annotations

import itertools
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from generator.fit.special import chi2_quantile, running_median


def _bits(a):
    return np.asarray(a, np.float64).view(np.uint64)


@settings(max_examples=300, deadline=None)
@given(p=st.one_of(st.sampled_from([0.5, 0.9, 0.99, 0.999, 1 - 1e-3, 1 - 1e-6, 1 - 1e-9]),
                   st.floats(1e-12, 1 - 1e-12)),
       dof=st.one_of(st.integers(1, 10**6), st.floats(1e-3, 1e7)))
def test_chi2_quantile_is_scipy_stats_ppf_bit_for_bit(p, dof):
    from scipy.stats import chi2

    want = float(chi2.ppf(p, dof))
    got = chi2_quantile(p, dof)
    assert _bits(got) == _bits(want)
    # and as the callers divide it (goodness, floor_check, coils)
    assert _bits(got / dof) == _bits(float(chi2.ppf(p, dof) / dof))


def _median_filter(a, size):
    from scipy.ndimage import median_filter

    return median_filter(np.asarray(a, float), size=size, mode="nearest")


@settings(max_examples=400, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 600),
       size=st.sampled_from([1, 3, 5, 7, 9]), quantum=st.sampled_from([0.0, 0.7, 1.0, 25.0]),
       spikes=st.floats(0.0, 0.1), special=st.sampled_from(["none", "nan", "negzero", "inf"]))
def test_running_median_is_ndimage_median_filter_bit_for_bit(seed, n, size, quantum, spikes,
                                                             special):
    rng = np.random.default_rng(seed)
    a = np.cumsum(rng.normal(0, 0.3, n)) + 20.0
    hit = rng.random(n) < spikes
    a[hit] += rng.normal(0, 50, hit.sum())
    if quantum:                     # reported in steps: many ties
        a = np.round(a / quantum) * quantum
    j = int(rng.integers(0, n))
    if special == "nan":
        a[j] = np.nan
    elif special == "negzero":
        a[j] = -0.0
    elif special == "inf":
        a[j] = -np.inf
    got, want = running_median(a, size), _median_filter(a, size)
    assert np.array_equal(_bits(got), _bits(want))


def test_running_median_of_5_exhaustive_orders():
    # every ordering, with ties, of 5 values from {0..4}: the middle of each window
    for t in itertools.product(range(5), repeat=5):
        a = np.array(t, float)
        assert running_median(a, 5)[2] == np.sort(a)[2]


def test_running_median_long_series_in_blocks():
    # beyond one block of the window copy (size 7 takes the partition path)
    a = np.round(np.random.default_rng(3).normal(0, 2, 200_001), 1)
    for size in (3, 5, 7):
        assert np.array_equal(_bits(running_median(a, size)), _bits(_median_filter(a, size)))


def test_fit_path_imports_neither_scipy_stats_nor_ndimage(fm1_dir):
    # the point of fit.special: `magcal fit` no longer pays these imports
    code = ("import sys; from generator import pipeline; "
            "pipeline.fit(sys.argv[1], [sys.argv[2]]); "
            "print(sorted(m for m in sys.modules if m in ('scipy.stats', 'scipy.ndimage')))")
    root = Path(__file__).resolve().parent.parent
    p = subprocess.run([sys.executable, "-c", code, str(fm1_dir / "unit.toml"),
                        str(fm1_dir / "thermal_12pos.csv")], capture_output=True, text=True,
                       env=dict(os.environ, PYTHONPATH=str(root), MAGCAL_WORKERS="1",
                                OPENBLAS_NUM_THREADS="1"), cwd=root)
    assert p.returncode == 0, p.stderr[-500:]
    assert p.stdout.strip().splitlines()[-1] == "[]"
