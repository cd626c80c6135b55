"""Issue 16 item 5, review fault 1: the SET/RESET gyro compensation is decided before the
fit and M is fitted to the compensated chain output, so the rotation error is removed
once, not twice.

A unit written here (not the bundled one): one MMC5883MA on a turntable that turns at a
constant 10 deg/s about the body z axis, the table axis tilted against the lab field in
eight steps (so the readings cover the sphere). The body rate is constant, so a free M
could absorb the SET/RESET rotation error W (I - c [w]x) B; the chain's compensation
would then take it off a second time (about 48 nT per axis at 10 deg/s and 50,000 nT,
against 28 nT of noise: the reviewer's 1.9 x the optimum residual).

The readings are simulated here from the physics (SET = W B + b + o, RESET = -(W B') + b
... as counts), not with the project's simulator, and the expected residual is computed
with the true parameters and a float64 chain written out in the test (not chain.py).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from generator.io.icd_write import write_telemetry_csv, write_unit_toml

LSB_NT = 25.0
ZERO = 32768
NOISE_NT = 40.0            # one reading, per axis
DELAY_S = 11e-3            # RESET 11 ms after SET: the delay the fit's decision assumes
RATE_DPS = 10.0
FIELD_NT = 50000.0
RATE_HZ = 10.0


def _rot(axis, ang):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K


def _turntable(path, rng, W, b, chip):
    """Constant body rate (0, 0, RATE_DPS); per step the field's elevation from the table
    plane changes; one turn per step. B_body(t) = exp(-[w]x t) B0."""
    w = np.array([0.0, 0.0, RATE_DPS])
    n_turn = int(round(360.0 / RATE_DPS * RATE_HZ))
    rows = {k: [] for k in ("t", "B", "Bd")}
    t0 = 0.0
    for elev in np.radians(np.linspace(-75.0, 75.0, 8)):
        B0 = FIELD_NT * np.array([np.cos(elev), 0.0, np.sin(elev)])
        t = np.arange(n_turn) / RATE_HZ
        for ti in t:
            R = _rot(w, -np.radians(RATE_DPS) * ti)
            Rd = _rot(w, -np.radians(RATE_DPS) * (ti + DELAY_S))
            rows["t"].append(t0 + ti)
            rows["B"].append(R @ B0)
            rows["Bd"].append(Rd @ B0)
        t0 += n_turn / RATE_HZ + 1.0
    t = np.array(rows["t"])
    B, Bd = np.array(rows["B"]), np.array(rows["Bd"])
    n = len(t)
    Winv_B = B @ W.T
    set_nT = Winv_B + b + chip + rng.normal(0, NOISE_NT, (n, 3))
    reset_nT = -(Bd @ W.T) + b + chip + rng.normal(0, NOISE_NT, (n, 3))
    # the offset b is the hard iron: it does not flip with SET/RESET
    reset_nT = reset_nT - 2 * b
    set_c = np.round(set_nT / LSB_NT) + ZERO
    reset_c = np.round(reset_nT / LSB_NT) + ZERO
    gyro = w + rng.normal(0, 0.05, (n, 3))
    cols = {"time_s": t}
    for k, a in enumerate("xyz"):
        cols[f"mmc_set_{a}"] = set_c[:, k]
        cols[f"mmc_reset_{a}"] = reset_c[:, k]
    cols["mmc_temp_C"] = np.full(n, 24.0)
    for k, a in enumerate("xyz"):
        cols[f"ref_{a}_nT"] = B[:, k]
    for k, a in enumerate("xyz"):
        cols[f"rate_{a}_dps"] = gyro[:, k]
    write_telemetry_csv(path, cols, meta={"unit": "turntable"})
    return set_c, reset_c, B, gyro


def _chain64(M, b, c, x, w):
    """(I + c [w]x) M (x - b), float64, written out here (the chain's order of terms)."""
    B0 = (x - b) @ M.T
    return B0 + c * np.cross(w, B0)


def test_steady_turn_compensated_fit_is_near_the_truth_residual(tmp_path):
    from generator.pipeline import fit

    rng = np.random.default_rng(1616)
    unit = write_unit_toml(tmp_path / "unit.toml", "turntable", [
        {"name": "mmc", "part": "MMC5883MA", "frame": "body", "axes": ["+x", "+y", "+z"],
         "lsb_nT": LSB_NT, "zero_count": ZERO, "set_reset": True, "noise_nT": NOISE_NT}],
        unit_keys={"lab_field_nT": FIELD_NT})
    W = np.eye(3) + rng.normal(0, 0.02, (3, 3))
    b = rng.normal(0, 800.0, 3)
    chip = rng.normal(0, 2000.0, 3)
    set_c, reset_c, B, gyro = _turntable(tmp_path / "turn.csv", rng, W, b, chip)
    cs = fit(unit, [tmp_path / "turn.csv"])
    s = cs.unit.sensor("mmc")
    sr = cs.fit_info["set_reset_compensation"]["mmc"]
    assert sr["enabled"] and sr.get("fit_on_compensated")
    assert cs.spec.opts(s).sr_compensation
    c = float(cs.sensors["mmc"]["sr_comp_s_per_deg"])
    # the decision's c is the simulated delay's (11 ms): the truth chain uses the same
    assert c == pytest.approx(DELAY_S / 2 * np.pi / 180, rel=1e-12)
    x = (set_c - reset_c) / 2 * LSB_NT                  # the pair's field, frame = sensor axes
    M_fit = np.asarray(cs.sensors["mmc"]["M_poly"], float)[0]
    b_fit = np.asarray(cs.sensors["mmc"]["b_poly_nT"], float)[0]
    r_fit = _chain64(M_fit, b_fit, c, x, gyro) - B
    r_true = _chain64(np.linalg.inv(W), b, c, x, gyro) - B
    rss_fit, rss_true = float(np.sum(r_fit ** 2)), float(np.sum(r_true ** 2))
    # With the right model the least-squares optimum is below the truth's RSS (it fits
    # the noise too), and an estimator whose error delta has the least-squares
    # covariance adds delta^T F delta ~ sigma^2 chi2(p), p = 12 (b, M). So RSS_fit <=
    # RSS_true + sigma^2 chi2_{p}(1 - 1e-6), sigma^2 = RSS_true / 3N. Removing the
    # rotation error twice adds ~c^2 |w x B|^2 per sample (48 nT vs 28 nT of noise):
    # a factor ~3 in RSS.
    n3 = r_true.size
    bound = 1.0 + chi2.ppf(1 - 1e-6, 12) / n3
    assert rss_fit / rss_true <= bound, (rss_fit / rss_true, bound)
    print(f"RSS fit / truth {rss_fit / rss_true:.5f} (bound {bound:.5f})")
    # and the truth residual is the noise: the pair's noise per axis (two readings and
    # quantisation, over 2), through M ~ I, within 5 sigma of its chi-square
    sig2 = (NOISE_NT ** 2 + LSB_NT ** 2 / 12) / 2
    assert abs(rss_true / (n3 * sig2) - 1) < 0.1


def test_without_compensation_the_fit_absorbs_it(tmp_path):
    """The fault itself, shown on the same physics: M fitted on the uncompensated
    reference and the chain's compensation added afterwards (the old order) leaves
    the doubled error c |w x B| (about 37 nT RMS here, cos^2 of the elevations
    averaging 0.6) on top of 49.5 nT of noise: far beyond the bound the test above
    holds the fit to, so that test can fail."""
    from generator.fit.reference import reference_fit

    rng = np.random.default_rng(1617)
    W = np.eye(3) + rng.normal(0, 0.02, (3, 3))
    b = rng.normal(0, 800.0, 3)
    chip = rng.normal(0, 2000.0, 3)
    set_c, reset_c, B, gyro = _turntable(tmp_path / "turn.csv", rng, W, b, chip)
    x = (set_c - reset_c) / 2 * LSB_NT
    sig = np.sqrt((NOISE_NT ** 2 + LSB_NT ** 2 / 12) / 2)
    bp, Mp, _ = reference_fit(x, B, None, 0, noise_nT=sig)
    c = DELAY_S / 2 * np.pi / 180
    r_old = _chain64(Mp[0], bp[0], c, x, gyro) - B
    r_true = _chain64(np.linalg.inv(W), b, c, x, gyro) - B
    bound = 1.0 + chi2.ppf(1 - 1e-6, 12) / r_true.size      # as in the test above
    assert np.sum(r_old ** 2) / np.sum(r_true ** 2) > 1.3 * bound
