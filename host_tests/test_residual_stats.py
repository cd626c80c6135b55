"""The Gauss-Newton iterates' cost and gradient from sums centred on the run's start
(fit/reference.py: ResidualStats) against the per-sample sums (vector_normal, itself
checked against an explicit Jacobian in test_reference_moments.py), and the start's
residual variance from blocked normal equations (_linear_residual_var) against a
least-squares solve of the whole design.

Tolerance: the same sums in a different order (and, for the cost, expanded as
r0 + L phi around the start), so they agree to float64 rounding: N = 3000 terms whose
largest parts are ~1e3 times the result (readings ~3e4 nT against residuals and offset
changes of ~10-300 nT), N * eps * 1e3 ~ 1e-10 relative; 1e-8 leaves margin, while a
wrong index, sign or missing term is an O(1e-2..1) relative error at the points tried
(each several nT or 1e-3 of M away from the start).
"""

import numpy as np
import pytest

from generator.fit.reference import (ResidualStats, _linear_residual_var, _linear_sums,
                                     _powers, reading_moments, vector_normal)

REL = 1e-8


def _case(K, seed, n=3000):
    rng = np.random.default_rng(seed)
    P = _powers(rng.uniform(-1.0, 1.0, n), K - 1)
    x = rng.normal(size=(n, 3)) * 3e4 + 500.0
    Mt = rng.normal(size=(K, 3, 3)) * 0.01
    Mt[0] += np.eye(3)
    bt = rng.normal(size=(K, 3)) * 300.0
    B = np.einsum("nk,kij,nj->ni", P, Mt, x - P @ bt) + rng.normal(size=(n, 3)) * 30.0
    w = rng.uniform(0.5, 2.0, n)
    return rng, P, x, B, bt, Mt, w


@pytest.mark.parametrize("K", [1, 2, 4])
@pytest.mark.parametrize("eiv_var", [0.0, 25.0])
def test_cost_and_gradient_equal_the_per_sample_sums(K, eiv_var):
    rng, P, x, B, bt, Mt, w = _case(K, 10 + K)
    b0 = bt + rng.normal(size=bt.shape) * 5.0          # the run's start
    M0 = Mt + rng.normal(size=Mt.shape) * 1e-3
    mom = reading_moments(P, x, w)
    rs = ResidualStats(P, x, B, w, b0, M0, mom)
    points = [(b0, M0), (bt, Mt),
              (b0 + rng.normal(size=bt.shape) * 20.0, M0 + rng.normal(size=Mt.shape) * 3e-3)]
    for bp, Mp in points:
        c_ref, _, g_ref, _ = vector_normal(P, x, B, bp, Mp, True, w, eiv_var, mom)
        c, g = rs.cost_grad(bp, Mp, True, eiv_var, mom["W"])
        assert abs(c - c_ref) <= REL * abs(c_ref)
        assert np.max(np.abs(g - g_ref)) <= REL * np.max(np.abs(g_ref))
        c_only, none = rs.cost_grad(bp, Mp, False, eiv_var, mom["W"])
        assert none is None and c_only == c


@pytest.mark.parametrize("K", [1, 4])
def test_linear_residual_variance_equals_least_squares(K):
    rng, P, x, B, *_ = _case(K, 20 + K)
    n = len(x)
    A = np.concatenate([(P[:, :, None] * x[:, None, :]).reshape(n, -1), P], axis=1)
    sol, *_ = np.linalg.lstsq(A, B, rcond=None)
    ref = float(np.sum((B - A @ sol) ** 2)) / (3 * (n - 4 * K))
    got = _linear_residual_var(P, x, B, _linear_sums(P, x, B))
    # the residual sum of squares is stationary at the solution: an error d in the
    # solution changes it by O(d^2), so it agrees to rounding despite the normal equations
    assert abs(got - ref) <= REL * ref
