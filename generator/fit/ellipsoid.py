"""Attitude-independent calibration at one temperature: ellipsoid fit (seed 000, eq. 5-6).

Readings B~ of a field of known magnitude |B| lie on the ellipsoid |M (B~ - b)| = |B|.

1. Algebraic fit. Each reading gives X_i = [x^2, y^2, z^2, 2yz, 2xz, 2xy, 2x, 2y, 2z, 1];
   nu = [a, b, c, f, g, h, p, q, r, d] minimises |D^T nu|^2 under the ellipsoid-specific
   normalisation of Li & Griffiths (2004), 4J - I^2 = 1 (I = a+b+c, J = ab+bc+ca-f^2-g^2-h^2),
   a generalised eigenproblem. With A = [[a,h,g],[h,b,f],[g,f,c]], n = [p,q,r]:
       b = -A^-1 n,   M = |B| / sqrt(n^T A^-1 n - d) * A^(1/2)      (symmetric square root)
   When the reference magnitude differs between samples (field model along an orbit) the
   algebraic stage instead solves X_i nu = |B_i|^2 in the least-squares sense.
2. Geometric refinement: minimise sum_i (|M (B~_i - b)| - |B_i|)^2 over b and symmetric M
   (Levenberg-Marquardt, analytic Jacobian), started from the algebraic fit. The algebraic
   fit is biased by noise; the geometric one is the maximum-likelihood estimate for
   isotropic noise, and gives the parameter covariance used to check that the geometry
   determines the ellipsoid at all.

Everything that cannot give a trustworthy ellipsoid raises InputError saying what is
missing; nothing returns a silently wrong number.
"""

from __future__ import annotations

import numpy as np

from generator.errors import InputError

# Order of the six independent entries of a symmetric 3x3 matrix (seed order a,b,c,f,g,h).
SYM_INDEX = ((0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1))
_SYM_BASIS = np.zeros((6, 3, 3))
for _k, (_i, _j) in enumerate(SYM_INDEX):
    _SYM_BASIS[_k, _i, _j] = 1.0
    _SYM_BASIS[_k, _j, _i] = 1.0

MIN_SAMPLES = 9
# Geometric checks: limits on the 1-sigma uncertainty the data leave on the parameters.
MAX_OFFSET_SIGMA_REL = 0.02     # offset sigma / |B|
MAX_MATRIX_SIGMA = 0.02         # sigma of an entry of M (M ~ identity)
MAX_COND = 1e8                  # condition number of the scaled geometric Jacobian
# The noise-normalised residual (maximum likelihood for reading noise) is used while at
# least half of the residual's variance is sample-to-sample (white): then the reading
# noise, whose size through the fit is |M^T u| sigma, is what the residual mostly is.
# Below, the residual is mostly model error (a smooth function of the orientation), whose
# size does not scale with |M^T u|: plain |B| residuals are tried and taken when they
# determine the ellipsoid and fit |B| better (_white_fraction, ellipsoid_fit).
MIN_WHITE_FRACTION = 0.5
_AXES = "xyz"


def sym_from6(m6) -> np.ndarray:
    """Symmetric 3x3 from its six entries in SYM_INDEX order (..., 6) -> (..., 3, 3)."""
    return np.einsum("...k,kij->...ij", np.asarray(m6, float), _SYM_BASIS)


def sym_to6(M) -> np.ndarray:
    M = np.asarray(M, float)
    return np.stack([M[..., i, j] for i, j in SYM_INDEX], axis=-1)


def sqrtm_spd(A) -> np.ndarray:
    """Symmetric square root of a symmetric positive definite matrix."""
    w, V = np.linalg.eigh(A)
    return (V * np.sqrt(w)) @ V.T


def polar_spd(M) -> np.ndarray:
    """Symmetric positive factor P of M = R P (R orthogonal): sqrtm(M^T M)."""
    M = np.asarray(M, float)
    return sqrtm_spd(M.T @ M)


