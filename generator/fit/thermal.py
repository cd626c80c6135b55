"""Temperature-dependent calibration of every sensor of a unit (seed 000 eq. 5-7, seed 001).

Model (generator.fit.calibration): B_cal = M(T) (B~ - b(T)), b and M polynomials in
dT = clamp(T) - t_ref. What is known about the true field decides the fit:

* reference vectors (`ref_x/y/z_nT`, body frame): `reference_fit` (generator.fit.reference)
  minimises the calibrated-minus-reference residual of the model itself (per-file
  errors-in-variables weights; what the data do not determine is held at the prior: a
  ground calibration given with --prior, else the part's nominal). M is the full matrix
  to the body frame.
* only the magnitude (`ref_norm_nT` or the unit's `lab_field_nT`): ellipsoid fit
  (generator.fit.ellipsoid), M symmetric (known only up to a rotation).

Temperature dependence is fitted two ways and the better one on held-out data is kept:

* "segments" (seed 000 sec. 5): find the constant-temperature segments in the reported
  temperature itself (`find_segments`), group them across positions into temperature
  levels, calibrate each level at constant temperature, then fit a weighted polynomial to
  every b_i and m_ij over the levels;
* "joint": fit the polynomial model directly to all usable samples, ramps included
  (linear least squares for reference vectors, Levenberg-Marquardt when magnitudes enter).

Held-out comparison: leave-positions-out cross-validation when the files have static
positions, contiguous time blocks otherwise; the score is the RMS of the held-out vector
residual (per axis) where reference vectors exist, else of the magnitude residual. The
figures and the choice go into SensorCalibration.stats.

Module layout: segments.py (constant-temperature segments and levels), samples.py (the
samples of one sensor, temperature screen), reference.py (the reference-vector fit and its
observability), joint.py (the joint polynomial fit), levels.py (per-level fits and the
polynomial over levels, seed 001 and seed 000 methods), sanity.py (checks before writing);
this module chooses between them (model selection) and fits the unit.

Temperatures outside -80..150 degC or off their file's running median are rejected and
counted (samples.screen_temperatures); the calibrated range is that of the rest. A constant
(degree 0) calibration keeps that range (outside it the chain flags TEMP_EXTRAPOLATED) and
is valid at every temperature.

A reference-vector fit whose residual the sensor's noise and the reference's stated error
cannot explain is refused (fit.goodness: most often a reference in another frame). With
body rates and a SET/RESET sensor, the gyro compensation is decided before the fit and M
fitted to the compensated output (fit.setreset_fit). Magnitude-only fits hold what the
magnitudes do not determine at the prior (fit.ellipsoid_prior). With a prior (--prior, a
ground calibration; in-flight recalibration) a magnitude-only fit estimates the change ON
the prior (ellipsoid_prior.ellipsoid_fit_on_prior): an offset change of the degree the
held-out error picks, a symmetric scale change where the attitude coverage determines it;
the rotation and the prior's temperature terms are kept, and the calibrated range is the
union of the prior's and the data's.

Samples with non-zero magnetorquer current are not used (coil coupling is fitted
elsewhere); they are counted in stats.

The above is method "auto". Two more methods (`fit_unit(..., method=)`, FIT_METHODS):

* "analytic" (seed 001): per constant-temperature level the known-vector model with a
  rotation, h = Q P R B + b (generator.fit.analytic.fit_analytic_rotated), M = (Q P R)^-1;
  then the weighted polynomial over the levels as in "segments". Per level, stats keep
  k, e, R, b with 1-sigma and the residual of seed 001's model without R. Without
  reference vectors the sensor falls back to "auto" (stats say so);
* "ellipsoid" (seed 000): per level an ellipsoid fit of the magnitudes only, even where
  vectors exist (M symmetric, up to a rotation); the polynomial over the levels.

Public API: fit_unit(unit, telemetries, progress, method="auto") -> {name:
SensorCalibration}; fit_sensor(name, [FitData], degree=3, method="auto"); FIT_METHODS;
reference_fit(...); rotated_fit_M(...); find_segments(...), group_levels(...),
temperature_quantum(...), temperature_noise(...).
"""

from __future__ import annotations

import numpy as np

from generator.errors import InputError
from generator.fit.calibration import POLY_DEGREE, SensorCalibration
from generator.fit.goodness import (Calibrated, check_misfit, noise_misfit, noise_warning,
                                    stuck_temperatures, vector_misfit)
from generator.fit.joint import (DEGREE_STEP_C, _degree_for_span, _fit_joint, _make_cal, _pad,
                                 _residuals, _rms, _score)
from generator.fit.levels import (_fit_segments, _fit_sensor_analytic, _fit_sensor_ellipsoid,
                                  _level_fits, _poly_over_levels, _temperature_levels,
                                  rotated_fit_M)
