"""Checks of the seed-001 analytic calibration (generator.fit.analytic).

Independent references:
  (a) ordinary linear least squares row by row in the reparametrised unknowns, solved by
      numpy's SVD-based lstsq on the raw (uncentred) design matrix, then mapped back;
  (b) the constrained problem on the original Phi solved by IPOPT (CasADi nlpsol), and the
      gradient of the Lagrangian by CasADi's automatic differentiation.
Tolerances on noisy data follow from conditioning (see `roundoff_tolerance`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from hypothesis import assume, given, settings, strategies as st
from scipy import stats

from generator.errors import InputError
from generator.fit.analytic import (
    MIN_SAMPLES,
    PLANARITY_MIN_RATIO,
    P_from_angles,
    angles_from_P,
    fit_analytic,
    fit_analytic_rotated,
    lagrangian_stationary_points,
    lq_split,
    rotation_from_rotvec,
    rotvec_from_rotation,
)

EPS = float(np.finfo(float).eps)
N_PROBLEMS = 60
PROBLEM_SEEDS = list(range(N_PROBLEMS))
IPOPT_TOL = 1e-12


# ----------------------------------------------------------------------------------------
# random problems
# ----------------------------------------------------------------------------------------

def random_unit_vectors(rng, n):
    u = rng.normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=1)[:, None]


def make_problem(seed, noise_nT=None, rotation_max_deg=0.0, n=None):
    """A random calibration problem: truth, true fields and readings."""
    rng = np.random.default_rng([2024, seed])
    if n is None:
        n = int(round(math.exp(rng.uniform(math.log(12), math.log(2000)))))
    k = rng.uniform(0.8, 1.2, 3)
    e_rad = np.radians(rng.uniform(-3.0, 3.0, 3))
    b_nT = rng.uniform(-3000.0, 3000.0, 3)
    rotvec_rad = np.radians(rng.uniform(-rotation_max_deg, rotation_max_deg, 3))
    B_nT = random_unit_vectors(rng, n) * rng.uniform(45_000.0, 55_000.0, (n, 1))
    sigma_nT = rng.uniform(0.0, 200.0) if noise_nT is None else noise_nT
    W = np.diag(k) @ P_from_angles(e_rad) @ rotation_from_rotvec(rotvec_rad)
    h_nT = B_nT @ W.T + b_nT + rng.normal(size=(n, 3)) * sigma_nT
    return dict(h=h_nT, B=B_nT, k=k, e=e_rad, b=b_nT, rotvec=rotvec_rad, W=W, sigma=sigma_nT, n=n)


def field_rms(B):
    return math.sqrt(float(np.mean(np.sum(B * B, axis=1))))


# ----------------------------------------------------------------------------------------
# reference (a): row-by-row linear least squares
# ----------------------------------------------------------------------------------------

def _lstsq_equilibrated(A, y):
    """lstsq with unit-norm columns; returns the solution and the design's condition number."""
    norms = np.linalg.norm(A, axis=0)
    As = A / norms
    x, *_ = np.linalg.lstsq(As, y, rcond=None)
    return x / norms, float(np.linalg.cond(As))


def row_lstsq(h, B):
    """Linear least squares per row in the reparametrised unknowns, mapped back to k, e, b.

    row 1: gamma1 h1 - (gamma1 b1) = B1
    row 2: (beta1 gamma2) h2 - (beta1 gamma2 b2) - alpha1 B1 = B2
    row 3: (beta2 beta3 gamma3) h3 - (beta2 beta3 gamma3 b3) - (alpha2 beta3) B1 - alpha3 B2 = B3
    Returns k, e, b and the condition number of each row's (column-equilibrated) design.
    """
    one = np.ones(len(h))
    (g1, w1), kap1 = _lstsq_equilibrated(np.column_stack([h[:, 0], -one]), B[:, 0])
    (u, v, alpha1), kap2 = _lstsq_equilibrated(np.column_stack([h[:, 1], -one, -B[:, 0]]), B[:, 1])
    (w, v3, a, alpha3), kap3 = _lstsq_equilibrated(
        np.column_stack([h[:, 2], -one, -B[:, 0], -B[:, 1]]), B[:, 2])
    beta1 = math.sqrt(1 + alpha1**2)
    beta3 = math.sqrt(1 + alpha3**2)
    alpha2 = a / beta3
    beta2 = math.sqrt(1 + alpha2**2)
    k = np.array([1 / g1, beta1 / u, beta2 * beta3 / w])
    e = np.arctan([alpha1, alpha2, alpha3])
    b = np.array([w1 / g1, v / u, v3 / w])
    return k, e, b, np.array([kap1, kap2, kap3])


