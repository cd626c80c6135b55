"""Seed 001: analytic calibration of a magnetometer against known field vectors.

Model (seed 001, eq. 1)::

    h = Q P B + b + n

``h`` the reading (nT, the sensor's frame after axis mapping), ``B`` the known true field
(nT), ``b`` the offsets, ``Q = diag(k1, k2, k3)`` the scale factors and ``P`` the unit vectors
of the measuring axes::

    P = [[1,      0,              0            ],
         [sin e1, cos e1,         0            ],
         [sin e2, cos e2 sin e3,  cos e2 cos e3]]

With ``alpha_i = tan e_i``, ``beta_i = sec e_i``, ``gamma_i = 1/k_i`` the model becomes, per
sample ``l`` (seed 001, eq. 7 after substituting the first row into the others)::

    r1 = gamma1 (h1 - b1)               - B1
    r2 = beta1 gamma2 (h2 - b2)         - alpha1 B1 - B2
    r3 = beta2 beta3 gamma3 (h3 - b3)   - alpha2 beta3 B1 - alpha3 B2 - B3

and ``Phi = sum_l (r1^2 + r2^2 + r3^2)`` (nT^2) is minimised under
``alpha_i^2 - beta_i^2 + 1 = 0``, ``beta_i > 0``.  The Lagrangian ``L = Phi + sum lambda_i
(alpha_i^2 - beta_i^2 + 1)`` has 15 unknowns.  With the sums (all over the samples)::

    N, C_i = sum B_i, H_i = sum h_i, F_i = sum h_i^2, D_ij = sum B_i h_j, G_ij = sum B_i B_j

its stationarity conditions split into three independent systems, one per row.

Derivation (formula numbers are the paper's).  The PDF text lost the systems (10)-(13),
the coefficients of (34), the roots (35) and most signs elsewhere, so everything below was
re-derived here; the factorisations were checked symbolically with sympy:

Row 1, unknowns (b1, gamma1).  dL/dgamma1 = 0 and dL/db1 = 0 (the latter divided by
gamma1 != 0) give ``gamma1 F~ = D11 - C1 b1`` and ``gamma1 (H1 - N b1) = C1`` with
``F~ = F1 - 2 H1 b1 + N b1^2``; eliminating gamma1 the b1^2 terms cancel::

    b1 = (D11 H1 - C1 F1) / (N D11 - C1 H1),   gamma1 = (N D11 - C1 H1) / (N F1 - H1^2)

Row 2, unknowns (b2, alpha1, beta1, gamma2, lambda1); write u = beta1 gamma2.  dL/dgamma2
and dL/dbeta1 together force lambda1 = 0 (paper, 17).  The rest is (paper, 18)::

    u (F2 - 2 H2 b2 + N b2^2) = D22 - C2 b2 + alpha1 (D12 - C1 b2)     (dL/dgamma2)
    u (D12 - C1 b2)           = alpha1 G11 + G12                         (dL/dalpha1)
    u (H2 - N b2)             = alpha1 C1 + C2                           (dL/db2)

Eliminating u between the first and third gives (19), between the second and third (20);
equating (19) and (20) gives the quadratic (21) in alpha1, which factorises exactly as::

    (C1 alpha1 + C2) (l1 alpha1 + l0) = 0
    l1 = C1 (C1 F2 - D12 H2) + G11 (H2^2 - N F2) + D12 (N D12 - C1 H2)  = -det M2
    l0 = C2 (C1 F2 - D12 H2) + G12 (H2^2 - N F2) + D22 (N D12 - C1 H2)
    M2 = [[N, H2, C1], [H2, F2, D12], [C1, D12, G11]]

so the roots (22) are ``alpha1' = -C2/C1`` and ``alpha1'' = -l0/l1``.  Then b2 from (19),
u from the first line, beta1 = sqrt(1 + alpha1^2), gamma2 = u / beta1.

Row 3, unknowns (b3, alpha2, alpha3, beta2, beta3, gamma3, lambda2, lambda3); write
w = beta2 beta3 gamma3 and a = alpha2 beta3.  lambda2 = lambda3 = 0 (paper, 25 and 27) and::

    w (D13 - C1 b3)               = a G11 + alpha3 G12 + G13                       (E1)
    w (F3 - 2 H3 b3 + N b3^2)     = a (D13 - C1 b3) + alpha3 (D23 - C2 b3) + D33 - C3 b3  (E2)
    w (H3 - N b3)                 = a C1 + alpha3 C2 + C3                          (E3)
    w (D23 - C2 b3)               = a G12 + alpha3 G22 + G23                       (E4)

The paper eliminates w with E3 (29-31), then a (32, 33), then alpha3: the quadratic (34)
in b3.  Re-derived, (34) factorises exactly as::

    (C1^2 b3 - C1 D13 + G11 H3 - N G11 b3) * (det(A_w) b3 - det(A_v)) = 0

where A is the matrix of the normal equations of r3 in the unknowns (w, v = w b3, a,
alpha3) and A_w, A_v are A with the w and v columns replaced by the right-hand side y::

    A = [[F3, -H3, -D13, -D23], [-H3, N, C1, C2], [-D13, C1, G11, G12], [-D23, C2, G12, G22]]
    y = [D33, -C3, -G13, -G23]

so the roots (35) are ``b3' = (C1 D13 - G11 H3) / (C1^2 - N G11)`` and
``b3'' = det(A_v) / det(A_w)``.  (The same way, the root alpha1'' of row 2 and the row-1
solution are Cramer's rule on their rows' normal equations.)

What the paper gets wrong, and how this module handles it:

* Only the double-primed roots are stationary points.  The primed roots are introduced by
  the cross-multiplications: at alpha1' = -C2/C1, b2 = H2/N the third line of (18) is 0 = 0
  but the first two give different u (so dL/dalpha1 or dL/dgamma2 != 0, whichever is
  used); at b3' the coefficient of a in (29) vanishes, (29) is 0/0 and (30), (31) give
  different a.  The paper's "four solutions" are therefore one stationary point (the
  minimum) and three points that are not stationary.  ``AnalyticFit.candidates`` holds all four with their Phi and their KKT
  residual, and the smallest Phi is always the true one (Phi is a convex quadratic in the
  reparametrised unknowns of each row, whose unique minimiser is the double-primed root).
* The Lagrangian does have further stationary points, at gamma_i = 0 (k_i infinite), which
  the paper excludes by dividing by gamma_i: per row one such saddle, so 2 x 2 x 2 = 8
  stationary points in all; ``lagrangian_stationary_points`` returns them.
* The paper's formulas that divide by (H_i - N b_i) or by C1 -- (20), (28)-(33) and the
  root alpha1' -- become 0/0 when sum B_i = 0 (balanced data, e.g. static positions in
  +- pairs), because then b_i = H_i/N at the solution.  The closed form used here for the
  minimum is (11), the second root of (22) with (19) and the first line of (18), and
  Cramer's rule for row 3 (the second root of (34)); none of them divides by those terms.
  Before forming the sums the data are centred on the mean reading and scaled by the RMS
  field magnitude (the model is equivariant under both), which keeps the sums O(N).

The point estimate is the minimiser of Phi (the field-space residual).  Its 1-sigma
uncertainties come from the Gauss-Newton approximation of the reading-space model
``h = Q P B + b`` (residual variance per axis, Jacobian at the estimate).

``fit_analytic_rotated`` adds a small rotation, ``h = Q P R B + b`` (12 parameters, the
same as an unconstrained ``h = W B + b``), fitted with scipy's least_squares started from
the analytic solution with R = I.  ``lq_split`` splits any W (det > 0) as Q P R.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.optimize import least_squares

from generator.errors import InputError

#: Fewest samples accepted.  Row 3 (and, in the rotated model, every axis) has four
#: unknowns, so four samples in general position determine them exactly; two more give
#: the residual variance behind the uncertainties at least two degrees of freedom.
MIN_SAMPLES = 6

#: Smallest accepted ratio of the smallest to the largest singular value of the centred
#: field vectors (B - mean B).  Below it the vectors lie (nearly) in one plane, and the
#: offset and scale along the normal of that plane are not separable: their uncertainty
#: grows as 1/ratio, and the closed form, which works with sums of products (it squares
#: the condition number), would lose more than about ten of the sixteen digits.
PLANARITY_MIN_RATIO = 1e-3

#: A reading column whose standard deviation is below this fraction of the RMS field
#: magnitude is treated as constant (a dead axis): its scale factor is undefined.
CONSTANT_AXIS_RATIO = 1e-9

#: Dimensionless KKT residual (see `_kkt_residual`) below which a point counts as
#: stationary.  Roundoff gives about 1e-16 times the condition number of the row's
#: normal equations; the paper's spurious roots gave 7e-3 .. 5e2 on the test problems.
STATIONARY_KKT_TOL = 1e-8

#: In the normalised units (readings centred, data scaled by the RMS field) a sum over
#: samples is O(N) and a product of two sums O(N^2); below this fraction of that size a
#: divisor of the paper's spurious roots is zero up to roundoff, and the root undefined.
_ROUNDOFF_ZERO = 1e-10

_AXIS = ("x", "y", "z")


# ----------------------------------------------------------------------------------------
# P, angles, rotations
# ----------------------------------------------------------------------------------------

def P_from_angles(e_rad) -> np.ndarray:
    """The non-orthogonality matrix P (rows: unit vectors of the axes) from e1, e2, e3."""
    e1, e2, e3 = (float(x) for x in np.asarray(e_rad, dtype=float).reshape(3))
    return np.array([
        [1.0, 0.0, 0.0],
        [math.sin(e1), math.cos(e1), 0.0],
        [math.sin(e2), math.cos(e2) * math.sin(e3), math.cos(e2) * math.cos(e3)],
    ])


def angles_from_P(P) -> np.ndarray:
    """e1, e2, e3 (rad) from a P of the form of `P_from_angles` (diagonal > 0)."""
    P = np.asarray(P, dtype=float)
    e1 = math.atan2(P[1, 0], P[1, 1])
    e2 = math.atan2(P[2, 0], math.hypot(P[2, 1], P[2, 2]))
    e3 = math.atan2(P[2, 1], P[2, 2])
    return np.array([e1, e2, e3])


def _skew(v) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rotation_from_rotvec(rotvec_rad) -> np.ndarray:
    """R = exp([rho]x) (Rodrigues) for a rotation vector rho in rad."""
    rho = np.asarray(rotvec_rad, dtype=float).reshape(3)
    theta = float(np.linalg.norm(rho))
    K = _skew(rho)
    if theta < 1e-6:
        a, c = 1.0 - theta**2 / 6.0, 0.5 - theta**2 / 24.0
    else:
        a, c = math.sin(theta) / theta, (1.0 - math.cos(theta)) / theta**2
    return np.eye(3) + a * K + c * (K @ K)


def rotvec_from_rotation(R) -> np.ndarray:
    """Rotation vector (rad) of a rotation matrix, for angles below pi."""
    R = np.asarray(R, dtype=float)
    cos_theta = min(1.0, max(-1.0, (np.trace(R) - 1.0) / 2.0))
    theta = math.acos(cos_theta)
    axis_times_sin = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-6:
        return axis_times_sin * (1.0 + theta**2 / 6.0)
    return axis_times_sin * (theta / math.sin(theta))


def _right_jacobian_so3(rotvec) -> np.ndarray:
    """J_r with exp(rho + d) ~= exp(rho) exp([J_r d]x)."""
    rho = np.asarray(rotvec, dtype=float)
    theta = float(np.linalg.norm(rho))
    K = _skew(rho)
    if theta < 1e-5:
        return np.eye(3) - 0.5 * K + (K @ K) / 6.0
    return (np.eye(3) - (1.0 - math.cos(theta)) / theta**2 * K
            + (theta - math.sin(theta)) / theta**3 * (K @ K))


def lq_split(W) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split W (3x3, det > 0) as W = Q P R.

    Q positive diagonal, P lower triangular with unit-norm rows and positive diagonal (the
    form of `P_from_angles`), R orthogonal with det +1.  This is the LQ decomposition
    W = L R (from the QR decomposition of W^T), made unique by giving L a positive
    diagonal, followed by L = Q P with k_i the norm of row i of L.
    """
    W = np.asarray(W, dtype=float)
    if W.shape != (3, 3) or not np.all(np.isfinite(W)):
        raise InputError(None, f"lq_split needs a finite 3x3 matrix, got shape {W.shape}")
    det = float(np.linalg.det(W))
    if not det > 0.0:
        raise InputError(None, f"lq_split needs det(W) > 0 (got {det:.6g}): "
                               "a reflection or a singular matrix is not Q P R")
    q_of_wt, r_of_wt = np.linalg.qr(W.T)
    L = r_of_wt.T
    R = q_of_wt.T
    signs = np.sign(np.diag(L))
    L = L * signs[None, :]
    R = signs[:, None] * R
    k = np.linalg.norm(L, axis=1)
    P = L / k[:, None]
    return np.diag(k), P, R


