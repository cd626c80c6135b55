"""The field along the track (generator/io/geomag.py, generator/io/orbit.py): IGRF-14
against its published test values, GMST and TEME -> ECEF against Vallado's worked
examples, SGP4 against its verification vector, the geodetic conversions, the cache and
the provenance, and the ICD section 4 hook in read_telemetry."""

from __future__ import annotations

import datetime as dt

import numpy as np
import pytest

from generator.errors import InputError
from generator.io import geomag, orbit

# IGRF-14's reference Python synthesis (BGS, Beggan: github.com/ciaranbe/pyIGRF,
# tests/tests_igrf14.py, "checked independently against igrf.f"): geocentric inputs
# (year, colatitude deg, east longitude deg, radius km) -> X north, Y east, Z down, nT,
# printed to 0.01 nT.
PUBLISHED_GEOCENTRIC = [
    (1900, 175, -150, 6300, (-5072.93, 10620.34, -67233.55)),
    (1915, 155, -120, 6350, (14692.62, 12387.97, -59640.81)),
    (1930, 135, -90, 6400, (23925.47, 10358.94, -30640.98)),
    (1945, 115, -60, 6450, (23642.86, -200.29, -7607.92)),
    (1960, 95, -30, 6500, (23647.00, -9302.27, -3610.73)),
    (1975, 75, 0, 6550, (30050.59, -3367.82, 6332.69)),
    (1990, 55, 30, 6600, (25224.81, 1058.25, 30965.61)),
    (2005, 35, 60, 6650, (14718.37, 2842.99, 46050.88)),
    (2020, 15, 90, 6700, (3734.07, 1294.17, 50833.13)),
    (2025, 90, 45, 6900, (25587.26, -826.43, -7422.32)),
]

# Geodetic (WGS-84) values from the IGRF-14 Fortran synthesis program igrf14syn, as
# tabulated by JuliaSpace/SatelliteToolboxGeomagneticField.jl test/IGRF14_test_geodetic.txt
# (generated with github.com/JuliaSpace/IGRF_Test): decimal year, height km, colatitude
# deg, east longitude deg -> X, Y, Z nT. Rows at LEO heights and within 1900..2030.
PUBLISHED_GEODETIC = [
    (2012.2, 77.18, 4.81, 190.69, (750.03774, 394.68103, 55395.16588)),
    (2022.1, 829.10, 46.47, 114.85, (17590.40262, -1731.07191, 33147.28408)),
    (2027.9, 139.86, 45.06, 138.29, (23759.41728, -4335.97718, 42511.80742)),
    (2027.0, 101.99, 68.54, 277.27, (24647.90876, -2283.98317, 29268.17197)),
    (2017.2, 1029.13, 66.26, 261.15, (16402.51962, 1108.31298, 21223.24303)),
    (2019.6, 861.84, 41.70, 23.47, (14724.38753, 1061.14256, 30350.70774)),
    (1971.9, 372.19, 4.23, 244.39, (-1032.48029, 117.36753, 48759.11091)),
    (1993.0, 1145.39, 88.84, 343.59, (16112.16708, -3907.33032, -3484.93100)),
    (2008.1, 1152.32, 66.75, 6.87, (19007.16917, -602.76526, 10717.49049)),
]

# The criterion: the computed field matches the published values within 1 nT.
PUBLISHED_TOLERANCE_nT = 1.0


def _decimal_year(y: float) -> dt.datetime:
    """igrf14syn's decimal year: the fraction of that calendar year's days."""
    year = int(y)
    start = dt.datetime(year, 1, 1)
    return start + dt.timedelta(days=(y - year) * (dt.datetime(year + 1, 1, 1) - start).days)


def test_ppigrf_ships_igrf14_and_it_is_the_default():
    info = geomag.model_info()
    assert info["model"] == "IGRF-14"
    assert info["coefficient_file"] == "IGRF14.shc"
    assert info["span_utc"] == ["1900-01-01T00:00:00", "2030-01-01T00:00:00"]
    assert len(info["coefficient_sha256"]) == 64


@pytest.mark.parametrize("year,colat,lon,r,xyz", PUBLISHED_GEOCENTRIC)
def test_published_geocentric_values(year, colat, lon, r, xyz):
    f = geomag.field_geocentric_nT(r, colat, lon, dt.datetime(year, 1, 1))[0]
    assert np.max(np.abs(f - np.asarray(xyz))) < PUBLISHED_TOLERANCE_nT


@pytest.mark.parametrize("year,h,colat,lon,xyz", PUBLISHED_GEODETIC)
def test_published_geodetic_values(year, h, colat, lon, xyz):
    f = geomag.field_ned_nT(90.0 - colat, lon, h, _decimal_year(year))[0]
    assert np.max(np.abs(f - np.asarray(xyz))) < PUBLISHED_TOLERANCE_nT


