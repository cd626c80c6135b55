"""The ellipsoid (magnitude-only) fit with a prior: what the magnitudes do not determine is
held at the prior (a ground calibration given with --prior), as in the reference-vector
fit (generator.fit.reference, module docstring item 4). The ellipsoid refinement itself
(generator.fit.ellipsoid) is used as it is; this layer calls it and its residual.

Parameters p = (b (3), m6 (6): the symmetric M in ellipsoid.SYM_INDEX order). The prior
of a polynomial calibration is taken at the data's temperature (b(T), M(T), 1-sigma
sqrt(sum_k sigma_k^2 dT^2k)); its M, known from magnitudes only up to a rotation, as its
symmetric polar factor (sigma of an off-diagonal pair: the RMS of the two entries').

1. The plain ellipsoid fit (ellipsoid.ellipsoid_fit). Without a prior its result, or its
   InputError when the data do not determine the ellipsoid, is final (unchanged
   behaviour); the per-coefficient tags are added.
2. With a prior: the maximum a posteriori estimate of the geometric residual
   |M (x - b)| - |B| with reading variance s^2 (the sensor's stated noise, else the
   residual's) and the prior as extra rows, always well-posed, locates the fit.
3. There the whitened information F~ = S J^T J S / s^2 (S = diag of the prior sigma) is
   split by its eigenvalues at reference.FISHER_THRESHOLD: directions the data determine
   better than the prior are fitted (geometric least squares restricted to them, started
   from 2.), the others held exactly at the prior. Where every direction is fitted and
   the plain fit succeeded, its result stands. Covariance S (V_f L_f^-1 V_f^T + V_p V_p^T)
   S; a parameter is "data" when >= reference.DATA_FRACTION of its whitened unit vector
   lies in the fitted subspace, else "prior".
"""

from __future__ import annotations

import numpy as np

from generator.errors import InputError
from generator.fit.ellipsoid import (SYM_INDEX, _geo_resid_jac, ellipsoid_fit, lm_solve,
                                     polar_spd, sym_from6, sym_to6)
from generator.fit.reference import DATA_FRACTION, FISHER_THRESHOLD, T_REF_C, nominal_prior

NAMES = ["b0_x", "b0_y", "b0_z"] + [f"M0_{'xyz'[i]}{'xyz'[j]}" for i, j in SYM_INDEX]


def prior_at(prior, temp_C, t_ref_C=T_REF_C):
    """(p0 (9,), sigma (9,)) of a reference.Prior at one temperature (module docstring)."""
    d = float(temp_C) - t_ref_C
    K = len(prior.b_poly_nT)
    pw = d ** np.arange(K)
    b = pw @ np.asarray(prior.b_poly_nT, float)
    M = np.einsum("k,kij->ij", pw, np.asarray(prior.M_poly, float))
    bs = np.sqrt((pw ** 2) @ np.asarray(prior.b_sigma_nT, float) ** 2)
    Ms = np.sqrt(np.einsum("k,kij->ij", pw ** 2, np.asarray(prior.M_sigma, float) ** 2))
    ms6 = np.array([np.sqrt(0.5 * (Ms[i, j] ** 2 + Ms[j, i] ** 2)) for i, j in SYM_INDEX])
    return np.concatenate([b, sym_to6(polar_spd(M))]), np.concatenate([bs, ms6])


def _sym_sigma(s6):
    out = np.zeros((3, 3))
    for k, (i, j) in enumerate(SYM_INDEX):
        out[i, j] = out[j, i] = s6[k]
    return out


def _tags(p, p0, S, sig, frac, held, EV, ev, source_name, names=NAMES,
          estimator="ellipsoid (magnitudes only, M symmetric); directions the magnitudes "
                    "do not determine held at the prior"):
    """Per-parameter data/prior tags and the directions held at the prior."""
    params = [{"name": nm, "value": float(p[i]), "sigma": float(sig[i]), "prior": float(p0[i]),
               "prior_sigma": float(S[i]), "data_fraction": float(frac[i]),
               "source": "data" if frac[i] >= DATA_FRACTION else "prior"}
              for i, nm in enumerate(names)]
    z = (p - p0) / S
    unobs = []
    for j in np.nonzero(held)[0]:
        v = EV[:, j]
        top = np.argsort(-np.abs(v))[:4]
        unobs.append({"information_vs_prior": float(ev[j]),
                      "direction": {names[i]: round(float(v[i]), 3) for i in top
                                    if abs(v[i]) > 0.2},
                      "vector": [float(a) for a in v], "offset_from_prior": float(v @ z)})
    return {"parameters": params, "unobservable": unobs, "prior_source": source_name,
            "estimator": estimator}


