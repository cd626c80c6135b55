"""Goodness of fit of a reference-vector calibration: is the residual the noise floor?

After the fit, the calibrated-minus-reference residual r_n (body axes) of the vector rows
should be what the sensor's noise and the reference's own error explain. Per axis

    sigma^2 = noise_nT^2 |M|_F^2 / 3                       (the reading noise through M)
            + (2/3) (theta_ref |B|)^2 + (f_ref |B|)^2 / 3   (the reference's error)

with theta_ref = REF_ANGLE_SIGMA_DEG and f_ref = REF_SCALE_SIGMA (module constants: the
reference error the toolchain states for reference vectors, since the ICD's ref_x/y/z_nT
carry none: a rig's encoder is good to a fraction of a degree, an autopilot's attitude
estimate to a few degrees in heading, a field model to ~1 %; a direction error of angle
theta about a random axis leaves (2/3) theta^2 |B|^2 per axis, a scale error f of the
magnitude f^2 |B|^2 / 3 per axis). Under that model chi2 = sum |r_n|^2 / sigma^2 is
chi-square with 3 N_eff degrees of freedom, where N_eff counts serially correlated
residuals as fewer samples (reference._correlation_inflation, per file); the fit's own
parameters take at most 12 (degree + 1) of them, which only makes the test more
lenient. The fit is refused (InputError, exit 2) when chi2 / (3 N_eff) passes the
chi-square quantile at 1 - MISFIT_ALPHA / (3 N_eff): a residual that size does not come
from noise and an honest reference. Its usual cause is a reference in another frame
(ENU against NED, a rotated mounting, a proper rotation that the reflection check of
fit.sanity cannot see); M cannot take it up, because an M that far from the part's
nominal is held at the prior (fit.reference, observability). The caller may accept it
(fit_unit(..., accept_misfit=True)); it is then reported, not refused.
"""

from __future__ import annotations

import numpy as np

from generator.errors import InputError

REF_ANGLE_SIGMA_DEG = 10.0     # reference direction error, 1-sigma per axis (see docstring)
REF_SCALE_SIGMA = 0.02         # reference magnitude error, 1-sigma, relative
MISFIT_ALPHA = 1e-6            # false-refusal probability of the test for a right reference


def vector_misfit(cal, S) -> dict | None:
    """The test above on the samples S (fit.samples._Samples) of a fitted calibration;
    None without vector rows or for a magnitude-only (symmetric M) calibration. JSON-able: chi2_per_dof, limit, n_eff, refuse, figures."""
    from scipy.stats import chi2 as _chi2

    from generator.fit.reference import _correlation_inflation

    if not S.is_vec.any() or not cal.body_frame:   # magnitudes only: M up to a rotation
        return None
    z = cal.apply64(S.x, S.T)
    r = z - S.ref
    v = S.is_vec
    M = cal.M_at(S.T[v])
    read2 = float(S.noise_nT or 0.0) ** 2 * np.einsum("nij,nij->n", M, M) / 3.0
    F2 = np.sum(S.ref[v] ** 2, axis=1)
    th = np.radians(REF_ANGLE_SIGMA_DEG)
    ref2 = (2.0 / 3.0) * th ** 2 * F2 + REF_SCALE_SIGMA ** 2 * F2 / 3.0
    var = read2 + ref2
    rv = r[v]
    chi2 = float(np.sum(np.sum(rv ** 2, axis=1) / var))
    n_eff = 0.0
    fid = S.file_id[v] if S.file_id is not None else np.zeros(int(v.sum()), int)
    for f in np.unique(fid):
        m = fid == f
        n_eff += m.sum() / _correlation_inflation(rv[m] / np.sqrt(var[m])[:, None])
    dof = max(3.0 * n_eff, 1.0)
    limit = float(_chi2.ppf(1.0 - MISFIT_ALPHA, dof) / dof)
    per_dof = chi2 / (3.0 * int(v.sum()))
    rms = float(np.sqrt(np.mean(rv ** 2)))
    return {"chi2_per_dof": per_dof, "limit": limit, "n_eff": float(n_eff),
            "refuse": bool(per_dof > limit), "rms_vector_per_axis_nT": rms,
            "allowed_per_axis_nT": float(np.sqrt(np.mean(var))),
            "from": (f"reading noise {float(S.noise_nT or 0.0):.1f} nT through M, reference "
                     f"error {REF_ANGLE_SIGMA_DEG:g} deg and {100 * REF_SCALE_SIGMA:g} % "
                     f"(1-sigma); chi-square quantile 1 - {MISFIT_ALPHA:g}")}


def check_misfit(name, gof, source, accept=False, progress=None):
    """InputError (exit 2, one line) when gof (vector_misfit) refuses, unless accept; then
    gof["accepted"] is set and the refusal's message returned (the caller puts it in the
    calibration's warnings). None when nothing is refused."""
    if not gof or not gof["refuse"]:
        return None
    msg = (f"sensor '{name}': {gof['rms_vector_per_axis_nT']:.0f} nT per axis left against "
           f"the reference vectors, chi2/dof {gof['chi2_per_dof']:.3g} > {gof['limit']:.3g} "
           f"(noise + reference good to {REF_ANGLE_SIGMA_DEG:g} deg); likely cause: "
           "ref_x/y/z_nT in another frame (ENU vs NED, a rotated mounting or axis mapping); "
           "fix them, or fit magnitudes only (--method ellipsoid)")
    if accept:
        gof["accepted"] = True
        if progress:
            progress(f"WARNING (accepted): {msg}")
        return msg
    raise InputError(source, msg)
