"""Sanity of a calibration before it is written (exit 2 with the likely cause if not).

* det M(T) > 0 over the calibrated range: a magnetometer calibration is a proper linear
  map; a negative determinant is a reflection, i.e. the reference vectors are mirrored
  against the readings (two reference columns swapped, one negated, or a wrong axis
  mapping in the unit file). It is never a property of a real sensor, unless the data do
  not determine its sign: a negative det within DET_SIGMAS of its own 1-sigma of 0
  (det_sigma; a column of M that a barely moving reading axis leaves free) is named as
  that, not as swapped columns (fit.reference holds such weak directions at the prior,
  and calls a linear start mirrored only where the determined directions make it so,
  so this too is a guard). A det near 0
  (|det M| < (1 - 3 s)^3, 0.343 for s = 0.1, s below) is not a reflection but a degenerate
  fit: M not determined by the data (observability in generator.fit.reference holds such
  directions at the prior, so this is a guard); the message says "degenerate".
* cond M(T) plausible for the part: with the prior's 1-sigma s on every element of M
  (generator.fit.reference.PART_PRIOR_SIGMA, 0.1), singular values within 1 +- 3 s, so
  cond <= (1 + 3 s) / (1 - 3 s) (1.86 for s = 0.1). Beyond it the fit has most likely
  absorbed something that is not the sensor (a wrong reference, a magnet next to it);
  but strong soft iron can be real, so this one is a flag (stats["sanity"]["warnings"]
  and the fit's progress), not an error.
* the scale of M (|det M|^(1/3), the geometric mean of its singular values) within the
  same 1 +- 3 s: a scale far outside is readings in another unit than the unit file says
  (counts declared as nT, mG data declared as uT: factors below the 20 of
  fit.scale_check's input check). A flag, like the condition number.
* offsets b(T) within the part's range: an offset larger than the full scale of the raw
  output cannot come from a sensor that still reads the field.
* H orthogonal with det +1 (boom alignment): |H^T H - I| < 1e-6.
* the rotation part of M (polar decomposition M = R S, R a proper rotation, S symmetric
  positive definite) within the sensor's mounting tolerance: a reference rotated against
  the sensor frame is absorbed into M unseen (M = R M_true; one campaign cannot tell a
  rotated reference from a rotated mounting). A flag, not an error (it may be a real
  mounting rotation): warned when the angle exceeds the tolerance by more than 3 sigma
  of its estimate (from M's 1-sigma); the rotation stays in M. The tolerance is the unit
  file's [[sensor]] key mounting_tolerance_deg (an optional extension key, kept in
  Unit.extra like every key the ICD does not name), else MOUNTING_TOLERANCE_DEG. With a
  ground calibration given as --prior, the rotation is taken relative to the prior's
  (whose own rotation was judged when it was fitted). Body-frame (reference-vector)
  calibrations only: a magnitude-only M is known only up to a rotation.
"""

from __future__ import annotations

import numpy as np

from generator.errors import InputError
from generator.fit.reference import PART_PRIOR_SIGMA, min_abs_det

ORTHO_TOL = 1e-6
# Default mounting tolerance of a sensor's axes against the unit's frame, degrees: a
# PCB-mounted chip sits within ~1 deg of its footprint (placement and die-to-package
# rotation), the board within ~1 deg of the structure, and non-orthogonal sensing axes
# put up to half their ~1 deg skew into the rotation part of M: 3 deg covers the sum.
# (The simulator's units, campaign.simulate.random_truth, rotate by at most ~2 deg.)
MOUNTING_TOLERANCE_DEG = 3.0
MOUNTING_KEY = "mounting_tolerance_deg"


# A negative det M within this many of its own 1-sigma of 0 is not a determined reflection
# (a mirrored reference makes det ~ -1 with a 1-sigma of a few % at most): 3 sigma, a
# 0.13 % one-sided chance that a determined reflection is called undetermined.
DET_SIGMAS = 3.0


def det_sigma(cal, T) -> float | None:
    """1-sigma of det M(T) from the coefficients' 1-sigma (first order, independent
    elements: d det / d M_ij is the cofactor det M (M^-1)_ji); None without 1-sigma.
    Degree-0 sigma only (M_poly_sigma[0]): the temperature terms' share is small at the
    reference temperature, where the reflection check first looks."""
    if getattr(cal, "M_poly_sigma", None) is None:
        return None
    M = cal.M_at(np.array([T]))[0]
    sM = np.asarray(cal.M_poly_sigma[0], float)
    cof = np.linalg.det(M) * np.linalg.inv(M).T
    return float(np.sqrt(np.sum((cof * sM) ** 2)))


def max_condition(part="default") -> float:
    s = PART_PRIOR_SIGMA.get(part, PART_PRIOR_SIGMA["default"])["M"][0]
    return (1.0 + 3.0 * s) / (1.0 - 3.0 * s)


