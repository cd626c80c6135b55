"""Figures of merit of one calibration (b, M: B_cal = M (x - b)) on one case."""

from __future__ import annotations

import numpy as np

from generator.fit.bounds import ellipsoid_crb
from generator.fit.ellipsoid import _sym_grad, polar_spd

PPM = 1e6


def rescale_to_magnitude(b_nT, M, x_nT, R_nT) -> np.ndarray:
    """M scaled so that the mean |M (x - b)| over the fitted readings is R: what a user
    of a unit-sphere calibration does with a known field magnitude."""
    mean = float(np.mean(np.linalg.norm((x_nT - b_nT) @ M.T, axis=1)))
    return M * (R_nT / mean)


def offset_error_nT(b_nT, case) -> np.ndarray:
    return np.asarray(b_nT) - case.b_true_nT


def matrix_error_ppm(M, case) -> float:
    """|P_fit - P_true|_F, P the symmetric polar factor (the ellipsoid fixes M only up to
    a rotation: P = sqrtm(M^T M)), in parts per million."""
    return float(np.linalg.norm(polar_spd(M) - case.P_true) * PPM)


def full_sphere_norm_error_nT(b_nT, M, case) -> float:
    """RMS of |M (x0 - b)| - |B| over noise-free readings x0 of the true sensor in
    directions uniform over the whole sphere: the calibration's error in every
    orientation, whatever part of the sphere it was fitted on."""
    m = np.linalg.norm((case.eval_true_nT - b_nT) @ M.T, axis=1)
    return float(np.sqrt(np.mean((m - case.ref_norm_nT) ** 2)))


def heldout_scatter_rel(b_nT, M, case) -> float:
    """std(|B_cal|) / mean(|B_cal|) over the held-out readings (scale-free)."""
    m = np.linalg.norm((case.heldout_nT - b_nT) @ M.T, axis=1)
    return float(np.std(m) / np.mean(m))


def offset_crb(case):
    """Cramér-Rao bound of the case's offset (generator.fit.bounds) at its truth."""
    return ellipsoid_crb(case.field_true_nT, case.b_true_nT, np.linalg.inv(case.W_true),
                         case.sigma_nT, case.ref_norm_nT)


def matrix_bound_sq(crb) -> float:
    """Cramér-Rao bound on E|P_fit - P_true|_F^2: the six symmetric entries' variances,
    off-diagonal ones counted twice (they appear twice in the Frobenius norm)."""
    return float(np.sum(np.diag(crb.matrix_cov) * np.array([1, 1, 1, 2, 2, 2])))


def full_sphere_norm_bound_sq_nT2(case, crb) -> float:
    """Bound on the mean over the evaluation directions of E(|M_hat (x0 - b_hat)| - |B|)^2:
    the parameter bound propagated to first order, g_e^T C g_e with g_e the gradient of
    |M (x0_e - b)| with respect to (b, m6) at the truth."""
    P = case.P_true
    y = case.eval_true_nT - case.b_true_nT
    z = y @ P.T
    u = z / np.linalg.norm(z, axis=1)[:, None]
    G = np.hstack([-(u @ P), _sym_grad(u, y)])
    return float(np.mean(np.einsum("ei,ij,ej->e", G, crb.cov, G)))


def ratio_with_interval(q) -> tuple[float, float]:
    """Mean of per-draw ratios and the half-width of its 95 % interval."""
    q = np.asarray(q, float)
    if len(q) < 2:
        return float(np.mean(q)) if len(q) else float("nan"), float("nan")
    return float(np.mean(q)), float(1.96 * np.std(q, ddof=1) / np.sqrt(len(q)))