# ----------------------------------------------------------------------------------------
# reference (b): IPOPT on the original constrained problem, CasADi gradients
# ----------------------------------------------------------------------------------------

def _phi_expression(x, h_s, B_s):
    """Phi of the brief (in units of the scale s squared) as a CasADi expression of
    x = (alpha1..3, beta1..3, gamma1..3, b1..3 / s)."""
    al, be, ga, bb = x[0:3], x[3:6], x[6:9], x[9:12]
    h = [ca.DM(h_s[:, i]) for i in range(3)]
    B = [ca.DM(B_s[:, i]) for i in range(3)]
    r1 = ga[0] * (h[0] - bb[0]) - B[0]
    r2 = be[0] * ga[1] * (h[1] - bb[1]) - al[0] * B[0] - B[1]
    r3 = be[1] * be[2] * ga[2] * (h[2] - bb[2]) - al[1] * be[2] * B[0] - al[2] * B[1] - B[2]
    return ca.sumsqr(r1) + ca.sumsqr(r2) + ca.sumsqr(r3)


def ipopt_solve(h, B):
    """Minimise Phi subject to alpha_i^2 - beta_i^2 + 1 = 0, beta_i >= 0 with IPOPT.

    Data and offsets in units of the RMS field s (this only rescales Phi by 1/s^2).
    Started from the nominal sensor (alpha = 0, beta = 1, gamma = 1, b = 0).
    """
    s = field_rms(B)
    x = ca.MX.sym("x", 12)
    phi = _phi_expression(x, h / s, B / s)
    constraints = x[0:3] ** 2 - x[3:6] ** 2 + 1
    solver = ca.nlpsol("s", "ipopt", {"x": x, "f": phi, "g": constraints},
                       {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
                        "ipopt.tol": IPOPT_TOL})
    x0 = np.r_[np.zeros(3), np.ones(3), np.ones(3), np.zeros(3)]
    lbx = np.r_[np.full(3, -np.inf), np.zeros(3), np.full(6, -np.inf)]
    res = solver(x0=x0, lbx=lbx, ubx=np.inf, lbg=0, ubg=0)
    xs = np.array(res["x"]).ravel()
    status = solver.stats()["return_status"]
    return 1 / xs[6:9], np.arctan(xs[0:3]), xs[9:12] * s, status


def lagrangian_gradient_ad(h, B, alpha, beta, gamma, b_nT):
    """|grad L| / (2N) by CasADi AD, data scaled by the RMS field (not centred), with the
    multipliers chosen by least squares over the alpha/beta components."""
    s = field_rms(B)
    x = ca.MX.sym("x", 12)
    phi = _phi_expression(x, h / s, B / s)
    grad_fn = ca.Function("g", [x], [ca.gradient(phi, x)])
    xv = np.concatenate([alpha, beta, gamma, np.asarray(b_nT) / s])
    g = np.array(grad_fn(xv)).ravel()
    lam = (-g[0:3] * alpha + g[3:6] * beta) / (2 * (alpha**2 + beta**2))
    g[0:3] += 2 * lam * alpha
    g[3:6] -= 2 * lam * beta
    return float(np.max(np.abs(g))) / (2 * len(h))


# ----------------------------------------------------------------------------------------
# comparing parameter sets
# ----------------------------------------------------------------------------------------

#: which parameters each row determines: (k index, e indices, b index)
ROW_PARAMS = [(0, [], 0), (1, [0], 1), (2, [1, 2], 2)]


def row_differences(k1, e1, b1, k2, e2, b2, scale_nT):
    """Per row, the largest difference in normalised units: k relative, e in rad, b / |B|."""
    out = []
    for ki, eis, bi in ROW_PARAMS:
        d = [abs(k1[ki] / k2[ki] - 1), abs(b1[bi] - b2[bi]) / scale_nT]
        d += [abs(e1[j] - e2[j]) for j in eis]
        out.append(max(d))
    return np.array(out)


def roundoff_tolerance(kappa, n, extra=0.0):
    """Allowed difference between two exact solutions of the same row least-squares problem.

    The closed form forms sums of products (pairwise summation: relative error about
    eps log2 N) and solves the row's normal equations, whose condition number is kappa^2
    (kappa: the column-equilibrated design's condition number); lstsq is backward stable
    (error <= eps kappa^2 too, for a non-zero residual).  So the two agree to about
    eps kappa^2 log2 N in the normalised unknowns, times a safety factor 16 for the
    determinant arithmetic and the mapping back.  `extra` adds a solver tolerance (IPOPT's
    KKT tolerance, also amplified by the Hessian's condition number kappa^2).
    """
    return kappa**2 * (16 * EPS * (1 + math.log2(n)) + extra)


