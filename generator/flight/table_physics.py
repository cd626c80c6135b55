"""The physical checks of a coefficient table: det M(T) of every sensor, H a rotation.

Pure arithmetic on the payload values, in the unit's float type and in the order of the
flight C (templates/table.c.j2 check_physics), so that the ground validator
(tables.check_table) and the flight code give the same verdict bit for bit, on the host
and on the Cortex-M4F. tables.py finds the values (MatrixIndex, the index of H) and turns
a fault into its status code.
"""

from __future__ import annotations

from dataclasses import dataclass


from generator.flight.chain import _horner


@dataclass(frozen=True)
class PhysicalLimits:
    """Checks of what the coefficients mean, beyond the range of each value.

    det_M: every sensor's calibration matrix M(T) (seed 000 eq. 5-7) must have its
    determinant within [lo, hi] at T = t_ref_C (M0, the constant term) and at the ends
    t_min_C, t_max_C of the calibrated range (the temperatures the chain clamps to), with
    M(T) by Horner in the unit's float type. det M is the product of M's singular values,
    the volume scale of the correction: the matrix_poly range lets each gain be up to 3,
    and a gain below 1/3 means the part's lsb is wrong by 3x, so with every gain within
    [1/3, 3] det M lies within [3^-3, 3^3]. Below: singular or nearly (a dead axis, an
    all-zero M gives 0); negative: an axis reflected (a sign error in the axis map or
    the fit). The bounds are rounded to the float type, as the value ranges are.

    rotation_tol: H_boom_to_body must be a rotation, |(H^T H - I)_ij| <= rotation_tol
    for every i <= j (computed in the unit's float type), and det H > 0 (an orthogonal H
    with det -1 is a reflection). The tolerance is a float32 rounding bound plus a
    physical allowance:
      * rounding: each stored element is within 2^-24 relative of the true rotation's
        (round to nearest), which moves (H^T H)_ij by at most 2 * 2^-24 (columns of unit
        length, Cauchy-Schwarz); the float32 evaluation (3 products, 2 sums, the
        subtraction of 1) adds at most 3 * 2^-24 + 2^-24; 6 * 2^-24 in all, taken as
        8 * 2^-24 = 2^-21 (4.8e-7) for margin;
      * physics: with E = H^T H - I, |H v|^2 = |v|^2 + v^T E v and |v^T E v| <= 3 max|E_ij|
        |v|^2, so an allowance of 1e-5 changes |B| by at most 1.5e-5 relative: 0.8 nT at
        the 55 000 nT of the strongest LEO field, 1/30 of the finest lsb of the parts
        (25 nT) and far below their noise (40 nT and more).
      H scaled by 1.0005 (1e-3 off) or sheared by 1e-4 is refused; a fitted rotation
      (Wahba's problem, orthogonal in float64) rounded to float32 passes.
    """

    det_M_lo: float = 1.0 / 27.0
    det_M_hi: float = 27.0
    rotation_rounding: float = 2.0 ** -21
    rotation_allowance: float = 1e-5

    @property
    def rotation_tol(self) -> float:
        return self.rotation_allowance + self.rotation_rounding


PHYSICAL_LIMITS = PhysicalLimits()


@dataclass(frozen=True)
class MatrixIndex:
    """Payload indices of one sensor's M_poly and temperatures (physical checks).
    A sensor without temperature (constant M) has no t_ref/t_min/t_max: None."""

    sensor: str
    m_poly: int        # index of M_poly[0][0][0]
    orders: int        # polynomial orders (poly_degree + 1)
    t_ref: int | None
    t_min: int | None
    t_max: int | None

    @property
    def points(self) -> int:
        """Temperatures det M is checked at: t_ref, t_min, t_max; the constant M once."""
        return 1 if self.t_ref is None else 3


def det3(m):
    """det of a row-major 3x3 (9 scalars), by the first row, in this order (the flight C's)."""
    return m[0] * (m[4] * m[8] - m[5] * m[7]) - m[1] * (m[3] * m[8] - m[5] * m[6]) \
        + m[2] * (m[3] * m[7] - m[4] * m[6])


def matrix_at(values, mi: MatrixIndex, dT) -> list:
    """M(T) row-major, each element by Horner in dT over the orders (chain._horner's
    order); dT None: the constant term M0."""
    out = []
    for e in range(9):
        if dT is None:
            out.append(values[mi.m_poly + e])
        else:
            out.append(_horner([values[mi.m_poly + 9 * k + e] for k in range(mi.orders)], dT))
    return out


def evaluate(values, matrices, h_index) -> dict:
    """What the checks compute, in the values' float type, in the flight C's order:
    {'det_M': [(sensor, [det at t_ref_C, t_min_C, t_max_C])], and with a boom (h_index not
    None) 'HtH_minus_I': [(H^T H - I)_ij for i <= j, row by row], 'det_H'}.
    values: the payload (numpy array of the flight type); matrices: MatrixIndex per sensor."""
    dets = []
    for mi in matrices:
        row = [det3(matrix_at(values, mi, None))]
        if mi.points == 3:
            t_ref = values[mi.t_ref]
            for end in (mi.t_min, mi.t_max):
                row.append(det3(matrix_at(values, mi, values[end] - t_ref)))
        dets.append((mi.sensor, row))
    out = {"det_M": dets}
    if h_index is not None:
        h = [values[h_index + e] for e in range(9)]
        one = values.dtype.type(1)
        g = []
        for i in range(3):
            for j in range(i, 3):   # (H^T H)_ij = column i . column j
                v = h[i] * h[j] + h[3 + i] * h[3 + j] + h[6 + i] * h[6 + j]
                g.append(v - one if i == j else v)
        out["HtH_minus_I"] = g
        out["det_H"] = det3(h)
    return out


def first_fault(values, matrices, h_index, limits: PhysicalLimits = PHYSICAL_LIMITS):
    """(status name, detail, bad value index) of the first failing check, in the flight C's
    order (each sensor: det at t_ref_C, t_min_C, t_max_C; then H^T H - I row by row, then
    det H), or None. The bounds are rounded to the values' float type, as the C literals."""
    ft = values.dtype.type
    lo, hi = ft(limits.det_M_lo), ft(limits.det_M_hi)
    phys = evaluate(values, matrices, h_index)
    for mi, (name, dets) in zip(matrices, phys["det_M"]):
        for where, d in zip(("t_ref_C", "t_min_C", "t_max_C"), dets):
            if not (d >= lo and d <= hi):
                return ("BAD_DETERMINANT", f"{name} det M at {where} = {d}, plausible within "
                                           f"[{lo}, {hi}]", mi.m_poly)
    if h_index is None:
        return None
    tol = ft(limits.rotation_tol)
    k = 0
    for i in range(3):
        for j in range(i, 3):
            g = phys["HtH_minus_I"][k]
            k += 1
            if not (g <= tol and g >= -tol):
                return ("NOT_A_ROTATION", f"(H^T H - I)[{i}][{j}] = {g}, tolerance {tol}",
                        h_index + 3 * i + j)
    if not phys["det_H"] > ft(0):
        return ("NOT_A_ROTATION", f"det H = {phys['det_H']}: a reflection", h_index)
    return None