def ellipsoid_fit_prior(field_nT, ref_norm_nT, prior=None, temp_C=T_REF_C, *, source=None,
                        noise_nT=None):
    """ellipsoid_fit with a prior (module docstring). prior: reference.Prior or None (the
    part's nominal, and the plain fit's behaviour). Returns (b (3,), M (3, 3) symmetric,
    info) as ellipsoid_fit, info["observability"] with per-coefficient data/prior tags."""
    x = np.asarray(field_nT, float)
    R = np.broadcast_to(np.asarray(ref_norm_nT, float), (len(x),)).astype(float)
    try:
        b, M, info = ellipsoid_fit(x, R, source=source)
        plain_err = None
    except InputError as e:
        if prior is None:
            raise
        b = M = info = None
        plain_err = e
    pr = prior if prior is not None else nominal_prior(0)
    p0, S = prior_at(pr, temp_C)
    w = np.ones(len(x))
    n = len(x)
    if noise_nT:
        s2 = float(noise_nT) ** 2
    elif info is not None:
        s2 = max(float(info["residual_sigma_nT"]) ** 2, 1e-6)
    else:
        s2 = None

    def information(q, s2_):
        _, J = _geo_resid_jac(q, x, R, w)
        F = (J * S).T @ (J * S) / s2_
        ev, EV = np.linalg.eigh(0.5 * (F + F.T))
        return ev, EV

    if info is not None and prior is None:
        p = np.concatenate([b, sym_to6(M)])
        ev, EV = information(p, s2)
        held = ev < FISHER_THRESHOLD
        if not held.any():
            frac = np.ones(9)
            sig = np.concatenate([info["b_sigma_nT"], [info["M_sigma"][i, j]
                                                        for i, j in SYM_INDEX]])
            info["observability"] = _tags(p, p0, S, sig, frac, held, EV, ev, pr.source)
            return b, M, info
        # the plain fit passed its own checks but some direction is below the (nominal)
        # prior's information: held there, as the reference-vector fit does
    # 2. maximum a posteriori (prior rows), in whitened coordinates z = (p - p0) / S
    z_start = np.zeros(9) if info is None else (np.concatenate([b, sym_to6(M)]) - p0) / S
    for _pass in range(2):
        s2_ = s2 if s2 else (1e-2 * float(np.mean(R))) ** 2

        def map_model(z, jac):
            q = p0 + S * z
            r, J = _geo_resid_jac(q, x, R, w)
            cost = float(r @ r) / s2_ + float(z @ z)
            if not jac:
                return cost, None, None, n + 9
            Jz = J * S
            return cost, Jz.T @ Jz / s2_ + np.eye(9), Jz.T @ r / s2_ + z, n + 9

        z_map, *_ = lm_solve(map_model, z_start)
        z_start = z_map
        if s2:
            break
        r, _ = _geo_resid_jac(p0 + S * z_map, x, R, w)
        s2 = max(float(r @ r) / max(n - 9, 1), 1e-6)
    q_map = p0 + S * z_map
    ev, EV = information(q_map, s2)
    fitted = ev >= FISHER_THRESHOLD
    if fitted.all() and info is not None:
        p = np.concatenate([b, sym_to6(M)])
        sig = np.concatenate([info["b_sigma_nT"], [info["M_sigma"][i, j] for i, j in SYM_INDEX]])
        info["observability"] = _tags(p, p0, S, sig, np.ones(9), ~fitted, EV, ev, pr.source)
        return b, M, info
    # 3. least squares restricted to the fitted directions, the rest at the prior
    Vf = EV[:, fitted]
    if Vf.shape[1]:
        SV = S[:, None] * Vf

        def sub_model(u, jac):
            r, J = _geo_resid_jac(p0 + SV @ u, x, R, w)
            if not jac:
                return float(r @ r), None, None, n
            Ju = J @ SV
            return float(r @ r), Ju.T @ Ju, Ju.T @ r, n

        u, cost, _, lm = lm_solve(sub_model, Vf.T @ z_map)
        p = p0 + SV @ u
    else:
        p, lm = p0.copy(), {"iterations": 0, "converged": True}
    b, M = p[:3], sym_from6(p[3:])
    if np.linalg.eigvalsh(M)[0] <= 0:
        raise InputError(source, "ellipsoid fit with the prior: the matrix left is not "
                                 "positive definite; the magnitudes contradict the prior")
    r, _ = _geo_resid_jac(p, x, R, w)
    dof = max(n - int(fitted.sum()), 1)
    s2f = s2 if s2 else max(float(r @ r) / dof, 1e-6)
    ev2, _ = information(p, s2f)          # at the final estimate, for the covariance
    Ft = (lambda J: (J * S).T @ (J * S) / s2f)(_geo_resid_jac(p, x, R, w)[1])
    Vp = EV[:, ~fitted]
    C = Vp @ Vp.T
    if Vf.shape[1]:
        C = C + Vf @ np.linalg.solve(Vf.T @ Ft @ Vf, Vf.T)
    C = C * np.outer(S, S)
    sig = np.sqrt(np.maximum(np.diag(C), 0))
    frac = np.sum(Vf ** 2, axis=1)
    rms = float(np.sqrt(np.mean(r ** 2)))
    out = {"n": int(n), "b_sigma_nT": sig[:3], "M_sigma": _sym_sigma(sig[3:]), "cov": C,
           "cond": float(ev2[-1] / max(ev2[0], 1e-300)),
           "residual_sigma_nT": float(np.sqrt(float(r @ r) / dof)), "lm": lm,
           "final": {"b_nT": b, "M": M, "rms_nT": rms, "residual": "geometric"},
           "plain_fit": (plain_err.message if plain_err is not None else "determined, "
                         "but some direction below the prior's information")}
    out["observability"] = _tags(p, p0, S, sig, frac, ~fitted, EV, ev, pr.source)
    return b, M, out