# ----------------------------------------------------------------------------------------
# agreement with the references
# ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("noise_free", [True, False], ids=["noise-free", "noisy"])
def test_closed_form_agrees_with_row_lstsq_and_ipopt(noise_free):
    worst_lstsq, worst_ipopt = 0.0, 0.0
    for seed in PROBLEM_SEEDS:
        pb = make_problem(seed, noise_nT=0.0 if noise_free else None)
        h, B, n = pb["h"], pb["B"], pb["n"]
        s = field_rms(B)
        fit = fit_analytic(h, B)
        k_a, e_a, b_a, kappa = row_lstsq(h, B)
        k_i, e_i, b_i, status = ipopt_solve(h, B)
        assert status == "Solve_Succeeded", (seed, status)

        d_lstsq = row_differences(fit.k, fit.e_rad, fit.b_nT, k_a, e_a, b_a, s)
        d_ipopt = row_differences(fit.k, fit.e_rad, fit.b_nT, k_i, e_i, b_i, s)
        if noise_free:
            d_truth = row_differences(fit.k, fit.e_rad, fit.b_nT, pb["k"], pb["e"], pb["b"], s)
            assert np.all(d_truth < 1e-9), (seed, d_truth)
            assert np.all(d_lstsq < 1e-9), (seed, d_lstsq)
            assert np.all(d_ipopt < 1e-9), (seed, d_ipopt)
        else:
            tol_lstsq = roundoff_tolerance(kappa, n)
            tol_ipopt = roundoff_tolerance(kappa, n, extra=IPOPT_TOL)
            assert np.all(d_lstsq <= tol_lstsq), (seed, d_lstsq, tol_lstsq)
            assert np.all(d_ipopt <= tol_ipopt), (seed, d_ipopt, tol_ipopt)
        worst_lstsq = max(worst_lstsq, float(d_lstsq.max()))
        worst_ipopt = max(worst_ipopt, float(d_ipopt.max()))
    print(f"\n{N_PROBLEMS} problems, noise-free={noise_free}: largest difference closed form vs "
          f"lstsq {worst_lstsq:.2e}, vs IPOPT {worst_ipopt:.2e} (normalised units)")


def test_problem_set_covers_the_brief():
    problems = [make_problem(seed) for seed in PROBLEM_SEEDS]
    ns = [p["n"] for p in problems]
    sigmas = [p["sigma"] for p in problems]
    assert len(problems) >= 50
    assert min(ns) < 40 and max(ns) > 1000
    assert min(sigmas) < 20 and max(sigmas) > 180


def test_balanced_data_where_the_paper_formulas_divide_by_zero():
    """sum B_i = 0 (positions in +- pairs): the paper's root alpha1' = -C2/C1 is 0/0 and
    (H_i - N b_i) = 0 at the solution; the closed form used here still solves it."""
    pb = make_problem(7, noise_nT=0.0, n=40)
    B = np.vstack([pb["B"], -pb["B"]])
    h = B @ pb["W"].T + pb["b"]
    assert np.all(np.abs(B.sum(axis=0)) < 1e-9 * np.abs(B).sum())
    fit = fit_analytic(h, B)
    d_truth = row_differences(fit.k, fit.e_rad, fit.b_nT, pb["k"], pb["e"], pb["b"], field_rms(B))
    assert np.all(d_truth < 1e-9), d_truth
    assert fit.candidates[fit.chosen_index].is_stationary
    spurious_row2 = [c for c in fit.candidates if "alpha1'" in c.label and "alpha1''" not in c.label]
    assert len(spurious_row2) == 2 and all(c.phi_nT2 == math.inf for c in spurious_row2)


# ----------------------------------------------------------------------------------------
# the four candidates and the stationary points
# ----------------------------------------------------------------------------------------

