"""Where the fit's reading noise comes from, and what a wrong one does (issue 16, review 16b
F1-F3).

A count sensor whose unit file states no noise_nT takes the part catalogue's typical
figure (plus the count quantisation lsb^2/12), recorded as "part catalogue (typical)";
only a part with no figure (generic) has its noise estimated from the data, by the second
differences' clipped mean square (right for quantised readings, where a MAD of whole-step
differences is 0). The noise figure's own uncertainty is a systematic error of the
errors-in-variables correction: on a yaw-only flight the vertical barely moves, the
correction is as large as the signal, and the direction is held at the prior instead of
fitted to a misjudged noise (F1).
"""

from __future__ import annotations

import copy
import math
import pickle

import numpy as np
import pytest
from scipy.stats import chi2, norm

from generator.campaign.simulate import random_truth, simulate_campaign
from generator.fit.reference import (CATALOGUE_NOISE_VAR_UNCERTAINTY, NOISE_CATALOGUE,
                                     NOISE_STATED, difference_noise_var, noise_source,
                                     noise_var_uncertainty, reference_fit)
from generator.fit.samples import field_noise_nT
from generator.fit.thermal import fit_unit
from generator.io.telemetry_csv import read_telemetry
from generator.io.unitfile import load_unit

QMC_LSB_nT = 8.333
QMC_NOISE_nT = 200.0           # parts.toml QMC5883L noise_nT
MPU_NOISE_nT = 250.0           # parts.toml MPU-9255 noise_nT


def _unit(tmp_path, sensors, lab_field_nT=50000.0, name="u"):
    text = f'[unit]\nid = "{name}"\nlab_field_nT = {lab_field_nT}\n'
    for s in sensors:
        text += "\n[[sensor]]\n" + "\n".join(f"{k} = {v}" for k, v in s.items()) + "\n"
    p = tmp_path / f"{name}.toml"
    p.write_text(text)
    return load_unit(p)


QMC = {"name": '"qmc"', "part": '"QMC5883L"', "frame": '"body"',
       "axes": '["+x", "+y", "+z"]', "lsb_nT": QMC_LSB_nT, "zero_count": 0}


def test_count_sensor_without_noise_takes_the_catalogue_figure(tmp_path):
    unit = _unit(tmp_path, [
        QMC,
        dict(QMC, name='"qmcs"', noise_nT=120.0),
        {"name": '"lis"', "part": '"LIS3MDL"', "frame": '"body"',
         "axes": '["+x", "+y", "+z"]', "input": '"uT"'},
        {"name": '"gen"', "part": '"generic"', "range_nT": 200000.0, "frame": '"body"',
         "axes": '["+x", "+y", "+z"]', "lsb_nT": 10.0, "zero_count": 0}])
    f = field_noise_nT(unit.sensor("qmc"))
    assert float(f) == pytest.approx(math.sqrt(QMC_NOISE_nT ** 2 + QMC_LSB_nT ** 2 / 12))
    assert noise_source(f) == NOISE_CATALOGUE
    assert noise_var_uncertainty(f) == CATALOGUE_NOISE_VAR_UNCERTAINTY
    s = field_noise_nT(unit.sensor("qmcs"))
    assert float(s) == pytest.approx(math.sqrt(120.0 ** 2 + QMC_LSB_nT ** 2 / 12))
    assert noise_source(s) == NOISE_STATED
    lis = field_noise_nT(unit.sensor("lis"))        # physical units: no quantisation
    assert noise_source(lis) == NOISE_CATALOGUE and float(lis) > 0
    assert field_noise_nT(unit.sensor("gen")) is None   # no figure anywhere: estimated
    assert noise_source(None) is None and noise_source(50.0) == NOISE_STATED
    # the label survives what the fit's data go through (copies, worker processes)
    assert noise_source(pickle.loads(pickle.dumps(f))) == NOISE_CATALOGUE
    assert noise_source(copy.deepcopy(f)) == NOISE_CATALOGUE


# n readings; the estimate of a variance from n second differences (white noise: lag
# correlations 1, -2/3, 1/6) has relative sd sqrt(2 (1 + 2 (4/9) + 2 (1/36)) / n) =
# sqrt(3.89 / n) for normal noise (a uniform quantisation error has a lighter tail, which
# only lowers it); the bound is 5 of those.
N_DIFF = 20000
DIFF_TOL = 5.0 * math.sqrt(3.89 / N_DIFF)


