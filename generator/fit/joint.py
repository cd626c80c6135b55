"""Joint fit of the polynomial temperature model to all samples at once (ramps included):
the reference-vector fit where every sample has a vector, else Levenberg-Marquardt in the
flight parametrisation over vector and magnitude rows. Also the calibration helpers the
other strategies share (padding, scoring).
"""

from __future__ import annotations

import numpy as np

from generator.errors import InputError
from generator.fit.calibration import POLY_DEGREE, SensorCalibration
from generator.fit.ellipsoid import SYM_INDEX, _sym_grad, covariance, lm_solve, sym_from6, sym_to6
from generator.fit.ellipsoid_prior import ellipsoid_fit_prior
from generator.fit.reference import (MAX_REF_COND, T_REF_C, _powers, reference_fit,
                                     temperature_bin_information, temperature_derivative,
                                     vector_gradient_rows)
from generator.fit.samples import _Samples

DEGREE_STEP_C = 5.0        # one polynomial degree per 5 degC of temperature span


def _pad(b_poly, M_poly, degree=POLY_DEGREE):
    b = np.zeros((degree + 1, 3))
    M = np.zeros((degree + 1, 3, 3))
    b[: len(b_poly)] = b_poly
    M[: len(M_poly)] = M_poly
    return b, M


def _make_cal(name, b_poly, M_poly, t_lo, t_hi, body_frame, method, b_sig=None, M_sig=None):
    b, M = _pad(b_poly, M_poly)
    bs = Ms = None
    if b_sig is not None:
        bs, Ms = _pad(b_sig, M_sig)
    return SensorCalibration(name, b, M, T_REF_C, float(t_lo), float(t_hi),
                             body_frame=body_frame, method=method, b_poly_sigma_nT=bs,
                             M_poly_sigma=Ms)


def _degree_for_span(span_C, max_degree=POLY_DEGREE):
    return int(min(max_degree, np.floor(span_C / DEGREE_STEP_C)))