# ----------------------------------------------------------------------------------------
# input checks
# ----------------------------------------------------------------------------------------

def _validated(h_nT, B_nT) -> tuple[np.ndarray, np.ndarray]:
    try:
        h = np.asarray(h_nT, dtype=float)
        B = np.asarray(B_nT, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InputError(None, f"readings and field vectors must be numeric arrays ({exc})")
    if h.ndim != 2 or h.shape[1] != 3:
        raise InputError(None, f"readings must have shape (N, 3), got {h.shape}")
    if B.ndim != 2 or B.shape[1] != 3:
        raise InputError(None, f"field vectors must have shape (N, 3), got {B.shape}")
    if h.shape[0] != B.shape[0]:
        raise InputError(None, f"{h.shape[0]} readings but {B.shape[0]} field vectors: "
                               "they must pair up sample by sample")
    n = h.shape[0]
    if n < MIN_SAMPLES:
        raise InputError(None, f"{n} samples, need at least {MIN_SAMPLES}: the third axis has "
                               "4 unknowns (4 samples determine them), and 2 more are needed "
                               "to estimate the noise behind the uncertainties")
    for name, arr in (("readings", h), ("field vectors", B)):
        bad = ~np.isfinite(arr)
        if bad.any():
            row, col = np.argwhere(bad)[0]
            raise InputError(None, f"{name}: non-finite value {arr[row, col]} at sample {row}, "
                                   f"axis {_AXIS[col]} ({int(bad.sum())} in all)")
    for i in range(3):
        if not np.any(B[:, i]):
            raise InputError(None, f"field vectors: axis {_AXIS[i]} is zero in every sample; "
                                   "the field must have a component along every axis")
    field_rms = math.sqrt(float(np.mean(np.sum(B * B, axis=1))))
    for i in range(3):
        if float(np.std(h[:, i])) <= CONSTANT_AXIS_RATIO * field_rms:
            raise InputError(None, f"readings: axis {_AXIS[i]} is constant "
                                   f"({h[0, i]:.6g} nT in every sample): a dead axis has no "
                                   "scale factor")
    centred = B - B.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    ratio = float(sv[-1] / sv[0]) if sv[0] > 0 else 0.0
    if ratio < PLANARITY_MIN_RATIO:
        raise InputError(None, "field vectors lie (nearly) in one plane: smallest/largest "
                               f"singular value of the centred vectors is {ratio:.3g} < "
                               f"{PLANARITY_MIN_RATIO:g}; offsets and scales along its normal "
                               "cannot be separated (turn the unit through more orientations)")
    return h, B


# ----------------------------------------------------------------------------------------
# sums and the closed form
# ----------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Sums:
    """The paper's sums over samples, 0-based: C[0] is C1, D[i, j] = sum B_i h_j."""
    N: float
    C: np.ndarray
    H: np.ndarray
    F: np.ndarray
    D: np.ndarray
    G: np.ndarray

    @staticmethod
    def of(h: np.ndarray, B: np.ndarray) -> "_Sums":
        return _Sums(N=float(h.shape[0]), C=B.sum(axis=0), H=h.sum(axis=0),
                     F=(h * h).sum(axis=0), D=B.T @ h, G=B.T @ B)


@dataclass(frozen=True)
class _Row:
    """One row's solution: the unknowns it fixes (alpha/beta entries may be absent)."""
    b: float
    gamma: float
    alpha: tuple = ()
    label: str = ""


def _row1(S: _Sums) -> _Row:
    N, C1, H1, F1, D11 = S.N, S.C[0], S.H[0], S.F[0], S.D[0, 0]
    gamma1 = (N * D11 - C1 * H1) / (N * F1 - H1 * H1)
    b1 = (D11 * H1 - C1 * F1) / (N * D11 - C1 * H1)
    return _Row(b=b1, gamma=gamma1, label="row 1 (11)")


def _row2_from_alpha1(S: _Sums, alpha1: float, b2: float, label: str) -> _Row:
    N, C1, C2, H2, F2 = S.N, S.C[0], S.C[1], S.H[1], S.F[1]
    D12, D22 = S.D[0, 1], S.D[1, 1]
    u = (D22 - C2 * b2 + alpha1 * (D12 - C1 * b2)) / (F2 - 2.0 * H2 * b2 + N * b2 * b2)  # (18)
    beta1 = math.sqrt(1.0 + alpha1 * alpha1)
    return _Row(b=b2, gamma=u / beta1, alpha=(alpha1,), label=label)


def _row2(S: _Sums) -> tuple[_Row, _Row]:
    """The two roots of (21): alpha1' = -C2/C1 (not stationary) and alpha1'' (the minimum)."""
    N, C1, C2, H2, F2 = S.N, S.C[0], S.C[1], S.H[1], S.F[1]
    D12, D22, G11, G12 = S.D[0, 1], S.D[1, 1], S.G[0, 0], S.G[0, 1]
    # alpha1'' = -l0/l1, the root of (22) that does not divide by C1
    l1 = C1 * (C1 * F2 - D12 * H2) + G11 * (H2 * H2 - N * F2) + D12 * (N * D12 - C1 * H2)
    l0 = C2 * (C1 * F2 - D12 * H2) + G12 * (H2 * H2 - N * F2) + D22 * (N * D12 - C1 * H2)
    alpha1 = -l0 / l1
    b2 = ((alpha1 * (D12 * H2 - C1 * F2) + D22 * H2 - C2 * F2)
          / (alpha1 * (N * D12 - C1 * H2) + N * D22 - C2 * H2))  # (19)
    genuine = _row2_from_alpha1(S, alpha1, b2, "row 2 root alpha1'' = -l0/l1")
    # alpha1' = -C2/C1, where (19) and (20) both give b2 = H2/N; C is O(N) in the
    # normalised units, so |C1| <= 1e-10 N is zero up to roundoff (balanced data)
    if abs(C1) > _ROUNDOFF_ZERO * N:
        spurious = _row2_from_alpha1(S, -C2 / C1, H2 / N, "row 2 root alpha1' = -C2/C1")
    else:
        spurious = _Row(b=math.nan, gamma=math.nan, alpha=(math.nan,),
                        label="row 2 root alpha1' = -C2/C1 (undefined: C1 = 0)")
    return spurious, genuine


def _row3_from_a_alpha3(a: float, alpha3: float, w: float, b3: float, label: str) -> _Row:
    beta3 = math.sqrt(1.0 + alpha3 * alpha3)
    alpha2 = a / beta3
    beta2 = math.sqrt(1.0 + alpha2 * alpha2)
    return _Row(b=b3, gamma=w / (beta2 * beta3), alpha=(alpha2, alpha3), label=label)


def _row3_normal_equations(S: _Sums) -> tuple[np.ndarray, np.ndarray]:
    """Normal equations A x = y of r3 in x = (w, v = w b3, a = alpha2 beta3, alpha3)."""
    N, C1, C2, C3 = S.N, S.C[0], S.C[1], S.C[2]
    H3, F3 = S.H[2], S.F[2]
    D13, D23, D33 = S.D[0, 2], S.D[1, 2], S.D[2, 2]
    G11, G12, G22, G13, G23 = S.G[0, 0], S.G[0, 1], S.G[1, 1], S.G[0, 2], S.G[1, 2]
    A = np.array([[F3, -H3, -D13, -D23],
                  [-H3, N, C1, C2],
                  [-D13, C1, G11, G12],
                  [-D23, C2, G12, G22]])
    y = np.array([D33, -C3, -G13, -G23])
    return A, y


def _row3(S: _Sums) -> tuple[_Row, _Row]:
    """The two roots of (34): b3' (not stationary) and b3'' (the minimum)."""
    N, C1, C2, C3 = S.N, S.C[0], S.C[1], S.C[2]
    H3, F3 = S.H[2], S.F[2]
    D13, D23, D33 = S.D[0, 2], S.D[1, 2], S.D[2, 2]
    G11, G12, G22, G13, G23 = S.G[0, 0], S.G[0, 1], S.G[1, 1], S.G[0, 2], S.G[1, 2]

    # b3'' = det(A_v) / det(A_w); with it (w, a, alpha3) by Cramer's rule on the same system
    A, y = _row3_normal_equations(S)
    dets = []
    for col in range(4):
        A_col = A.copy()
        A_col[:, col] = y
        dets.append(float(np.linalg.det(A_col)))
    det_A = float(np.linalg.det(A))
    w, a, alpha3 = dets[0] / det_A, dets[2] / det_A, dets[3] / det_A
    genuine = _row3_from_a_alpha3(a, alpha3, w, dets[1] / dets[0], "row 3 root b3'' = det(A_v)/det(A_w)")

    # b3' zeroes the coefficient of a in (29), i.e. in E1 (H3 - N b3) - E3 (D13 - C1 b3);
    # there that combination fixes alpha3 alone (= (32) at this root), a comes from (31)
    # and w from E2.  Products of two sums are O(N^2) in the normalised units.
    b3 = (C1 * D13 - G11 * H3) / (C1 * C1 - N * G11)
    e, d1, d2, d3 = H3 - N * b3, D13 - C1 * b3, D23 - C2 * b3, D33 - C3 * b3
    f = F3 - 2.0 * H3 * b3 + N * b3 * b3
    coef_alpha3 = G12 * e - C2 * d1
    coef_a_31 = G12 * e - C1 * d2
    if min(abs(coef_alpha3), abs(coef_a_31)) > _ROUNDOFF_ZERO * N * N:
        alpha3_p = (C3 * d1 - G13 * e) / coef_alpha3
        a_p = (C3 * d2 - G23 * e - alpha3_p * (G22 * e - C2 * d2)) / coef_a_31
        w_p = (a_p * d1 + alpha3_p * d2 + d3) / f
        spurious = _row3_from_a_alpha3(a_p, alpha3_p, w_p, b3,
                                       "row 3 root b3' = (C1 D13 - G11 H3)/(C1^2 - N G11)")
    else:
        spurious = _Row(b=math.nan, gamma=math.nan, alpha=(math.nan, math.nan),
                        label="row 3 root b3' (undefined: 0/0 in (31)-(32), sum B = 0)")
    return spurious, genuine


# ----------------------------------------------------------------------------------------
# Phi, Lagrangian gradient
# ----------------------------------------------------------------------------------------

def _row_residuals(h, B, alpha, beta, gamma, b) -> np.ndarray:
    """(N, 3) residuals r1, r2, r3 of the reparametrised model (units of h and B)."""
    a1, a2, a3 = alpha
    b1_, b2_, b3_ = beta
    g1, g2, g3 = gamma
    r = np.empty_like(h)
    r[:, 0] = g1 * (h[:, 0] - b[0]) - B[:, 0]
    r[:, 1] = b1_ * g2 * (h[:, 1] - b[1]) - a1 * B[:, 0] - B[:, 1]
    r[:, 2] = b2_ * b3_ * g3 * (h[:, 2] - b[2]) - a2 * b3_ * B[:, 0] - a3 * B[:, 1] - B[:, 2]
    return r


def _kkt_residual(h, B, alpha, beta, gamma, b) -> tuple[float, np.ndarray]:
    """Dimensionless size of the Lagrangian's gradient, and the best multipliers.

    Evaluated on the normalised data (readings centred, both scaled by the RMS field
    magnitude, so every unknown and every residual is O(1)): the gradient of L with
    respect to the 12 unknowns alpha, beta, gamma, b, divided by 2N, i.e. the mean over
    samples of r * dr/dx.  The multipliers lambda_i are chosen by least squares over the
    alpha_i and beta_i components (lambda = 0 at every true stationary point); the
    constraints hold by construction (beta = sqrt(1 + alpha^2)).  Returns (max abs, lambda).
    """
    a1, a2, a3 = alpha
    be1, be2, be3 = beta
    g1, g2, g3 = gamma
    r = _row_residuals(h, B, alpha, beta, gamma, b)
    x1, x2, x3 = h[:, 0] - b[0], h[:, 1] - b[1], h[:, 2] - b[2]
    r1, r2, r3 = r[:, 0], r[:, 1], r[:, 2]
    grad = 2.0 * np.array([
        r2 @ -B[:, 0],                          # alpha1
        r3 @ (-be3 * B[:, 0]),                  # alpha2
        r3 @ -B[:, 1],                          # alpha3
        r2 @ (g2 * x2),                         # beta1
        r3 @ (be3 * g3 * x3),                   # beta2
        r3 @ (be2 * g3 * x3 - a2 * B[:, 0]),    # beta3
        r1 @ x1,                                # gamma1
        r2 @ (be1 * x2),                        # gamma2
        r3 @ (be2 * be3 * x3),                  # gamma3
        -g1 * r1.sum(),                         # b1
        -be1 * g2 * r2.sum(),                   # b2
        -be2 * be3 * g3 * r3.sum(),             # b3
    ])
    alpha = np.asarray(alpha, dtype=float)
    beta = np.asarray(beta, dtype=float)
    # dL/dalpha_i = g_a + 2 lam alpha_i, dL/dbeta_i = g_b - 2 lam beta_i
    lam = (-grad[0:3] * alpha + grad[3:6] * beta) / (2.0 * (alpha * alpha + beta * beta))
    grad_l = grad.copy()
    grad_l[0:3] += 2.0 * lam * alpha
    grad_l[3:6] -= 2.0 * lam * beta
    return float(np.max(np.abs(grad_l)) / (2.0 * len(h))), lam


# ----------------------------------------------------------------------------------------
# results
# ----------------------------------------------------------------------------------------

@dataclass(frozen=True)
class StationaryCandidate:
    """One solution of the paper's system (10), or one stationary point of the Lagrangian.

    alpha = tan e, beta = sec e, gamma = 1/k, b_nT offsets, lam the multipliers that best
    zero the Lagrangian's gradient, phi_nT2 the penalty Phi, kkt_residual the
    dimensionless size of the gradient (`_kkt_residual`), label which roots it combines.
    """
    alpha: np.ndarray
    beta: np.ndarray
    gamma: np.ndarray
    b_nT: np.ndarray
    lam: np.ndarray
    phi_nT2: float
    kkt_residual: float
    label: str

    @property
    def is_stationary(self) -> bool:
        return bool(self.kkt_residual < STATIONARY_KKT_TOL)

    @property
    def k(self) -> np.ndarray:
        with np.errstate(divide="ignore"):
            return 1.0 / self.gamma

    @property
    def e_rad(self) -> np.ndarray:
        return np.arctan(self.alpha)

    @property
    def unknowns(self) -> np.ndarray:
        """The 15 unknowns of the Lagrangian: alpha1..3, beta1..3, gamma1..3, b1..3, lambda1..3."""
        return np.concatenate([self.alpha, self.beta, self.gamma, self.b_nT, self.lam])


@dataclass(frozen=True)
class AnalyticFit:
    """Result of `fit_analytic`.  Parameter order in `cov`: k1..3, e1..3 (rad), b1..3 (nT)."""
    k: np.ndarray
    e_rad: np.ndarray
    b_nT: np.ndarray
    Q: np.ndarray
    P: np.ndarray
    W: np.ndarray
    candidates: tuple
    chosen_index: int
    phi_nT2: float
    residual_rms_nT: float
    residual_rms_axis_nT: np.ndarray
    cov: np.ndarray
    sigma_k: np.ndarray
    sigma_e_rad: np.ndarray
    sigma_b_nT: np.ndarray
    n_samples: int

    def predict(self, B_nT) -> np.ndarray:
        """Readings the model expects for true fields B (N, 3): W B + b."""
        return np.asarray(B_nT, dtype=float) @ self.W.T + self.b_nT

    def apply(self, h_nT) -> np.ndarray:
        """Field estimate from readings (N, 3): B = (Q P)^-1 (h - b)."""
        return np.linalg.solve(self.W, (np.asarray(h_nT, dtype=float) - self.b_nT).T).T


@dataclass(frozen=True)
class RotatedFit:
    """Result of `fit_analytic_rotated`: h = Q P R B + b.

    `cov` is 12x12 in the order k1..3, e1..3 (rad), delta1..3 (rad), b1..3 (nT), where
    delta is a small rotation about the estimate: R_true = R exp([delta]x).
    """
    k: np.ndarray
    e_rad: np.ndarray
    R: np.ndarray
    rotvec_rad: np.ndarray
    b_nT: np.ndarray
    Q: np.ndarray
    P: np.ndarray
    W: np.ndarray
    cov: np.ndarray
    sigma_k: np.ndarray
    sigma_e_rad: np.ndarray
    sigma_rot_rad: np.ndarray
    sigma_b_nT: np.ndarray
    residual_rms_nT: float
    residual_rms_axis_nT: np.ndarray
    analytic: AnalyticFit
    n_samples: int
    optimizer_message: str

    def predict(self, B_nT) -> np.ndarray:
        return np.asarray(B_nT, dtype=float) @ self.W.T + self.b_nT

    def apply(self, h_nT) -> np.ndarray:
        """Field estimate from readings (N, 3): B = (Q P R)^-1 (h - b)."""
        return np.linalg.solve(self.W, (np.asarray(h_nT, dtype=float) - self.b_nT).T).T


# ----------------------------------------------------------------------------------------
# fitting
# ----------------------------------------------------------------------------------------

def _normalised(h: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Centre readings on their mean and scale both by the RMS field magnitude."""
    h_mean = h.mean(axis=0)
    scale = math.sqrt(float(np.mean(np.sum(B * B, axis=1))))
    return (h - h_mean) / scale, B / scale, h_mean, scale


def _candidate(h_n, B_n, h_mean, scale, r1: _Row, r2: _Row, r3: _Row) -> StationaryCandidate:
    alpha = np.array([r2.alpha[0], r3.alpha[0], r3.alpha[1]])
    beta = np.sqrt(1.0 + alpha * alpha)
    gamma = np.array([r1.gamma, r2.gamma, r3.gamma])
    b_n = np.array([r1.b, r2.b, r3.b])
    if not (np.all(np.isfinite(alpha)) and np.all(np.isfinite(gamma)) and np.all(np.isfinite(b_n))):
        return StationaryCandidate(alpha, beta, gamma, h_mean + scale * b_n, np.full(3, np.nan),
                                   math.inf, math.nan, f"{r2.label}; {r3.label}")
    phi = float(np.sum(_row_residuals(h_n, B_n, alpha, beta, gamma, b_n) ** 2)) * scale**2
    kkt, lam = _kkt_residual(h_n, B_n, alpha, beta, gamma, b_n)
    return StationaryCandidate(alpha, beta, gamma, h_mean + scale * b_n, lam * scale**2,
                               phi, kkt, f"{r2.label}; {r3.label}")


def _axis_jacobians(B: np.ndarray, k: np.ndarray, e: np.ndarray) -> list[np.ndarray]:
    """d(model reading)/d(parameters) for each axis of h = Q P B + b (block-diagonal)."""
    s1, c1 = math.sin(e[0]), math.cos(e[0])
    s2, c2 = math.sin(e[1]), math.cos(e[1])
    s3, c3 = math.sin(e[2]), math.cos(e[2])
    ones = np.ones(len(B))
    B1, B2, B3 = B[:, 0], B[:, 1], B[:, 2]
    p3B = s2 * B1 + c2 * s3 * B2 + c2 * c3 * B3
    return [
        np.column_stack([B1, ones]),                                             # k1, b1
        np.column_stack([s1 * B1 + c1 * B2, k[1] * (c1 * B1 - s1 * B2), ones]),  # k2, e1, b2
        np.column_stack([p3B,                                                    # k3
                         k[2] * (c2 * B1 - s2 * s3 * B2 - s2 * c3 * B3),         # e2
                         k[2] * (c2 * c3 * B2 - c2 * s3 * B3),                   # e3
                         ones]),                                                 # b3
    ]


#: positions of each axis' parameters in the (k1..3, e1..3, b1..3) vector
_AXIS_PARAMS = ([0, 6], [1, 3, 7], [2, 4, 5, 8])


def fit_analytic(h_nT, B_nT) -> AnalyticFit:
    """Closed-form seed-001 calibration of readings h (N, 3) against known fields B (N, 3).

    Computes the paper's four candidate solutions (one root of row 1 x two of row 2 x two of
    row 3), keeps the one with the smallest Phi, and adds Gauss-Newton 1-sigma
    uncertainties.  Raises InputError on data that cannot determine the parameters.
    """
    h, B = _validated(h_nT, B_nT)
    h_n, B_n, h_mean, scale = _normalised(h, B)
    S = _Sums.of(h_n, B_n)
    row1 = _row1(S)
    row2 = _row2(S)
    row3 = _row3(S)
    candidates = tuple(_candidate(h_n, B_n, h_mean, scale, row1, r2, r3)
                       for r2 in row2 for r3 in row3)
    chosen = int(np.argmin([c.phi_nT2 for c in candidates]))
    best = candidates[chosen]

    k = best.k
    e = best.e_rad
    b = best.b_nT
    Q = np.diag(k)
    P = P_from_angles(e)
    W = Q @ P
    resid = h - (B @ W.T + b)
    n = len(h)
    cov = np.zeros((9, 9))
    rms_axis = np.sqrt(np.mean(resid**2, axis=0))
    for i, J in enumerate(_axis_jacobians(B, k, e)):
        dof = n - J.shape[1]
        var = float(resid[:, i] @ resid[:, i]) / dof
        idx = _AXIS_PARAMS[i]
        cov[np.ix_(idx, idx)] = var * np.linalg.inv(J.T @ J)
    sigma = np.sqrt(np.diag(cov))
    return AnalyticFit(
        k=k, e_rad=e, b_nT=b, Q=Q, P=P, W=W, candidates=candidates, chosen_index=chosen,
        phi_nT2=best.phi_nT2, residual_rms_nT=float(np.sqrt(np.mean(resid**2))),
        residual_rms_axis_nT=rms_axis, cov=cov, sigma_k=sigma[0:3], sigma_e_rad=sigma[3:6],
        sigma_b_nT=sigma[6:9], n_samples=n)


def lagrangian_stationary_points(h_nT, B_nT) -> list[StationaryCandidate]:
    """All stationary points of the paper's Lagrangian (9), gamma_i = 0 included.

    Each row has its minimum (the root used by `fit_analytic`) and, where it exists, one
    more stationary point with gamma_i = 0 (k_i infinite), which the paper excludes by
    dividing by gamma_i:

    * row 1: gamma1 = 0, b1 = D11 / C1                       (needs C1 != 0)
    * row 2: gamma2 = 0, alpha1 = -G12/G11, b2 = (D22 + alpha1 D12) / (C2 + alpha1 C1)
    * row 3: gamma3 = 0, (a, alpha3) the least-squares fit of -B3 on (B1, B2),
             b3 = (a D13 + alpha3 D23 + D33) / (a C1 + alpha3 C2 + C3)

    (at gamma_i = 0 the row's residual no longer depends on b_i, so dL/db_i = 0, and
    dL/dgamma_i = 0 fixes b_i).  Up to 2 x 2 x 2 = 8 points; all have lambda = 0.
    """
    h, B = _validated(h_nT, B_nT)
    h_n, B_n, h_mean, scale = _normalised(h, B)
    S = _Sums.of(h_n, B_n)
    C, D, G = S.C, S.D, S.G
    rows1 = [_row1(S)]
    if C[0] != 0.0:
        rows1.append(_Row(b=D[0, 0] / C[0], gamma=0.0, label="row 1 gamma1 = 0"))
    rows2 = [_row2(S)[1]]
    alpha1 = -G[0, 1] / G[0, 0]
    den2 = C[1] + alpha1 * C[0]
    if den2 != 0.0:
        rows2.append(_Row(b=(D[1, 1] + alpha1 * D[0, 1]) / den2, gamma=0.0, alpha=(alpha1,),
                          label="row 2 gamma2 = 0"))
    rows3 = [_row3(S)[1]]
    a, alpha3 = np.linalg.solve(G[:2, :2], -G[:2, 2])
    den3 = a * C[0] + alpha3 * C[1] + C[2]
    if den3 != 0.0:
        b3 = (a * D[0, 2] + alpha3 * D[1, 2] + D[2, 2]) / den3
        rows3.append(_row3_from_a_alpha3(float(a), float(alpha3), 0.0, float(b3), "row 3 gamma3 = 0"))
    points = []
    for r1 in rows1:
        for r2 in rows2:
            for r3 in rows3:
                c = _candidate(h_n, B_n, h_mean, scale, r1, r2, r3)
                points.append(StationaryCandidate(c.alpha, c.beta, c.gamma, c.b_nT, c.lam,
                                                  c.phi_nT2, c.kkt_residual,
                                                  f"{r1.label}; {c.label}"))
    return points


def _rotated_residual_and_jacobian(x, h_n, B_n):
    k, e, rho, b = x[0:3], x[3:6], x[6:9], x[9:12]
    R = rotation_from_rotvec(rho)
    P = P_from_angles(e)
    g = B_n @ R.T                         # R B
    Pg = g @ P.T                          # P R B
    model = Pg * k + b
    resid = (h_n - model).ravel()         # sample-major: (l, axis)
    n = len(h_n)
    J = np.zeros((n, 3, 12))
    for i in range(3):
        J[:, i, i] = -Pg[:, i]
    dP = _dP_de(e)
    for j in range(3):
        J[:, :, 3 + j] = -(g @ dP[j].T) * k
    Jr = _right_jacobian_so3(rho)
    QP = np.diag(k) @ P
    for j in range(3):
        # d(R B)/d rho_j = R (J_r e_j x B) = -R [B]x J_r e_j
        d_rB = np.cross(Jr[:, j][None, :], B_n) @ R.T
        J[:, :, 6 + j] = -(d_rB @ QP.T)
    for i in range(3):
        J[:, i, 9 + i] = -1.0
    return resid, J.reshape(3 * n, 12)


def _dP_de(e) -> list[np.ndarray]:
    s1, c1 = math.sin(e[0]), math.cos(e[0])
    s2, c2 = math.sin(e[1]), math.cos(e[1])
    s3, c3 = math.sin(e[2]), math.cos(e[2])
    d1 = np.zeros((3, 3)); d1[1] = [c1, -s1, 0.0]
    d2 = np.zeros((3, 3)); d2[2] = [c2, -s2 * s3, -s2 * c3]
    d3 = np.zeros((3, 3)); d3[2] = [0.0, c2 * c3, -c2 * s3]
    return [d1, d2, d3]


def fit_analytic_rotated(h_nT, B_nT, analytic: Optional[AnalyticFit] = None) -> RotatedFit:
    """Fit h = Q P R B + b: seed 001 plus a small rotation R (3 parameters).

    Starts from the analytic solution with R = I and runs scipy's least_squares (trust
    region, analytic Jacobian) on the reading-space residual.  1-sigma uncertainties: the
    Gauss-Newton covariance with a separate residual variance per axis (sandwich form),
    the rotation as a small rotation delta about the estimate (R_true = R exp([delta]x)).
    """
    h, B = _validated(h_nT, B_nT)
    if analytic is None:
        analytic = fit_analytic(h, B)
    h_n, B_n, h_mean, scale = _normalised(h, B)
    x0 = np.concatenate([analytic.k, analytic.e_rad, np.zeros(3), (analytic.b_nT - h_mean) / scale])
    sol = least_squares(lambda x: _rotated_residual_and_jacobian(x, h_n, B_n)[0], x0,
                        jac=lambda x: _rotated_residual_and_jacobian(x, h_n, B_n)[1],
                        method="trf", x_scale="jac", ftol=1e-15, xtol=1e-15, gtol=1e-15,
                        max_nfev=200)
    x = sol.x
    k, e, rho = x[0:3], x[3:6], x[6:9]
    b = h_mean + scale * x[9:12]
    R = rotation_from_rotvec(rho)
    Q, P = np.diag(k), P_from_angles(e)
    W = Q @ P @ R
    resid = h - (B @ W.T + b)
    n = len(h)

    # covariance in (k, e, delta, b) with delta a rotation about the estimate, in nT units
    J = np.zeros((n, 3, 12))
    g = B @ R.T
    Pg = g @ P.T
    for i in range(3):
        J[:, i, i] = Pg[:, i]
    for j, dP in enumerate(_dP_de(e)):
        J[:, :, 3 + j] = (g @ dP.T) * k
    QPR = Q @ P @ R
    for j in range(3):
        J[:, :, 6 + j] = np.cross(np.eye(3)[j][None, :], B) @ QPR.T
    for i in range(3):
        J[:, i, 9 + i] = 1.0
    var_axis = np.sum(resid**2, axis=0) / (n - 4)      # 4 unknowns per axis (row of W, b_i)
    weights = np.tile(var_axis, n)
    Jf = J.reshape(3 * n, 12)
    bread = np.linalg.inv(Jf.T @ Jf)
    cov = bread @ (Jf.T @ (Jf * weights[:, None])) @ bread
    sigma = np.sqrt(np.diag(cov))
    return RotatedFit(
        k=k, e_rad=e, R=R, rotvec_rad=rho, b_nT=b, Q=Q, P=P, W=W, cov=cov,
        sigma_k=sigma[0:3], sigma_e_rad=sigma[3:6], sigma_rot_rad=sigma[6:9],
        sigma_b_nT=sigma[9:12], residual_rms_nT=float(np.sqrt(np.mean(resid**2))),
        residual_rms_axis_nT=np.sqrt(np.mean(resid**2, axis=0)), analytic=analytic,
        n_samples=n, optimizer_message=str(sol.message))