def offset_range_nT(spec) -> float:
    """Full scale of one raw axis in nT. Counts input: range_nT when the unit file gives
    it, else the count range from the zero count to the further rail times lsb_nT.
    Physical input (nT, uT, G, ...): the sensor's full scale (the unit file's range_nT,
    else the part's, Sensor.full_scale_nT), which does not depend on the input unit; a
    generic part without range_nT has no known full scale (inf: no offset check)."""
    if getattr(spec, "range_nT", None):
        return float(spec.range_nT)
    if getattr(spec, "counts", True):
        return float(max(spec.count_max - spec.zero_count, spec.zero_count - spec.count_min)
                     * spec.lsb_nT)
    fs = float(spec.full_scale_nT)
    return fs if fs > 0 else float("inf")


def offset_cause(spec) -> str:
    """Likely cause of an offset beyond the part's range, for the error message."""
    if getattr(spec, "counts", True):
        return ("wrong lsb_nT or zero_count in the unit file, or a reference in other "
                "units")
    return (f"wrong input unit (input = \"{spec.input}\" in the unit file: the readings "
            "are in other units), or a reference in other units")


def mounting_tolerance_deg(unit, name) -> tuple:
    """(tolerance in degrees, where it came from) of sensor `name`: the unit file's
    [[sensor]] mounting_tolerance_deg, else MOUNTING_TOLERANCE_DEG. InputError naming the
    key when the value is not a number in (0, 180]."""
    extra = (((getattr(unit, "extra", None) or {}).get("sensor") or {}).get(name) or {})
    if MOUNTING_KEY not in extra:
        return MOUNTING_TOLERANCE_DEG, "default"
    v = extra[MOUNTING_KEY]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) \
            or not 0.0 < float(v) <= 180.0:
        raise InputError(getattr(unit, "path", None),
                         f"key 'sensor.{name}.{MOUNTING_KEY}': {v!r} is not a number of "
                         "degrees in (0, 180]")
    return float(v), "unit file"


def rotation_part(M, M_ref=None) -> dict:
    """Angle (deg) and unit axis of the rotation R of the polar decomposition M = R S,
    relative to that of M_ref when given (R R_ref^T)."""
    from scipy.linalg import polar
    from scipy.spatial.transform import Rotation

    R = polar(np.asarray(M, float))[0]
    if M_ref is not None:
        R = R @ polar(np.asarray(M_ref, float))[0].T
    rv = Rotation.from_matrix(R).as_rotvec()
    ang = float(np.linalg.norm(rv))
    axis = rv / ang if ang > 0 else np.array([0.0, 0.0, 1.0])
    return {"angle_deg": float(np.degrees(ang)), "axis": axis.tolist()}


def _rotation_check(cal, spec, unit, prior) -> tuple:
    """(figures, warning or None) of the mounting-rotation check (module docstring)."""
    tol, where = mounting_tolerance_deg(unit, cal.name)
    T = float(np.clip(cal.t_ref_C, cal.t_min_C, cal.t_max_C))
    M = cal.M_at(T)
    M_ref = None
    if prior is not None and not str(getattr(prior, "source", "")).startswith("part nominal"):
        M_ref = np.asarray(prior.M_poly[0], float)
    rot = rotation_part(M, M_ref)
    # 1-sigma of the angle: the small-angle rotation vector is w_x = (M_zy - M_yz) / 2 etc.
    sig = 0.0
    if cal.M_poly_sigma is not None:
        s = np.asarray(cal.M_poly_sigma[0], float)
        sw = np.array([np.hypot(s[2, 1], s[1, 2]), np.hypot(s[0, 2], s[2, 0]),
                       np.hypot(s[1, 0], s[0, 1])]) / 2.0
        sig = float(np.degrees(np.sqrt(np.sum((np.asarray(rot["axis"]) * sw) ** 2))))
    fig = dict(rot, sigma_deg=sig, tolerance_deg=tol, tolerance_from=where,
               relative_to="the --prior calibration" if M_ref is not None
               else "the unit file's axes")
    if rot["angle_deg"] - 3.0 * sig <= tol:
        return fig, None
    ax = ", ".join(f"{a:+.2f}" for a in rot["axis"])
    return fig, (f"sensor '{cal.name}': the fitted M rotates the sensor's axes by "
                 f"{rot['angle_deg']:.1f} deg (1-sigma {sig:.2g}) about ({ax}) relative to "
                 f"{fig['relative_to']}, beyond the mounting tolerance {tol:g} deg "
                 f"({where}; key {MOUNTING_KEY}): a real mounting rotation, or a reference "
                 "in a rotated frame (one campaign cannot tell them apart); the rotation is "
                 "kept in M. Check the reference's frame; if the mounting is known to be "
                 f"rotated, set {MOUNTING_KEY}")


def _beside(value, other) -> str:
    """value with the digits that tell it from other (3 significant, more when close)."""
    for digits in range(3, 9):
        if f"{value:#.{digits}g}" != f"{other:#.{digits}g}":
            return f"{value:.3g}" if digits == 3 else f"{value:#.{digits}g}"
    return f"{value:.9g}"