# =======================================================================================
# Recalibration ON TOP OF a polynomial prior (in-flight, magnitudes only)
# =======================================================================================
def _on_prior_model(prior, x, T, t_ref_C, degree):
    """The residual |M_p(T) (I + E) (x - b_p(T) - db(T))| - |B| and its Jacobian in
    q = (E (6, ellipsoid.SYM_INDEX order), db_poly (degree+1, 3) k-major)."""
    d = np.asarray(T, float) - t_ref_C
    K = len(prior.b_poly_nT)
    Pp = d[:, None] ** np.arange(K)
    bp = Pp @ np.asarray(prior.b_poly_nT, float)
    Mp = np.einsum("nk,kij->nij", Pp, np.asarray(prior.M_poly, float))
    P = d[:, None] ** np.arange(degree + 1)

    def resid_jac(q, R):
        E = sym_from6(q[:6])
        C = q[6:].reshape(degree + 1, 3)
        v = x - bp - P @ C
        w = v + v @ E                       # (I + E) v, E symmetric
        B = np.einsum("nij,nj->ni", Mp, w)
        nB = np.linalg.norm(B, axis=1)
        r = nB - R
        g = np.einsum("nij,ni->nj", Mp, B / nB[:, None])     # dr/dw
        JE = np.empty((len(x), 6))
        for k, (i, j) in enumerate(SYM_INDEX):
            JE[:, k] = g[:, i] * v[:, i] if i == j else g[:, i] * v[:, j] + g[:, j] * v[:, i]
        gw = g + g @ E                      # (I + E)^T g
        JC = -(P[:, :, None] * gw[:, None, :]).reshape(len(x), -1)
        return r, np.hstack([JE, JC])

    return resid_jac


