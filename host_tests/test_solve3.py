"""reference._solve_M's per-sample M(T_n)^-1 v_n by the adjugate (reference._solve3, issue
20 item 3: a per-sample LAPACK solve was ~7 % of the thermal fit): the same solutions as
LU up to float64 rounding, and LU itself where an M is near singular."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from generator.fit.reference import CLOSED_SOLVE_MIN_ORTHOGONALITY, _solve3, _solve_M


def _lu(P, Mp, v):
    return np.linalg.solve(np.einsum("nk,kij->nij", P, Mp), v[:, :, None])[:, :, 0]


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 400), K=st.integers(2, 4),
       spread=st.floats(0.0, 0.4))
def test_same_solution_as_lu_on_calibration_like_matrices(seed, n, K, spread):
    # M(T) = I + a polynomial in the scaled temperature d in [-1, 1], coefficients up to
    # `spread` / K each: singular values within 1 -/+ spread, condition number <= ~2.3.
    # Both solves err by a few ulps times the condition number (a 3x3 adjugate: each
    # cofactor a difference of two products, the determinant a sum of three), so their
    # difference is < 1e-14 of the solution's size; 1e-13 is that with a margin of 10.
    rng = np.random.default_rng(seed)
    d = rng.uniform(-1, 1, n)
    P = d[:, None] ** np.arange(K)
    Mp = rng.uniform(-1, 1, (K, 3, 3)) * spread / K
    Mp[0] += np.eye(3)
    Mp[1, 0, 0] += 1e-3                       # a temperature term: the per-sample path
    v = rng.normal(0, 5e4, (n, 3))
    got, want = _solve_M(P, Mp, v), _lu(P, Mp, v)
    scale = np.abs(want).max(axis=1, keepdims=True)
    assert np.all(np.abs(got - want) <= 1e-13 * scale)


def test_near_singular_is_left_to_lu():
    # M(d) = I + d D with the last row (0, d, 1 - d (1 - 1e-6)): at d = 1 it is
    # (0, 1, 1e-6), nearly the middle row (det 1e-6, not 0): |det| / (product of the row
    # norms) below CLOSED_SOLVE_MIN_ORTHOGONALITY -> _solve3 declines and _solve_M
    # returns LU's bits
    n = 50
    P = np.stack([np.ones(n), np.linspace(-1, 1, n)], 1)
    Mp = np.zeros((2, 3, 3))
    Mp[0] = np.eye(3)
    Mp[1, 2] = [0.0, 1.0, -(1 - 1e-6)]
    M = np.einsum("nk,kij->nij", P, Mp)
    rows = np.linalg.norm(M, axis=2).prod(axis=1)
    assert 0 < abs(np.linalg.det(M[-1])) < CLOSED_SOLVE_MIN_ORTHOGONALITY * rows[-1]
    v = np.random.default_rng(1).normal(size=(n, 3))
    assert _solve3(np.ascontiguousarray(M.reshape(n, 9).T), v) is None
    assert np.array_equal(_solve_M(P, Mp, v), _lu(P, Mp, v))
    # the same without that sample: every M well conditioned, the adjugate's solution
    assert _solve3(np.ascontiguousarray(M[:-5].reshape(n - 5, 9).T), v[:-5]) is not None
