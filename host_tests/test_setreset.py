"""MMC5883 SET/RESET offset while the satellite turns (seed 000 eq. 4)."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from generator.errors import InputError
from generator.fit.setreset import (SEED_OFFSET_ERROR_BOUND_PCT, T_TM_MS, StoredOffset,
                                chip_offset_compensated, compensate_offset,
                                compensation_gain, field_after, format_compensation_table,
                                format_worst_case_table, offset_and_field,
                                offset_and_field_from_counts, offset_error_maps,
                                offset_error_vector, plot_error_maps,
                                plane_rotation_offset_error,
                                rotation_matrix, t_delay_ms, worst_case_offset_error)

B_NT = 51540.0


def _unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


# ---------------------------------------------------------------------------------------
# (a) formulas
# ---------------------------------------------------------------------------------------
def test_offset_and_field_formulas():
    rng = np.random.default_rng(0)
    B = rng.normal(0, 30000, (100, 3))
    o = rng.normal(0, 3000, (100, 3))
    field, off = offset_and_field(B + o, -B + o)
    assert np.allclose(field, B, atol=1e-9)
    assert np.allclose(off, o, atol=1e-9)


def test_rotation_helpers():
    rng = np.random.default_rng(1)
    a = rng.normal(0, 0.3, (50, 3))
    R = rotation_matrix(a)
    assert np.allclose(R @ np.swapaxes(R, -1, -2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    assert np.allclose(rotation_matrix(np.zeros(3)), np.eye(3))
    # dB/dt = -w x B: a short delay moves the field by -(w x B) dt to first order
    B = B_NT * _unit(rng, 20)
    w = rng.normal(0, 5, (20, 3))
    dt_ms = 1e-3
    d = field_after(B, w, dt_ms) - B
    assert np.allclose(d, -np.cross(np.radians(w), B) * dt_ms * 1e-3, rtol=1e-5, atol=1e-12)


def test_counts_formula_matches_preprocess(fm1_dir):
    """The float64 formulas give the toolchain's own SET/RESET field and chip offset."""
    from generator.io.telemetry_csv import preprocess, read_telemetry
    from generator.io.unitfile import load_unit
    unit = load_unit(fm1_dir / "unit.toml")
    tel = read_telemetry(fm1_dir / "rotation.csv", unit)
    data = preprocess(tel, unit)
    s = unit.sensor("mmc1")
    sets = np.column_stack([tel.columns[f"mmc1_set_{a}"] for a in "xyz"])
    resets = np.column_stack([tel.columns[f"mmc1_reset_{a}"] for a in "xyz"])
    field_s, off_s = offset_and_field_from_counts(sets, resets, s.lsb_nT, s.zero_count)
    assert np.allclose(off_s, data["mmc1"].chip_offset_sensor_nT, atol=1e-9)
    idx, sign = s.axis_map()
    field_f = np.column_stack([sign[k] * field_s[:, idx[k]] for k in range(3)])
    assert np.allclose(field_f, data["mmc1"].field_frame_nT, atol=1e-9)


# ---------------------------------------------------------------------------------------
# (b) error while turning
# ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def maps():
    return offset_error_maps(B_NT, rates_dps=np.arange(0.0, 10.001, 0.5),
                             theta_deg=np.arange(0.0, 180.001, 2.5), tilt_deg=(0.0, 45.0, 90.0))


def test_seed_plane_rotation_reproduced(maps):
    """theta = 0, rotation in the plane: B (1 - cos phi)/2, below 0.001 % of B for every
    t_TM at up to 10 deg/s (the seed's conclusion)."""
    it = int(np.where(maps["theta_deg"] == 0.0)[0][0])
    exact = maps["error_abs_nT"][:, :, it, 0]
    assert np.allclose(exact, maps["seed_plane_nT"], rtol=1e-6, atol=1e-12)
    # independently: phi = w (1 ms + t_TM), small-angle (1 - cos phi)/2 = phi^2/4
    for k, tTM in enumerate(T_TM_MS):
        phi = np.radians(10.0) * (1.0 + tTM) * 1e-3
        assert maps["seed_plane_nT"][k, -1] == pytest.approx(B_NT * phi ** 2 / 4, rel=1e-5)
        assert plane_rotation_offset_error(B_NT, 10.0, t_delay_ms(tTM)) == \
            pytest.approx(B_NT * phi ** 2 / 4, rel=1e-5)
    assert np.all(maps["seed_plane_pct"] < SEED_OFFSET_ERROR_BOUND_PCT)
    rows = maps["worst_case"]
    assert [r["t_TM_ms"] for r in rows] == list(T_TM_MS)
    assert all(r["seed_bound_holds_plane"] for r in rows)


