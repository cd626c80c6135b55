"""Variants of this toolchain's fits, built from the pipeline's own pieces, for the peer
comparison. Nothing here changes the pipeline; these are what the table compares.

* `ours_fit`: generator.fit.ellipsoid.ellipsoid_fit as `magcal fit` runs it (algebraic
  Li-Griffiths start in normalised coordinates + geometric Levenberg-Marquardt refinement,
  with its refusal checks).
* `ours_algebraic`: its algebraic stage alone.
* `geometric_fit`: the pipeline's fit with the plain geometric refinement, as it was
  before the noise-normalised residuals became the default. The default refines the
  NOISE-NORMALISED residuals (|M (x - b)| - R) / |M^T u| of generator.fit.bounds,
  whose variance is the same for every sample: the first-order maximum likelihood. The
  plain geometric cost sum (|M (x - b)| - R)^2 can lower itself by shrinking M along the
  directions where the data's normals point (the residual of the same reading noise is
  sigma |M^T u|); on a full sphere every direction is a normal somewhere and the pull
  cancels, on a cap it biases the offset along the cap axis.
* `px4_thermal_fit`: PX4's temperature model (cubic polynomial offsets per axis, no
  temperature terms in the matrix) fitted to reference vectors with the pipeline's sample
  gathering and temperature scaling: readings = W0 B_ref + b(T), linear least squares.
"""

from __future__ import annotations

import numpy as np

from generator.fit.calibration import POLY_DEGREE, SensorCalibration
from generator.fit.bounds import normalised_residuals
from generator.errors import InputError
from generator.fit.ellipsoid import (_normalised_resid_jac, algebraic_ellipsoid,
                                     ellipsoid_fit, sym_from6, sym_to6)
from generator.fit.thermal import T_REF_C, _gather, _powers


def ours_fit(x_nT, R_nT):
    b, M, _ = ellipsoid_fit(x_nT, R_nT)
    return b, M


def ours_algebraic(x_nT, R_nT):
    b, M, _ = algebraic_ellipsoid(x_nT, R_nT)
    return b, M


def geometric_fit(x_nT, R_nT):
    """The pipeline's fit with the plain geometric refinement (as before the noise-
    normalised residuals became the default): kept for the comparison."""
    b, M, _ = ellipsoid_fit(x_nT, R_nT, residual="geometric")
    return b, M


# check of the Jacobian above against central differences of the residuals
def check_normalised_jacobian(rng=None) -> float:
    rng = rng or np.random.default_rng(0)
    x = rng.normal(size=(50, 3)) * 5e4 + 1e3
    A = rng.normal(size=(3, 3))
    p = np.concatenate([[900.0, -400.0, 1200.0], sym_to6(np.eye(3) + 0.05 * (A + A.T))])
    s, J = _normalised_resid_jac(p, x, 5e4, np.ones(len(x)))
    assert np.allclose(s, normalised_residuals(p[:3], sym_from6(p[3:]), x, 5e4))
    h = np.concatenate([np.full(3, 1e-3), np.full(6, 1e-9)])
    one = np.ones(len(x))
    Jn = np.stack([(_normalised_resid_jac(p + h[j] * np.eye(9)[j], x, 5e4, one)[0] -
                    _normalised_resid_jac(p - h[j] * np.eye(9)[j], x, 5e4, one)[0]) / (2 * h[j])
                   for j in range(9)], axis=1)
    return float(np.max(np.abs(Jn - J)) / np.max(np.abs(J)))


# ---------------------------------------------------------------------------------------
# PX4's temperature model
# ---------------------------------------------------------------------------------------
def px4_thermal_fit(name, datas, degree=POLY_DEGREE) -> SensorCalibration:
    """Cubic offsets b(T), constant matrix: B~ = W0 B_ref + sum_k b_k dT^k, solved by
    linear least squares over all usable reference-vector samples; M = W0^-1."""
    S = _gather(name, datas, [], [])
    v = S.is_vec
    if not v.any():
        raise InputError(datas[0].source, f"{name}: the PX4-model variant needs reference vectors")
    x, B, T = S.x[v], S.ref[v], S.T[v]
    t_lo, t_hi = float(T.min()), float(T.max())
    tau = max(abs(t_lo - T_REF_C), abs(t_hi - T_REF_C), 1.0)
    P = _powers((np.clip(T, t_lo, t_hi) - T_REF_C) / tau, degree)
    Phi = np.hstack([B, P])
    theta, *_ = np.linalg.lstsq(Phi, x, rcond=None)      # (3 + degree + 1, 3)
    W0 = theta[:3].T
    b_poly = theta[3:] / tau ** np.arange(degree + 1)[:, None]
    M_poly = np.zeros((degree + 1, 3, 3))
    M_poly[0] = np.linalg.inv(W0)
    return SensorCalibration(name, b_poly, M_poly, T_REF_C, t_lo, t_hi, body_frame=True,
                             method="PX4 model: cubic b(T), constant M")


def ours_thermal_fit(name, datas) -> SensorCalibration:
    from generator.fit.thermal import fit_sensor
    return fit_sensor(name, datas)
