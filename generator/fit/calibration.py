"""Fitted calibration of one sensor: what the fitters return and the chain consumes.

Model (seed 000 eq. 5 and 7), in the sensor's frame axes (after the axis mapping):

    B_cal = M(T) (B~ - b(T)),   b(T) = sum_k b_poly_nT[k] dT^k,   M(T) = sum_k M_poly[k] dT^k,
    dT = clamp(T, t_min_C, t_max_C) - t_ref_C

B~ is the uncalibrated field in frame axes (nT). When `body_frame` is True, M maps to the
frame of the reference vectors (body frame, or the jig frame for boom sensors); when False
(only magnitudes were known, ellipsoid fit), M is known only up to a rotation and is taken
symmetric.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

POLY_DEGREE = 3  # cubic in temperature (seed 000 eq. 7)


def _horner(coeffs, d) -> np.ndarray:
    """sum_k coeffs[k] * d**k by Horner's rule, in place: (((c_K d + c_K-1) d + ...) d + c_0.
    coeffs (K, *shape), d broadcastable against shape (a trailing 1 per axis of shape). The
    float64 fitting model: no powers of d (a pow per sample for d**3) and no temporaries per
    term; the last bits differ from the sum of powers (the float32 flight reference,
    generator.flight.chain, has its own order, as the C)."""
    out = np.empty(np.broadcast_shapes(np.shape(d), coeffs.shape[1:]))
    out[...] = coeffs[-1]
    for k in range(coeffs.shape[0] - 2, -1, -1):
        out *= d
        out += coeffs[k]
    return out


@dataclass
class SensorCalibration:
    name: str
    b_poly_nT: np.ndarray              # (POLY_DEGREE+1, 3)
    M_poly: np.ndarray                 # (POLY_DEGREE+1, 3, 3)
    t_ref_C: float = 25.0
    t_min_C: float = -40.0
    t_max_C: float = 85.0
    body_frame: bool = False
    method: str = ""
    b_poly_sigma_nT: np.ndarray | None = None   # 1-sigma of b_poly_nT, same shape
    M_poly_sigma: np.ndarray | None = None      # 1-sigma of M_poly, same shape
    stats: dict = field(default_factory=dict)   # rms, samples, segments, ... (JSON-able)
    # per coefficient data/prior, unobservable directions, noise (reference fit; JSON-able)
    observability: dict = field(default_factory=dict)

    @staticmethod
    def constant(name, b_nT, M, t_ref_C=25.0, t_min_C=-40.0, t_max_C=85.0, **kw):
        """Temperature-independent calibration (rotation campaign at one temperature)."""
        b = np.zeros((POLY_DEGREE + 1, 3))
        Mp = np.zeros((POLY_DEGREE + 1, 3, 3))
        b[0] = b_nT
        Mp[0] = M
        return SensorCalibration(name, b, Mp, t_ref_C, t_min_C, t_max_C, **kw)

    def dT(self, temp_C):
        t = np.clip(np.asarray(temp_C, dtype=float), self.t_min_C, self.t_max_C)
        return t - self.t_ref_C

    def b_at(self, temp_C) -> np.ndarray:
        """b(T), shape (..., 3), float64 (for fitting and plots, not the flight reference)."""
        d = self.dT(temp_C)
        if d.ndim == 1:         # per axis along the samples (contiguous rows), then (N, 3):
            # the same arithmetic per element, without inner loops of 3
            return np.ascontiguousarray(_horner(self.b_poly_nT[:, :, None], d).T)
        return _horner(self.b_poly_nT, d[..., None])

    def M_at(self, temp_C) -> np.ndarray:
        """M(T), shape (..., 3, 3), float64."""
        return _horner(self.M_poly, self.dT(temp_C)[..., None, None])

    def apply64(self, field_frame_nT, temp_C) -> np.ndarray:
        """B_cal in float64 (fitting and diagnostics; the flight reference is chain.py)."""
        x = np.asarray(field_frame_nT, dtype=float) - self.b_at(temp_C)
        return np.einsum("...ij,...j->...i", self.M_at(temp_C), x)

    def per_value(self, temp_C, index=None) -> "PerValue":
        """b(T), M(T) and apply64 at many samples' temperatures, evaluated once per
        distinct value (a reported temperature takes few: its reporting step). index:
        (values, at) already known (values sorted and distinct, temp_C = values[at]; they
        may include values no sample has)."""
        return PerValue(self, temp_C, index)


class PerValue:
    """SensorCalibration.b_at / M_at / apply64 at temp_C (+ a shift h_C), computed at the
    distinct values of temp_C and spread to the samples: the same numbers as per sample
    (each value's polynomial is the same arithmetic), one sort instead of a polynomial
    per sample and call."""

    def __init__(self, cal: SensorCalibration, temp_C, index=None):
        self.cal = cal
        if index is None:
            self.values, at = np.unique(np.asarray(temp_C, float), return_inverse=True)
        else:
            self.values, at = index[0], index[1]
        self.at = np.ravel(at)
        self._at0 = {}          # M_at(), b_at() at the temperatures themselves, kept

    def M_at(self, h_C=0.0) -> np.ndarray:
        """M(T + h_C) per sample (at h_C = 0 computed once; not to be written to)."""
        if h_C == 0.0 and "M" in self._at0:
            return self._at0["M"]
        out = self.cal.M_at(self.values + h_C)[self.at]
        if h_C == 0.0:
            out.flags.writeable = False
            self._at0["M"] = out
        return out

    def b_at(self, h_C=0.0) -> np.ndarray:
        """b(T + h_C) per sample (at h_C = 0 computed once; not to be written to)."""
        if h_C == 0.0 and "b" in self._at0:
            return self._at0["b"]
        out = self.cal.b_at(self.values + h_C)[self.at]
        if h_C == 0.0:
            out.flags.writeable = False
            self._at0["b"] = out
        return out

    def apply64(self, field_frame_nT, h_C=0.0) -> np.ndarray:
        """cal.apply64(field_frame_nT, temp_C + h_C)."""
        x = np.asarray(field_frame_nT, dtype=float) - self.b_at(h_C)
        return np.einsum("...ij,...j->...i", self.M_at(h_C), x)

    def finite_values(self) -> np.ndarray:
        """The distinct finite temperatures, sorted: np.unique of the finite samples (made
        without an index, or with one of these samples' own)."""
        return self.values[np.isfinite(self.values)]
