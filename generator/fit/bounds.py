"""Cramér-Rao bound of the ellipsoid (attitude-independent) calibration.

Model (seed 000 eq. 5-6, generator.fit.ellipsoid): readings x_i = x0_i + n_i, where the
noise-free reading x0_i lies on the ellipsoid |M (x0_i - b)| = R_i (R_i the known field
magnitude) and n_i ~ N(0, diag(sigma^2)) per axis, independent between samples.

Parameters theta = (b (3, nT), m (6 entries of the symmetric M, SYM_INDEX order)). The
residual of sample i, r_i = |M (x_i - b)| - R_i, is to first order in the noise

    r_i = u_i^T M n_i,     u_i = M (x0_i - b) / |M (x0_i - b)|   (unit calibrated vector)

so var(r_i) = (M^T u_i)^T diag(sigma^2) (M^T u_i) = sigma^2 |M^T u_i|^2 for isotropic noise.
That is the noise propagated into the residual: |M^T u_i| is the gain of M along the
ellipsoid's normal, which varies over the ellipsoid when M is not a multiple of the
identity. The Fisher information of theta is

    F = sum_i J_i J_i^T / var(r_i),    J_i = d r_i / d theta = [-(M^T u_i), u_i^T E_k y_i]

(y_i = x0_i - b, E_k the symmetric basis matrices). The bound on the offset is the
MARGINAL one, [F^-1]_bb: the six matrix entries are nuisance parameters estimated from the
same data. With M known, the bound would be the smaller conditional one, (F_bb)^-1; on a
partial sphere the two differ by orders of magnitude, which is why the nuisance
parameters must be in.

Only M^T M enters |M y|, so a general (e.g. true, non-symmetric W^-1) matrix is replaced
by its symmetric positive polar factor before anything is evaluated. The bound is the
small-noise (first-order) one: it ignores the O(sigma^2/R) bias of |M (x - b)| and is
attained by an unbiased estimator whose residuals are weighted by 1/|M^T u_i|, i.e. the
"normalised" residuals of `normalised_residuals`; the plain geometric fit reaches it
when |M^T u_i| is nearly the same for all samples (M close to a multiple of identity and
the samples spread over the sphere).

Public API: ellipsoid_crb(field_true_nT, b_nT, M, sigma_nT, ref_norm_nT=None) -> Crb;
residual_gain(b_nT, M, field_nT) -> |M^T u_i|; normalised_residuals(...).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from generator.fit.ellipsoid import _sym_grad, polar_spd

N_PARAMS = 9     # b (3) + symmetric M (6)


@dataclass
class Crb:
    """Cramér-Rao bound at one set of true parameters and samples."""
    fisher: np.ndarray              # (9, 9) Fisher information of (b, m6)
    cov: np.ndarray                 # (9, 9) its inverse: the bound on the covariance
    offset_cov_nT2: np.ndarray      # (3, 3) marginal bound on cov(b) (nuisance M estimated)
    offset_cov_known_M_nT2: np.ndarray  # (3, 3) conditional bound (M known): (F_bb)^-1
    n: int

    @property
    def offset_sigma_nT(self) -> np.ndarray:
        """Marginal 1-sigma bound per offset axis (nT)."""
        return np.sqrt(np.diag(self.offset_cov_nT2))

    @property
    def offset_trace_nT2(self) -> float:
        """Bound on E|b_hat - b|^2 (nT^2) for an unbiased estimator."""
        return float(np.trace(self.offset_cov_nT2))

    @property
    def matrix_cov(self) -> np.ndarray:
        """(6, 6) bound on the covariance of M's six entries (SYM_INDEX order)."""
        return self.cov[3:, 3:]


def _as_sigma(sigma_nT) -> np.ndarray:
    s = np.asarray(sigma_nT, float)
    if s.ndim == 0:
        s = np.full(3, float(s))
    if s.shape != (3,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError(f"sigma_nT must be a positive number or three (per axis), got {sigma_nT!r}")
    return s


def residual_gain(b_nT, M, field_nT) -> np.ndarray:
    """|M^T u_i| for the readings field_nT (N, 3): the factor by which M scales reading
    noise along the ellipsoid's normal into the residual |M (x - b)| - R (M symmetrised
    to its polar factor first)."""
    P = polar_spd(M)
    z = (np.asarray(field_nT, float) - np.asarray(b_nT, float)) @ P.T
    u = z / np.linalg.norm(z, axis=1)[:, None]
    return np.linalg.norm(u @ P, axis=1)          # P symmetric: M^T u = P u


def normalised_residuals(b_nT, M, field_nT, ref_norm_nT) -> np.ndarray:
    """(|M (x_i - b)| - R_i) / |M^T u_i|: the residual in reading units, to first order
    the distance of x_i from the ellipsoid along its normal (Sampson distance). Its
    variance is sigma^2 for every sample, so its sum of squares is the (first-order)
    likelihood of isotropic reading noise."""
    P = polar_spd(M)
    z = (np.asarray(field_nT, float) - np.asarray(b_nT, float)) @ P.T
    rho = np.linalg.norm(z, axis=1)
    u = z / rho[:, None]
    return (rho - np.asarray(ref_norm_nT, float)) / np.linalg.norm(u @ P, axis=1)


def ellipsoid_crb(field_true_nT, b_nT, M, sigma_nT, ref_norm_nT=None) -> Crb:
    """Cramér-Rao bound of (b, symmetric M) for the ellipsoid model.

    field_true_nT: (N, 3) NOISE-FREE readings (frame axes) at which the bound is taken;
    b_nT (3,) the true offset; M (3, 3) the true calibration matrix (any matrix with the
    right M^T M, e.g. W^-1; its symmetric polar factor is used); sigma_nT: reading noise
    1-sigma, a number (isotropic) or three numbers (per frame axis); ref_norm_nT: the
    field magnitude(s) R_i, only used to check that the readings lie on the ellipsoid
    (within 1e-6 relative) when given.
    """
    x = np.asarray(field_true_nT, float)
    if x.ndim != 2 or x.shape[1] != 3 or len(x) < N_PARAMS:
        raise ValueError(f"field_true_nT must be (N >= {N_PARAMS}, 3), got {x.shape}")
    sig = _as_sigma(sigma_nT)
    P = polar_spd(M)
    y = x - np.asarray(b_nT, float)
    z = y @ P.T
    rho = np.linalg.norm(z, axis=1)
    if ref_norm_nT is not None:
        R = np.broadcast_to(np.asarray(ref_norm_nT, float), rho.shape)
        worst = float(np.max(np.abs(rho - R) / R))
        if worst > 1e-6:
            raise ValueError(f"readings are not on the ellipsoid |M (x - b)| = R (relative "
                             f"misfit up to {worst:.2g}): pass noise-free readings")
    u = z / rho[:, None]
    v = u @ P                                          # M^T u (P symmetric), (N, 3)
    var = (v * v) @ (sig * sig)                        # sigma^2 |M^T u|^2 per sample
    J = np.hstack([-v, _sym_grad(u, y)])               # (N, 9)
    Jw = J / np.sqrt(var)[:, None]
    F = Jw.T @ Jw
    # Invert with column scaling (b in nT, m dimensionless: ~10 orders apart).
    d = np.sqrt(np.diag(F))
    cov = np.linalg.inv(F / np.outer(d, d)) / np.outer(d, d)
    cov = 0.5 * (cov + cov.T)
    return Crb(fisher=F, cov=cov, offset_cov_nT2=cov[:3, :3].copy(),
               offset_cov_known_M_nT2=np.linalg.inv(F[:3, :3]), n=int(len(x)))