def test_four_candidates_phi_and_the_chosen_minimum():
    """The paper's four solutions: Phi at each, the chosen one is the minimum and the only
    stationary one (gradient of the Lagrangian by CasADi AD, best multipliers)."""
    for seed in PROBLEM_SEEDS[:20]:
        pb = make_problem(seed)
        h, B = pb["h"], pb["B"]
        fit = fit_analytic(h, B)
        assert len(fit.candidates) == 4
        phis = np.array([c.phi_nT2 for c in fit.candidates])
        assert fit.chosen_index == int(np.argmin(phis))
        assert np.all(phis[np.arange(4) != fit.chosen_index] > phis[fit.chosen_index])
        unknowns = np.array([c.unknowns[:12] for c in fit.candidates])
        for i in range(4):
            for j in range(i + 1, 4):
                assert np.max(np.abs(unknowns[i] - unknowns[j])) > 1e-6
        grads = [lagrangian_gradient_ad(h, B, c.alpha, c.beta, c.gamma, c.b_nT)
                 for c in fit.candidates]
        chosen = fit.candidates[fit.chosen_index]
        assert grads[fit.chosen_index] < 1e-10, grads
        # the module's own KKT residual (analytic gradient, centred data) matches AD's
        for c, g in zip(fit.candidates, grads):
            assert abs(c.kkt_residual - g) <= 1e-9 * max(g, 1e-6), (c.label, c.kkt_residual, g)
        # multipliers zero, relative to the gradient scale 2 N s^2 of Phi in nT^2
        assert np.all(np.abs(chosen.lam) / (2 * len(h) * field_rms(B) ** 2) < 1e-10), chosen.lam
        # Finding: the paper's other three roots are not stationary points of its Lagrangian
        for i, c in enumerate(fit.candidates):
            if i != fit.chosen_index:
                assert grads[i] > 1e-3, (seed, i, c.label, grads[i])
                assert not c.is_stationary
        np.testing.assert_allclose([fit.k, fit.e_rad, fit.b_nT],
                                   [chosen.k, chosen.e_rad, chosen.b_nT], rtol=0, atol=0)
        if seed == 0:
            print("\nseed 0, the paper's four candidates:")
            for i, (c, g) in enumerate(zip(fit.candidates, grads)):
                mark = "*" if i == fit.chosen_index else " "
                print(f" {mark} Phi = {c.phi_nT2:12.5e} nT^2  |grad L|/2N = {g:9.2e}  {c.label}")


def test_all_stationary_points_of_the_lagrangian():
    """The Lagrangian's true stationary points (gamma_i = 0 included): gradient ~ 0 at each
    (CasADi AD), all distinct, and the minimum of Phi among them is the chosen solution."""
    for seed in PROBLEM_SEEDS[:20]:
        pb = make_problem(seed)
        h, B = pb["h"], pb["B"]
        fit = fit_analytic(h, B)
        points = lagrangian_stationary_points(h, B)
        assert len(points) == 8
        for p in points:
            g = lagrangian_gradient_ad(h, B, p.alpha, p.beta, p.gamma, p.b_nT)
            assert g < 1e-10, (seed, p.label, g)
            assert p.is_stationary
        unknowns = np.array([np.r_[p.alpha, p.gamma, p.b_nT / field_rms(B)] for p in points])
        for i in range(len(points)):
            for j in range(i + 1, len(points)):
                assert np.max(np.abs(unknowns[i] - unknowns[j])) > 1e-6
        phis = np.array([p.phi_nT2 for p in points])
        best = points[int(np.argmin(phis))]
        assert np.all(np.isfinite(best.k))
        np.testing.assert_allclose(best.k, fit.k, rtol=1e-12)
        np.testing.assert_allclose(best.b_nT, fit.b_nT, rtol=0, atol=1e-9 * field_rms(B))
        assert sorted(phis)[1] > 1e3 * max(phis.min(), 1.0)
        if seed == 0:
            print("\nseed 0, stationary points of the Lagrangian:")
            for p in sorted(points, key=lambda q: q.phi_nT2):
                print(f"   Phi = {p.phi_nT2:12.5e} nT^2  {p.label}")


# ----------------------------------------------------------------------------------------
# uncertainties, apply
# ----------------------------------------------------------------------------------------

def test_analytic_uncertainties_match_monte_carlo():
    """Reported 1-sigma of k, e, b against the scatter over 300 noise realisations."""
    base = make_problem(3, noise_nT=0.0, n=150)
    rng = np.random.default_rng(99)
    noise_nT, runs = 120.0, 300
    estimates, sigmas = [], []
    for _ in range(runs):
        h = base["h"] + rng.normal(size=base["h"].shape) * noise_nT
        fit = fit_analytic(h, base["B"])
        estimates.append(np.r_[fit.k, fit.e_rad, fit.b_nT])
        sigmas.append(np.r_[fit.sigma_k, fit.sigma_e_rad, fit.sigma_b_nT])
    estimates, sigmas = np.array(estimates), np.array(sigmas)
    truth = np.r_[base["k"], base["e"], base["b"]]
    scatter = estimates.std(axis=0, ddof=1)
    reported = np.sqrt(np.mean(sigmas**2, axis=0))
    # sample variance / true variance ~ chi2(runs-1)/(runs-1); two-sided 1e-3 per parameter
    lo, hi = np.sqrt(stats.chi2.ppf([5e-4, 1 - 5e-4], runs - 1) / (runs - 1))
    ratio = scatter / reported
    assert np.all((ratio > lo) & (ratio < hi)), (ratio, lo, hi)
    # no bias beyond 4 standard errors of the mean (the errors-in-variables bias of the
    # field-space estimator, ~noise^2 / var(h) relative in k, is far below that here)
    assert np.all(np.abs(estimates.mean(axis=0) - truth) < 4 * scatter / math.sqrt(runs))