@pytest.mark.parametrize("ratio", [0.2, 0.5, 1.0, 2.0, 5.0])
def test_difference_estimate_of_quantised_readings(ratio):
    # a reading that sweeps many steps between samples (a rotation at 10 Hz moves a field
    # component by hundreds of nT per sample), so the quantisation error is uniform and
    # independent: per reading sigma^2 + q^2/12, the figure field_noise_nT states
    rng = np.random.default_rng(int(ratio * 10))
    q = 100.0
    sigma = ratio * q
    t = np.arange(N_DIFF)
    signal = 1e4 * q * np.sin(2 * np.pi * t / 6.0e4 + 0.3) + 1.37 * q * t / 7.0
    x = np.round((signal[:, None] + rng.normal(0, sigma, (N_DIFF, 3))) / q) * q
    # what the fit hands in is the residual against the truth's signal (here the signal
    # itself; its second differences are < 1e-4 q); split in two files
    res = x - signal[:, None]
    v = difference_noise_var([res[:N_DIFF // 2], res[N_DIFF // 2:]])
    truth = sigma ** 2 + q ** 2 / 12.0
    assert np.all(np.abs(v / truth - 1.0) < DIFF_TOL), (v / truth, DIFF_TOL)
    # a steady ramp of the residual (the field changing between samples, a drift) is not
    # noise: second differences cancel it exactly
    v2 = difference_noise_var([res + 37.0 * t[:, None]])
    assert np.allclose(v2, difference_noise_var([res]), rtol=1e-9)


def _sim_unit(tmp_path, sensors, seed, campaigns, name="u", **opts):
    unit = _unit(tmp_path, sensors, name=name)
    truth = random_truth(unit, np.random.default_rng(seed))
    tels, arrays = [], {}
    for i, kind in enumerate(campaigns):
        path, arr = simulate_campaign(kind, unit, truth, np.random.default_rng(seed * 10 + i),
                                      tmp_path, name=f"{name}_{kind}_{seed}",
                                      **opts.get(kind, {}))
        tels.append(read_telemetry(path, unit))
        arrays[kind] = arr
    return unit, truth, tels, arrays


MPU600 = {"name": '"mpub"', "part": '"MPU-9255"', "frame": '"body"',
          "axes": '["-x", "+y", "-z"]', "lsb_nT": 600.0, "zero_count": 0}


@pytest.mark.parametrize("seed", [31, 32, 33])
def test_clean_coarse_mpu_gets_no_noise_warning(tmp_path, seed):
    # F2: MPU-9255 at 600 nT per count, noise 250 nT < 1 step; truth per axis
    # sqrt(250^2 + 600^2/12) = 304 nT. The goodness test's false-warning rate on such data
    # is below NOISE_ALPHA (test_fit_warnings), so over 3 seeds none is expected.
    unit, _, tels, _ = _sim_unit(tmp_path, [MPU600], seed, ("thermal_12pos", "rotation"))
    cal = fit_unit(unit, tels)["mpub"]
    g = cal.stats["noise_goodness"]
    assert g["noise_from"] == NOISE_CATALOGUE
    assert g["noise_nT"] == pytest.approx(math.sqrt(MPU_NOISE_nT ** 2 + 600.0 ** 2 / 12))
    assert not g["flagged"], g
    assert not cal.stats["sanity"]["warnings"], cal.stats["sanity"]["warnings"]


def test_reference_noise_on_a_count_sensor_is_warned(tmp_path):
    # F3: white reference noise of 300 nT per axis on a QMC5883L (200 nT, none stated):
    # chi2/row ~ (200^2 + 300^2) / 200^2 = 3.25 against a limit of about
    # 1.5 (the catalogue figure's uncertainty) x the chi-square quantile (~1.03)
    unit, _, tels, _ = _sim_unit(tmp_path, [QMC], 21, ("thermal_12pos",))
    tel = tels[0]
    rng = np.random.default_rng(5)
    for c in "xyz":
        tel.columns[f"ref_{c}_nT"] = tel.columns[f"ref_{c}_nT"] + rng.normal(0, 300.0, tel.n)
    cal = fit_unit(unit, [tel])["qmc"]
    g = cal.stats["noise_goodness"]
    assert g["noise_from"] == NOISE_CATALOGUE
    assert g["flagged"], g
    assert any("beyond what the reading noise explains" in w
               for w in cal.stats["sanity"]["warnings"])


# Every degree-0 coefficient's error within K_SIGMA of its 1-sigma: the union bound over
# the 12 coefficients at a false-failure probability of 1e-3 per fit (the marginals are
# normal whatever their correlations): K = Phi^-1(1 - 1e-3 / 24). The held ones' 1-sigma is
# the prior's, which the simulator's truth lies within.
K_SIGMA = float(norm.ppf(1.0 - 1e-3 / 24))
# The predicted field error is the RMS the 1-sigma implies; the achieved error's square is
# a weighted sum of chi-square(1) terms, at most chi2_1(1 - 1e-3) times its mean when one
# term dominates.
K_PRED = float(math.sqrt(chi2.ppf(1.0 - 1e-3, 1)))


@pytest.mark.parametrize("seed", [401, 402, 403])
def test_yaw_flight_of_a_count_sensor_without_noise(tmp_path, seed):
    # F1: tilt under 2 deg, QMC5883L with no noise_nT: the vertical moves ~200 nT, as much
    # as the noise. Coefficients within K_SIGMA or held at the prior; on a full-sphere
    # rotation of the same unit the error is within what the fit predicts.
    unit, truth, tels, arrays = _sim_unit(
        tmp_path, [QMC], seed, ("yaw_flight", "rotation"),
        yaw_flight={"tilt_max_deg": 2.0, "yaw_rate_dps": 10.0})
    cal = fit_unit(unit, tels[:1])["qmc"]
    T = float(np.median(tels[0].columns["qmc_temp_C"]))
    st = truth.sensors["qmc"]
    dT = T - truth.t_ref_C
    M_true = np.linalg.inv(sum(np.asarray(w) * dT ** k for k, w in enumerate(st.W_poly_frame)))
    b_true = sum(np.asarray(b) * dT ** k for k, b in enumerate(st.b_poly_frame_nT))
    par = {p["name"]: p for p in cal.observability["parameters"]}
    for i, a in enumerate("xyz"):
        p = par[f"b0_{a}"]
        assert abs(cal.b_at(T)[i] - b_true[i]) < K_SIGMA * p["sigma"], (a, p)
        for j, c in enumerate("xyz"):
            p = par[f"M0_{a}{c}"]
            assert abs(cal.M_at(T)[i, j] - M_true[i, j]) < K_SIGMA * p["sigma"], (a, c, p)
    # held-out: the full sphere (rotation campaign), calibrated against the true field
    rot = tels[1]
    x = np.stack([rot.columns[f"qmc_{c}"] for c in "xyz"], axis=1) * QMC_LSB_nT
    z = cal.apply64(x, np.asarray(rot.columns["qmc_temp_C"], float))
    err = float(np.sqrt(np.sum(np.mean((z - arrays["rotation"]["b_body_nT"]) ** 2, axis=0))))
    pred = cal.stats["predicted_error"]["field_error_nT"]
    assert err < K_PRED * pred, (err, pred)


def test_misjudged_noise_does_not_bend_a_barely_moving_axis():
    # The reading's z barely moves (signal ~ noise): with the noise figure off by its
    # own uncertainty, the errors-in-variables correction would move M_zz by ~20 %; the
    # direction is held (prior M_zz = 1 +- 0.1) and the two figures give the same M_zz
    rng = np.random.default_rng(7)
    n = 6000
    yaw = np.cumsum(rng.normal(0, 0.02, n))
    tilt = np.radians(2.0) * np.sin(np.arange(n) / 300.0)
    B = np.stack([17000 * np.cos(yaw), 17000 * np.sin(yaw),
                  47000 + 17000 * tilt * np.cos(yaw)], axis=1)
    M = np.array([[1.0, 0.01, -0.004], [0.011, 0.97, -0.009], [0.014, 0.004, 0.966]])
    b = np.array([-2200.0, 2000.0, -1860.0])
    x = np.linalg.solve(M, B.T).T + b + rng.normal(0, 200.0, (n, 3))
    Ms = []
    for noise in (200.0, 200.0 * math.sqrt(1.25)):
        _, Mf, info = reference_fit(x, B, None, noise_nT=noise)
        src = {p["name"]: p["source"] for p in info["parameters"]}
        assert src["M0_zz"] == "prior", src
        Ms.append(Mf[0])
    assert abs(Ms[0][2, 2] - Ms[1][2, 2]) < 0.01
