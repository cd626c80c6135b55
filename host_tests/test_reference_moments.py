"""The reference fit's normal equations from sufficient statistics (fit/reference.py:
reading_moments, normal_matrix, ReadingStats, vector_normal) against an explicit
per-sample Jacobian built here from the model r_n = M(T_n)(x_n - b(T_n)) - B_n itself.

Tolerance: the two are the same sums in a different order, so they agree to float64
rounding: each entry is a sum of N = 2000 products whose terms carry at most ~1e3 times
the entry's size (x ~ 3e4 nT against offsets ~3e2 nT, powers of d in [-1, 1]), so
N * eps * 1e3 ~ 1e-10 relative to the largest entry; 1e-8 leaves margin, while a wrong
index or a missing term is an O(1) relative error.
"""

import numpy as np
import pytest

from generator.fit.reference import (ReadingStats, _powers, _split_information,
                                     normal_matrix, reading_moments, vector_normal)

REL = 1e-8


def _case(K, seed, n=2000):
    rng = np.random.default_rng(seed)
    P = _powers(rng.uniform(-1.0, 1.0, n), K - 1)
    x = rng.normal(size=(n, 3)) * 3e4 + 500.0
    B = x + rng.normal(size=(n, 3)) * 200.0
    bp = rng.normal(size=(K, 3)) * 300.0
    Mp = rng.normal(size=(K, 3, 3)) * 0.05
    Mp[0] += np.eye(3)
    grp = np.sort(rng.integers(0, 3, n))
    w = np.array([1.0, 0.4, 2.5])[grp]
    return P, x, B, bp, Mp, w, grp


def _jacobian(P, x, bp, Mp):
    """(N, 3, 12K) d r_n / d(b[k,l], M[k,a,c]), written out from the model."""
    n, K = P.shape
    MT = np.einsum("nk,kij->nij", P, Mp)
    y = x - P @ bp
    J = np.zeros((n, 3, 12 * K))
    for k in range(K):
        for l in range(3):
            J[:, :, 3 * k + l] = -P[:, k, None] * MT[:, :, l]
        for a in range(3):
            for c in range(3):
                J[:, a, 3 * K + 9 * k + 3 * a + c] = P[:, k] * y[:, c]
    return J


def _close(a, b):
    return np.max(np.abs(a - b)) <= REL * np.max(np.abs(b))


@pytest.mark.parametrize("K", [1, 2, 3, 4])
@pytest.mark.parametrize("eiv_var", [0.0, 25.0])
def test_normal_equations_equal_the_explicit_jacobian(K, eiv_var):
    P, x, B, bp, Mp, w, _ = _case(K, seed=K)
    J = _jacobian(P, x, bp, Mp)
    r = np.einsum("nk,kij->nij", P, Mp) @ (x - P @ bp)[:, :, None]
    r = r[:, :, 0] - B
    JTJ = np.einsum("nip,n,niq->pq", J, w, J)
    g = np.einsum("nip,n,ni->p", J, w, r)
    cost = float(np.sum(w[:, None] * r * r))
    if eiv_var:        # adjusted least squares: eiv_var |M(T_n)|_F^2 taken off per sample
        Pw = P * w[:, None]
        JTJ[3 * K:, 3 * K:] -= eiv_var * np.kron(P.T @ Pw, np.eye(9))
        g[3 * K:] -= eiv_var * ((P.T @ Pw) @ Mp.reshape(K, 9)).ravel()
        cost -= eiv_var * float(np.sum(w * np.sum(np.einsum("nk,kij->nij", P, Mp) ** 2,
                                                  axis=(1, 2))))
    c2, JTJ2, g2, r2 = vector_normal(P, x, B, bp, Mp, True, w, eiv_var)
    assert _close(JTJ2, JTJ)
    assert _close(g2, g)
    assert abs(c2 - cost) <= REL * abs(cost)
    assert _close(r2, r)
    # the cost-only call gives the same cost and residuals
    c3, none1, none2, r3 = vector_normal(P, x, B, bp, Mp, False, w, eiv_var)
    assert none1 is None and none2 is None and c3 == c2 and np.array_equal(r3, r2)


@pytest.mark.parametrize("K", [1, 3])
def test_cross_information_is_the_symmetrised_cross_moment(K):
    """_split_information: J^T W J with the regressor's outer products replaced by the
    symmetrised cross products of x and x_hat (linear terms by their mean)."""
    P, x, B, bp, Mp, w, grp = _case(K, seed=10 + K)
    x_hat = x + np.random.default_rng(5).normal(size=x.shape) * 50.0
    Jx, Jh, Jm = (_jacobian(P, u, bp, Mp) for u in (x, x_hat, 0.5 * (x + x_hat)))

    def info(J):
        return np.einsum("nip,n,niq->pq", J, w, J)
    want = 2.0 * info(Jm) - 0.5 * (info(Jx) + info(Jh))
    assert _close(_split_information(P, x, x_hat, B, (bp, Mp), w), want)
    stats = ReadingStats(P, x, grp, x_hat)
    assert _close(_split_information(P, x, x_hat, B, (bp, Mp), w, stats), want)


def test_per_file_statistics_and_blocks_equal_one_weighted_pass(monkeypatch):
    """ReadingStats (per file, weights applied afterwards) and reading_moments in small
    blocks with files interleaved equal reading_moments with per-sample weights."""
    import generator.fit.reference as R

    P, x, B, bp, Mp, w, grp = _case(3, seed=21)
    want = normal_matrix(reading_moments(P, x, w), bp, Mp)
    assert _close(normal_matrix(ReadingStats(P, x, grp).weighted(w), bp, Mp), want)
    monkeypatch.setattr(R, "MOMENT_CHUNK", 333)
    perm = np.random.default_rng(2).permutation(len(x))      # files interleaved
    st = ReadingStats(P[perm], x[perm], grp[perm])
    assert _close(normal_matrix(st.weighted(w[perm]), bp, Mp), want)