def _joint_nonlinear(S: _Samples, degree, t_lo, t_hi, body_frame, init, source,
                     uncertainty=True):
    """Levenberg-Marquardt on the flight parameterisation over vector and magnitude rows.
    uncertainty=False: without the temperature reporting step's covariance (_fit_joint)."""
    tau = max(abs(t_lo - T_REF_C), abs(t_hi - T_REF_C), 1.0)
    P = _powers((np.clip(S.T, t_lo, t_hi) - T_REF_C) / tau, degree)
    scale = tau ** np.arange(degree + 1)
    b0, M0 = init
    b0s = np.zeros((degree + 1, 3))
    M0s = np.zeros((degree + 1, 3, 3))
    k0 = min(len(b0), degree + 1)
    b0s[:k0] = b0[:k0] * scale[:k0, None]
    M0s[:k0] = M0[:k0] * scale[:k0, None, None]
    nb = 3 * (degree + 1)
    vec, mag = S.is_vec, ~S.is_vec
    Bv = S.ref[vec]
    Rm = S.norm[mag]

    if body_frame:
        def unpack(q):
            return q[:nb].reshape(degree + 1, 3), q[nb:].reshape(degree + 1, 3, 3)
        q0 = np.concatenate([b0s.ravel(), M0s.ravel()])
    else:
        def unpack(q):
            return q[:nb].reshape(degree + 1, 3), sym_from6(q[nb:].reshape(degree + 1, 6))
        q0 = np.concatenate([b0s.ravel(), sym_to6(M0s).ravel()])

    K = degree + 1
    Pv, Pm = P[vec], P[mag]
    xv, xm = S.x[vec], S.x[mag]
    nv, nm = len(Pv), len(Pm)

    PPv = (Pv[:, :, None] * Pv[:, None, :]).reshape(nv, K * K)

    def vector_normal(bp, Mp, jac):
        """Vector rows r = M(T)(x - b(T)) - B_ref: cost and, in closed form, J^T J, J^T r
        (params: b[k,l], then M[k,a,c]); no (3N x p) Jacobian is formed."""
        MT = (Pv @ Mp.reshape(K, 9)).reshape(nv, 3, 3)
        y = xv - Pv @ bp
        r = np.einsum("nij,nj->ni", MT, y) - Bv
        cost = float(np.sum(r * r))
        if not jac:
            return cost, None, None
        # M-M: delta_aa' sum_n P_k y_c P_m y_d
        Py = (Pv[:, :, None] * y[:, None, :]).reshape(nv, 3 * K)
        G = (Py.T @ Py).reshape(K, 3, K, 3)
        MM = np.einsum("kcmd,ab->kacmbd", G, np.eye(3)).reshape(9 * K, 9 * K)
        # b-b: sum_n P_k P_m (M^T M)[l,p]
        Q = np.einsum("nil,nip->nlp", MT, MT).reshape(nv, 9)
        bb = (PPv.T @ Q).reshape(K, K, 3, 3).transpose(0, 2, 1, 3).reshape(nb, nb)
        # M-b: -sum_n P_k P_m y_c M[a,l]
        YM = (y[:, :, None, None] * MT[:, None, :, :]).reshape(nv, 27)       # [c,a,l]
        Mb = -(PPv.T @ YM).reshape(K, K, 3, 3, 3).transpose(0, 3, 2, 1, 4).reshape(9 * K, nb)
        JTJ = np.block([[bb, Mb.T], [Mb, MM]])
        gM = (Py.T @ r).reshape(K, 3, 3).transpose(0, 2, 1).reshape(-1)       # [k,a,c]
        gb = -(Pv.T @ np.einsum("nil,ni->nl", MT, r)).reshape(-1)              # [k,l]
        return cost, JTJ, np.concatenate([gb, gM])

    def magnitude_rows(bp, Mp, jac):
        """Magnitude rows r = |M(T)(x - b(T))| - |B| and their Jacobian."""
        MT = (Pm @ Mp.reshape(K, 9)).reshape(nm, 3, 3)
        y = xm - Pm @ bp
        z = np.einsum("nij,nj->ni", MT, y)
        nz = np.linalg.norm(z, axis=1)
        r = nz - Rm
        if not jac:
            return r, None
        u = z / nz[:, None]
        v = np.einsum("ni,nij->nj", u, MT)                       # u^T M
        Jb = -(Pm[:, :, None] * v[:, None, :]).reshape(nm, nb)
        if body_frame:
            Jm = (Pm[:, :, None, None] * u[:, None, :, None]
                  * y[:, None, None, :]).reshape(nm, -1)
        else:
            Jm = (Pm[:, :, None] * _sym_grad(u, y)[:, None, :]).reshape(nm, -1)
        return r, np.hstack([Jb, Jm])

    n_par = len(q0)

    def model(q, jac):
        bp, Mp = unpack(q)
        cost, JTJ, g = 0.0, np.zeros((n_par, n_par)), np.zeros(n_par)
        if nv:
            c, A, gv = vector_normal(bp, Mp, jac)
            cost += c
            if jac:
                JTJ += A
                g += gv
        if nm:
            r, J = magnitude_rows(bp, Mp, jac)
            cost += float(r @ r)
            if jac:
                JTJ += J.T @ J
                g += J.T @ r
        return cost, (JTJ if jac else None), (g if jac else None), 3 * nv + nm

    q, cost, JTJ, lm = lm_solve(model, q0, max_iter=60)
    cov, cond, s2 = covariance(JTJ, cost, 3 * nv + nm)
    if degree > 0 and uncertainty and np.all(np.isfinite(cov)):
        cov = cov + _temperature_cov(S, P, unpack(q), tau, (t_lo, t_hi), JTJ, body_frame,
                                     magnitude_rows)
    if not cond < MAX_REF_COND:
        raise InputError(source, f"joint temperature fit: the data do not determine the "
                                 f"degree-{degree} model (condition {cond:.3g}); temperature "
                                 f"spans {t_hi - t_lo:.1f} degC")
    sig = np.sqrt(np.maximum(np.diag(cov), 0))
    bp, Mp = unpack(q)
    bsig = sig[:nb].reshape(degree + 1, 3)
    if body_frame:
        Msig = sig[nb:].reshape(degree + 1, 3, 3)
    else:
        m6 = sig[nb:].reshape(degree + 1, 6)
        Msig = np.zeros((degree + 1, 3, 3))
        for k, (i, j) in enumerate(SYM_INDEX):
            Msig[:, i, j] = Msig[:, j, i] = m6[:, k]
    return (bp / scale[:, None], Mp / scale[:, None, None], bsig / scale[:, None],
            Msig / scale[:, None, None], lm)