@pytest.mark.parametrize("year,h,colat,lon,xyz", PUBLISHED_GEODETIC[:4])
def test_magnitude_through_ecef_equals_the_geodetic_one(year, h, colat, lon, xyz):
    """The orbit path (geodetic -> ECEF -> geocentric spherical) gives the same |B|."""
    e = orbit.geodetic_to_ecef_km(np.array([90.0 - colat]), np.array([lon]), np.array([h]))
    r, th, ph = orbit.ecef_to_spherical(e)
    f = geomag.field_geocentric_nT(r, th, ph, _decimal_year(year))[0]
    assert abs(np.linalg.norm(f) - np.linalg.norm(xyz)) < PUBLISHED_TOLERANCE_nT


def test_time_within_a_day_is_honoured_exactly():
    """Two evaluations a day, linearly weighted, equal ppigrf at the exact time (the
    coefficients are linear in time between epochs)."""
    import ppigrf
    t = dt.datetime(2026, 3, 1, 17, 23, 11)
    Be, Bn, Bu = ppigrf.igrf(30.0, 45.0, 500.0, t)
    f = geomag.field_ned_nT(45.0, 30.0, 500.0, t)[0]
    np.testing.assert_allclose(f, [Bn.item(), Be.item(), -Bu.item()], atol=1e-6)


def test_dates_outside_the_model_refused():
    with pytest.raises(ValueError, match="outside the field model"):
        geomag.check_model_dates([dt.datetime(2031, 1, 1)])


def test_gmst_vallado_example_3_5():
    # Vallado, Fundamentals of Astrodynamics and Applications, Example 3-5:
    # 1992 August 20, 12:14 UT1 -> GMST = 152.578787810 deg
    g = orbit.gmst_rad(np.array(["1992-08-20T12:14:00"], dtype="datetime64[us]"))
    assert abs(np.degrees(g[0]) - 152.578787810) < 1e-6


def test_teme_to_ecef_vallado_example():
    """Vallado et al. 2006 (AIAA 2006-6753) / Vallado Example 3-15: r_TEME -> r_ITRF at
    2004-04-06 07:51:28.386009 UTC with UT1 - UTC = -0.4399619 s. With UT1 given, what we
    leave out is polar motion (xp = -0.140682", yp = 0.333309": 0.36" of 6380 km, 11 m,
    so within 0.02 km); with UT1 = UTC the 0.44 s of Earth rotation at 7970 km from the
    axis moves the point by 7.29e-5 rad/s * 0.44 s * 7970 km = 0.26 km (so within 0.3)."""
    r_teme = np.array([[5094.18016210, 6127.64465950, 6380.34453270]])
    r_itrf = np.array([-1033.4793830, 7901.2952754, 6380.3565958])
    t_utc = np.array(["2004-04-06T07:51:28.386009"], dtype="datetime64[us]")
    t_ut1 = t_utc + np.timedelta64(-439962, "us")
    assert np.linalg.norm(orbit.teme_to_ecef_km(r_teme, t_ut1)[0] - r_itrf) < 0.02
    d = np.linalg.norm(orbit.teme_to_ecef_km(r_teme, t_utc)[0] - r_itrf)
    assert 0.2 < d < 0.3


def test_sgp4_verification_vector():
    # Vallado et al. 2006, SGP4-VER.TLE, satellite 00005 at its epoch (tsince = 0):
    # r = (7022.46529266, -1400.08296755, 0.03995155) km in TEME
    tle = ["1 00005U 58002B   00179.78495062  .00000023  00000-0  28098-4 0  4753",
           "2 00005  34.2682 348.7242 1859667 331.7664  19.3264 10.82419157413667"]
    ep = orbit.tle_epoch_utc(tle)
    r = orbit.sgp4_teme_km(tle, np.array([ep]))[0]
    # the epoch is rounded to 1 us here; the satellite moves ~8 km/s: < 0.01 m
    np.testing.assert_allclose(r, [7022.46529266, -1400.08296755, 0.03995155], atol=1e-4)


def test_geodetic_round_trip():
    rng = np.random.default_rng(3)
    lat = np.concatenate([rng.uniform(-89.9, 89.9, 200), [90.0, -90.0, 0.0]])
    lon = np.concatenate([rng.uniform(-180, 180, 200), [0.0, 0.0, 180.0]])
    h = np.concatenate([rng.uniform(-1, 2000, 200), [500.0, 0.0, 0.0]])
    la, lo, hh = orbit.ecef_to_geodetic(orbit.geodetic_to_ecef_km(lat, lon, h))
    np.testing.assert_allclose(la, lat, atol=1e-9)
    np.testing.assert_allclose(lo, lon, atol=1e-9)
    np.testing.assert_allclose(hh, h, atol=1e-6)