from generator.fit.reference import MAX_REF_COND, T_REF_C, _powers, reference_fit
from generator.fit.samples import (CV_FOLDS, MAX_FIT_SAMPLES, FitData, _gather, _Samples,
                                   fit_data_from, record_all_samples_residual)
from generator.fit.segments import (Segment, find_segments, group_levels, temperature_noise,
                                    temperature_quantum)

#: The fit methods of fit_unit / fit_sensor (the CLI's `magcal fit --method`).
FIT_METHODS = ("auto", "analytic", "ellipsoid")
# Operating temperature of the parts (MMC5883MA, MPU-9255 datasheets: -40..85 degC).
OPERATING_C = (-40.0, 85.0)


# =======================================================================================
# Entry points
# =======================================================================================
def fit_sensor(name, datas, *, degree=POLY_DEGREE, progress=None,
               method="auto", prior=None, ref_floor_nT=None,
               max_samples=MAX_FIT_SAMPLES) -> SensorCalibration:
    """Temperature calibration of one sensor from all its files (list of FitData).

    degree: highest polynomial degree in temperature; the degree used is also limited to
    one per DEGREE_STEP_C of covered temperature span (a single temperature gives a
    constant calibration). Returns a SensorCalibration padded to POLY_DEGREE.

    method (FIT_METHODS):

    * "auto": reference vectors where the files carry them (held-out choice between the
      "joint" and "segments" temperature models), else magnitudes (ellipsoid). stats:
      files and exclusions, segments and levels found, the held-out comparison, the
      model chosen and why, and the fit RMS.
    * "analytic": seed 001 on the samples with reference vectors: per constant-
      temperature level the known-vector model with a rotation, h = Q P R B + b
      (fit_analytic_rotated), M = (Q P R)^-1 in the frame of the vectors; then a
      weighted polynomial of b and M over the levels. stats["segments"]["level_fits"]
      holds k, e, R, b with 1-sigma and the residual with and without R per level.
      Falls back to "auto" (stats["method_fallback"] says why) when no sample has a
      reference vector, or when a temperature-dependent fit finds fewer than 2 levels.
    * "ellipsoid": seed 000 from magnitudes only (|reference vector| where there is one),
      even where vectors exist: per level an ellipsoid fit, M symmetric (known only up to
      a rotation), then the polynomial over the levels.

    stats["method"] is the method used, stats["method_requested"] the one asked for.

    prior: reference.Prior of the coefficients (a ground calibration), used by the
    reference-vector fits for what the data do not determine; None: the part's nominal.
    A constant (degree 0) calibration keeps the data's temperature range as its calibrated
    range (the chain flags TEMP_EXTRAPOLATED outside it) and is valid at every
    temperature (stats["valid_outside_range"]; flight.coeffs.temp_margin_C).
    stats["observability"]: per coefficient data or prior, with 1-sigma;
    stats["predicted_error"]: field and angle error at the unit's field from the 1-sigma,
    raised to the residual the noise does not explain where fit.goodness.noise_misfit
    flags it (stats["noise_goodness"]; ref_floor_nT: per data the reference's stated |B|
    error, e.g. the field model's floor).

    max_samples: the most usable samples the fit takes (0: all; samples.MAX_FIT_SAMPLES,
    and why); above it a systematic random subsample, stats["files"][i]["fit_samples"] and
    a note say so, and stats["all_samples_residual_nT"] is the residual over every usable
    sample (samples._gather, samples.all_samples_residual).
    """
    if method not in FIT_METHODS:
        raise InputError(datas[0].source if datas else None,
                         f"fit: unknown method {method!r} (choose from "
                         f"{', '.join(FIT_METHODS)})")
    say = progress or (lambda msg: None)
    notes, per_file = [], []
    source = datas[0].source if datas else None
    S = _gather(name, datas, notes, per_file, max_samples, say)
    S.prior = prior
    try:
        return _fit_sensor_method(name, S, datas, degree, say, notes, per_file, source,
                                  method, ref_floor_nT)
    except InputError as err:
        if S.all_usable is None:          # every usable sample was in the fit
            raise
        # a fit refused on a subsample: the cap, not the file, may be what is short
        n_usable = sum(len(u[1]) for u in S.all_usable)
        raise InputError(err.path, f"{err.message} (sensor '{name}' was fitted on a "
                                   f"subsample of {S.n:,} of its {n_usable:,} usable "
                                   f"samples, --max-samples {max_samples}: a larger cap, "
                                   "or 0 for every sample, gives the fit more)",
                         line=err.line, column=err.column) from None