def test_general_case_is_first_order(maps):
    """Doubling the rate doubles the error at theta = 90 deg, quadruples it at theta = 0."""
    r5 = int(np.where(maps["rate_dps"] == 5.0)[0][0])
    r10 = int(np.where(maps["rate_dps"] == 10.0)[0][0])
    i0 = int(np.where(maps["theta_deg"] == 0.0)[0][0])
    i90 = int(np.where(maps["theta_deg"] == 90.0)[0][0])
    e = maps["error_abs_nT"][..., 0]
    assert np.allclose(e[:, r10, i90] / e[:, r5, i90], 2.0, rtol=1e-3)
    assert np.allclose(e[:, r10, i0] / e[:, r5, i0], 4.0, rtol=1e-3)
    # B sin(theta) phi / 2 to first order, away from theta = 0, 180
    inner = (maps["theta_deg"] >= 20) & (maps["theta_deg"] <= 160)
    fo = maps["first_order_nT"][:, 1:, inner]
    assert np.allclose(e[:, 1:, inner], fo, rtol=0.01)
    # the general case breaks the seed's bound by orders of magnitude
    rows = maps["worst_case"]
    assert not any(r["seed_bound_holds_general"] for r in rows)
    assert all(r["worst_over_seed"] > 100 for r in rows)


def test_rotation_about_axis_in_the_plane_is_second_order(maps):
    """tilt 90: the body turns about an axis in the plane of field and measuring axis."""
    ip = int(np.where(maps["tilt_deg"] == 90.0)[0][0])
    r5 = int(np.where(maps["rate_dps"] == 5.0)[0][0])
    r10 = int(np.where(maps["rate_dps"] == 10.0)[0][0])
    e = maps["error_abs_nT"][..., ip]
    big = e[:, r5, :] > 1e-6
    assert np.allclose(e[:, r10, :][big] / e[:, r5, :][big], 4.0, rtol=1e-3)


def test_worst_case_bound(maps):
    """|B| sin(phi/2) bounds the error over every geometry and the grid reaches it."""
    w = maps["worst_nT"]
    assert np.all(maps["error_abs_nT"] <= w[:, :, None, None] * (1 + 1e-9) + 1e-12)
    assert np.allclose(maps["error_abs_nT"][..., 0].max(axis=2)[:, 1:], w[:, 1:], rtol=1e-3)
    rng = np.random.default_rng(2)
    B = B_NT * _unit(rng, 20000)
    wv = 10.0 * _unit(rng, 20000)
    e = np.abs(offset_error_vector(B, wv, t_delay_ms(10.0)))
    assert e.max() <= worst_case_offset_error(B_NT, 10.0, t_delay_ms(10.0)) * (1 + 1e-9)
    assert e.max() > 0.9 * worst_case_offset_error(B_NT, 10.0, t_delay_ms(10.0))
    assert format_worst_case_table(maps["worst_case"]).count("\n") == len(T_TM_MS) + 1


def test_plot_error_maps(tmp_path):
    m = offset_error_maps(B_NT)
    paths = plot_error_maps(m, tmp_path / "maps")
    assert len(paths) == len(T_TM_MS) + 1
    for p in paths:
        with open(p, "rb") as f:
            assert f.read(8) == b"\x89PNG\r\n\x1a\n"


def test_map_input_errors():
    with pytest.raises(InputError):
        offset_error_maps(-1.0)
    with pytest.raises(InputError):
        offset_error_maps(B_NT, rates_dps=[])
    with pytest.raises(InputError):
        offset_error_maps(B_NT, t_TM_ms=[np.nan])


# ---------------------------------------------------------------------------------------
# (c) gyro compensation
# ---------------------------------------------------------------------------------------
def test_compensation_perfect_gyro_removes_the_error():
    g = compensation_gain(B_NT, rates_dps=(1.0, 10.0), gyro_noise_dps=(0.0,), n_trials=2000)
    assert np.all(g["rms_before_nT"] > 0.1)
    assert np.all(g["removed"] > 0.999999)
    g1 = compensation_gain(B_NT, rates_dps=(10.0,), gyro_noise_dps=(0.0,), n_trials=2000,
                           method="first_order")
    assert np.all(g1["removed"] > 0.999)     # first order leaves a second-order remainder


def test_compensation_noisy_gyro_removes_less():
    noise = (0.0, 0.01, 0.03, 0.1)
    g = compensation_gain(B_NT, rates_dps=(1.0, 10.0), gyro_noise_dps=noise, n_trials=4000)
    removed = g["removed"]
    # monotonic: more gyro noise, less removed; a lower rate suffers more from the same noise
    assert np.all(np.diff(removed, axis=2) < 0)
    assert np.all(removed[0, :, 1:] < removed[1, :, 1:])
    # still worth it: most of the error goes even with 0.1 deg/s at 1 deg/s
    assert np.all(removed > 0.5)
    # what is left is the gyro error x field x t_delay / 2, as predicted
    assert np.allclose(g["rms_after_nT"][..., 1:], g["expected_after_nT"][..., 1:], rtol=0.1)
    # a bias acts the same way
    gb = compensation_gain(B_NT, rates_dps=(1.0,), gyro_noise_dps=(0.0,), gyro_bias_dps=0.1,
                           n_trials=4000)
    assert 0.5 < gb["removed"].max() < 0.99
    assert "removed" in format_compensation_table(g)