ISS_TLE = ["1 25544U 98067A   08264.51782528 -.00002182  00000-0 -11606-4 0  2927",
           "2 25544  51.6416 247.4627 0006703 130.5360 325.0288 15.72125391563537"]


def test_iss_track_is_physical():
    """SGP4 + TEME -> ECEF for the ISS: latitude within the inclination, height of the
    2008 ISS (~350 km), and ~15.7 revolutions a day in the Earth-fixed longitude."""
    ep = orbit.tle_epoch_utc(ISS_TLE)
    t = ep + (np.arange(0, 5400, 30) * 1e6).astype("timedelta64[us]")
    e = orbit.teme_to_ecef_km(orbit.sgp4_teme_km(ISS_TLE, t), t)
    lat, lon, h = orbit.ecef_to_geodetic(e)
    assert np.max(np.abs(lat)) <= 51.6416 + 0.2      # geodetic vs geocentric latitude
    assert np.max(np.abs(lat)) > 51.0
    assert 330 < h.min() and h.max() < 380


def _write_orbit_case(tmp_path, columns: str, rows, orbit_toml=""):
    from generator.campaign.simulate import make_example_unit, write_unit_toml
    unit = make_example_unit()
    p = tmp_path / "unit.toml"
    write_unit_toml(unit, p)
    if orbit_toml:
        p.write_text(p.read_text() + "\n" + orbit_toml)
    header = "time_s," + ",".join(c for s in unit.sensors for c in s.required_columns)
    n_sensor = header.count(",")
    zeros = []
    for s in unit.sensors:
        zeros += [str(s.zero_count)] * len(s.count_columns) + ["25.2"] * (len(s.required_columns) - len(s.count_columns))
    csv = tmp_path / "orbit.csv"
    lines = [header + ("," + columns if columns else "")]
    for i, r in enumerate(rows):
        lines.append(",".join([str(10.0 * i)] + zeros) + ("," + r if r else ""))
    csv.write_text("\n".join(lines) + "\n")
    assert n_sensor == len(zeros)
    return p, csv


def test_read_telemetry_computes_the_reference_from_gnss(tmp_path, monkeypatch):
    from generator.io.telemetry_csv import read_telemetry
    from generator.io.unitfile import load_unit
    monkeypatch.setenv("MAGCAL_CACHE", str(tmp_path / "cache"))
    u, csv = _write_orbit_case(tmp_path, "lat_deg,lon_deg,alt_km,kp_index",
                               ["45.0,10.0,500.0,1", "46.0,11.0,500.0,5", "47.0,12.0,500.0,"],
                               '[orbit]\nepoch_utc = "2026-03-01T00:00:00Z"\n')
    unit = load_unit(u)
    tel = read_telemetry(csv, unit)
    prov = tel.meta["field_reference"]
    assert prov["model"] == "IGRF-14" and prov["cache"] == "miss"
    assert prov["kp_left_out"] == 1
    expect = np.linalg.norm(geomag.field_ned_nT(45.0, 10.0, 500.0,
                                                dt.datetime(2026, 3, 1))[0])
    assert abs(tel.columns["ref_norm_nT"][0] - expect) < 1e-6
    assert np.isnan(tel.columns["ref_norm_nT"][1])     # Kp 5: left out
    assert np.isfinite(tel.columns["ref_norm_nT"][2])  # Kp unknown: kept
    again = read_telemetry(csv, unit)
    assert again.meta["field_reference"]["cache"] == "hit"
    np.testing.assert_array_equal(again.columns["ref_norm_nT"], tel.columns["ref_norm_nT"])
    assert "IGRF-14" in orbit.describe(prov)


def test_read_telemetry_from_the_tle(tmp_path, monkeypatch):
    from generator.io.telemetry_csv import read_telemetry
    from generator.io.unitfile import load_unit
    monkeypatch.setenv("MAGCAL_CACHE", str(tmp_path / "cache"))
    toml = ('[orbit]\nepoch_utc = "2008-09-20T12:25:40Z"\n'
            f'tle = ["{ISS_TLE[0]}", "{ISS_TLE[1]}"]\n')
    u, csv = _write_orbit_case(tmp_path, "", [""] * 5, toml)
    tel = read_telemetry(csv, load_unit(u))
    assert tel.meta["field_reference"]["position_source"].startswith("SGP4")
    B = tel.columns["ref_norm_nT"]
    assert np.all((B > 18000) & (B < 60000))       # |B| at 350 km is 20,000 - 55,000 nT


def test_position_without_epoch_reads_but_cannot_be_fitted(tmp_path):
    """Read: the positions are channels (apply needs no reference); the fit refuses the
    file instead of taking the unit's lab_field_nT for orbit data."""
    from generator.io.telemetry_csv import read_telemetry
    from generator.io.unitfile import load_unit
    u, csv = _write_orbit_case(tmp_path, "lat_deg,lon_deg,alt_km", ["45,10,500"])
    tel = read_telemetry(csv, load_unit(u))
    assert "ref_norm_nT" not in tel.columns
    with pytest.raises(InputError, match="epoch_utc"):
        orbit.require_field_reference(tel)


