"""Temperature models built per constant-temperature level: a constant calibration at
each level (reference vectors, seed 001 analytic, or seed 000 ellipsoid), then a weighted
polynomial of every coefficient over the levels (seed 000 eq. 7).
"""

from __future__ import annotations

import numpy as np

from generator.errors import InputError
from generator.fit.calibration import SensorCalibration
from generator.fit.ellipsoid_prior import ellipsoid_fit_prior
from generator.fit.joint import (DEGREE_STEP_C, _degree_for_span, _fit_joint, _make_cal, _pad,
                                 _rms, _score, reference_options)
from generator.fit.reference import T_REF_C, _powers, reference_fit
from generator.fit.samples import _Samples
from generator.fit.segments import Segment, group_levels, temperature_quantum


def _level_fits(S: _Samples, levels, body_frame, source, mask=None, uncertainty=True):
    """Constant calibration per temperature level -> list of (temp, b, M, b_sig, M_sig).
    uncertainty=False (the held-out comparison): reference_fit's coefficients and 1-sigma
    without its diagnostics (residual_sigma_nT, cond), the levels' reference fits run
    side by side (fit.reference_batch: their Gauss-Newton iterates stacked; the same
    coefficients to float64 rounding)."""
    out, dropped = [], []
    idxs = []
    for lev in levels:
        idx = np.concatenate([s.index for s in lev])
        idxs.append(idx if mask is None else idx[mask[idx]])
    batched = {}
    if body_frame and not uncertainty:
        from generator.fit.reference_batch import reference_fits

        calls = {}
        for j, idx in enumerate(idxs):
            iv = idx[S.is_vec[idx]]
            if len(iv):
                calls[j] = ((S.x[iv], S.ref[iv], None),
                            dict(source=source, uncertainty=False,
                                 **reference_options(S, iv, with_prior=False)))
        batched = dict(zip(calls, reference_fits(list(calls.values()))))
    for j, idx in enumerate(idxs):
        if len(idx) == 0:
            continue
        temp = float(np.mean(S.T[idx]))
        try:
            if body_frame:
                iv = idx[S.is_vec[idx]]
                if len(iv) == 0:
                    raise InputError(source, "no reference vectors at this level")
                if j in batched:
                    if isinstance(batched[j], InputError):
                        raise batched[j]
                    b, M, info = batched[j]
                else:
                    b, M, info = reference_fit(S.x[iv], S.ref[iv], None, source=source,
                                               uncertainty=uncertainty,
                                               **reference_options(S, iv, with_prior=False))
                out.append((temp, b[0], M[0], info["b_poly_sigma_nT"][0],
                            info["M_poly_sigma"][0], len(iv)))
            else:
                b, M, info = ellipsoid_fit_prior(S.x[idx], S.norm[idx], S.prior, temp,
                                                 source=source)
                out.append((temp, b, M, info["b_sigma_nT"], info["M_sigma"], len(idx)))
        except InputError as e:
            dropped.append(f"level {temp:.1f} degC: {e.message}")
    return out, dropped


def _poly_over_levels(fits, degree, t_lo, t_hi):
    """Weighted polynomial of each coefficient over the level results."""
    temps = np.array([f[0] for f in fits])
    vals = np.array([np.concatenate([f[1], f[2].ravel()]) for f in fits])      # (L, 12)
    sigs = np.array([np.concatenate([f[3], f[4].ravel()]) for f in fits])
    sigs = np.where(sigs > 0, sigs, np.max(sigs) if np.max(sigs) > 0 else 1.0)
    tau = max(abs(t_lo - T_REF_C), abs(t_hi - T_REF_C), 1.0)
    V = _powers((temps - T_REF_C) / tau, degree)
    coef = np.zeros((degree + 1, 12))
    csig = np.zeros((degree + 1, 12))
    for c in range(12):
        w = 1.0 / sigs[:, c]
        A = V * w[:, None]
        sol, *_ = np.linalg.lstsq(A, vals[:, c] * w, rcond=None)
        cov = np.linalg.pinv(A.T @ A)
        dof = len(temps) - (degree + 1)
        chi2 = float(np.sum(((V @ sol - vals[:, c]) * w) ** 2))
        inflate = max(1.0, chi2 / dof) if dof > 0 else 1.0
        coef[:, c] = sol
        csig[:, c] = np.sqrt(np.maximum(np.diag(cov) * inflate, 0))
    scale = tau ** -np.arange(degree + 1)
    b = coef[:, :3] * scale[:, None]
    M = coef[:, 3:].reshape(degree + 1, 3, 3) * scale[:, None, None]
    bs = csig[:, :3] * scale[:, None]
    Ms = csig[:, 3:].reshape(degree + 1, 3, 3) * scale[:, None, None]
    return b, M, bs, Ms