def _temperature_cov(S, P, bM, tau, t_range, JTJ, body_frame, magnitude_rows):
    """The temperature reporting step's covariance of the joint fit's parameters (scaled),
    as reference._temperature_error_cov: rows perturbed by D_n e_v, vector rows by D_n,
    magnitude rows by u_n^T D_n; the response (J^T J)^-1 J^T."""
    vec, mag = S.is_vec, ~S.is_vec
    bp, Mp = bM
    D = temperature_derivative(P, S.x, (bp, Mp), S.T, tau, t_range)
    rows = np.zeros((S.n, JTJ.shape[0]))
    if vec.any():
        rows[vec] = vector_gradient_rows(P[vec], S.x[vec], (bp, Mp), None, D[vec])
    if mag.any():
        _, J = magnitude_rows(bp, Mp, True)
        K = P.shape[1]
        MT = (P[mag] @ Mp.reshape(K, 9)).reshape(-1, 3, 3)
        z = np.einsum("nij,nj->ni", MT, S.x[mag] - P[mag] @ bp)
        u = z / np.linalg.norm(z, axis=1)[:, None]
        rows[mag] = J * np.sum(u * D[mag], axis=1)[:, None]
    grp = S.file_id if S.file_id is not None else np.zeros(S.n, int)
    Q, _ = temperature_bin_information(rows, S.T, grp)
    Ji = np.linalg.pinv(JTJ)
    C = Ji @ Q @ Ji
    return 0.5 * (C + C.T)


def _fit_joint(name, S: _Samples, body_frame, degree, t_lo, t_hi, source, uncertainty=True):
    """Polynomial model fitted to all samples at once. Returns SensorCalibration.
    uncertainty=False (the held-out comparison, which uses only the coefficients): the
    same coefficients without the temperature reporting step's share of the 1-sigma
    (reference_fit's uncertainty)."""
    if body_frame and S.is_vec.all():
        b, M, info = reference_fit(S.x, S.ref, S.T, degree, t_range_C=(t_lo, t_hi),
                                   source=source, uncertainty=uncertainty,
                                   **reference_options(S))
        cal = _make_cal(name, b, M, t_lo, t_hi, True, f"reference-vector joint, degree "
                        f"{degree}", info["b_poly_sigma_nT"], info["M_poly_sigma"])
        cal.observability = observability_of(info)
        return cal
    # initial values
    if body_frame:
        v = S.is_vec
        span = float(np.ptp(S.T[v]))
        dv = min(degree, _degree_for_span(span))
        b0, M0, _ = reference_fit(S.x[v], S.ref[v], S.T[v], dv, source=source,
                                  **reference_options(S, v))
    else:
        b0c, M0c, info = ellipsoid_fit_prior(S.x, S.norm, S.prior, float(np.mean(S.T)),
                                             source=source)
        b0, M0 = b0c[None, :], M0c[None]
        if degree == 0:
            cal = _make_cal(name, b0, M0, t_lo, t_hi, False, "ellipsoid, constant",
                            info["b_sigma_nT"][None], info["M_sigma"][None])
            cal.observability = info["observability"]
            return cal
    b, M, bs, Ms, lm = _joint_nonlinear(S, degree, t_lo, t_hi, body_frame, (b0, M0), source,
                                        uncertainty)
    kind = "reference-vector + magnitude" if body_frame else "ellipsoid"
    return _make_cal(name, b, M, t_lo, t_hi, body_frame, f"{kind} joint, degree {degree}",
                     bs, Ms)


def reference_options(S: _Samples, mask=None, with_prior=True) -> dict:
    """reference_fit's prior, file groups (EIV weights) and stated noise for samples S.
    with_prior=False: the part's nominal prior (a constant fit at one temperature level
    must not be drawn to a ground calibration's value at t_ref)."""
    fid = S.file_id if S.file_id is None or mask is None else S.file_id[mask]
    return {"prior": S.prior if with_prior else None, "group": fid, "noise_nT": S.noise_nT}


def observability_of(info) -> dict:
    """The JSON-able part of reference_fit's info for SensorCalibration.observability."""
    return {k: info[k] for k in ("parameters", "unobservable", "prior_source", "noise",
                                 "estimator")} | {"cond": info["cond"]}


def _residuals(cal: SensorCalibration, S: _Samples):
    """(vector residuals (n_vec, 3), magnitude residuals (n,)) of a calibration on S
    (b(T), M(T) once per reported value where S has its temperature index: the same
    numbers)."""
    z = (cal.per_value(S.T, S.t_index[:2]).apply64(S.x) if S.t_index is not None
         else cal.apply64(S.x, S.T))
    nz = np.linalg.norm(z, axis=1)
    return z[S.is_vec] - S.ref[S.is_vec], nz - S.norm


def _rms(a):
    a = np.asarray(a, float)
    return float(np.sqrt(np.mean(a ** 2))) if a.size else None


def _score(S: _Samples, cal):
    rv, rn = _residuals(cal, S)
    return {"rms_vector_nT": _rms(rv), "rms_norm_nT": _rms(rn), "n": int(S.n)}