def check_calibration(cal, spec, source=None, unit=None, prior=None) -> dict:
    """Raise InputError when a calibration is not physical (module docstring); else
    return the figures checked (JSON-able) for the fit report. unit: for the sensor's
    mounting tolerance (Unit.extra); prior: the reference.Prior the fit used (a ground
    calibration's rotation is the mounting's)."""
    n_grid = 1 if np.all(cal.M_poly[1:] == 0) and np.all(cal.b_poly_nT[1:] == 0) else 21
    T = np.linspace(cal.t_min_C, cal.t_max_C, n_grid)
    M = cal.M_at(T)
    b = cal.b_at(T)
    det = np.linalg.det(M)
    cond = np.linalg.cond(M)
    name = cal.name
    if not np.all(np.isfinite(M)) or not np.all(np.isfinite(b)):
        raise InputError(source, f"sensor '{name}': the fit gave non-finite coefficients")
    if np.min(det) <= 0:
        k = int(np.argmin(det))
        if abs(det[k]) < min_abs_det(spec.part):
            raise InputError(source, f"sensor '{name}': the fitted matrix M is degenerate "
                                     f"(det M = {det[k]:.3g} at {T[k]:.1f} degC, implausible "
                                     f"for a {spec.part}: |det M| >= "
                                     f"{min_abs_det(spec.part):.3f}): the data do not "
                                     "determine M (readings that hardly move, or a reference "
                                     "that does not follow them); record a rotation, or give "
                                     "a ground calibration with --prior")
        sd = det_sigma(cal, T[k])
        if sd is not None and abs(det[k]) <= DET_SIGMAS * sd:
            raise InputError(source, f"sensor '{name}': the sign of det M is not determined "
                                     f"by the data (det M = {det[k]:.3g} +- {sd:.2g} at "
                                     f"{T[k]:.1f} degC, within {DET_SIGMAS:g} sigma of 0): a "
                                     "reading axis that hardly moves (a flat flight), not a "
                                     "mirrored reference; record more attitude change, or "
                                     "give a ground calibration with --prior")
        raise InputError(source, f"sensor '{name}': the fitted matrix M is a reflection "
                                 f"(det M = {det[k]:.3f} at {T[k]:.1f} degC): the reference "
                                 "vectors are mirrored against the readings; likely cause: "
                                 "swapped or negated ref_x_nT/ref_y_nT/ref_z_nT columns, or a "
                                 "wrong axis mapping (sensor axes) in the unit file")
    cmax = max_condition(spec.part)
    warnings = []
    if np.max(cond) > cmax:
        warnings.append(f"sensor '{name}': the fitted matrix M has condition number "
                        f"{_beside(np.max(cond), cmax)}, implausible for a {spec.part} "
                        f"(at most {_beside(cmax, np.max(cond))}: scale and cross-axis "
                        "terms within 3 sigma of the "
                        "part's); check the reference's scale, and for a magnetised object "
                        "next to the sensor")
    scale = np.abs(det) ** (1.0 / 3.0)            # the geometric mean of M's singular values
    s_part = PART_PRIOR_SIGMA.get(spec.part, PART_PRIOR_SIGMA["default"])["M"][0]
    lo, hi = 1.0 - 3.0 * s_part, 1.0 + 3.0 * s_part
    k = int(np.argmax(np.abs(np.log(np.maximum(scale, 1e-300)))))
    if not lo <= scale[k] <= hi:
        how = (f"lsb_nT = {spec.lsb_nT:g}" if getattr(spec, "counts", True)
               else f"input = \"{spec.input}\"")
        warnings.append(f"sensor '{name}': the fitted M scales the readings by "
                        f"{scale[k]:.3g} (|det M|^(1/3) at {T[k]:.1f} degC), beyond a "
                        f"{spec.part}'s scale tolerance {lo:.2f}..{hi:.2f} (3 sigma of the "
                        f"part's): the readings are most likely not in the unit the unit "
                        f"file says ({how}), or the reference's magnitude is not the field's "
                        "(lab_field_nT, ref_* columns); check both before using this "
                        "calibration")
    lim = offset_range_nT(spec)
    bmax = float(np.max(np.abs(b)))
    if bmax > lim:
        raise InputError(source, f"sensor '{name}': fitted offset {bmax:.0f} nT exceeds the "
                                 f"part's range {lim:.0f} nT; likely cause: {offset_cause(spec)}")
    out = {"det_M_min": float(np.min(det)), "cond_M_max": float(np.max(cond)),
           "scale_M_min": float(np.min(scale)), "scale_M_max": float(np.max(scale)),
           "cond_M_limit": cmax, "offset_max_nT": bmax,
           "offset_limit_nT": lim if np.isfinite(lim) else None,
           "warnings": warnings}
    if cal.body_frame:
        out["rotation"], w = _rotation_check(cal, spec, unit, prior)
        if w:
            warnings.append(w)
    return out


def check_rotation(H, what="boom alignment H", source=None) -> dict:
    H = np.asarray(H, float)
    err = float(np.max(np.abs(H.T @ H - np.eye(3))))
    det = float(np.linalg.det(H))
    if not (err < ORTHO_TOL and det > 0):
        raise InputError(source, f"{what} is not a rotation (|H^T H - I| = {err:.2g}, det "
                                 f"{det:.3f}); likely cause: mirrored boom sensor axes in the "
                                 "unit file")
    return {"orthogonality_error": err, "det": det}