def _fit_sensor_method(name, S, datas, degree, say, notes, per_file, source, method,
                       ref_floor_nT):
    """fit_sensor's method dispatch on the gathered samples S."""
    fallback = None
    if method == "analytic":
        if S.is_vec.any():
            cal, fallback = _fit_sensor_analytic(name, S, datas, degree, say, notes,
                                                 per_file, source)
            if cal is not None:
                return _with_method(cal, "analytic", "analytic", S, ref_floor_nT)
        else:
            fallback = ("no file carries reference vectors for this sensor: the known-vector "
                        "method needs them; fitted with auto")
        notes.append(f"analytic method not used: {fallback}")
        say(f"{name}: analytic method not used ({fallback})")
    elif method == "ellipsoid":
        cal = _fit_sensor_ellipsoid(name, S, datas, degree, say, notes, per_file, source)
        return _with_method(cal, "ellipsoid", "ellipsoid", S, ref_floor_nT)
    cal = _fit_sensor_auto(name, S, datas, degree, say, notes, per_file, source)
    if fallback:
        cal.stats["method_fallback"] = fallback
    return _with_method(cal, method, "auto", S, ref_floor_nT)


def _with_method(cal, requested, used, S, ref_floor_nT=None):
    cal.stats["method_requested"] = requested
    cal.stats["method"] = used
    _finish(cal, S, ref_floor_nT)
    record_all_samples_residual(cal, S)
    return cal


def _finish(cal, S, ref_floor_nT=None):
    """Temperature range of a constant model, observability, predicted error (fit_sensor)."""
    st = cal.stats
    if np.all(cal.b_poly_nT[1:] == 0) and np.all(cal.M_poly[1:] == 0):
        # the calibrated range stays the data's (the chain flags TEMP_EXTRAPOLATED outside
        # it); the model is valid at every temperature (flight.coeffs.temp_margin_C gives
        # it the largest margin: st["valid_outside_range"])
        st["valid_outside_range"] = True
        st["temperature_model"] = (
            "constant (degree 0): temperature-independent, valid (usable) at every "
            f"temperature; calibrated (measured) over {cal.t_min_C:.1f}..{cal.t_max_C:.1f} "
            "degC, outside it flagged TEMP_EXTRAPOLATED; its error away from the data's "
            "temperatures is the sensor's uncalibrated drift")
    else:
        st["temperature_model"] = (f"polynomial in temperature, valid (not clamped) over the "
                                   f"data's range {cal.t_min_C:.1f}..{cal.t_max_C:.1f} degC")
    st["calibrated_range_C"] = [float(cal.t_min_C), float(cal.t_max_C)]
    st["observability"] = cal.observability or {
        "note": "every coefficient from the data (this method has no prior"
                + ("; the --prior given is used only by the constant and per-level fits"
                   if S.prior is not None else "") + "); 1-sigma in uncertainty_1sigma"}
    ev = Calibrated(cal, S)        # the calibration on its samples, once for both tests
    noise_gof = noise_misfit(cal, S, ref_floor_nT, ev)
    if noise_gof is not None:
        st["noise_goodness"] = noise_gof
    st["predicted_error"] = predicted_error(cal, S.norm[np.isfinite(S.norm)], noise_gof)
    gof = vector_misfit(cal, S, ev)
    if gof is not None:
        st["goodness_of_fit"] = gof
    st["extrapolation"] = extrapolation_growth(cal, S.norm[np.isfinite(S.norm)])
    unfitted = unfitted_degree_sigma(cal)
    if unfitted:
        st["observability"] = dict(st["observability"], temperature_terms=unfitted)


def unfitted_degree_sigma(cal) -> str | None:
    """The polynomial degrees the fit did not determine (above the degree fitted: a
    constant model's temperature terms, or a fit of lower degree padded to POLY_DEGREE)
    are 0 by construction, not a measurement of a zero drift: their 1-sigma is the part's
    prior one (reference.PART_PRIOR_SIGMA), not 0. Sets it in place; returns the note
    for stats["observability"]["temperature_terms"] (None when every degree was fitted).
    predicted_error and extrapolation_growth are taken before (they treat those degrees
    themselves)."""
    from generator.fit.reference import PART_PRIOR_SIGMA

    if cal.b_poly_sigma_nT is None or cal.M_poly_sigma is None:
        return None
    K = cal.b_poly_nT.shape[0]
    fitted = [k for k in range(K) if np.any(cal.b_poly_sigma_nT[k] > 0)
              or np.any(cal.M_poly_sigma[k] > 0)]
    top = max(fitted) if fitted else -1
    rest = [k for k in range(top + 1, K)
            if np.all(cal.b_poly_nT[k] == 0) and np.all(cal.M_poly[k] == 0)]
    if not rest:
        return None
    prior = PART_PRIOR_SIGMA["default"]
    for k in rest:
        cal.b_poly_sigma_nT[k] = prior["b_nT"][k]
        cal.M_poly_sigma[k] = prior["M"][k]
    return (f"degree(s) {', '.join(map(str, rest))} not fitted (the model is of degree "
            f"{top}): value 0, 1-sigma the part's prior (not a measured zero drift)")


