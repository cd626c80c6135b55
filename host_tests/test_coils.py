"""Magnetorquer coupling K: fit, uncertainty, interference report, correction table."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from generator.errors import InputError
from generator.fit.coils import (DEFAULT_DISTANCE_CM, SEED_30CM_NO_PANEL_NT,
                                 SEED_30CM_PANEL_NT, correction_table, fit_coils,
                                 fit_coupling, format_correction_table,
                                 format_interference_table, interference_table,
                                 scale_inverse_cube)

LEVELS_A = np.array([0.025, 0.05, 0.075, 0.1, -0.025, -0.05, -0.075, -0.1])


def _campaign(rng, K, n_positions=2, per_step=10, noise_nT=40.0):
    """Each coil stepped through +-25..100 mA with zero-current gaps, per static position."""
    nc = K.shape[1]
    rows_I, rows_g = [], []
    for p in range(n_positions):
        for j in range(nc):
            for lev in LEVELS_A:
                for cur in (0.0, lev):
                    I = np.zeros(nc)
                    I[j] = cur
                    rows_I.extend([I] * per_step)
                    rows_g.extend([p] * per_step)
    I = np.array(rows_I)
    g = np.array(rows_g)
    const = rng.normal(0, 30000, (n_positions, 3))
    y = const[g] + I @ K.T + rng.normal(0, noise_nT, (len(g), 3))
    return y, I, g, const


def test_synthetic_K_and_constants_recovered():
    rng = np.random.default_rng(0)
    K = rng.normal(0, 3000, (3, 3))
    y, I, g, const = _campaign(rng, K)
    f = fit_coupling(y, I, g, coils=("coil_x_A", "coil_y_A", "coil_z_A"), name="s")
    z = (f.K_nT_per_A - K) / f.K_sigma_nT_per_A
    assert np.all(np.abs(z) < 4.5)
    assert np.allclose(f.constants_nT, const, atol=20.0)
    assert np.allclose(f.residual_sigma_nT, 40.0, rtol=0.1)


def test_sigma_matches_monte_carlo():
    K = np.array([[100.0, -2500.0, 1300.0], [-600.0, -250.0, 1700.0], [-9000.0, 11500.0, -5700.0]])
    errs, sig = [], []
    for k in range(300):
        rng = np.random.default_rng(500 + k)
        y, I, g, _ = _campaign(rng, K, n_positions=1, per_step=5)
        f = fit_coupling(y, I, g)
        errs.append(f.K_nT_per_A - K)
        sig.append(f.K_sigma_nT_per_A)
    ratio = np.array(errs).std(axis=0) / np.array(sig).mean(axis=0)
    assert np.all(np.abs(ratio - 1.0) < 0.2), ratio


def test_constant_per_position_absorbs_field():
    """A different field in each position must not leak into K."""
    rng = np.random.default_rng(2)
    K = rng.normal(0, 1000, (3, 2))
    y, I, g, _ = _campaign(rng, K, n_positions=4, noise_nT=0.0)
    # unbalanced: only positive steps in even positions, only negative in odd ones, so
    # the mean current differs between positions
    keep = np.where(g % 2 == 0, (I >= 0).all(axis=1), (I <= 0).all(axis=1))
    y, I, g = y[keep], I[keep], g[keep]
    f = fit_coupling(y, I, g)
    assert np.allclose(f.K_nT_per_A, K, atol=1e-6)
    # one constant for all would not work: the position constants differ by ~30 uT
    f1 = fit_coupling(y, I, np.zeros_like(g))
    assert not np.allclose(f1.K_nT_per_A, K, atol=1.0)


def test_undetermined_couplings_rejected():
    rng = np.random.default_rng(3)
    K = rng.normal(0, 1000, (3, 3))
    y, I, g, _ = _campaign(rng, K)
    I0 = I.copy()
    I0[:, 1] = 0.0
    with pytest.raises(InputError, match="never changes"):
        fit_coupling(y, I0, g, coils=("a", "b", "c"), name="s")
    I2 = I.copy()
    I2[:, 2] = 2.0 * I2[:, 0]
    with pytest.raises(InputError, match="move together"):
        fit_coupling(y, I2, g, name="s")
    with pytest.raises(InputError, match="usable samples"):
        fit_coupling(y[:4], I[:4], g[:4], name="s")


# ---------------------------------------------------------------------------------------
# shared example unit: coils.csv
# ---------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=None)
def _load(fm1_dir):
    from generator.fit import thermal as fit_thermal
    from generator.io.telemetry_csv import read_telemetry
    from generator.io.unitfile import load_unit
    unit = load_unit(fm1_dir / "unit.toml")
    cals = fit_thermal.fit_unit(unit, [read_telemetry(fm1_dir / "thermal_12pos.csv", unit)])
    coils = read_telemetry(fm1_dir / "coils.csv", unit)
    return unit, cals, coils


@pytest.fixture(scope="module")
def shared(fm1_dir):
    from generator.io.truth import load_truth
    unit, cals, coils = _load(fm1_dir)
    return unit, cals, coils, load_truth(fm1_dir / "truth.json"), fit_coils(unit, [coils])


def test_shared_K_matches_truth(shared):
    unit, _, _, truth, cf = shared
    assert cf.coils == ("coil_x_A", "coil_y_A", "coil_z_A")
    chi2, n = 0.0, 0
    for name, f in cf.sensors.items():
        K_true = truth["sensors"][name]["K_nT_per_A"]
        z = (f.K_nT_per_A - K_true) / f.K_sigma_nT_per_A
        assert np.all(np.abs(z) < 4.0), (name, z)
        chi2 += float(np.sum(z ** 2))
        n += z.size
    assert chi2 / n < 2.0, chi2 / n


def test_shared_K_is_in_raw_units_not_scaled_by_M(shared):
    """K is subtracted before M: it must match K_true, not W K_true, on the sensor whose
    W departs most from I at the largest coupling (mmc1)."""
    unit, cals, coils, truth, cf = shared
    from generator.io.truth import true_W
    f = cf.sensors["mmc1"]
    K_true = truth["sensors"]["mmc1"]["K_nT_per_A"]
    W = true_W(truth, "mmc1", np.array([25.0]))[0]
    chi_K = np.sum(((f.K_nT_per_A - K_true) / f.K_sigma_nT_per_A) ** 2)
    chi_WK = np.sum(((f.K_nT_per_A - W @ K_true) / f.K_sigma_nT_per_A) ** 2)
    assert chi_K < chi_WK / 3


def test_shared_correction_table_improves(shared):
    unit, cals, coils, _, cf = shared
    tab = correction_table(unit, coils, cals, cf)
    assert set(tab) == set(unit.sensor_names)
    for name, r in tab.items():
        noise = unit.sensor(name).noise_nT
        assert r["rms_norm_nT"]["with"] < r["rms_norm_nT"]["without"], name
        assert r["rms_norm_on_nT"]["with"] < r["rms_norm_on_nT"]["without"], name
        assert r["rms_vector_nT"]["with"] < r["rms_vector_nT"]["without"], name
        # after the correction only noise is left (the SET/RESET field noise is noise/sqrt 2)
        assert r["rms_norm_nT"]["with"] < 1.2 * noise, name
    text = format_correction_table(tab)
    assert "mmc1" in text and "with K" in text


def test_shared_interference_table(shared):
    unit, _, _, _, cf = shared
    rows = interference_table(unit, cf)
    assert len(rows) == len(unit.sensors) * 3
    for r in rows:
        f = cf.sensors[r["sensor"]]
        j = f.coils.index(r["coil"])
        assert r["interference_nT"] == pytest.approx(0.1 * np.linalg.norm(f.K_nT_per_A[:, j]))
        assert r["pct_of_lab_field"] == pytest.approx(
            100 * r["interference_nT"] / unit.lab_field_nT)
        assert r["distance_cm"] == DEFAULT_DISTANCE_CM[r["frame"]]
        # 1/r^3: halving the distance multiplies by 8
        assert r["at_cm"][15.0] == pytest.approx(8 * r["at_cm"][30.0])
        if r["distance_cm"] in r["at_cm"]:
            assert r["at_cm"][r["distance_cm"]] == pytest.approx(r["interference_nT"])
        assert r["seed_no_panel_at_cm"][30.0] == pytest.approx(SEED_30CM_NO_PANEL_NT)
        assert r["seed_panel_at_cm"][30.0] == pytest.approx(SEED_30CM_PANEL_NT)
        # the equivalent distance reproduces the measured value from the seed's coil
        assert scale_inverse_cube(SEED_30CM_NO_PANEL_NT, 30.0, r["equivalent_distance_cm"]) == \
            pytest.approx(r["interference_nT"])
        if r["frame"] == "boom":
            # seed 000: at the boom length the coils move |B| by no more than 3 %
            assert r["pct_of_lab_field"] < 3.0
    # the assumed distance is a parameter
    rows2 = interference_table(unit, cf, distance_cm={"mmc2": 15.0}, current_A=0.05)
    r2 = next(r for r in rows2 if r["sensor"] == "mmc2" and r["coil"] == "coil_x_A")
    r1 = next(r for r in rows if r["sensor"] == "mmc2" and r["coil"] == "coil_x_A")
    assert r2["distance_cm"] == 15.0
    assert r2["interference_nT"] == pytest.approx(0.5 * r1["interference_nT"])
    assert r2["at_cm"][30.0] == pytest.approx(r2["interference_nT"] / 8)
    assert "167.87" in format_interference_table(rows)


def test_fit_coils_file_errors(shared):
    unit, _, coils, _, _ = shared
    with pytest.raises(InputError, match="missing current"):
        fit_coils(unit, [coils], coils=("coil_q_A",))
    with pytest.raises(InputError, match="no telemetry"):
        fit_coils(unit, [])
