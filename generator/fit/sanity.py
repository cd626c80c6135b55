"""Sanity of a calibration before it is written (exit 2 with the likely cause if not).

* det M(T) > 0 over the calibrated range: a magnetometer calibration is a proper linear
  map; a negative determinant is a reflection, i.e. the reference vectors are mirrored
  against the readings (two reference columns swapped, one negated, or a wrong axis
  mapping in the unit file). It is never a property of a real sensor. A det near 0
  (|det M| < (1 - 3 s)^3, 0.343 for s = 0.1, s below) is not a reflection but a degenerate
  fit: M not determined by the data (observability in generator.fit.reference holds such
  directions at the prior, so this is a guard); the message says "degenerate".
* cond M(T) plausible for the part: with the prior's 1-sigma s on every element of M
  (generator.fit.reference.PART_PRIOR_SIGMA, 0.1), singular values within 1 +- 3 s, so
  cond <= (1 + 3 s) / (1 - 3 s) (1.86 for s = 0.1). Beyond it the fit has most likely
  absorbed something that is not the sensor (a wrong reference, a magnet next to it);
  but strong soft iron can be real, so this one is a flag (stats["sanity"]["warnings"]
  and the fit's progress), not an error.
* offsets b(T) within the part's range: an offset larger than the full scale of the raw
  output cannot come from a sensor that still reads the field.
* H orthogonal with det +1 (boom alignment): |H^T H - I| < 1e-6.
"""

from __future__ import annotations

import numpy as np

from generator.errors import InputError
from generator.fit.reference import PART_PRIOR_SIGMA, min_abs_det

ORTHO_TOL = 1e-6


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


def check_calibration(cal, spec, source=None) -> dict:
    """Raise InputError when a calibration is not physical (module docstring); else
    return the figures checked (JSON-able) for the fit report."""
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
        raise InputError(source, f"sensor '{name}': the fitted matrix M is a reflection "
                                 f"(det M = {det[k]:.3f} at {T[k]:.1f} degC): the reference "
                                 "vectors are mirrored against the readings; likely cause: "
                                 "swapped or negated ref_x_nT/ref_y_nT/ref_z_nT columns, or a "
                                 "wrong axis mapping (sensor axes) in the unit file")
    cmax = max_condition(spec.part)
    warnings = []
    if np.max(cond) > cmax:
        warnings.append(f"sensor '{name}': the fitted matrix M has condition number "
                        f"{np.max(cond):.3g}, implausible for a {spec.part} (at most "
                        f"{cmax:.2f}: scale and cross-axis terms within 3 sigma of the "
                        "part's); check the reference's scale, and for a magnetised object "
                        "next to the sensor")
    lim = offset_range_nT(spec)
    bmax = float(np.max(np.abs(b)))
    if bmax > lim:
        raise InputError(source, f"sensor '{name}': fitted offset {bmax:.0f} nT exceeds the "
                                 f"part's range {lim:.0f} nT; likely cause: {offset_cause(spec)}")
    return {"det_M_min": float(np.min(det)), "cond_M_max": float(np.max(cond)),
            "cond_M_limit": cmax, "offset_max_nT": bmax,
            "offset_limit_nT": lim if np.isfinite(lim) else None,
            "warnings": warnings}


def check_rotation(H, what="boom alignment H", source=None) -> dict:
    H = np.asarray(H, float)
    err = float(np.max(np.abs(H.T @ H - np.eye(3))))
    det = float(np.linalg.det(H))
    if not (err < ORTHO_TOL and det > 0):
        raise InputError(source, f"{what} is not a rotation (|H^T H - I| = {err:.2g}, det "
                                 f"{det:.3f}); likely cause: mirrored boom sensor axes in the "
                                 "unit file")
    return {"orthogonality_error": err, "det": det}