def extrapolation_growth(cal, field_nT) -> dict:
    """How fast the calibration's error grows with the temperature's distance outside the
    calibrated range, nT per degC, at the unit's field (median reference magnitude).

    Beyond an end the chain holds b and M at their values there (the clamp), while the
    sensor goes on drifting; its drift is taken as the fitted polynomial's slope at that
    end plus the slope's 1-sigma (from the coefficients' 1-sigma, correlations ignored).
    A term the fit did not determine (a constant, degree 0, model has no slope at all)
    takes the part's prior 1-sigma for the slope (reference.PART_PRIOR_SIGMA, degree 1):
    not knowing the drift is not a drift of zero. Per end, for a field in a random
    direction (as predicted_error): g^2 = sum_ij (M'_ij)^2 |B|^2 / 3 + | |M| |b'| |^2,
    with M' = dM/dT, b' = db/dT, each taken as |slope| + 1-sigma and |M| elementwise (an
    upper bound of |M b'|); the larger end is returned as growth_nT_per_C."""
    from generator.fit.reference import PART_PRIOR_SIGMA

    F = float(np.median(field_nT)) if len(field_nT) else None
    if not F:
        return {"note": "no reference magnitude: no growth estimate"}
    K = cal.b_poly_nT.shape[0]
    deg = int(max([k for k in range(K) if np.any(cal.b_poly_nT[k] != 0)
                   or np.any(cal.M_poly[k] != 0)] + [0]))
    prior = PART_PRIOR_SIGMA["default"]
    bs = cal.b_poly_sigma_nT if cal.b_poly_sigma_nT is not None else np.zeros_like(
        cal.b_poly_nT)
    Ms = cal.M_poly_sigma if cal.M_poly_sigma is not None else np.zeros_like(cal.M_poly)
    ends = {}
    for where, T in (("low", cal.t_min_C), ("high", cal.t_max_C)):
        d = float(T) - cal.t_ref_C
        dk = np.array([k * d ** (k - 1) if k else 0.0 for k in range(K)])   # d(dT^k)/dT
        db = np.einsum("k,ki->i", dk, cal.b_poly_nT)
        dM = np.einsum("k,kij->ij", dk, cal.M_poly)
        sdb = np.sqrt(np.einsum("k,ki->i", dk ** 2, bs ** 2))
        sdM = np.sqrt(np.einsum("k,kij->ij", dk ** 2, Ms ** 2))
        if deg == 0:    # no slope fitted: the part's prior 1-sigma of the slope
            sdb = np.full(3, float(prior["b_nT"][1]))
            sdM = np.full((3, 3), float(prior["M"][1]))
        gb, gM = np.abs(db) + sdb, np.abs(dM) + sdM
        M = cal.M_at(T)
        g = float(np.sqrt(np.sum(gM ** 2) * F ** 2 / 3.0 + np.sum((np.abs(M) @ gb) ** 2)))
        ends[where] = g
    return {"growth_nT_per_C": max(ends.values()), "per_end_nT_per_C": ends,
            "at_field_nT": F,
            "from": ("slope of the fitted polynomial at the range's ends plus its 1-sigma"
                     if deg else "the part's prior 1-sigma of the slope (constant model)")}


def predicted_error(cal, field_nT, noise_gof=None) -> dict:
    """Calibration error expected from the coefficients' 1-sigma at the unit's field
    (median of the reference magnitudes), for a field in a random direction:
    per body axis var_i = sum_j sigma(M_ij)^2 |B|^2 / 3 + sum_j M_ij^2 sigma(b_j)^2, at
    the worst of t_ref and the ends of the calibrated range (sigma(T)^2 = sum_k sigma_k^2
    dT^2k); correlations between coefficients ignored. Field error: the vector's RMS;
    angle error: its part across the field, sqrt(2/3) of it, over |B|.

    The one definition of the calibration's predicted error (stats["predicted_error"],
    flight.coeffs.temp_margin_C, the report). It is never below what the fit achieved on
    its own data: noise_gof (fit.goodness.noise_misfit) gives the residual the reading
    noise does not explain (excess_field_error_nT; the noise itself is not an error of the
    calibration). Where that test flags the residual and the excess is larger than the
    1-sigma figure, field_error_nT and angle_error_deg are the excess (conservatively all
    of it taken as the calibration's), "raised_to_achieved" says so, and the 1-sigma
    figure stays as field_error_from_sigma_nT / angle_error_from_sigma_deg. Where the test
    does not flag, the excess is consistent with 0 (the noise explains the residual) and
    the 1-sigma figure stands; "achieved" holds the residual and what explains it."""
    out = _sigma_error(cal, field_nT)
    if noise_gof is None or "field_error_nT" not in out:
        return out
    F = out["at_field_nT"]
    ex = float(noise_gof["excess_field_error_nT"])
    out["field_error_from_sigma_nT"] = out["field_error_nT"]
    out["angle_error_from_sigma_deg"] = out["angle_error_deg"]
    out["achieved"] = {k: noise_gof[k] for k in ("kind", "rms_residual_nT", "explained_nT",
                                                 "excess_field_error_nT", "flagged")}
    out["raised_to_achieved"] = bool(noise_gof["flagged"] and ex > out["field_error_nT"])
    if out["raised_to_achieved"]:
        tot = out["field_error_nT"]
        out["field_error_per_axis_nT"] = [float(a * ex / tot) if tot > 0
                                          else ex / np.sqrt(3.0)
                                          for a in out["field_error_per_axis_nT"]]
        out["field_error_nT"] = ex
        out["angle_error_deg"] = float(np.degrees(np.sqrt(2.0 / 3.0) * ex / F))
        out["from"] = ("the fit's own residual beyond the reading noise (larger than the "
                       "coefficients' 1-sigma figure, field_error_from_sigma_nT)")
    return out