def test_apply_inverts_the_model():
    pb = make_problem(11, noise_nT=0.0)
    fit = fit_analytic(pb["h"], pb["B"])
    np.testing.assert_allclose(fit.W, fit.Q @ fit.P)
    np.testing.assert_allclose(fit.apply(pb["h"]), pb["B"], rtol=0, atol=1e-7)
    np.testing.assert_allclose(fit.predict(pb["B"]), pb["h"], rtol=0, atol=1e-7)
    assert fit.residual_rms_nT < 1e-7


# ----------------------------------------------------------------------------------------
# rotated extension and lq_split
# ----------------------------------------------------------------------------------------

def _rotated_errors(fit, pb):
    """Estimate minus truth in (k, e, delta, b); delta = log(R_true^T R_hat)."""
    delta = rotvec_from_rotation(rotation_from_rotvec(pb["rotvec"]).T @ fit.R)
    return np.r_[fit.k - pb["k"], fit.e_rad - pb["e"], delta, fit.b_nT - pb["b"]]


def test_rotated_fit_recovers_known_parameters_within_3_sigma():
    """Over 8 seeds: each seed's 12-parameter error is inside the 3-sigma ellipsoid (the
    chi2(12) quantile of the 1-D 3-sigma probability, 0.9973), and the pooled squared
    z-scores average 1 within their 99.9 % band, so sigma is neither too small nor inflated."""
    chi2_3sigma = stats.chi2.ppf(stats.chi2.cdf(9, 1), 12)
    z_all = []
    for seed in range(100, 108):
        pb = make_problem(seed, noise_nT=40.0 + 20.0 * (seed - 100), rotation_max_deg=3.0,
                          n=200 + 200 * (seed - 100))
        fit = fit_analytic_rotated(pb["h"], pb["B"])
        err = _rotated_errors(fit, pb)
        mahalanobis2 = float(err @ np.linalg.solve(fit.cov, err))
        assert mahalanobis2 < chi2_3sigma, (seed, mahalanobis2)
        z_all.append(err / np.sqrt(np.diag(fit.cov)))
        # the seed-001 model cannot absorb the rotation: its residual is far above the noise
        assert fit.analytic.residual_rms_nT > 3 * fit.residual_rms_nT
        assert fit.residual_rms_nT < 1.1 * pb["sigma"]
    z2 = np.concatenate(z_all) ** 2
    lo, hi = stats.chi2.ppf([5e-4, 1 - 5e-4], z2.size) / z2.size
    assert lo < z2.mean() < hi, (z2.mean(), lo, hi)


def test_rotated_uncertainties_match_monte_carlo():
    """Reported 1-sigma of k, e, R, b of the rotated fit against the scatter over 250 runs."""
    base = make_problem(300, noise_nT=0.0, rotation_max_deg=3.0, n=80)
    rng = np.random.default_rng(301)
    noise_nT, runs = 150.0, 250
    errors, sigmas = [], []
    for _ in range(runs):
        h = base["h"] + rng.normal(size=base["h"].shape) * noise_nT
        fit = fit_analytic_rotated(h, base["B"])
        errors.append(_rotated_errors(fit, base))
        sigmas.append(np.sqrt(np.diag(fit.cov)))
    errors, sigmas = np.array(errors), np.array(sigmas)
    scatter = errors.std(axis=0, ddof=1)
    ratio = scatter / np.sqrt(np.mean(sigmas**2, axis=0))
    lo, hi = np.sqrt(stats.chi2.ppf([5e-4, 1 - 5e-4], runs - 1) / (runs - 1))
    assert np.all((ratio > lo) & (ratio < hi)), (ratio, lo, hi)
    assert np.all(np.abs(errors.mean(axis=0)) < 4 * scatter / math.sqrt(runs))


