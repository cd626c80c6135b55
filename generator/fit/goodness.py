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

A second test, noise_misfit, asks the sharper question: does the reading noise alone
(through M) plus the reference model's own stated floor explain the residual? Per row

    vector rows, per axis:  sigma^2 = noise_nT^2 |M|_F^2 / 3 + floor^2 / 3 + q^2/12 |dz/dT|^2 / 3
    magnitude rows:         sigma^2 = noise_nT^2 |M^T u|^2   + floor^2     + q^2/12 (u . dz/dT)^2

(u the calibrated field's direction; floor the |B| error 1-sigma the reference states
of itself, e.g. the geomagnetic field model's, io.orbit.model_floor_nT, 0 for reference
vectors and a lab field; q the temperature channel's reporting step, an error the model
carries by construction, fit.reference point 5). chi2 / n over the rows is tested against
the chi-square quantile 1 - NOISE_ALPHA with the effective degrees of freedom (3 N_eff
for vectors plus N_eff for magnitudes, reference._correlation_inflation per file),
widened by the noise figure's own uncertainty (reference.noise_var_uncertainty: a
figure the unit file states has its variance known to +-25 %, the part catalogue's
typical figure, used where the unit states none, to +-50 %; a residual is beyond the
noise only when it passes the quantile times 1.25, or 1.5). A sensor with no figure at
all (a generic part) has its noise estimated from the residual's second differences
(reference.difference_noise_var), which also carry the reference's white noise: that
test cannot see a noisy reference. The fit's own parameters (at most 12 (degree + 1)) take some
degrees of freedom, which only makes the test more lenient. Passing it is a WARNING, not
a refusal: the reference may honestly carry more error than the sensor (an attitude
estimate, a magnetically disturbed lab). Its causes are named in the message
(noise_warning): a reference worse than the sensor, a stuck or wrong temperature column
(for a sensor with no temperature channel instead: the board's drift over a thermal
sweep, which its constant model cannot take), an effect the model lacks (magcal trace
finds those). A stated or catalogue figure below the readings' own sample-to-sample
scatter (beyond its uncertainty) is warned as such ("check noise_nT", or a sensor noisier
than the catalogue's typical figure; _figure_below_scatter); the fit counts the noise up
to that scatter in its 1-sigma (fit.reference.noise_var_sigma).
"""

from __future__ import annotations

import numpy as np

from generator.errors import InputError
from generator.fit.reference import (CATALOGUE_NOISE_VAR_UNCERTAINTY, NOISE_CATALOGUE,
                                    NOISE_STATED, NOISE_VAR_UNCERTAINTY)

REF_ANGLE_SIGMA_DEG = 10.0     # reference direction error, 1-sigma per axis (see docstring)
REF_SCALE_SIGMA = 0.02         # reference magnitude error, 1-sigma, relative
MISFIT_ALPHA = 1e-6            # false-refusal probability of the test for a right reference
# false-warning probability per sensor of the noise-only test (noise_misfit) on data the
# noise, the reference's stated floor and the model explain
NOISE_ALPHA = 1e-3
# The note fit.samples._gather leaves for a sensor with temperature = false
NO_TEMPERATURE_NOTE = "temperature = false"


class Calibrated:
    """A fitted calibration evaluated on its samples S, once for the tests of this module
    (vector_misfit and noise_misfit evaluate the same): at_T, cal.per_value(S.T); z, the
    calibrated readings (float64)."""

    def __init__(self, cal, S):
        self.cal, self.S = cal, S
        self._at_T = self._z = None

    @property
    def at_T(self):
        if self._at_T is None:          # b(T), M(T) once per reported value
            own = getattr(self.S, "t_index", None)
            self._at_T = self.cal.per_value(
                self.S.T, own[:2] if own is not None and own[2] else None)
        return self._at_T

    @property
    def z(self):
        if self._z is None:
            self._z = self.at_T.apply64(self.S.x)
        return self._z


def vector_misfit(cal, S, ev: Calibrated | None = None) -> dict | None:
    """The test above on the samples S (fit.samples._Samples) of a fitted calibration;
    None without vector rows or for a magnitude-only (symmetric M) calibration. JSON-able: chi2_per_dof, limit, n_eff, refuse, figures.
    ev: Calibrated(cal, S), shared with noise_misfit (None: made here)."""
    from generator.fit.special import chi2_quantile

    from generator.fit.reference import _correlation_inflation

    if not S.is_vec.any() or not cal.body_frame:   # magnitudes only: M up to a rotation
        return None
    ev = ev or Calibrated(cal, S)
    at_T, z = ev.at_T, ev.z
    r = z - S.ref
    v = S.is_vec
    M = at_T.M_at()[v]
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
    limit = chi2_quantile(1.0 - MISFIT_ALPHA, dof) / dof
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


def noise_misfit(cal, S, floor_nT=None, ev: Calibrated | None = None) -> dict | None:
    """The noise-only test of the module docstring on the samples S (fit.samples._Samples)
    of a fitted calibration. floor_nT: per file (S.file_id) the reference's stated |B|
    error 1-sigma (None or 0: none stated). JSON-able:
    chi2_per_row, limit, n_eff, flagged, rms_residual_nT / explained_nT (per axis for
    vector rows, of |B| for magnitude rows), excess_field_error_nT (the vector error the
    noise does not explain, sqrt(3 (rms^2 - explained^2)) for vector rows, rms^2 -
    explained^2 of |B| for magnitude-only fits). ev: Calibrated(cal, S), shared with
    vector_misfit (None: made here)."""
    from generator.fit.special import chi2_quantile

    from generator.fit.reference import (_correlation_inflation, noise_source,
                                         noise_var_uncertainty)
    from generator.fit.segments import quantum_of_values, temperature_quantum

    if S.n == 0 or not (np.all(np.isfinite(cal.M_poly)) and np.all(np.isfinite(cal.b_poly_nT))):
        return None       # nothing to test (non-finite coefficients: fit.sanity refuses them)
    fid = S.file_id if S.file_id is not None else np.zeros(S.n, int)
    noise = float(S.noise_nT or 0.0)
    has_figure = noise > 0    # stated, or the part catalogue's
    ev = ev or Calibrated(cal, S)
    at_T, z = ev.at_T, ev.z
    if not has_figure:      # none stated (a generic part): from the residual's own differences
        noise = _difference_noise(cal, S, z, fid, at_T)
        if noise <= 0:
            return None
    floor = np.zeros(S.n)
    if floor_nT is not None:
        fl = np.asarray([float(f or 0.0) for f in floor_nT])
        floor = fl[np.clip(fid, 0, len(fl) - 1)] if len(fl) else floor
    M = at_T.M_at()
    # the temperature's reporting step: z's change per degC times q^2/12 (per file)
    q2 = np.zeros(S.n)
    files = np.unique(fid)
    for f in files:
        m = fid == f
        # one file: its values are at_T's (the same np.unique)
        q = (quantum_of_values(at_T.finite_values()) if len(files) == 1
             else temperature_quantum(S.T[m]))
        q2[m] = q ** 2 / 12.0
    h = 0.5
    dz = (at_T.apply64(S.x, h) - at_T.apply64(S.x, -h)) / (2 * h)
    # a magnitude-only calibration (M symmetric, known up to a rotation) is judged on |B|
    v = S.is_vec if cal.body_frame else np.zeros(S.n, bool)
    vec_var = (noise ** 2 * np.einsum("nij,nij->n", M, M) / 3.0 + floor ** 2 / 3.0
               + q2 * np.sum(dz ** 2, axis=1) / 3.0)
    nz = np.linalg.norm(z, axis=1)
    u = z / np.where(nz > 0, nz, 1.0)[:, None]
    Mtu = np.einsum("nji,nj->ni", M, u)
    mag_var = (noise ** 2 * np.sum(Mtu ** 2, axis=1) + floor ** 2
               + q2 * np.sum(u * dz, axis=1) ** 2)
    n_rows, n_eff, chi2 = 0, 0.0, 0.0
    for f in np.unique(fid):
        m = fid == f
        mv, mm = m & v, m & ~v
        if mv.any():
            w = (z[mv] - S.ref[mv]) / np.sqrt(vec_var[mv])[:, None]
            chi2 += float(np.sum(w ** 2))
            n_rows += w.size
            n_eff += 3.0 * mv.sum() / _correlation_inflation(w)
        if mm.any():
            w = ((nz[mm] - S.norm[mm]) / np.sqrt(mag_var[mm]))[:, None]
            chi2 += float(np.sum(w ** 2))
            n_rows += w.size
            n_eff += mm.sum() / _correlation_inflation(w)
    if n_rows == 0:
        return None
    dof = max(n_eff, 1.0)
    quant = chi2_quantile(1.0 - NOISE_ALPHA, dof) / dof
    unc = noise_var_uncertainty(S.noise_nT if has_figure else None)
    limit = (1.0 + unc) * quant
    per_row = chi2 / n_rows
    out = {"chi2_per_row": per_row, "limit": limit, "quantile": quant,
           "n_eff": float(n_eff), "n_rows": int(n_rows), "alpha": NOISE_ALPHA,
           "flagged": bool(per_row > limit), "noise_nT": noise,
           "floor_nT": float(np.max(floor)) if floor.size else 0.0}
    if v.any():
        r2 = float(np.mean((z[v] - S.ref[v]) ** 2))
        e2 = float(np.mean(vec_var[v]))
        out.update(kind="vector", rms_residual_nT=float(np.sqrt(r2)),
                   explained_nT=float(np.sqrt(e2)),
                   excess_field_error_nT=float(np.sqrt(3.0 * max(r2 - e2, 0.0))))
    else:
        r2 = float(np.mean((nz - S.norm) ** 2))
        e2 = float(np.mean(mag_var))
        out.update(kind="magnitude", rms_residual_nT=float(np.sqrt(r2)),
                   explained_nT=float(np.sqrt(e2)),
                   excess_field_error_nT=float(np.sqrt(max(r2 - e2, 0.0))))
    src = noise_source(S.noise_nT) if has_figure else None
    out["noise_from"] = src or "sample-to-sample differences"
    # a sensor with no temperature channel (temperature = false) has a constant model:
    # a temperature column cannot be its cause, its board's drift can (noise_warning)
    out["no_temperature_channel"] = any(NO_TEMPERATURE_NOTE in str(m)
                                        for m in (cal.stats or {}).get("notes", []))
    if src in (NOISE_STATED, NOISE_CATALOGUE):
        below = _figure_below_scatter(cal, S, z, fid, noise, NOISE_VAR_UNCERTAINTY
                                      if src == NOISE_STATED
                                      else CATALOGUE_NOISE_VAR_UNCERTAINTY, at_T)
        if below:
            below["figure_from"] = src
            out["stated_below_data"] = below
    out["from"] = (f"reading noise {noise:.1f} nT per axis through M"
                   + (" (none stated: the part catalogue's typical figure)"
                      if src == NOISE_CATALOGUE else "")
                   + ("" if has_figure else " (none stated and none in the part catalogue: "
                      "estimated from the residual's sample-to-sample differences)")
                   + (f", reference floor {out['floor_nT']:.0f} nT" if out["floor_nT"] else "")
                   + (", temperature reporting step" if np.any(q2 > 0) else "")
                   + f"; chi-square quantile 1 - {NOISE_ALPHA:g} "
                   f"with {n_eff:.0f} effective degrees of freedom, times "
                   f"{1 + unc:g} for the noise figure's uncertainty")
    return out


def _figure_below_scatter(cal, S, z, fid, noise, unc, at_T=None) -> dict | None:
    """A stated noise figure below the data's own sample-to-sample scatter beyond its
    uncertainty (None otherwise). The scatter, per axis, is the smaller of two upper
    bounds of the reading noise (fit.reference.data_noise_var_bound's reasoning): the
    readings' own second differences (noise plus the field's motion between samples) and
    the residual's mapped back to the reading (noise plus the reference's white noise;
    _difference_noise_var). Flagged when their mean over the axes exceeds the figure's
    variance by more than its own 1-sigma (unc, relative) plus three standard errors of
    the estimate itself (fit.reference.DIFF_VAR_REL_SE / sqrt(n) per axis, over 3 axes
    / sqrt(3 n))."""
    from generator.fit.reference import DIFF_VAR_REL_SE, data_noise_var_bound

    bound = data_noise_var_bound(S.x, fid)
    res = _difference_noise_var(cal, S, z, fid, at_T)
    if bound is None or res is None:
        return None
    data_var = float(np.mean(np.minimum(bound, res)))
    n_diff = max(S.n - 2 * len(np.unique(fid)), 1)
    limit = noise ** 2 * (1.0 + unc) * (1.0 + 3.0 * DIFF_VAR_REL_SE / np.sqrt(3.0 * n_diff))
    if data_var <= limit:
        return None
    return {"stated_nT": float(noise), "data_scatter_nT": float(np.sqrt(data_var)),
            "limit_nT": float(np.sqrt(limit)),
            "from": "second differences of the readings and of the residual mapped back "
                    "to the reading, the smaller per axis, mean over the axes"}


def _difference_noise(cal, S, z, fid, at_T=None) -> float:
    """Per-axis reading noise (nT, in the reading's scale) when the sensor has no figure
    (a generic part, none stated): fit.reference.difference_noise_var of the residual
    within each file, mapped back through M^-1 for vector rows (the |B| residual for
    magnitude rows is one axis's worth), averaged over the axes. Only what changes from
    sample to sample counts (white noise of the reading and of the reference); a slow
    error is exactly what the test is to find. 0 with too few rows."""
    var = _difference_noise_var(cal, S, z, fid, at_T)
    return 0.0 if var is None else float(np.sqrt(np.mean(var)))


def _difference_noise_var(cal, S, z, fid, at_T=None) -> np.ndarray | None:
    """_difference_noise's variance per axis (3,), None with too few rows. at_T:
    cal.per_value(S.T), whose distinct values serve where one file's rows are all of S's
    and all vector rows."""
    from generator.fit.reference import difference_noise_var

    v = S.is_vec if cal.body_frame else np.zeros(S.n, bool)
    parts = []
    for f in np.unique(fid):
        m = fid == f
        if (m & v).sum() >= 3:
            r = z[m & v] - S.ref[m & v]
            # pinv: a degenerate M is refused by fit.sanity after this, not here. M(T) is
            # a function of the reported temperature, which takes few distinct values
            # (a reporting step): one pseudo-inverse per value, the same matrices
            if at_T is not None and bool(np.all(m & v)):    # the same np.unique
                T_u, at = at_T.values, at_T.at
            else:
                T_u, at = np.unique(S.T[m & v], return_inverse=True)
            Minv = np.linalg.pinv(cal.M_at(T_u))[np.ravel(at)]
            parts.append(np.einsum("nij,nj->ni", Minv, r))
        if (m & ~v).sum() >= 3:
            e = np.linalg.norm(z[m & ~v], axis=1) - S.norm[m & ~v]
            parts.append(np.repeat(e[:, None], 3, axis=1))       # each axis's worth
    if not parts:
        return None
    return difference_noise_var(parts)


def noise_warning(name, gof, predicted=None) -> str | None:
    """The one-line warning of a flagged noise_misfit (None when not flagged); predicted:
    the calibration's stats["predicted_error"] (whether it was raised). A stated figure
    below the data's own scatter (gof["stated_below_data"]) is warned too, flagged or
    not (figure_warning)."""
    fig = figure_warning(name, gof)
    if not gof or not gof.get("flagged"):
        return fig
    pe = predicted or {}
    if pe.get("raised_to_achieved"):
        tail = (f"its predicted error is raised to that residual's part beyond the noise, "
                f"{pe['field_error_nT']:.0f} nT (from the coefficients' 1-sigma alone "
                f"{pe['field_error_from_sigma_nT']:.0f} nT)")
    elif pe.get("field_error_nT") is not None:
        tail = (f"its predicted error from the coefficients' 1-sigma, "
                f"{pe['field_error_nT']:.0f} nT, already covers the residual's part beyond "
                f"the noise ({gof['excess_field_error_nT']:.0f} nT)")
    else:
        tail = f"{gof['excess_field_error_nT']:.0f} nT of it the noise does not explain"
    what = "per axis against the reference vectors" if gof["kind"] == "vector" else \
        "of |B| against the reference magnitude"
    temp_cause = ("no temperature channel (temperature = false: a constant calibration, "
                  "so the board's drift over a thermal sweep cannot be modelled)"
                  if gof.get("no_temperature_channel")
                  else "a stuck or wrong temperature column")
    return (f"sensor '{name}': the fit leaves {gof['rms_residual_nT']:.0f} nT rms {what}, "
            f"beyond what the reading noise explains ({gof['explained_nT']:.0f} nT: "
            f"{gof['from']}; chi2/row {gof['chi2_per_row']:.3g} > {gof['limit']:.3g}). "
            "Likely causes: the reference carries more error than the sensor noise (an "
            f"attitude estimate, a field model, a disturbed lab), {temp_cause}, or an "
            "effect the model lacks (run `magcal trace` to find "
            f"it); the calibration is kept, {tail}" + (f". Also: {fig}" if fig else ""))


def figure_warning(name, gof) -> str | None:
    """The one-line warning of a stated noise figure below the readings' own scatter
    (noise_misfit's stated_below_data), None when there is none."""
    b = (gof or {}).get("stated_below_data")
    if not b:
        return None
    if b.get("figure_from") == NOISE_CATALOGUE:
        return (f"sensor '{name}': the part catalogue's typical noise ({b['stated_nT']:.0f} "
                f"nT per axis, quantisation included; the unit file states none) is below "
                f"the readings' own sample-to-sample scatter ({b['data_scatter_nT']:.0f} nT; "
                f"beyond the figure's uncertainty, {b['limit_nT']:.0f} nT): the readings are "
                "noisier than the typical part (a noisier unit, or interference changing "
                "from sample to sample), which explains a residual beyond the catalogue's "
                "noise; state the unit's noise_nT in the unit file; the fit's 1-sigma counts "
                "the noise up to that scatter")
    return (f"sensor '{name}': the unit's noise_nT ({b['stated_nT']:.0f} nT per axis, "
            f"quantisation included) is below the readings' own sample-to-sample scatter "
            f"({b['data_scatter_nT']:.0f} nT; beyond the figure's uncertainty, "
            f"{b['limit_nT']:.0f} nT): check noise_nT; the fit's 1-sigma counts the "
            "noise up to that scatter")


# A temperature column that stays on one reported value while another sensor of the same
# board frame sweeps: sensors of one board share its temperature to within their
# self-heating (a degree or two), so a sweep of more than STUCK_SWEEP_C there and not one
# reporting step here is a stuck (or wrongly mapped) column, not a steady board.
STUCK_SWEEP_C = 10.0


def stuck_temperatures(unit, temps) -> dict:
    """{sensor name: warning} for the case above. temps: {sensor name: [(file, temp_C of
    the usable samples)]} of the sensors that report a temperature."""
    frame = {s.name: s.frame for s in unit.sensors}
    out = {}
    for name, files in temps.items():
        for src, T in files:
            T = np.asarray(T, float)
            T = T[np.isfinite(T)]
            if len(T) < 2 or np.ptp(T) > 0:
                continue
            for other, ofiles in temps.items():
                if other == name or frame.get(other) != frame.get(name):
                    continue
                for osrc, OT in ofiles:
                    OT = np.asarray(OT, float)
                    OT = OT[np.isfinite(OT)]
                    if osrc == src and len(OT) and np.ptp(OT) > STUCK_SWEEP_C:
                        out[name] = (
                            f"sensor '{name}': its temperature column holds one value "
                            f"({T[0]:g} degC) over all of {src}, while sensor '{other}' on "
                            f"the same ({frame[name]}) board spans {OT.min():.1f}.."
                            f"{OT.max():.1f} degC there: a stuck or wrongly mapped "
                            f"temperature column (the fit took this sensor as one "
                            f"temperature); check {name}_temp_C")
                        break
                if name in out:
                    break
    return out