def _sigma_error(cal, field_nT) -> dict:
    """predicted_error from the coefficients' 1-sigma alone."""
    if cal.b_poly_sigma_nT is None or cal.M_poly_sigma is None or len(field_nT) == 0:
        return {"note": "no 1-sigma for this calibration"}
    F = float(np.median(field_nT))
    worst = None
    for T in sorted({cal.t_ref_C, cal.t_min_C, cal.t_max_C}):
        d = np.clip(T, cal.t_min_C, cal.t_max_C) - cal.t_ref_C
        pw = d ** (2 * np.arange(cal.b_poly_nT.shape[0]))
        sb2 = np.einsum("k,ki->i", pw, cal.b_poly_sigma_nT ** 2)
        sM2 = np.einsum("k,kij->ij", pw, cal.M_poly_sigma ** 2)
        M = cal.M_at(T)
        var = sM2.sum(axis=1) * F ** 2 / 3.0 + (M ** 2) @ sb2
        tot = float(np.sqrt(var.sum()))
        if worst is None or tot > worst[1]:
            worst = (T, tot, np.sqrt(var))
    T, tot, per_axis = worst
    return {"at_field_nT": F, "at_temp_C": float(T), "field_error_nT": tot,
            "field_error_per_axis_nT": per_axis.tolist(),
            "angle_error_deg": float(np.degrees(np.sqrt(2.0 / 3.0) * tot / F)),
            "from": "the coefficients' 1-sigma (correlations ignored), random field direction"}