def test_stored_offset():
    rng = np.random.default_rng(3)
    o = np.array([-3385.0, 349.0, -2085.0])
    B = B_NT * _unit(rng, 1)[0]
    w = np.array([3.0, -6.0, 7.0])
    td = t_delay_ms(10.0)
    out1 = B + o
    out2 = -field_after(B, w, td) + o
    plain = StoredOffset()
    with pytest.raises(ValueError):
        plain.field_from_set(out1)
    plain.update(out1, out2)
    # a later SET-only reading carries the offset error into the field one-to-one
    B_later = field_after(B, w, 500.0)
    err_plain = plain.field_from_set(B_later + o) - B_later
    assert np.allclose(err_plain, -offset_error_vector(B, w, td), atol=1e-9)
    comp = StoredOffset(td)
    comp.update(out1, out2, rate_dps=w)
    assert np.allclose(comp.offset_nT, o, atol=1e-8)
    assert np.allclose(comp.field_from_set(B_later + o), B_later, atol=1e-8)
    with pytest.raises(ValueError, match="t_delay"):
        StoredOffset().update(out1, out2, rate_dps=w)
    with pytest.raises(ValueError, match="non-finite"):
        comp.update(out1 * np.nan, out2)
    assert np.allclose(comp.offset_nT, o, atol=1e-8)       # kept
    assert np.allclose(StoredOffset.field_from_pair(out1, out2),
                       0.5 * (B + field_after(B, w, td)))


def test_compensate_offset_vectorised_matches_loop():
    rng = np.random.default_rng(4)
    B = B_NT * _unit(rng, 30)
    o = rng.normal(0, 3000, (30, 3))
    w = rng.normal(0, 8, (30, 3))
    td = rng.uniform(2, 12, 30)
    out2 = -field_after(B, w, td) + o
    vec = compensate_offset(B + o, out2, w, td)
    loop = np.array([compensate_offset(B[i] + o[i], out2[i], w[i], td[i]) for i in range(30)])
    assert np.allclose(vec, loop, atol=1e-9)
    assert np.allclose(vec, o, atol=1e-8)
    with pytest.raises(ValueError):
        compensate_offset(B, B, w, td, method="magic")


# ---------------------------------------------------------------------------------------
# On the shared rotation campaign: 12 ms between SET and RESET, hand rotation to 25 deg/s
# ---------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=None)
def _shared(fm1_dir):
    from generator.fit import thermal as fit_thermal
    from generator.fit.alignment import align_boom
    from generator.io.telemetry_csv import preprocess, read_telemetry
    from generator.io.truth import load_truth
    from generator.io.unitfile import load_unit
    unit = load_unit(fm1_dir / "unit.toml")
    cals = fit_thermal.fit_unit(unit, [read_telemetry(fm1_dir / "thermal_12pos.csv", unit)])
    rot = read_telemetry(fm1_dir / "rotation.csv", unit)
    H = align_boom(unit, rot, cals).H
    return unit, cals, rot, preprocess(rot, unit), H, load_truth(fm1_dir / "truth.json"), \
        np.load(fm1_dir / "rotation.truth.npz")


@pytest.mark.parametrize("name", ["mmc1", "mmc2"])
def test_shared_chip_offset_gyro_compensation(fm1_dir, name):
    """The bridge offset from the pairs in rotation.csv carries the turn during the 12 ms;
    the gyro rate (and the fitted calibration and H) removes it down to the noise, and the
    delay that removes most is the README's 12 ms."""
    unit, cals, rot, data, H, truth, npz = _shared(fm1_dir)
    spec = unit.sensor(name)
    poly = truth["sensors"][name]["chip_offset_poly_sensor_nT"]
    temp = npz["temp_body_C"] if spec.frame == "body" else npz["temp_boom_C"]
    o_true = sum(poly[k] * (temp - truth["t_ref_C"])[:, None] ** k for k in range(len(poly)))
    rate = np.column_stack([rot.columns[f"rate_{a}_dps"] for a in "xyz"])

    def rms(delay_ms):
        o = chip_offset_compensated(spec, data[name], cals[name], rate, t_delay_ms_=delay_ms,
                                    H_boom_to_body=H)
        return float(np.sqrt(np.mean((o - o_true) ** 2)))

    before = float(np.sqrt(np.mean((data[name].chip_offset_sensor_nT - o_true) ** 2)))
    assert rms(0.0) == pytest.approx(before, rel=1e-9)
    after = rms(12.0)
    assert after < 0.5 * before
    # what is left is the pair's own noise: noise / sqrt(2) per axis
    assert after < 1.15 * spec.noise_nT / np.sqrt(2)
    assert after < min(rms(6.0), rms(18.0))