# ---------------------------------------------------------------------------------------
# Levenberg-Marquardt on the normal equations (few parameters, many residuals)
# ---------------------------------------------------------------------------------------
def lm_solve(model, x0, *, max_iter=100, rtol=1e-12, xtol=1e-12):
    """Minimise a sum of squares given through its normal equations.

    model(x, jac) -> (cost, JTJ, JTr, m): cost = |r|^2, and when jac is True the Gauss-
    Newton matrix J^T J and gradient J^T r (else None), m the number of residuals.
    Moré-style scaling by the diagonal of J^T J; stops when the relative decrease of the
    cost or the relative step falls below tolerance, or when even the undamped Gauss-Newton
    step promises a relative decrease below rtol (g^T (J^T J)^-1 g < rtol cost: the
    minimum of the local quadratic model is within tolerance, so the trial steps that
    would only find that out by raising the damping tenfold at a time are skipped).
    Returns (x, cost, JTJ, info).
    """
    x = np.asarray(x0, float).copy()
    cost, JTJ, g, m = model(x, True)
    lam = 1e-3
    it = 0
    converged = False
    for it in range(1, max_iter + 1):
        d = np.sqrt(np.maximum(np.diag(JTJ), 1e-300))
        Js = JTJ / np.outer(d, d)
        gs = g / d
        try:
            gn_drop = float(gs @ np.linalg.solve(Js, gs))
        except np.linalg.LinAlgError:
            gn_drop = np.inf
        if 0.0 <= gn_drop < rtol * cost:
            converged = True  # the Gauss-Newton minimum is within tolerance of the cost
            break
        improved = False
        for _ in range(30):
            try:
                step = -np.linalg.solve(Js + lam * np.eye(len(x)), gs) / d
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            x_new = x + step
            cost_new = model(x_new, False)[0]
            if np.isfinite(cost_new) and cost_new <= cost:
                improved = True
                break
            lam *= 10.0
        if not improved:
            converged = True  # no descent possible: at a minimum to working precision
            break
        rel_drop = (cost - cost_new) / max(cost, 1e-300)
        rel_step = np.linalg.norm(step * d) / max(np.linalg.norm(x * d), 1e-300)
        x = x_new
        cost, JTJ, g, m = model(x, True)
        lam = max(lam / 10.0, 1e-12)
        if rel_drop < rtol or rel_step < xtol:
            converged = True
            break
    return x, cost, JTJ, {"iterations": it, "cost": float(cost), "converged": converged,
                          "residuals": int(m)}


def covariance(JTJ, cost, m):
    """Parameter covariance s^2 (J^T J)^-1 with s^2 = cost/(m - p), and the condition
    number of the column-scaled Jacobian. Returns (cov, cond, s2)."""
    p = JTJ.shape[0]
    d = np.sqrt(np.maximum(np.diag(JTJ), 1e-300))
    Js = JTJ / np.outer(d, d)
    w = np.linalg.eigvalsh(Js)
    cond = float(np.sqrt(w[-1] / w[0])) if w[0] > 0 else np.inf
    s2 = float(cost) / max(m - p, 1)
    try:
        cov = np.linalg.inv(Js) / np.outer(d, d) * s2
    except np.linalg.LinAlgError:
        cov = np.full((p, p), np.inf)
    return cov, cond, s2