def _fit_sensor_auto(name, S, datas, degree, say, notes, per_file, source):
    """The "auto" method (see fit_sensor)."""
    body_frame = bool(S.is_vec.any())
    t_lo, t_hi = float(S.T.min()), float(S.T.max())
    span = t_hi - t_lo
    deg = min(degree, _degree_for_span(span))
    stats = {"files": per_file, "samples_used": int(S.n),
             "samples_vector": int(S.is_vec.sum()),
             "samples_magnitude": int((~S.is_vec).sum()),
             "temperature_range_C": [t_lo, t_hi], "degree": int(deg), "notes": notes}
    if body_frame and (~S.is_vec).any():
        notes.append("magnitude-only samples enter through |B| residuals; M stays in the "
                     "frame of the reference vectors")
    say(f"{name}: {S.n} samples, {t_lo:.1f}..{t_hi:.1f} degC, "
        f"{'reference vectors' if body_frame else 'magnitude only'}")

    if not body_frame and S.prior is not None:
        return _fit_on_prior(name, S, deg, t_lo, t_hi, source, stats, say)

    # ---- temperature levels for the segments method
    levels, stats["segments"] = _temperature_levels(S, datas, deg)

    if deg == 0:
        cal = _fit_joint(name, S, body_frame, 0, t_lo, t_hi, source)
        stats["chosen"] = "constant"
        stats["why"] = ("degree 0 requested" if degree == 0 else
                        f"reported temperature spans {span:.1f} degC: a constant calibration "
                        f"(one polynomial degree per {DEGREE_STEP_C:g} degC of span)")
        stats["fit"] = _score(S, cal)
        cal.stats = stats
        return cal

    seg_ok = len(levels) >= 2
    if not seg_ok:
        stats["segments"]["unavailable"] = (f"{len(levels)} constant-temperature level(s) "
                                            "found; the segments method needs 2 or more")
    # ---- held-out comparison
    S.temperature_index()       # shared by the folds' test sets and the final checks
    groups, group_no = np.unique(S.group, return_inverse=True)
    k = min(CV_FOLDS, len(groups))
    methods = ["joint"] + (["segments"] if seg_ok else [])
    held = {m: {"vec": [], "norm": [], "failed": []} for m in methods}
    if seg_ok and k >= 2:
        fold = np.ravel(group_no) % k        # the i-th group (sorted) in fold i mod k
        for f in range(k):
            train = fold != f
            Str, Ste = S.subset(train), S.subset(~train)
            lo, hi = float(Str.T.min()), float(Str.T.max())
            dgf = min(deg, _degree_for_span(hi - lo))
            for m in methods:
                try:
                    if m == "joint":
                        c = _fit_joint(name, Str, body_frame, dgf, lo, hi, source,
                                       uncertainty=False)     # only its coefficients
                    else:
                        c, _, _ = _fit_segments(name, S, levels, body_frame, dgf, lo, hi,
                                                source, mask=train)
                except InputError as e:
                    held[m]["failed"].append(f"fold {f + 1}: {e.message}")
                    continue
                rv, rn = _residuals(c, Ste)
                held[m]["vec"].append(rv)
                held[m]["norm"].append(rn)
        say(f"{name}: held-out comparison over {k} folds done")
    kinds = sorted({f["holdout_groups"] for f in per_file})
    scheme = "leave-positions-out" if kinds == ["static positions"] else \
        "held-out " + " and ".join(kinds)
    holdout = {"scheme": f"{scheme}, {k} folds",
               "metric": "vector RMS per axis" if body_frame else "|B| RMS"}
    scores = {}
    for m in methods:
        h = held[m]
        entry = {"failed_folds": h["failed"]}
        if h["norm"] and not h["failed"]:
            entry["rms_vector_nT"] = _rms(np.concatenate(h["vec"])) if body_frame else None
            entry["rms_norm_nT"] = _rms(np.concatenate(h["norm"]))
            scores[m] = entry["rms_vector_nT"] if body_frame else entry["rms_norm_nT"]
        holdout[m] = entry
    if scores:
        chosen = min(scores, key=scores.get)
        why = "smaller held-out error: " + ", ".join(f"{m} {v:.2f} nT" for m, v in
                                                      scores.items())
    else:
        chosen = "joint"
        why = ("segments method not available" if not seg_ok else
               "held-out comparison not possible") + "; joint fit of all samples"
    stats["holdout"] = holdout
    stats["chosen"] = chosen
    stats["why"] = why

    # ---- final fit on everything with the chosen method
    if chosen == "segments":
        cal, fits, dropped = _fit_segments(name, S, levels, body_frame, deg, t_lo, t_hi,
                                           source)
        stats["segments"]["level_fits"] = [
            {"temp_C": f[0], "samples": int(f[5]), "b_nT": [float(v) for v in f[1]],
             "b_sigma_nT": [float(v) for v in f[3]]} for f in fits]
        if dropped:
            notes.extend(dropped)
    else:
        cal = _fit_joint(name, S, body_frame, deg, t_lo, t_hi, source)
    stats["fit"] = _score(S, cal)
    say(f"{name}: {cal.method}; held-out winner {chosen}")
    cal.stats = stats
    return cal