def test_rotated_fit_equals_linear_regression_split():
    """h = Q P R B + b has 12 parameters like h = W B + b: ordinary linear regression of
    h on (B, 1) followed by lq_split must give the same answer."""
    for seed in range(200, 205):
        pb = make_problem(seed, noise_nT=150.0, rotation_max_deg=3.0)
        fit = fit_analytic_rotated(pb["h"], pb["B"])
        X = np.column_stack([pb["B"], np.ones(pb["n"])])
        coef, *_ = np.linalg.lstsq(X, pb["h"], rcond=None)
        W_lin, b_lin = coef[:3].T, coef[3]
        Q, P, R = lq_split(W_lin)
        s = field_rms(pb["B"])
        np.testing.assert_allclose(fit.W, W_lin, rtol=0, atol=1e-10)
        np.testing.assert_allclose(fit.b_nT / s, b_lin / s, rtol=0, atol=1e-10)
        np.testing.assert_allclose(fit.k, np.diag(Q), rtol=1e-10)
        np.testing.assert_allclose(fit.e_rad, angles_from_P(P), rtol=0, atol=1e-10)
        np.testing.assert_allclose(fit.R, R, rtol=0, atol=1e-10)
        np.testing.assert_allclose(fit.apply(pb["h"]), np.linalg.solve(W_lin, (pb["h"] - b_lin).T).T,
                                   rtol=0, atol=1e-6)


def test_lq_split_recovers_known_factors():
    rng = np.random.default_rng(5)
    for _ in range(50):
        k = rng.uniform(0.8, 1.2, 3)
        e = np.radians(rng.uniform(-10, 10, 3))
        R = rotation_from_rotvec(random_unit_vectors(rng, 1)[0] * rng.uniform(0, 3.0))
        Q_s, P_s, R_s = lq_split(np.diag(k) @ P_from_angles(e) @ R)
        np.testing.assert_allclose(np.diag(Q_s), k, rtol=1e-12)
        np.testing.assert_allclose(angles_from_P(P_s), e, rtol=0, atol=1e-12)
        np.testing.assert_allclose(R_s, R, rtol=0, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-3.0, 3.0, allow_nan=False), min_size=9, max_size=9))