def ellipsoid_fit_on_prior(field_nT, ref_norm_nT, temp_C, prior, degree, *, t_ref_C=T_REF_C,
                           source=None, noise_nT=None):
    """In-flight recalibration from magnitudes only, on top of a polynomial prior (a ground
    calibration): B = M_p(T) (I + E) (x - b_p(T) - db(T)).

    E symmetric (scale and non-orthogonality relative to the prior), db(T) a polynomial of
    `degree` (the degree the data's temperature span supports; the caller picks it). The
    rotation (the antisymmetric part of M, which magnitudes cannot see) and every
    temperature term of the prior (M's, and b's above `degree`) are held at the prior.
    Prior 1-sigma of the change q: E_ij the prior's symmetric M 1-sigma at the data's
    mean temperature (prior_at), db_k the prior's b_k 1-sigma (Prior.truncated), each
    combined (root sum square) with the part's (reference.PART_PRIOR_SIGMA): a change
    after the ground calibration is bounded by the part's spread, not by the ground fit's
    precision. Then as
    ellipsoid_fit_prior steps 2-3: the maximum a posteriori estimate, the whitened
    information split at reference.FISHER_THRESHOLD, least squares in the directions the
    data determine, the rest exactly at the prior (E = 0, db = 0 there).

    Returns (b_poly (K, 3), M_poly (K, 3, 3), b_sigma, M_sigma, info); K the prior's
    length. 1-sigma: b_k for k <= degree from the covariance of db_k, above it the prior's;
    M_k for k >= 1 the prior's; M_0: diagonal the covariance of E_ii, off-diagonal
    sqrt(sigma(E_ij)^2 + prior_ij^2 / 2) (the symmetric part from the fit, the
    antisymmetric - rotation - half of the prior's variance held).
    info["observability"]: per parameter data/prior tags (as ellipsoid_fit_prior) and
    "held" saying what was kept from the prior."""
    x = np.asarray(field_nT, float)
    T = np.asarray(temp_C, float)
    R = np.broadcast_to(np.asarray(ref_norm_nT, float), (len(x),)).astype(float)
    n = len(x)
    K = max(len(prior.b_poly_nT), degree + 1)
    pr = prior.truncated(K - 1)
    resid_jac = _on_prior_model(pr, x, T, t_ref_C, degree)
    _, s_pr = prior_at(pr, float(np.mean(T)), t_ref_C)
    nq = 6 + 3 * (degree + 1)
    # the CHANGE since the ground calibration (a deployed panel, a new current, drift) is
    # not bounded by the ground fit's 1-sigma: its 1-sigma is that combined with the
    # part's own (reference.PART_PRIOR_SIGMA, the spread of an uncalibrated part)
    part = nominal_prior(K - 1)
    S = np.concatenate([np.hypot(s_pr[3:], part.M_sigma[0, 0, 0]),
                        np.hypot(np.asarray(pr.b_sigma_nT, float)[:degree + 1],
                                 part.b_sigma_nT[:degree + 1]).ravel()])
    names = ([f"E_{'xyz'[i]}{'xyz'[j]}" for i, j in SYM_INDEX]
             + [f"db{k}_{'xyz'[i]}" for k in range(degree + 1) for i in range(3)])
    def map_fit(z0, s2_, weight):
        """Minimum of |r|^2 / s2_ + weight |z|^2 (weight 1: the posterior)."""
        def map_model(z_, jac):
            r, J = resid_jac(S * z_, R)
            cost = float(r @ r) / s2_ + weight * float(z_ @ z_)
            if not jac:
                return cost, None, None, n + nq
            Jz = J * S
            return (cost, Jz.T @ Jz / s2_ + weight * np.eye(nq),
                    Jz.T @ r / s2_ + weight * z_, n + nq)
        return lm_solve(map_model, z0)[0]

    z = np.zeros(nq)
    if noise_nT:
        s2 = float(noise_nT) ** 2
    else:
        # no stated noise: the residual variance of the model fitted to the data alone (a
        # prior weight of 1e-9 only regularises the directions the data leave free). Not
        # the posterior's residual: a prior far from the data (a post-launch shift many
        # sigma away) would inflate it and so make the data look uninformative.
        z = map_fit(z, (1e-2 * float(np.mean(R))) ** 2, 1e-9)
        r, _ = resid_jac(S * z, R)
        s2 = max(float(r @ r) / max(n - nq, 1), 1e-6)
    # 2. maximum a posteriori, whitened z = q / S (the prior is q = 0)
    z = map_fit(z, s2, 1.0)

    def whitened_info(q):
        J = resid_jac(q, R)[1] * S
        F = J.T @ J / s2
        return 0.5 * (F + F.T)

    ev, EV = np.linalg.eigh(whitened_info(S * z))
    fitted = ev >= FISHER_THRESHOLD
    # 3. least squares in the directions the data determine, the rest at the prior
    Vf = EV[:, fitted]
    if Vf.shape[1]:
        SV = S[:, None] * Vf

        def sub_model(u, jac):
            r, J = resid_jac(SV @ u, R)
            if not jac:
                return float(r @ r), None, None, n
            Ju = J @ SV
            return float(r @ r), Ju.T @ Ju, Ju.T @ r, n

        u, _, _, lm = lm_solve(sub_model, Vf.T @ z)
        q = SV @ u
    else:
        q, lm = np.zeros(nq), {"iterations": 0, "converged": True}
    E = sym_from6(q[:6])
    C = q[6:].reshape(degree + 1, 3)
    if np.linalg.eigvalsh(np.eye(3) + E)[0] <= 0:
        raise InputError(source, "recalibration on the prior: the scale left is not positive "
                                 "definite; the magnitudes contradict the prior")
    r, _ = resid_jac(q, R)
    Ft = whitened_info(q)
    Vp = EV[:, ~fitted]
    Cov = Vp @ Vp.T
    if Vf.shape[1]:
        Cov = Cov + Vf @ np.linalg.solve(Vf.T @ Ft @ Vf, Vf.T)
    Cov = Cov * np.outer(S, S)
    sig = np.sqrt(np.maximum(np.diag(Cov), 0))
    frac = np.sum(Vf ** 2, axis=1)
    b_poly = np.asarray(pr.b_poly_nT, float).copy()
    b_poly[:degree + 1] += C
    M_poly = np.einsum("kij,jl->kil", np.asarray(pr.M_poly, float), np.eye(3) + E)
    b_sig = np.asarray(pr.b_sigma_nT, float).copy()
    b_sig[:degree + 1] = sig[6:].reshape(degree + 1, 3)
    M_sig = np.asarray(pr.M_sigma, float).copy()
    sE = _sym_sigma(sig[:6])
    M_sig[0] = np.where(np.eye(3, dtype=bool), sE, np.sqrt(sE ** 2 + M_sig[0] ** 2 / 2))
    obs = _tags(q, np.zeros_like(q), S, sig, frac, ~fitted, EV, ev, pr.source, names,
                ("recalibration on the prior from magnitudes only: B = M_p(T) (I + E) "
                 "(x - b_p(T) - db(T)), E symmetric and db of degree "
                 f"{degree} where the data determine them better than the prior, the rest "
                 "held at the prior"))
    params = obs["parameters"]
    held = ["the rotation (antisymmetric part of M): magnitudes do not see it",
            "every temperature term of M (degrees 1..): the prior's"]
    if K > degree + 1:
        held.append(f"b's temperature terms of degree {degree + 1}..{K - 1}: the prior's "
                    f"(the data's span supports degree {degree})")
    held += [f"{p['name']} (scale/non-orthogonality E or offset change db relative to the "
             "prior)" for p in params if p["source"] == "prior"]
    dof = max(n - int(fitted.sum()), 1)
    obs.update({"held_at_prior": held,
                "note": "E and db are changes relative to the prior (" + pr.source + ")"})
    info = {"n": int(n), "cov": Cov, "lm": lm, "degree": int(degree),
            "residual_sigma_nT": float(np.sqrt(float(r @ r) / dof)),
            "rms_nT": float(np.sqrt(np.mean(r ** 2))), "observability": obs}
    return b_poly, M_poly, b_sig, M_sig, info