def _fit_on_prior(name, S, deg, t_lo, t_hi, source, stats, say):
    """Magnitudes only with a prior (in-flight recalibration against a ground calibration):
    ellipsoid_prior.ellipsoid_fit_on_prior, what the data determine on top of the prior
    (offset change of the degree the data's span supports, symmetric scale change where
    the attitude coverage determines it), the rotation and the prior's other temperature
    terms held. The calibrated range is the union of the prior's and the data's: the
    prior's terms remain valid over its range."""
    from generator.fit.ellipsoid_prior import ellipsoid_fit_on_prior

    # the offset change's degree: held-out |B| error over the file's contiguous time
    # blocks (the orbital thermal cycle repeats, so each block spans the data's range),
    # among degrees 0..deg (deg: one per DEGREE_STEP_C of span); a failed fold rules
    # that degree out
    groups, group_no = np.unique(S.group, return_inverse=True)
    k = min(CV_FOLDS, len(groups))
    scores = {}
    if deg > 0 and k >= 2:
        fold = np.ravel(group_no) % k        # the i-th group (sorted) in fold i mod k
        for d in range(deg + 1):
            res = []
            for f in range(k):
                tr, te = fold != f, fold == f
                try:
                    b, M, *_ = ellipsoid_fit_on_prior(S.x[tr], S.norm[tr], S.T[tr], S.prior,
                                                      d, source=source, noise_nT=S.noise_nT)
                except InputError:
                    res = None
                    break
                c = _make_cal(name, b, M, t_lo, t_hi, False, "fold")
                res.append(np.linalg.norm(c.apply64(S.x[te], S.T[te]), axis=1) - S.norm[te])
            if res:
                scores[d] = _rms(np.concatenate(res))
        if scores:
            deg = min(scores, key=scores.get)
            stats["holdout"] = {"scheme": f"contiguous time blocks, {k} folds",
                                "metric": "|B| RMS",
                                "offset_change_degree_nT": {str(d): v for d, v in
                                                            scores.items()}}
    b, M, bs, Ms, info = ellipsoid_fit_on_prior(S.x, S.norm, S.T, S.prior, deg,
                                                source=source, noise_nT=S.noise_nT)
    lo, hi = t_lo, t_hi
    if S.prior.t_range_C is not None:
        lo, hi = min(lo, S.prior.t_range_C[0]), max(hi, S.prior.t_range_C[1])
    cal = _make_cal(name, b, M, lo, hi, False, f"ellipsoid on the prior, offset change of "
                    f"degree {deg}", bs, Ms)
    cal.observability = info["observability"]
    # the model's degree (trace reads it: model.declared_degree) is the prior's with the
    # change's: the prior's temperature terms are part of the calibration
    nz = [j for j in range(b.shape[0]) if np.any(b[j] != 0) or np.any(M[j] != 0)]
    stats["degree"] = int(max([deg] + nz))
    stats["offset_change_degree"] = int(deg)
    stats["chosen"] = "on the prior"
    stats["why"] = (f"magnitudes only with a prior ({S.prior.source}): the change from it "
                    f"is fitted (offset of degree {deg}: "
                    + ("smallest held-out error" if scores else
                       f"the data's {t_hi - t_lo:.1f} degC span")
                    + "), the rotation and the prior's other temperature terms held; "
                    "calibrated range the union of the prior's and the data's")
    stats["fit"] = _score(S, cal)
    say(f"{name}: recalibrated on the prior ({cal.method})")
    cal.stats = stats
    return cal


def _import_for_sensor_fits() -> None:
    """The module a sensor's fit imports lazily (scipy.special: the misfit and noise
    checks' chi2 quantile, fit.special), imported once before the sensor fits are forked
    rather than once in every child."""
    import scipy.special  # noqa: F401