def _fit_segments(name, S: _Samples, levels, body_frame, degree, t_lo, t_hi, source,
                  mask=None):
    fits, dropped = _level_fits(S, levels, body_frame, source, mask,
                                uncertainty=mask is None)    # a fold: the coefficients only
    if len(fits) < 2:
        raise InputError(source, f"segments method: {len(fits)} calibratable temperature "
                                 "level(s); at least 2 are needed"
                         + (f" ({'; '.join(dropped)})" if dropped else ""))
    deg = min(degree, len(fits) - 1)
    b, M, bs, Ms = _poly_over_levels(fits, deg, t_lo, t_hi)
    kind = "reference-vector" if body_frame else "ellipsoid"
    cal = _make_cal(name, b, M, t_lo, t_hi, body_frame,
                    f"{kind} per temperature segment, degree {deg} over {len(fits)} levels",
                    bs, Ms)
    return cal, fits, dropped


def _floats(a):
    """JSON-able nested lists of float."""
    return np.asarray(a, float).tolist()


def _level_windows(S: _Samples, idx, file_offsets):
    """Where a level's samples come from: [file number, first time_s, last time_s] per
    run of consecutive used samples (file number: 0-based position in stats["files"]).
    The level holds exactly the samples in these windows that the fit used (usable, with
    a reference, no coil current)."""
    idx = np.sort(np.asarray(idx))
    if len(idx) == 0 or S.time_s is None:
        return []
    file_no = np.searchsorted(file_offsets, idx, side="right")
    cuts = np.nonzero((np.diff(idx) != 1) | (np.diff(file_no) != 0))[0] + 1
    return [[int(file_no[run[0]]), float(S.time_s[idx[run[0]]]), float(S.time_s[idx[run[-1]]])]
            for run in np.split(np.arange(len(idx)), cuts)]


def _subset_with_segments(S: _Samples, mask):
    """S restricted to mask, its segments re-indexed (samples outside mask dropped)."""
    new_index = np.cumsum(mask) - 1
    sub = S.subset(mask)
    for seg in S.segments:
        keep = seg.index[mask[seg.index]]
        if len(keep):
            sub.segments.append(Segment(index=new_index[keep], temp_C=seg.temp_C,
                                        temp_range_C=seg.temp_range_C,
                                        t_start_s=seg.t_start_s, t_stop_s=seg.t_stop_s,
                                        position=seg.position))
    return sub


def rotated_fit_M(fit):
    """M = W^-1 = (Q P R)^-1 of a RotatedFit and its 1-sigma (3, 3), propagated to first
    order from fit.cov (order k, e, delta, b): dM = -M dW M with dW/dk_i = E_ii P R,
    dW/de_j = Q dP/de_j R, dW/ddelta_j = Q P R [u_j]x (R_true = R exp([delta]x))."""
    M = np.linalg.inv(fit.W)
    PR = fit.P @ fit.R
    dW = []
    for i in range(3):
        E = np.zeros((3, 3))
        E[i, i] = 1.0
        dW.append(E @ PR)
    from generator.fit.analytic import _dP_de   # only the analytic method needs it (and scipy.optimize)

    dW += [fit.Q @ dP @ fit.R for dP in _dP_de(fit.e_rad)]
    for j in range(3):
        u = np.zeros(3)
        u[j] = 1.0
        dW.append(fit.W @ np.cross(np.eye(3), u))      # W [u]x: row i of [u]x is e_i x u
    J = np.zeros((9, 12))
    for c, d in enumerate(dW):
        J[:, c] = (-M @ d @ M).ravel()
    var = np.einsum("ic,cd,id->i", J, fit.cov, J)
    return M, np.sqrt(np.maximum(var, 0.0)).reshape(3, 3)


def _analytic_level(x_nT, ref_nT):
    """Seed 001 at one temperature: the plain model h = Q P B + b (for its residual) and
    the rotated one h = Q P R B + b. Returns (rotated fit, plain fit, M, M_sigma)."""
    from generator.fit.analytic import fit_analytic, fit_analytic_rotated

    plain = fit_analytic(x_nT, ref_nT)
    rot = fit_analytic_rotated(x_nT, ref_nT, analytic=plain)
    M, M_sig = rotated_fit_M(rot)
    return rot, plain, M, M_sig


