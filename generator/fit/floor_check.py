"""Is a calibration against the geomagnetic field model at its floor? (issue 18)

A fit against the field model's |B| cannot go below the floor
sqrt(noise^2 + model^2) (the sensor's per-axis noise, fit.samples.field_noise_nT, and
the model's own |B| error, io.orbit.model_floor_nT). A residual well beyond it on the
fit's own samples means the reference is wrong for these data, most often a time/epoch
error (the position, so the field, is taken at the wrong instant: an 18 s GPS-UTC
offset moves a LEO satellite by ~140 km) or a position from the wrong orbit; the
calibration then absorbs part of that error and is not trustworthy.

The test: S = rms^2 (mean square |B| residual over n samples) against its expectation
E = noise^2 + model^2 under the floor. The two parts have different numbers of
independent samples: the noise is white (n), the model error is correlated along the
track, so it has about duration / MODEL_CORRELATION_s independent values. The
Satterthwaite approximation gives S / E ~ chi2(nu) / nu with the effective degrees of
freedom nu = 2 E^2 / (2 noise^4 / n + 2 model^4 / n_model). Flagged when S / E exceeds
the QUANTILE (0.999, one-sided) of chi2(nu) / nu. Conservative: the fitted parameters
absorb some of any error, so the own-samples rms is, if anything, too small.
"""

from __future__ import annotations

import math

from generator.fit.special import chi2_quantile

# One-sided quantile of the test: a quiet, correct campaign is flagged 1 time in 1000.
QUANTILE = 0.999

# Correlation time of the model's |B| error along a LEO track: its largest quiet-time
# parts (the external field, the main field's error, io.orbit.MODEL_FLOOR_nT) vary on
# scales of tens of degrees of latitude; a LEO satellite covers 360 deg in ~ 90 min, i.e.
# 36 deg in 600 s. Taking the long end makes n_model small and the test conservative.
MODEL_CORRELATION_s = 600.0


def floor_check(rms_nT: float, n: int, noise_nT: float, model_nT: float,
                duration_s: float, quantile: float = QUANTILE) -> dict:
    """{"ratio": S / E, "limit": chi2 quantile / nu, "nu", "n_model", "flagged"}."""
    n = max(int(n), 1)
    n_model = max(1.0, float(duration_s) / MODEL_CORRELATION_s)
    E = noise_nT ** 2 + model_nT ** 2
    var = 2.0 * noise_nT ** 4 / n + 2.0 * model_nT ** 4 / n_model
    nu = 2.0 * E ** 2 / var if var > 0 else float(n)
    ratio = float(rms_nT) ** 2 / E if E > 0 else math.inf
    limit = chi2_quantile(quantile, nu) / nu
    return {"ratio": ratio, "limit": limit, "nu": nu, "n_model": n_model,
            "quantile": quantile, "flagged": bool(ratio > limit)}


def floor_warning(sensor: str, rms_nT: float, floor_nT: float, check: dict) -> str:
    """The one-line warning of a flagged check (naming the likely causes)."""
    return (f"{sensor}: the |B| residual against the field model, {rms_nT:.0f} nT rms on the "
            f"fit's own samples, is well beyond the floor {floor_nT:.0f} nT (mean square "
            f"{check['ratio']:.1f}x the floor's; the chi-square {check['quantile']} quantile "
            f"with {check['nu']:.0f} effective degrees of freedom allows "
            f"{check['limit']:.2f}x): the reference does not fit these data. Likely cause: a "
            "time/epoch error ([orbit] epoch_utc, time_s, a GPS-UTC offset) or a position "
            "mismatch (TLE of another object, wrong position columns), else an effect the "
            "calibration model lacks (a temperature dependence of a sensor stated without "
            "temperature, an unmodelled current); the calibration is not trustworthy")
