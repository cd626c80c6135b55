"""Temperature-dependent calibration of every sensor of a unit (seed 000 eq. 5-7, seed 001).

Model (generator.fit.calibration): B_cal = M(T) (B~ - b(T)), b and M polynomials in
dT = clamp(T) - t_ref. What is known about the true field decides the fit:

* reference vectors (`ref_x/y/z_nT`, body frame): `reference_fit`. The measurement model
  B~ = W(T) B_ref + b(T) is linear in the coefficients of W and b, so it is solved by
  ordinary least squares with the noise where it is, in B~; then M(T) = W(T)^-1 is fitted
  by a polynomial of the same degree (truncation ~(|W2| dT^2)^2 + (|W1| dT)^4, about 1e-6
  or 0.05 nT for parts like the SamSat ones, far below the noise). M is then the full
  matrix to the body frame.
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
from generator.fit.joint import (DEGREE_STEP_C, _degree_for_span, _fit_joint, _make_cal, _pad,
                                 _residuals, _rms, _score)
from generator.fit.levels import (_fit_segments, _fit_sensor_analytic, _fit_sensor_ellipsoid,
                                  _level_fits, _poly_over_levels, _temperature_levels,
                                  rotated_fit_M)
from generator.fit.reference import MAX_REF_COND, T_REF_C, _powers, reference_fit
from generator.fit.samples import CV_FOLDS, FitData, _gather, _Samples, fit_data_from
from generator.fit.segments import (Segment, find_segments, group_levels, temperature_noise,
                                    temperature_quantum)

#: The fit methods of fit_unit / fit_sensor (the CLI's `magcal fit --method`).
FIT_METHODS = ("auto", "analytic", "ellipsoid")


# =======================================================================================
# Entry points
# =======================================================================================
def fit_sensor(name, datas, *, degree=POLY_DEGREE, progress=None,
               method="auto") -> SensorCalibration:
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
    """
    if method not in FIT_METHODS:
        raise InputError(datas[0].source if datas else None,
                         f"fit: unknown method {method!r} (choose from "
                         f"{', '.join(FIT_METHODS)})")
    say = progress or (lambda msg: None)
    notes, per_file = [], []
    source = datas[0].source if datas else None
    S = _gather(name, datas, notes, per_file)
    fallback = None
    if method == "analytic":
        if S.is_vec.any():
            cal, fallback = _fit_sensor_analytic(name, S, datas, degree, say, notes,
                                                 per_file, source)
            if cal is not None:
                return _with_method(cal, "analytic", "analytic")
        else:
            fallback = ("no file carries reference vectors for this sensor: the known-vector "
                        "method needs them; fitted with auto")
        notes.append(f"analytic method not used: {fallback}")
        say(f"{name}: analytic method not used ({fallback})")
    elif method == "ellipsoid":
        cal = _fit_sensor_ellipsoid(name, S, datas, degree, say, notes, per_file, source)
        return _with_method(cal, "ellipsoid", "ellipsoid")
    cal = _fit_sensor_auto(name, S, datas, degree, say, notes, per_file, source)
    if fallback:
        cal.stats["method_fallback"] = fallback
    return _with_method(cal, method, "auto")



def _with_method(cal, requested, used):
    cal.stats["method_requested"] = requested
    cal.stats["method"] = used
    return cal


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
    groups = np.unique(S.group)
    k = min(CV_FOLDS, len(groups))
    methods = ["joint"] + (["segments"] if seg_ok else [])
    held = {m: {"vec": [], "norm": [], "failed": []} for m in methods}
    if seg_ok and k >= 2:
        fold_of = {g: i % k for i, g in enumerate(groups)}
        fold = np.array([fold_of[g] for g in S.group])
        for f in range(k):
            train = fold != f
            Str, Ste = S.subset(train), S.subset(~train)
            lo, hi = float(Str.T.min()), float(Str.T.max())
            dgf = min(deg, _degree_for_span(hi - lo))
            for m in methods:
                try:
                    if m == "joint":
                        c = _fit_joint(name, Str, body_frame, dgf, lo, hi, source)
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


def fit_unit(unit, telemetries, progress=None, method="auto") -> dict:
    """Fit every sensor of the unit from all telemetry files jointly.

    Each file contributes what it carries: reference vectors -> reference-vector rows,
    else ref_norm_nT (or the unit's lab_field_nT) -> magnitude rows. method: one of
    FIT_METHODS, see fit_sensor. Returns {sensor name: SensorCalibration}. Raises
    InputError when a sensor cannot be fitted or the method is unknown.
    """
    from generator.io import telemetry_csv as _telemetry
    if method not in FIT_METHODS:
        raise InputError(unit.path, f"fit: unknown method {method!r} (choose from "
                                    f"{', '.join(FIT_METHODS)})")
    if not telemetries:
        raise InputError(unit.path, "fit: no telemetry files given")
    pre = [(_telemetry.preprocess(tel, unit), tel) for tel in telemetries]
    out = {}
    for s in unit.sensors:
        datas = [fit_data_from(tel, data[s.name], unit) for data, tel in pre if s.name in data]
        if not datas:
            raise InputError(telemetries[0].path, f"fit: no file has data of sensor '{s.name}'")
        out[s.name] = fit_sensor(s.name, datas, progress=progress, method=method)
    return out


# The names other stages import from here (the public API and the shared helpers of the
# modules this one was split into).
__all__ = ["FIT_METHODS", "fit_unit", "fit_sensor", "FitData", "fit_data_from", "reference_fit",
           "rotated_fit_M", "find_segments", "group_levels", "temperature_quantum",
           "temperature_noise", "Segment", "T_REF_C", "DEGREE_STEP_C", "MAX_REF_COND",
           "CV_FOLDS", "_powers", "_gather", "_Samples", "_make_cal", "_pad", "_level_fits",
           "_poly_over_levels"]