def _analytic_level_stats(rot, plain):
    deg = np.degrees
    return {
        "k": _floats(rot.k), "k_sigma": _floats(rot.sigma_k),
        "e_deg": _floats(deg(rot.e_rad)), "e_sigma_deg": _floats(deg(rot.sigma_e_rad)),
        "R_rotvec_deg": _floats(deg(rot.rotvec_rad)),
        "R_rotvec_sigma_deg": _floats(deg(rot.sigma_rot_rad)),
        "R_angle_deg": float(deg(np.linalg.norm(rot.rotvec_rad))),
        "b_nT": _floats(rot.b_nT), "b_sigma_nT": _floats(rot.sigma_b_nT),
        "residual_rms_nT": float(rot.residual_rms_nT),
        "residual_rms_axis_nT": _floats(rot.residual_rms_axis_nT),
        "residual_rms_seed001_nT": float(plain.residual_rms_nT),
        "residual_rms_axis_seed001_nT": _floats(plain.residual_rms_axis_nT),
        "seed001_k": _floats(plain.k), "seed001_e_deg": _floats(deg(plain.e_rad)),
        "seed001_b_nT": _floats(plain.b_nT),
    }


def _file_offsets(per_file):
    """Where each file's samples end in the gathered arrays (the subsample's counts where
    the fit subsampled: fit/samples.py MAX_FIT_SAMPLES)."""
    return np.cumsum([f.get("fit_samples", f["used"]) for f in per_file])


def _fit_sensor_analytic(name, S_all, datas, degree, say, notes, per_file, source):
    """The "analytic" method (see fit_sensor). Returns (cal, None), or (None, why) when
    it cannot be used and the caller falls back to auto."""
    S = _subset_with_segments(S_all, S_all.is_vec)
    my_notes = []
    no_vec = [f["source"] for f in per_file if f["used"] and "ref vectors" not in f["reference"]]
    if (~S_all.is_vec).any():
        my_notes.append(f"{int((~S_all.is_vec).sum())} magnitude-only samples not used by the "
                        "known-vector method" + (f" (files {', '.join(no_vec)})" if no_vec else ""))
    t_lo, t_hi = float(S.T.min()), float(S.T.max())
    span = t_hi - t_lo
    deg = min(degree, _degree_for_span(span))
    stats = {"files": per_file, "samples_used": int(S.n), "samples_vector": int(S.n),
             "samples_magnitude": 0, "temperature_range_C": [t_lo, t_hi],
             "degree": int(deg), "notes": notes,
             "model": "h = Q P R B + b per temperature level (seed 001 with a rotation R); "
                      "M = (Q P R)^-1; b, M polynomial over the levels, weighted by 1/sigma"}
    say(f"{name}: analytic known-vector method, {S.n} samples with reference vectors, "
        f"{t_lo:.1f}..{t_hi:.1f} degC")
    offsets = _file_offsets(per_file)
    if deg == 0:
        idx_all = np.arange(S.n)
        levels, stats["segments"] = [], {"found": len(S.segments), "levels": []}
        groups = [(None, idx_all)]
    else:
        levels, stats["segments"] = _temperature_levels(S, datas, deg)
        groups = [(lev, np.concatenate([s.index for s in lev])) for lev in levels]
    vec_index = np.nonzero(S_all.is_vec)[0]          # S index -> S_all index (for windows)
    fits, level_stats, dropped = [], [], []
    for lev, idx in groups:
        temp = float(np.mean(S.T[idx]))
        try:
            rot, plain, M, M_sig = _analytic_level(S.x[idx], S.ref[idx])
        except InputError as e:
            dropped.append(f"level {temp:.1f} degC: {e.message}")
            continue
        fits.append((temp, rot.b_nT, M, rot.sigma_b_nT, M_sig, len(idx)))
        entry = {"temp_C": temp, "samples": int(len(idx)),
                 "positions": sorted({int(s.position) for s in
                                      (lev if lev is not None else S.segments)}),
                 "windows_s": _level_windows(S_all, vec_index[idx], offsets)}
        entry.update(_analytic_level_stats(rot, plain))
        level_stats.append(entry)
    if dropped:
        my_notes.extend(dropped)
    if deg == 0:
        if not fits:
            return None, f"the known-vector fit failed: {'; '.join(dropped)}"
        _, b0, M0, b0_sig, M0_sig, _ = fits[0]
        b_sig, M_sig = _pad(b0_sig[None], M0_sig[None])
        cal = SensorCalibration.constant(name, b0, M0, T_REF_C, t_lo, t_hi, body_frame=True,
                                         method="analytic known-vector (seed 001 + R), constant",
                                         b_poly_sigma_nT=b_sig, M_poly_sigma=M_sig)
        stats["why"] = ("degree 0 requested" if degree == 0 else
                        f"reported temperature spans {span:.1f} degC: one constant fit of "
                        "all samples")
    else:
        if len(fits) < 2:
            return None, (f"{len(fits)} calibratable constant-temperature level(s) for a "
                          f"temperature span of {span:.1f} degC; the polynomial over levels "
                          "needs 2 or more" + (f" ({'; '.join(dropped)})" if dropped else ""))
        dl = min(deg, len(fits) - 1)
        b, M, bs, Ms = _poly_over_levels(fits, dl, t_lo, t_hi)
        cal = _make_cal(name, b, M, t_lo, t_hi, True,
                        f"analytic known-vector (seed 001 + R) per temperature level, degree "
                        f"{dl} over {len(fits)} levels", bs, Ms)
        stats["degree"] = int(dl)
    notes.extend(my_notes)
    stats["segments"]["level_fits"] = level_stats
    stats["fit"] = _score(S_all, cal)
    say(f"{name}: {cal.method}")
    cal.stats = stats
    return cal, None


