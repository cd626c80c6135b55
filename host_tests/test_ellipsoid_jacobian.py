"""The ellipsoid refinement's analytic, vectorised Jacobian (generator.fit.ellipsoid._Refinement)
against central finite differences of its own residuals, and its cost-only path.

Tolerance: central differences err by O(h^2 f''') (truncation) plus O(eps |r| / h)
(rounding). The point is chosen away from the optimum (|B| misfits of ~1,000 nT on a
50,000 nT field) with a strongly anisotropic M (entries up to ~0.3 off identity), so the
smallest term of the Jacobian, the s dg/g of the normalised residual, is ~|r|/R * 0.3 ~ 1e-2
of its column: a dropped or wrong term moves a column by far more than 1e-6 of its size.
With h = 1e-2 nT for offsets and 1e-7 for matrix entries (x ~ 1e5 nT), the truncation error
is ~(h/|x|)^2 ~ 1e-14 relative and the rounding error eps * 1e5 / h ~ 2e-9 (offsets) and
eps * 1e5 / (1e-7 * 1e5) ~ 2e-9 (entries) relative to columns of size ~1 and ~1e5:
1e-6 leaves a factor ~500 of margin for the finite-difference noise alone.
"""

from __future__ import annotations

import numpy as np
import pytest

from generator.fit.bounds import normalised_residuals
from generator.fit.ellipsoid import (_Refinement, _geo_resid_jac, _normalised_resid_jac,
                                     _sym_grad, SYM_INDEX, ellipsoid_fit, sym_from6, sym_to6)

R_NT = 5e4
REL_TOL = 1e-6     # see the module docstring


def _point(rng, n, cap=False):
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    if cap:
        u = u[u[:, 2] > 0.5]
    A = rng.normal(size=(3, 3))
    M = np.eye(3) + 0.08 * (A + A.T)
    assert np.linalg.eigvalsh(M)[0] > 0.2           # symmetric positive definite, anisotropic
    x = (u * R_NT) @ np.linalg.inv(M).T + [2500.0, -1200.0, 800.0]
    x += rng.normal(size=x.shape) * 1000.0           # misfit: s dg/g is not negligible
    p = np.concatenate([[2400.0, -1100.0, 900.0], sym_to6(M)])
    return x, p


def _fd_jacobian(kind, p, x, w):
    h = np.concatenate([np.full(3, 1e-2), np.full(6, 1e-7)])
    cols = []
    for j in range(9):
        e = np.zeros(9)
        e[j] = h[j]
        rp = _Refinement(x, R_NT, w, kind).residuals(p + e)
        rm = _Refinement(x, R_NT, w, kind).residuals(p - e)
        cols.append((rp - rm) / (2 * h[j]))
    return np.stack(cols, axis=1)


@pytest.mark.parametrize("kind", ["normalised", "geometric"])
@pytest.mark.parametrize("cap", [False, True])
def test_analytic_jacobian_matches_central_differences(kind, cap):
    rng = np.random.default_rng(7 + cap)
    x, p = _point(rng, 400, cap)
    w = rng.uniform(0.5, 2.0, len(x))
    ref = _Refinement(x, R_NT, w, kind)
    J = ref.jacobian_T(p).T
    Jn = _fd_jacobian(kind, p, x, w)
    err = np.max(np.abs(J - Jn), axis=0) / np.max(np.abs(Jn), axis=0)
    assert np.all(err < REL_TOL), f"{kind}: relative column errors {err}"


def test_residuals_are_the_documented_ones():
    rng = np.random.default_rng(3)
    x, p = _point(rng, 300)
    w = rng.uniform(0.5, 2.0, len(x))
    b, M = p[:3], sym_from6(p[3:])
    # residuals are differences of ~5e4 nT magnitudes (ulp 7e-12 nT): a few ulps through
    # 1/g (g > 0.2) and w (< 2) stay below 1e-9 nT; a wrong formula is off by ~1 nT or more
    s, _ = _normalised_resid_jac(p, x, R_NT, w)
    assert np.allclose(s, normalised_residuals(b, M, x, R_NT) * w, rtol=0, atol=1e-6)
    r, Jg = _geo_resid_jac(p, x, R_NT, w)
    assert np.allclose(r, (np.linalg.norm((x - b) @ M.T, axis=1) - R_NT) * w,
                       rtol=0, atol=1e-6)
    # the geometric Jacobian's matrix block is d|M y|/dm = u^T E_k y, times w
    z = (x - b) @ M.T
    u = z / np.linalg.norm(z, axis=1)[:, None]
    assert np.allclose(Jg[:, 3:], _sym_grad(u, x - b) * w[:, None], rtol=1e-12, atol=0)


def test_sym_grad_matches_the_basis_definition():
    rng = np.random.default_rng(5)
    a, c = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    G = _sym_grad(a, c)
    for k, (i, j) in enumerate(SYM_INDEX):
        E = np.zeros((3, 3))
        E[i, j] = E[j, i] = 1.0
        assert np.allclose(G[:, k], np.einsum("ni,ij,nj->n", a, E, c), rtol=1e-14, atol=1e-14)


def test_cost_only_calls_build_no_jacobian(monkeypatch):
    """lm_solve's trial steps ask for the cost only; those calls must not form J."""
    rng = np.random.default_rng(11)
    x, _ = _point(rng, 2000)
    calls = {"cost": 0, "jac": 0, "jacobian_T": 0}
    call, jt = _Refinement.__call__, _Refinement.jacobian_T

    def counting_call(self, p, jac):
        calls["jac" if jac else "cost"] += 1
        before = calls["jacobian_T"]
        out = call(self, p, jac)
        if not jac:
            assert calls["jacobian_T"] == before and out[1] is None
        return out

    def counting_jt(self, p, sl=slice(None)):
        calls["jacobian_T"] += 1
        return jt(self, p, sl)

    monkeypatch.setattr(_Refinement, "__call__", counting_call)
    monkeypatch.setattr(_Refinement, "jacobian_T", counting_jt)
    ellipsoid_fit(x, R_NT)
    assert calls["cost"] >= 1 and calls["jac"] >= 1 and calls["jacobian_T"] >= calls["jac"]


def test_blockwise_normal_equations_equal_the_whole_jacobian():
    """J^T J and J^T r accumulated over blocks of samples are those of the whole J."""
    rng = np.random.default_rng(13)
    x, p = _point(rng, 2500)                # more than two blocks, the last one partial
    w = rng.uniform(0.5, 2.0, len(x))
    for kind in ("normalised", "geometric"):
        ref = _Refinement(x, R_NT, w, kind)
        cost, JTJ, JTr, m = ref(p, True)
        J, r = ref.jacobian_T(p).T, ref.residuals(p)
        assert m == len(x) and np.isclose(cost, r @ r, rtol=1e-13)
        # summing in another order: the error is bounded by N eps sum_i |J_ik J_il|
        # (2.8e-13 of it at N = 2,500); a missing or doubled block is off by >= 1/3
        aJ = np.abs(J)
        assert np.all(np.abs(JTJ - J.T @ J) <= 1e-12 * (aJ.T @ aJ))
        assert np.all(np.abs(JTr - J.T @ r) <= 1e-12 * (aJ.T @ np.abs(r)))