def test_lq_split_reconstructs_any_matrix_with_positive_determinant(entries):
    W = np.array(entries).reshape(3, 3)
    det = np.linalg.det(W)
    if det <= 0:
        with pytest.raises(InputError):
            lq_split(W)
        return
    assume(det > 1e-3)
    Q, P, R = lq_split(W)
    np.testing.assert_allclose(Q @ P @ R, W, rtol=0, atol=1e-12 * max(1.0, np.abs(W).max()))
    assert np.all(np.diag(Q) > 0) and np.allclose(Q, np.diag(np.diag(Q)))
    assert np.allclose(np.triu(P, 1), 0) and np.all(np.diag(P) > 0)
    np.testing.assert_allclose(np.linalg.norm(P, axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(P_from_angles(angles_from_P(P)), P, rtol=0, atol=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), rtol=0, atol=1e-12)
    assert abs(np.linalg.det(R) - 1) < 1e-12


def test_lq_split_rejects_reflections_and_bad_shapes():
    with pytest.raises(InputError, match="det"):
        lq_split(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(InputError, match="det"):
        lq_split(np.zeros((3, 3)))
    with pytest.raises(InputError, match="3x3"):
        lq_split(np.eye(2))


# ----------------------------------------------------------------------------------------
# degenerate data
# ----------------------------------------------------------------------------------------

def _expect_input_error(h, B, *words):
    with pytest.raises(InputError) as info:
        fit_analytic(h, B)
    message = str(info.value)
    assert info.value.path is None and message.startswith("<input>: ")
    for word in words:
        assert word in message, message
    return message


def test_too_few_samples():
    pb = make_problem(1, noise_nT=10.0, n=MIN_SAMPLES)
    fit_analytic(pb["h"], pb["B"])  # exactly the minimum works
    _expect_input_error(pb["h"][:-1], pb["B"][:-1], f"{MIN_SAMPLES - 1} samples",
                        f"at least {MIN_SAMPLES}", "4 unknowns")


def test_field_vectors_in_one_plane():
    pb = make_problem(2, noise_nT=10.0, n=200)
    B = pb["B"].copy()
    B[:, 2] = 0.3 * B[:, 0] - 0.2 * B[:, 1]                   # plane through the origin
    _expect_input_error(pb["h"], B, "one plane", "singular value")
    B = pb["B"].copy()
    B[:, 2] = 20_000.0                                         # affine plane: turned about z only
    _expect_input_error(pb["h"], B, "one plane")


def test_planarity_threshold_is_relative_to_the_spread():
    rng = np.random.default_rng(8)
    n = 300
    flat = np.column_stack([rng.normal(size=n), rng.normal(size=n), np.zeros(n)])
    flat /= np.std(flat[:, :2])
    h_of = lambda B: B * 1.01 + 100.0 + rng.normal(size=B.shape)  # noqa: E731
    for ratio, ok in [(0.3 * PLANARITY_MIN_RATIO, False), (3 * PLANARITY_MIN_RATIO, True)]:
        B = flat.copy()
        B[:, 2] = ratio * rng.choice([-1.0, 1.0], n)
        B *= 50_000.0
        if ok:
            fit_analytic(h_of(B), B)
        else:
            _expect_input_error(h_of(B), B, "one plane")


def test_zero_field_axis_and_dead_reading_axis():
    pb = make_problem(4, noise_nT=10.0, n=100)
    B = pb["B"].copy()
    B[:, 2] = 0.0
    _expect_input_error(pb["h"], B, "axis z is zero")
    h = pb["h"].copy()
    h[:, 1] = 1234.0
    _expect_input_error(h, pb["B"], "axis y is constant")


def test_non_finite_input():
    pb = make_problem(5, noise_nT=10.0, n=50)
    h = pb["h"].copy()
    h[7, 1] = np.nan
    _expect_input_error(h, pb["B"], "readings", "non-finite", "sample 7", "axis y")
    B = pb["B"].copy()
    B[3, 0] = np.inf
    _expect_input_error(pb["h"], B, "field vectors", "non-finite", "sample 3")


def test_mismatched_and_wrong_shapes():
    pb = make_problem(6, noise_nT=10.0, n=50)
    _expect_input_error(pb["h"][:-1], pb["B"], "49 readings but 50 field vectors")
    _expect_input_error(pb["h"][:, :2], pb["B"], "shape (N, 3)")
    _expect_input_error(pb["h"], pb["B"].ravel(), "shape (N, 3)")
    with pytest.raises(InputError):
        fit_analytic_rotated(pb["h"][:5], pb["B"][:5])


# ----------------------------------------------------------------------------------------
# the example unit
# ----------------------------------------------------------------------------------------

SENSORS = {
    # name: (columns, lsb_nT, axes, set_reset)
    "mmc1": (25.0, ["+z", "+y", "+x"], True),
    "mpu1": (150.0, ["-z", "-y", "-x"], False),
}


def read_csv(path: Path) -> dict:
    lines = path.read_text().splitlines()
    header_index = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    names = lines[header_index].split(",")
    data = np.loadtxt(path, delimiter=",", comments="#", skiprows=header_index + 1)
    return {name: data[:, i] for i, name in enumerate(names)}


def frame_field_nT(cols: dict, sensor: str) -> np.ndarray:
    lsb_nT, axes, set_reset = SENSORS[sensor]
    if set_reset:
        sensor_xyz = np.column_stack([(cols[f"{sensor}_set_{a}"] - cols[f"{sensor}_reset_{a}"]) / 2
                                      for a in "xyz"]) * lsb_nT
    else:
        sensor_xyz = np.column_stack([cols[f"{sensor}_{a}"] for a in "xyz"]) * lsb_nT
    out = np.empty_like(sensor_xyz)
    for k, axis in enumerate(axes):
        out[:, k] = (1.0 if axis[0] == "+" else -1.0) * sensor_xyz[:, "xyz".index(axis[1])]
    return out


def plateau_mask(time_s, position, temp_C, target_C=25.0, near_C=1.0,
                 settled_before_s=300.0, settled_after_s=100.0, max_span_C=0.35):
    """Samples of the target-temperature hold in the static positions.

    The 25 degC hold reads 25.8 degC on mmc1 (0.7 degC steps) and 25.6-25.8 on mpu1: the
    board sits about 0.75 degC above the chamber, so the window is +-1 degC.  Settled: the
    reported temperature spans at most 0.35 degC (half an mmc1 step, i.e. unchanged) from
    300 s before to 100 s after the sample, all within the same position.
    """
    mask = np.zeros(len(time_s), dtype=bool)
    for pos in np.unique(position[position > 0]):
        idx = np.flatnonzero(position == pos)
        t, T = time_s[idx], temp_C[idx]
        for j in range(len(idx)):
            if t[j] - settled_before_s < t[0] or t[j] + settled_after_s > t[-1]:
                continue
            window = (t >= t[j] - settled_before_s) & (t <= t[j] + settled_after_s)
            if abs(T[j] - target_C) <= near_C and np.ptp(T[window]) <= max_span_C:
                mask[idx[j]] = True
    return mask


@pytest.fixture(scope="module")
def thermal(fm1_dir):
    cols = read_csv(fm1_dir / "thermal_12pos.csv")
    truth = json.loads((fm1_dir / "truth.json").read_text())
    truth_npz = np.load(fm1_dir / "thermal_12pos.truth.npz")
    return cols, truth, truth_npz


@pytest.mark.parametrize("sensor", ["mmc1", "mpu1"])
def test_example_unit_thermal_plateau(thermal, sensor):
    cols, truth, truth_npz = thermal
    mask = plateau_mask(cols["time_s"], cols["position"], cols[f"{sensor}_temp_C"])
    assert set(np.unique(cols["position"][mask])) == set(range(1, 13))
    h = frame_field_nT(cols, sensor)[mask]
    B = np.column_stack([cols["ref_x_nT"], cols["ref_y_nT"], cols["ref_z_nT"]])[mask]

    plain = fit_analytic(h, B)
    fit = fit_analytic_rotated(h, B, analytic=plain)

    # truth at the samples' true board temperatures, averaged (the fit of a constant W, b
    # to data whose W(T), b(T) drift with T estimates their average over the samples)
    dT = truth_npz["temp_body_C"][mask] - truth["t_ref_C"]
    W_poly = np.array(truth["sensors"][sensor]["W_poly_frame"])
    b_poly = np.array(truth["sensors"][sensor]["b_poly_frame_nT"])
    W_true = sum(W_poly[i] * np.mean(dT**i) for i in range(len(W_poly)))
    b_true = sum(b_poly[i] * np.mean(dT**i) for i in range(len(b_poly)))
    Q_t, P_t, R_t = lq_split(W_true)
    true = dict(k=np.diag(Q_t), e=angles_from_P(P_t), rotvec=rotvec_from_rotation(R_t), b=b_true)
    err = _rotated_errors(fit, true)
    z = err / np.sqrt(np.diag(fit.cov))

    # the model's residual against the truth model's own residual on the same samples
    T_true = truth_npz["temp_body_C"][mask] - truth["t_ref_C"]
    W_each = sum(W_poly[i] * T_true[:, None, None] ** i for i in range(len(W_poly)))
    b_each = sum(b_poly[i] * T_true[:, None] ** i for i in range(len(b_poly)))
    truth_resid = h - (np.einsum("nij,nj->ni", W_each, truth_npz["b_body_nT"][mask]) + b_each)
    truth_rms = float(np.sqrt(np.mean(truth_resid**2)))

    deg = np.degrees
    print(f"\n{sensor}: {mask.sum()} samples, true board temperature "
          f"{truth_npz['temp_body_C'][mask].min():.2f}..{truth_npz['temp_body_C'][mask].max():.2f} degC")
    print(f"  residual RMS seed-001 model {plain.residual_rms_nT:7.1f} nT "
          f"(axes {np.round(plain.residual_rms_axis_nT, 1)}), with R {fit.residual_rms_nT:7.1f} nT "
          f"(axes {np.round(fit.residual_rms_axis_nT, 1)}), truth model {truth_rms:7.1f} nT")
    rows = [("k", fit.k, true["k"], fit.sigma_k, 1.0, ""),
            ("e", fit.e_rad, true["e"], fit.sigma_e_rad, deg(1.0), " deg"),
            ("R", fit.rotvec_rad, true["rotvec"], fit.sigma_rot_rad, deg(1.0), " deg"),
            ("b", fit.b_nT, true["b"], fit.sigma_b_nT, 1.0, " nT")]
    fmt = lambda x, spec: "[" + " ".join(format(v, spec) for v in x) + "]"  # noqa: E731
    for i, (name, got, want, sig, unit, label) in enumerate(rows):
        print(f"  {name}{label}: fit {fmt(got * unit, '.6f')} true {fmt(want * unit, '.6f')} "
              f"sigma {fmt(sig * unit, '.2g')} z {fmt(z[3 * i:3 * i + 3], '+.2f')}")
    print(f"  seed-001 model alone: k {np.round(plain.k, 6)} e {np.round(deg(plain.e_rad), 4)} deg "
          f"b {np.round(plain.b_nT, 1)} nT")

    assert plain.residual_rms_nT > fit.residual_rms_nT
    assert fit.residual_rms_nT < 1.02 * truth_rms
    assert np.all(np.abs(z) < 3.0), z