def _fit_sensor_ellipsoid(name, S_all, datas, degree, say, notes, per_file, source):
    """The "ellipsoid" method (see fit_sensor): magnitudes only, per level."""
    n = S_all.n
    S = _Samples(S_all.x, S_all.T, np.full((n, 3), np.nan), S_all.norm, np.zeros(n, bool),
                 S_all.group, list(S_all.segments), time_s=S_all.time_s,
                 file_id=S_all.file_id, noise_nT=S_all.noise_nT, prior=S_all.prior)
    t_lo, t_hi = float(S.T.min()), float(S.T.max())
    span = t_hi - t_lo
    deg = min(degree, _degree_for_span(span))
    stats = {"files": per_file, "samples_used": int(n), "samples_vector": 0,
             "samples_magnitude": int(n), "temperature_range_C": [t_lo, t_hi],
             "degree": int(deg), "notes": notes,
             "model": "|M (B~ - b)| = |B| per temperature level (seed 000 ellipsoid, M "
                      "symmetric: known up to a rotation); b, M polynomial over the levels"}
    if S_all.is_vec.any():
        notes.append(f"ellipsoid method: the reference vectors of {int(S_all.is_vec.sum())} "
                     "samples are used only through their magnitude")
    say(f"{name}: ellipsoid method, {n} samples, {t_lo:.1f}..{t_hi:.1f} degC")
    levels, stats["segments"] = _temperature_levels(S, datas, deg)
    offsets = _file_offsets(per_file)
    fits, level_stats, dropped = [], [], []
    for lev in levels:
        idx = np.concatenate([s.index for s in lev])
        temp = float(np.mean(S.T[idx]))
        try:
            b, M, info = ellipsoid_fit_prior(S.x[idx], S.norm[idx], S.prior, temp,
                                             source=source)
        except InputError as e:
            dropped.append(f"level {temp:.1f} degC: {e.message}")
            continue
        fits.append((temp, b, M, info["b_sigma_nT"], info["M_sigma"], len(idx)))
        resid = np.linalg.norm((S.x[idx] - b) @ M.T, axis=1) - S.norm[idx]
        level_stats.append({
            "temp_C": temp, "samples": int(len(idx)),
            "positions": sorted({int(s.position) for s in lev}),
            "windows_s": _level_windows(S, idx, offsets),
            "b_nT": _floats(b), "b_sigma_nT": _floats(info["b_sigma_nT"]),
            "M": _floats(M), "M_sigma": _floats(info["M_sigma"]),
            "residual_rms_norm_nT": _rms(resid)})
    if dropped:
        notes.extend(dropped)
    if deg > 0 and len(fits) >= 2:
        dl = min(deg, len(fits) - 1)
        b, M, bs, Ms = _poly_over_levels(fits, dl, t_lo, t_hi)
        cal = _make_cal(name, b, M, t_lo, t_hi, False,
                        f"ellipsoid (magnitudes only) per temperature level, degree {dl} over "
                        f"{len(fits)} levels", bs, Ms)
        stats["degree"] = int(dl)
    else:
        if deg > 0:
            notes.append(f"ellipsoid method: {len(fits)} calibratable constant-temperature "
                         "level(s), the polynomial over levels needs 2; joint ellipsoid fit "
                         "of all samples instead")
        cal = _fit_joint(name, S, False, deg, t_lo, t_hi, source)
    stats["segments"]["level_fits"] = level_stats
    stats["fit"] = _score(S, cal)
    say(f"{name}: {cal.method}")
    cal.stats = stats
    return cal



def _temperature_levels(S: _Samples, datas, deg):
    """Constant-temperature levels of the segments found in S (none for degree 0), and
    their description for stats."""
    quantum = max([temperature_quantum(d.temp_C) for d in datas] + [0.0])
    tol = max(2.0, 3.0 * quantum, DEGREE_STEP_C / 2)
    segs = S.segments
    levels = group_levels(segs, tol) if deg > 0 else []
    desc = {
        "found": len(segs),
        "levels": [{"temp_C": float(np.mean([s.temp_C for s in lev])),
                    "segments": len(lev),
                    "samples": int(sum(len(s.index) for s in lev)),
                    "positions": sorted({int(s.position) for s in lev})} for lev in levels],
    }
    return levels, desc