def fit_unit(unit, telemetries, progress=None, method="auto", prior=None,
             accept_misfit=False, max_samples=MAX_FIT_SAMPLES, beside=None):
    """Fit every sensor of the unit from all telemetry files jointly.

    Each file contributes what it carries: reference vectors -> reference-vector rows,
    else ref_norm_nT (or the unit's lab_field_nT) -> magnitude rows. method: one of
    FIT_METHODS, see fit_sensor. prior: {sensor name: reference.Prior} (a ground
    calibration) or None. Every calibration passes the sanity checks (fit.sanity) before
    it is returned; stats["sanity"] holds the figures. A reference-vector fit whose
    residual the noise and the reference's stated error cannot explain (fit.goodness) is
    refused, unless accept_misfit (then stats["goodness_of_fit"] says so). stats["set_reset_compensation"]:
    whether the chain should compensate the SET/RESET rotation error with the gyro
    (fit.setreset.compensation_decision). max_samples: per sensor, see fit_sensor.
    Returns {sensor name: SensorCalibration}.
    Raises InputError when a sensor cannot be fitted, a calibration is not physical, or
    the method is unknown.

    beside: a callable of no argument, independent of the fits (the caller's own analysis
    of the same files, e.g. pipeline.fit's settling warnings), run as one more item after
    the sensors in the forked hand-out: a child that has finished its sensors takes it
    while the other still fits (five sensors over two children leave one idle for a
    sensor's time). Returns ({sensor name: SensorCalibration}, beside()) then; beside's
    InputError comes after the sensors', as if it ran after fit_unit.
    """
    from generator.fit.sanity import check_calibration
    from generator.fit.setreset import DEFAULT_FIELD_NT, compensation_decision
    from generator.fit.setreset_fit import _field_of, _rates_of, compensate_references
    from contextlib import closing

    from generator.forked import forked_map
    from generator.io import telemetry_csv as _telemetry
    if method not in FIT_METHODS:
        raise InputError(unit.path, f"fit: unknown method {method!r} (choose from "
                                    f"{', '.join(FIT_METHODS)})")
    if not telemetries:
        raise InputError(unit.path, "fit: no telemetry files given")
    pre = [(_telemetry.preprocess(tel, unit), tel) for tel in telemetries]

    def one_sensor(s):
        """Sensor s's calibration, checked: (its progress lines, cal, its usable
        temperatures per file or None). The sensors are independent: they run in forked
        children (generator.forked), their lines buffered and printed here in sensor order."""
        lines = []
        say = lines.append
        used = [(tel, data[s.name]) for data, tel in pre if s.name in data]
        datas = [fit_data_from(tel, sd, unit) for tel, sd in used]
        if not datas:
            raise InputError(telemetries[0].path, f"fit: no file has data of sensor '{s.name}'")
        # SET/RESET gyro compensation is decided BEFORE the fit, and where it is on, M is
        # fitted to what the chain will output (compensated): otherwise, under a steady
        # turn, M absorbs the rotation error and the chain removes it a second time
        # (setreset_fit.compensate_references)
        rates = [_rates_of(tel) for tel, _ in used]
        sr = compensation_decision(
            s, np.concatenate([r for r in rates if r is not None])
            if any(r is not None for r in rates) else None,
            float(_field_of(datas) or unit.lab_field_nT or DEFAULT_FIELD_NT),
            datas[0].noise_nT)
        if sr.get("enabled"):
            datas = compensate_references(datas, rates, float(sr["sr_comp_s_per_deg"]))
            sr["fit_on_compensated"] = True
            sr["why"] += ("; M is fitted to the compensated chain output (the reference "
                          "vectors carry the rotation error the chain then adds back)")
        # the reference's own stated |B| error per file (the field model's floor, ICD 4)
        floors = [(tel.meta.get("field_reference") or {}).get("model_floor_nT")
                  for tel, _ in used]
        cal = fit_sensor(s.name, datas, progress=say, method=method,
                         prior=(prior or {}).get(s.name), ref_floor_nT=floors,
                         max_samples=max_samples)
        vec_files = [d.source for d in datas if d.ref_body_nT is not None]
        cal.stats["sanity"] = check_calibration(cal, s, vec_files[0] if vec_files
                                                else datas[0].source, unit=unit,
                                                prior=(prior or {}).get(s.name))
        noisy = noise_warning(s.name, cal.stats.get("noise_goodness"),
                              cal.stats.get("predicted_error"))
        if noisy:     # a warning, not a refusal (fit.goodness): the reference may be worse
            cal.stats["sanity"]["warnings"].append(noisy)
        misfit = check_misfit(s.name, cal.stats.get("goodness_of_fit"),
                              vec_files[0] if vec_files else datas[0].source,
                              accept=accept_misfit)
        if misfit:      # accepted (--accept-misfit): a warning of the fit, in the report
            cal.stats["sanity"]["warnings"].append(
                f"misfit accepted with --accept-misfit, the calibration may be wrong: {misfit}")
        held = [p["name"] for p in cal.observability.get("parameters", [])
                if p["source"] == "prior"]
        if held:
            say(f"{s.name}: held at the prior ({cal.observability.get('prior_source')}; "
                "data share of the information in brackets): " + ", ".join(
                    f"{p['name']} ({100 * p['data_fraction']:.0f} %)"
                    for p in cal.observability.get("parameters", []) if p["source"] == "prior"))
        for w in cal.stats["sanity"]["warnings"]:
            say(f"WARNING: {w}")
            cal.stats.setdefault("notes", []).append(w)
        cal.stats["set_reset_compensation"] = sr
        return lines, cal, ([(d.source, d.temp_C[d.usable]) for d in datas]
                            if s.temperature else None)

    out, temps = {}, {}
    items = list(unit.sensors) + ([None] if beside is not None else [])

    def one_item(s):
        return beside() if s is None else one_sensor(s)

    # closing: children still running when this loop stops early are killed and reaped now
    # on demand: a child that finished a cheap sensor (no held-out folds, e.g. a boom
    # sensor without temperature) takes the next one, not the share dealt to it
    with closing(forked_map(one_item, items, keep=(InputError,),
                            before_fork=_import_for_sensor_fits, on_demand=True)) as results:
        for s, r in zip(items, results):
            if s is None:
                beside_result = r
                continue
            lines, cal, t = r
            for line in lines:
                if progress:
                    progress(line)
            out[s.name] = cal
            if t is not None:
                temps[s.name] = t
    for n, w in stuck_temperatures(unit, temps).items():
        out[n].stats["sanity"]["warnings"].append(w)
        out[n].stats.setdefault("notes", []).append(w)
        (progress or (lambda m: None))(f"WARNING: {w}")
    return out if beside is None else (out, beside_result)


# The names other stages import from here (the public API and the shared helpers of the
# modules this one was split into).
__all__ = ["FIT_METHODS", "fit_unit", "fit_sensor", "FitData", "fit_data_from", "reference_fit",
           "rotated_fit_M", "find_segments", "group_levels", "temperature_quantum",
           "temperature_noise", "Segment", "T_REF_C", "DEGREE_STEP_C", "MAX_REF_COND",
           "CV_FOLDS", "_powers", "_gather", "_Samples", "_make_cal", "_pad", "_level_fits",
           "_poly_over_levels"]