def test_partial_position_is_bad_input(tmp_path):
    from generator.io.telemetry_csv import read_telemetry
    from generator.io.unitfile import load_unit
    u, csv = _write_orbit_case(tmp_path, "lat_deg,lon_deg", ["45,10"],
                               '[orbit]\nepoch_utc = "2026-03-01T00:00:00Z"\n')
    with pytest.raises(InputError, match="alt_km"):
        read_telemetry(csv, load_unit(u))


def test_epoch_outside_the_model_is_bad_input(tmp_path, monkeypatch):
    from generator.io.telemetry_csv import read_telemetry
    from generator.io.unitfile import load_unit
    monkeypatch.setenv("MAGCAL_CACHE", str(tmp_path / "cache"))
    u, csv = _write_orbit_case(tmp_path, "lat_deg,lon_deg,alt_km", ["45,10,500"],
                               '[orbit]\nepoch_utc = "2031-03-01T00:00:00Z"\n')
    with pytest.raises(InputError, match="outside the field model"):
        read_telemetry(csv, load_unit(u))


def test_file_with_a_reference_is_left_alone(tmp_path):
    from generator.io.telemetry_csv import read_telemetry
    from generator.io.unitfile import load_unit
    u, csv = _write_orbit_case(tmp_path, "lat_deg,lon_deg,alt_km,ref_norm_nT",
                               ["45,10,500,40000"])
    tel = read_telemetry(csv, load_unit(u))
    assert "field_reference" not in tel.meta
    assert tel.columns["ref_norm_nT"][0] == 40000.0


def test_ecef_in_metres_is_bad_input_naming_the_line(tmp_path):
    from generator.io.telemetry_csv import read_telemetry
    from generator.io.unitfile import load_unit
    u, csv = _write_orbit_case(tmp_path, "ecef_x_km,ecef_y_km,ecef_z_km",
                               ["6878.0,0,0", "6878000.0,0,0"],
                               '[orbit]\nepoch_utc = "2026-03-01T00:00:00Z"\n')
    with pytest.raises(InputError, match="from the Earth's centre") as e:
        read_telemetry(csv, load_unit(u))
    assert e.value.line == 3 and e.value.column == "ecef_x_km"


def test_cli_fit_on_bad_orbit_input_is_one_line_exit_2(tmp_path, capsys):
    from generator.cli import main
    u, csv = _write_orbit_case(tmp_path, "lat_deg,lon_deg,alt_km", ["45,10,500"])
    assert main(["fit", str(u), str(csv), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "epoch_utc" in err[0]
    assert not (tmp_path / "o").exists()


def test_tle_sgp4_cannot_use_is_bad_input(tmp_path, monkeypatch):
    """Checksums right, but a mean motion of 0 rev/day: SGP4 refuses the elements."""
    from generator.io.telemetry_csv import read_telemetry
    from generator.io.unitfile import _tle_checksum, load_unit
    monkeypatch.setenv("MAGCAL_CACHE", str(tmp_path / "cache"))
    l2 = ISS_TLE[1][:52] + "00.00000000" + ISS_TLE[1][63:68]
    l2 += _tle_checksum(l2 + "0")
    toml = f'[orbit]\nepoch_utc = "2008-09-21T00:00:00Z"\ntle = ["{ISS_TLE[0]}", "{l2}"]\n'
    u, csv = _write_orbit_case(tmp_path, "", [""], toml)
    with pytest.raises(InputError, match=r"\[orbit\] tle"):
        read_telemetry(csv, load_unit(u))


def test_time_far_beyond_any_model_is_bad_input(tmp_path):
    from generator.io.telemetry_csv import read_telemetry
    from generator.io.unitfile import load_unit
    u, csv = _write_orbit_case(tmp_path, "lat_deg,lon_deg,alt_km", ["45,10,500"],
                               '[orbit]\nepoch_utc = "2026-03-01T00:00:00Z"\n')
    csv.write_text(csv.read_text().replace("\n0.0,", "\n1e15,"))
    with pytest.raises(InputError, match="200 years") as e:
        read_telemetry(csv, load_unit(u))
    assert e.value.column == "time_s"


def test_cli_trace_on_orbit_input_without_epoch_is_one_line_exit_2(tmp_path, capsys):
    from generator.cli import main
    u, csv = _write_orbit_case(tmp_path, "lat_deg,lon_deg,alt_km", ["45,10,500"] * 3)
    assert main(["trace", str(u), str(csv), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "epoch_utc" in err[0]
    assert not (tmp_path / "o").exists()