# ---------------------------------------------------------------------------------------
# Input checks
# ---------------------------------------------------------------------------------------
def _check_inputs(field_nT, ref_norm_nT, source):
    x = np.asarray(field_nT, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3:
        raise InputError(source, f"ellipsoid fit: field must be (N, 3), got shape {x.shape}")
    n = x.shape[0]
    bad = ~np.isfinite(x).all(axis=1)
    if bad.any():
        raise InputError(source, f"ellipsoid fit: {int(bad.sum())} of {n} readings are not "
                                 "finite (drop unusable samples first)")
    R = np.broadcast_to(np.asarray(ref_norm_nT, dtype=float), (n,)).copy() if n else \
        np.zeros(0)
    if np.ndim(ref_norm_nT) not in (0, 1) or (np.ndim(ref_norm_nT) == 1 and
                                               np.shape(ref_norm_nT)[0] != n):
        raise InputError(source, "ellipsoid fit: reference magnitude must be a number or one "
                                 f"per sample ({n}), got shape {np.shape(ref_norm_nT)}")
    if not (np.isfinite(R).all() and (R > 0).all()):
        raise InputError(source, "ellipsoid fit: reference field magnitude must be finite "
                                 "and positive")
    if n < MIN_SAMPLES:
        raise InputError(source, f"ellipsoid fit: {n} usable readings, at least {MIN_SAMPLES}"
                                 " in different orientations are needed")
    return x, R


def _plane_hint(x) -> str:
    """Describe how the readings fail to fill 3-D: plane normal / line direction."""
    c = x - x.mean(axis=0)
    w, V = np.linalg.eigh(c.T @ c / len(x))
    spread = np.sqrt(np.maximum(w, 0))
    axis = V[:, 0]
    k = int(np.argmax(np.abs(axis)))
    return (f"the readings spread only {spread[0]:.0f} nT along direction "
            f"[{axis[0]:+.2f}, {axis[1]:+.2f}, {axis[2]:+.2f}] (mostly frame {_AXES[k]}) "
            f"against {spread[2]:.0f} nT across it: turn the unit about another axis")


def coverage(unit_vectors) -> dict:
    """How well calibrated directions cover the sphere (JSON-able).

    eig: eigenvalues of mean(u u^T) (1/3 each for a full sphere; ~0 along a direction
    never sampled off the plane); mean_resultant: |mean(u)| (0 full sphere, 0.5 hemisphere
    cap, 1 one direction).
    """
    u = np.asarray(unit_vectors, float)
    S = u.T @ u / max(len(u), 1)
    w, V = np.linalg.eigh(S)
    return {"eig": [float(v) for v in w], "least_direction": [float(v) for v in V[:, 0]],
            "mean_resultant": float(np.linalg.norm(u.mean(axis=0)))}


def distinct_rows(v, resolution, at_most=None) -> int:
    """Number of distinct rows of an (N, 3) array on a grid of `resolution`; counting
    stops at `at_most` when given (a cheap test for 'enough different values')."""
    q = np.round(np.asarray(v, float) / resolution)
    if at_most is not None:
        seen = [q[0]] if len(q) else []
        rest = q
        while len(seen) < at_most:
            rest = rest[np.any(rest != seen[-1], axis=1)]
            if not len(rest):
                break
            seen.append(rest[0])
        if len(seen) >= at_most:
            return len(seen)
    return int(np.unique(q, axis=0).shape[0])


def _distinct_readings(x, rel=1e-4) -> int:
    scale = np.sqrt(np.mean(np.sum((x - x.mean(axis=0)) ** 2, axis=1)))
    if not np.isfinite(scale) or scale == 0:
        return 1
    return distinct_rows(x - x.mean(axis=0), rel * scale, at_most=MIN_SAMPLES)


def _sym_gradT(a, c):
    """d(a^T M c)/dm for the six entries of symmetric M, component-major: a, c (3, N) ->
    (6, N), rows in SYM_INDEX order: a_i c_i on the diagonal, a_i c_j + a_j c_i off it."""
    P = np.empty((6, a.shape[1]))
    np.multiply(a, c, out=P[:3])
    P[3] = a[1] * c[2] + a[2] * c[1]
    P[4] = a[0] * c[2] + a[2] * c[0]
    P[5] = a[0] * c[1] + a[1] * c[0]
    return P


def _sym_grad(u, y):
    """d(u^T M y)/dm for the six entries of symmetric M: (N, 6)."""
    return _sym_gradT(np.asarray(u, float).T, np.asarray(y, float).T).T


# ---------------------------------------------------------------------------------------
# Algebraic fit
# ---------------------------------------------------------------------------------------
def _design(x) -> np.ndarray:
    X, Y, Z = x[:, 0], x[:, 1], x[:, 2]
    one = np.ones_like(X)
    return np.stack([X * X, Y * Y, Z * Z, 2 * Y * Z, 2 * X * Z, 2 * X * Y,
                     2 * X, 2 * Y, 2 * Z, one], axis=1)


def _quadric_to_bM(nu, R_scaled):
    """nu (10,) in scaled coordinates -> centre b, symmetric M mapping to radius R_scaled."""
    A = sym_from6(nu[:6])
    n = nu[6:9]
    d = nu[9]
    w = np.linalg.eigvalsh(A)
    if w[0] < 0 and w[-1] < 0:
        A, n, d = -A, -n, -d
        w = -w[::-1]
    if w[0] <= 0:
        return None
    Ainv_n = np.linalg.solve(A, n)
    b = -Ainv_n
    k = float(n @ Ainv_n - d)
    if not k > 0:
        return None
    M = R_scaled / np.sqrt(k) * sqrtm_spd(A)
    return b, M


def algebraic_ellipsoid(field_nT, ref_norm_nT, *, source=None):
    """Algebraic ellipsoid fit (Li & Griffiths 2004; linear variant for varying |B|).

    Returns (b_nT, M symmetric, details). Raises InputError when the readings do not fix
    a unique quadric or the best quadric is not an ellipsoid.
    """
    x, R = _check_inputs(field_nT, ref_norm_nT, source)
    n_distinct = _distinct_readings(x)
    if n_distinct < MIN_SAMPLES:
        raise InputError(source, f"ellipsoid fit: only {n_distinct} distinct readings among "
                                 f"{len(x)}; at least {MIN_SAMPLES} orientations are needed")
    # Centre and scale to O(1) coordinates for conditioning.
    mu = x.mean(axis=0)
    s = float(np.sqrt(np.mean(np.sum((x - mu) ** 2, axis=1))))
    xs = (x - mu) / s
    Rs = R / s
    D = _design(xs)
    col = np.sqrt(np.mean(D * D, axis=0))
    sv = np.linalg.svd(D / col, compute_uv=False)
    if sv[-2] < 1e-9 * sv[0]:
        raise InputError(source, "ellipsoid fit: the readings fit more than one quadric "
                                 f"(orientations cover too little of the sphere): {_plane_hint(x)}")
    varying = np.ptp(R) > 1e-9 * R.mean()
    method = "li-griffiths"
    result = None
    if not varying:
        S = D.T @ D
        S11, S12, S22 = S[:6, :6], S[:6, 6:], S[6:, 6:]
        try:
            S22inv_S21 = np.linalg.solve(S22, S12.T)
        except np.linalg.LinAlgError:
            S22inv_S21 = np.linalg.lstsq(S22, S12.T, rcond=None)[0]
        Mred = S11 - S12 @ S22inv_S21
        C1 = np.zeros((6, 6))
        C1[:3, :3] = [[-1, 1, 1], [1, -1, 1], [1, 1, -1]]   # k = 4: k/2 - 1 = 1
        C1[3:, 3:] = -4 * np.eye(3)
        # Generalised eigenproblem Mred v = lam C1 v, i.e. C1^-1 Mred v = lam v.
        w, V = np.linalg.eig(np.linalg.solve(C1, Mred))
        w, V = np.real(w), np.real(V)
        # The solution is the eigenvector with v^T C1 v > 0 of smallest algebraic cost
        # v^T Mred v / v^T C1 v (>= 0; exactly 0 for exact data, so allow rounding).
        cand = []
        scale = max(float(np.max(np.abs(w))), 1e-300)
        for i in range(len(w)):
            v1 = V[:, i]
            q = float(v1 @ C1 @ v1)
            if q > 0:
                cost = float(v1 @ Mred @ v1) / q
                if cost >= -1e-9 * scale:
                    cand.append((cost, np.concatenate([v1, -S22inv_S21 @ v1])))
        for _, nu in sorted(cand, key=lambda c: c[0]):
            result = _quadric_to_bM(nu, Rs[0])
            if result is not None:
                break
    if result is None:
        # Linear fit X_i nu = |B_i|^2 (exact scale, no normalisation constraint needed).
        method = "linear-rhs" if varying else "linear-rhs (fallback)"
        nu = np.linalg.lstsq(D, Rs ** 2, rcond=None)[0]
        A = sym_from6(nu[:6])
        w = np.linalg.eigvalsh(A)
        if w[0] <= 0:
            raise InputError(source, "ellipsoid fit: the best-fitting quadric is not an "
                                     f"ellipsoid (eigenvalues {w[0]:.3g} .. {w[-1]:.3g}); "
                                     f"{_plane_hint(x)}")
        b_s = -np.linalg.solve(A, nu[6:9])
        # |sqrtm(A)(x - b)|^2 = |B|^2 + k: rescale so the mean magnitude matches.
        Ms = sqrtm_spd(A)
        mag = np.linalg.norm((xs - b_s) @ Ms.T, axis=1)
        Ms = Ms * float(np.mean(Rs) / np.mean(mag))
        result = (b_s, Ms)
    b_s, M_s = result
    # |M_s (x' - b')| = |B|/s with x' = (x - mu)/s  <=>  |M_s (x - b)| = |B|, b = mu + s b'.
    b = mu + s * b_s
    M = 0.5 * (M_s + M_s.T)
    return b, M, {"method": method, "distinct_readings": n_distinct,
                  "design_sv_ratio": float(sv[-2] / sv[0])}


# ---------------------------------------------------------------------------------------
# Geometric refinement
# ---------------------------------------------------------------------------------------
_BLOCK = 1024       # samples per block of the Jacobian (_Refinement)


class _Refinement:
    """The refinement's residuals as the normal-equation model of lm_solve, vectorised.

    Samples are held component-major ((3, N) rows) so every step is a whole-array numpy
    operation; a cost-only call (lm_solve's trial steps) computes the residuals and nothing
    else, and the Jacobian call that follows an accepted step reuses that step's
    intermediate arrays instead of recomputing them. J^T J and J^T r are accumulated over
    blocks of _BLOCK samples: the Jacobian's temporaries then stay in cache and below the
    allocator's mmap threshold (with whole-array temporaries of (6, N) doubles, measured
    on the project machine, the Jacobian at N = 4,000 took 8.5x its time at N = 1,000).

    kind "geometric": r_i = (|M (x_i - b)| - R_i) w_i.
    kind "normalised": s_i = (|M (x_i - b)| - R_i) / |M^T u_i| w_i (the noise-normalised
    residual: a reading noise of sigma per axis moves |M (x - b)| by sigma |M^T u|, u the
    unit calibrated vector, so every s_i has the same variance: least squares on s is the
    first-order maximum likelihood; the plain geometric cost can fall by shrinking M along
    the directions the data's normals point, which cancels on a full sphere but biases the
    offset along the axis of a cap of orientations: bench/peers, docs/peer_comparison.md).

    Analytic Jacobian (M symmetric). y = x - b, z = M y, rho = |z|, u = z / rho,
    v = M u, g = |v|, q = M v (u.q = g^2), r = rho - R.
      d rho: -v for b; sym(u, y) for m          (sym(a, c) = d(a^T M c)/dm, _sym_gradT)
      d g = v.dv / g with dv = dM u + M du, du = (I - u u^T) dz / rho, hence
      d g: (g^2 v - M q) / (rho g) for b; (sym(v, u) + (sym(q, y) - g^2 sym(u, y)) / rho) / g for m
      d s = (d rho - s d g) / g.
    """

    def __init__(self, x, R, w, kind):
        if kind not in ("normalised", "geometric"):
            raise ValueError(f"residual must be one of {sorted(RESIDUALS)}")
        self.xT = np.ascontiguousarray(np.asarray(x, float).T)
        n = self.xT.shape[1]
        self.R = np.broadcast_to(np.asarray(R, float), (n,))
        self.w = np.broadcast_to(np.asarray(w, float), (n,))
        self.kind = kind
        self._last = None

    def _eval(self, p):
        """Residuals at p and the intermediates the Jacobian needs (cached for p)."""
        if self._last is not None and np.array_equal(self._last[0], p):
            return self._last[1]
        M = sym_from6(p[3:])
        y = self.xT - p[:3, None]
        z = M @ y
        rho = np.sqrt(np.einsum("in,in->n", z, z))
        r = rho - self.R
        st = {"M": M, "y": y, "rho": rho, "r": r}
        if self.kind == "normalised":
            u = z / rho
            v = M @ u
            g = np.sqrt(np.einsum("in,in->n", v, v))
            st.update(u=u, v=v, g=g, res=(r / g) * self.w)
        else:
            st["res"] = r * self.w
        self._last = (np.array(p, float), st)
        return st

    def residuals(self, p):
        return self._eval(np.asarray(p, float))["res"]

    def jacobian_T(self, p, sl=slice(None)):
        """(9, n) transposed Jacobian of the weighted residuals of the samples sl."""
        st = self._eval(np.asarray(p, float))
        M, y, rho = st["M"], st["y"][:, sl], st["rho"][sl]
        w = self.w[sl]
        JT = np.empty((9, y.shape[1]))
        if self.kind == "geometric":
            uw = (M @ y) * (w / rho)
            JT[:3] = -(M @ uw)
            JT[3:] = _sym_gradT(uw, y)
        else:
            # J = (d rho - s d g) / g regrouped by linearity of sym: with t = s / (rho g),
            # J_b = -(v + t (g^2 v - M q)) / g, J_m = sym(a, y) - sym(s v / g^2, u),
            # a = (u - t (q - g^2 u)) / g (weights folded into a, v before sym)
            u, v, g = st["u"][:, sl], st["v"][:, sl], st["g"][sl]
            s = st["r"][sl] / g
            q = M @ v
            g2 = g * g
            t = s / (rho * g)
            wg = w / g
            JT[:3] = -(v + t * (g2 * v - M @ q)) * wg
            JT[3:] = _sym_gradT((u - t * (q - g2 * u)) * wg, y)
            JT[3:] -= _sym_gradT(v * (s * wg / g), u)
        return JT

    def __call__(self, p, jac):
        """lm_solve's model: (cost, J^T J, J^T r, m); the cost alone unless jac."""
        p = np.asarray(p, float)
        res = self.residuals(p)
        cost = float(res @ res)
        if not jac:
            return cost, None, None, len(res)
        JTJ, JTr = np.zeros((9, 9)), np.zeros(9)
        for k in range(0, len(res), _BLOCK):
            sl = slice(k, k + _BLOCK)
            JT = self.jacobian_T(p, sl)
            JTJ += JT @ JT.T
            JTr += JT @ res[sl]
        return cost, JTJ, JTr, len(res)


def _geo_resid_jac(params, x, R, w):
    """Plain geometric residuals (|M (x_i - b)| - R_i) w_i and their Jacobian (N, 9)."""
    ref = _Refinement(x, R, w, "geometric")
    return ref.residuals(params), ref.jacobian_T(params).T


def _normalised_resid_jac(params, x, R, w):
    """Noise-normalised residuals s_i = (|M (x_i - b)| - R_i) / |M^T u_i| times the weights
    w and their Jacobian (N, 9) (_Refinement)."""
    ref = _Refinement(x, R, w, "normalised")
    return ref.residuals(params), ref.jacobian_T(params).T


RESIDUALS = {"normalised": _normalised_resid_jac, "geometric": _geo_resid_jac}


def _undetermined_message(cond, R_mean, b_sig, M_sig, x):
    what = []
    bad_b = b_sig > MAX_OFFSET_SIGMA_REL * R_mean
    if np.any(bad_b):
        what.append("the offset along " + "/".join(_AXES[i] for i in np.nonzero(bad_b)[0])
                    + f" (1-sigma up to {b_sig.max():.0f} nT)")
    if np.any(M_sig > MAX_MATRIX_SIGMA):
        what.append(f"the matrix (1-sigma up to {M_sig.max():.3g})")
    if not what:
        what.append(f"the parameters (condition number {cond:.3g})")
    return ("ellipsoid fit: orientations cover too little of the sphere to determine "
            + " and ".join(what) + ": " + _plane_hint(x))


def _white_fraction(r) -> float:
    """Fraction of the residual's variance that changes from sample to sample (samples in
    time order): var(diff r) / (2 var r), 1 for white noise, -> 0 for a residual that
    varies slowly (with the orientation: a field that is not an ellipsoid, a model that
    does not hold). Clipped to [0, 1]."""
    r = np.asarray(r, float) - np.mean(r)
    v = float(np.mean(r * r))
    if len(r) < 3 or v <= 0:
        return 1.0
    return float(min(max(np.mean(np.diff(r) ** 2) / (2.0 * v), 0.0), 1.0))


def ellipsoid_fit(field_nT, ref_norm_nT, *, refine=True, weights=None, source=None,
                  residual="normalised"):
    """Fit b (offset, nT) and symmetric M with |M (B~ - b)| = |B| (seed 000 eq. 5-6).

    field_nT: (N, 3) uncalibrated readings in frame axes (usable samples only).
    ref_norm_nT: scalar or (N,) reference field magnitude.
    refine: follow the algebraic fit by the least-squares refinement, on the
    noise-normalised residuals ("normalised", the maximum-likelihood one, efficient on
    partial coverage too) or the plain geometric ones ("geometric", for comparison).
    weights: optional (N,) residual weights (1/sigma).
    Returns (b_nT (3,), M (3, 3) symmetric, info) where info holds both stages:
    info["algebraic"] / info["geometric"] = {"b_nT", "M", "rms_nT"}, the 1-sigma
    b_sigma_nT / M_sigma (geometric stage), the covariance, coverage and iterations.
    """
    x, R = _check_inputs(field_nT, ref_norm_nT, source)
    w = np.ones(len(x)) if weights is None else np.broadcast_to(
        np.asarray(weights, float), (len(x),)).copy()
    b_a, M_a, det = algebraic_ellipsoid(x, R, source=source)

    def rms(b, M):
        return float(np.sqrt(np.mean((np.linalg.norm((x - b) @ M.T, axis=1) - R) ** 2)))

    info = {"n": int(len(x)), "algebraic": {"b_nT": b_a, "M": M_a, "rms_nT": rms(b_a, M_a),
                                            **det}}
    p0 = np.concatenate([b_a, sym_to6(M_a)])
    if residual not in RESIDUALS:
        raise ValueError(f"residual must be one of {sorted(RESIDUALS)}")
    model = _Refinement(x, R, w, residual)
    if refine:
        p, cost, JTJ, lm = lm_solve(model, p0)
        info["lm"] = lm
        if residual == "normalised":
            white = _white_fraction(np.linalg.norm((x - p[:3]) @ sym_from6(p[3:]).T, axis=1)
                                    - R)
            info["residual_white_fraction"] = white
            if white < MIN_WHITE_FRACTION:
                # the misfit is not reading noise: the 1/|M^T u| weighting has no basis
                # (it rewards an M stretched where the misfit is). Plain |B| residuals
                # instead, where they determine the ellipsoid (on part of the sphere they
                # can run off to a large far sphere) and fit |B| better
                gmodel = _Refinement(x, R, w, "geometric")
                pg, cost_g, JTJ_g, lm_g = lm_solve(gmodel, p0)
                Mg = sym_from6(pg[3:])
                ok = (np.linalg.eigvalsh(Mg)[0] > 0
                      and _undetermined(JTJ_g, cost_g, len(x), float(R.mean())) is None
                      and rms(pg[:3], Mg) < rms(p[:3], sym_from6(p[3:])))
                info["residual_switch"] = (
                    f"normalised residuals {white:.0%} white (sample-to-sample): the misfit is "
                    "model error, not reading noise; plain |B| residuals "
                    + ("taken (determined, smaller |B| misfit)" if ok else
                       "tried, not taken (not determined, or no smaller |B| misfit)"))
                if ok:
                    residual, model, p, cost, JTJ = "geometric", gmodel, pg, cost_g, JTJ_g
                    info["lm"] = lm_g
    else:
        p = p0
        cost, JTJ, _, _ = model(p, True)
    b, M = p[:3], sym_from6(p[3:])
    wev = np.linalg.eigvalsh(M)
    if wev[0] <= 0:
        raise InputError(source, "ellipsoid fit: refinement left a matrix that is not "
                                 f"positive definite (eigenvalues {wev[0]:.3g}..{wev[-1]:.3g})"
                                 f"; {_plane_hint(x)}")
    cov, cond, s2 = covariance(JTJ, cost, len(x))
    sig = np.sqrt(np.maximum(np.diag(cov), 0))
    b_sig, m_sig = sig[:3], sig[3:]
    M_sig = np.zeros((3, 3))  # entry-wise 1-sigma (an off-diagonal pair is one parameter)
    for k, (i, j) in enumerate(SYM_INDEX):
        M_sig[i, j] = M_sig[j, i] = m_sig[k]
    z = (x - b) @ M.T
    u = z / np.linalg.norm(z, axis=1)[:, None]
    info["geometric" if refine else "final"] = {"b_nT": b, "M": M, "rms_nT": rms(b, M),
                                                "residual": residual}
    info.update({"b_sigma_nT": b_sig, "M_sigma": M_sig, "cov": cov, "cond": cond,
                 "residual_sigma_nT": float(np.sqrt(s2)), "coverage": coverage(u)})
    bad = _undetermined(JTJ, cost, len(x), float(R.mean()))
    if bad is not None:
        raise InputError(source, _undetermined_message(*bad, x))
    return b, M, info


def _undetermined(JTJ, cost, m, R_mean):
    """None when the fit determines the ellipsoid (the limits above), else the figures
    for _undetermined_message: (cond, R_mean, b_sigma, m_sigma)."""
    cov, cond, _ = covariance(JTJ, cost, m)
    sig = np.sqrt(np.maximum(np.diag(cov), 0))
    b_sig, m_sig = sig[:3], sig[3:]
    if (cond > MAX_COND or not np.all(np.isfinite(sig))
            or np.any(b_sig > MAX_OFFSET_SIGMA_REL * R_mean) or np.any(m_sig > MAX_MATRIX_SIGMA)):
        return cond, R_mean, b_sig, m_sig
    return None
