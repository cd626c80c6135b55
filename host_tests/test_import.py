"""Issue 15 items 3, 4 (reading) and 6: ICD section 4 keys and columns, the field model, the
importers (`magcal import px4 | csv`). Synthetic inputs only; the real recordings are in
test_realdata_e2e.py."""

from __future__ import annotations

import datetime as dt
import math

import numpy as np
import pytest

from generator.cli import main
from generator.errors import InputError
from generator.io.telemetry_csv import preprocess, read_telemetry
from generator.io.unitfile import load_unit

UNIT = """[unit]
id = "quad"

[[sensor]]
name = "ist"
part = "IST8310"
frame = "body"
axes = ["+x", "+y", "+z"]
input = "uT"
temperature = false

[[sensor]]
name = "mmc"
part = "MMC5883MA"
frame = "body"
axes = ["+x", "+y", "+z"]
lsb_nT = 25.0
zero_count = 32768
set_reset = false
"""

ISS_TLE = ["1 25544U 98067A   08264.51782528 -.00002182  00000-0 -11606-4 0  2927",
           "2 25544  51.6416 247.4627 0006703 130.5360 325.0288 15.72125391563537"]


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


# --------------------------------------------------------------------------- unit file

def test_icd4_keys_read(tmp_path):
    text = UNIT + ('\n[orbit]\nepoch_utc = "2026-03-01T00:00:00Z"\n'
                   f'tle = ["{ISS_TLE[0]}", "{ISS_TLE[1]}"]\n'
                   "\n[requirements]\nfield_error_nT = 150.0\nangle_deg = 0.5\n")
    u = load_unit(_write(tmp_path, "u.toml", text))
    ist, mmc = u.sensors
    assert (ist.input, ist.temperature, ist.nT_per_input) == ("uT", False, 1000.0)
    assert ist.required_columns == ("ist_x", "ist_y", "ist_z")
    assert (mmc.input, mmc.temperature) == ("counts", True)
    assert mmc.required_columns[-1] == "mmc_temp_C"
    assert u.extra["orbit"] == {"epoch_utc": "2026-03-01T00:00:00Z", "tle": ISS_TLE}
    assert u.extra["requirements"] == {"field_error_nT": 150.0, "angle_deg": 0.5}


BAD_UNITS = {
    "input unknown": ('input = "uT"', 'input = "T"', "input: 'T' is not one of counts, nT, uT, mG, G"),
    "temperature not bool": ("temperature = false", 'temperature = "no"',
                             "temperature: 'no' is not true or false"),
    "generic without range": ('part = "IST8310"', 'part = "generic"', "range_nT: missing"),
    "counts without lsb": ('lsb_nT = 25.0\n', '', "lsb_nT: missing"),
}


@pytest.mark.parametrize("case", list(BAD_UNITS))
def test_icd4_sensor_key_faults(tmp_path, case):
    old, new, fragment = BAD_UNITS[case]
    p = _write(tmp_path, "u.toml", UNIT.replace(old, new, 1))
    with pytest.raises(InputError) as e:
        load_unit(p)
    assert str(e.value).startswith(str(p)) and fragment in str(e.value)


BAD_TABLES = {
    "epoch not UTC": ('[orbit]\nepoch_utc = "1 March 2026"\n', "[orbit]: epoch_utc"),
    "epoch impossible": ('[orbit]\nepoch_utc = "2026-02-30T00:00:00Z"\n', "[orbit]: epoch_utc"),
    "epoch missing": ('[orbit]\ntle = []\n', "[orbit]: epoch_utc: missing"),
    "tle checksum": ('[orbit]\nepoch_utc = "2026-03-01T00:00:00Z"\n'
                     f'tle = ["{ISS_TLE[0][:-1]}8", "{ISS_TLE[1]}"]\n', "line 1: checksum '8'"),
    "tle one line": ('[orbit]\nepoch_utc = "2026-03-01T00:00:00Z"\n'
                     f'tle = ["{ISS_TLE[0]}"]\n', "[orbit]: tle: must be a list of the two lines"),
    "requirement negative": ("[requirements]\nangle_deg = -0.5\n",
                             "[requirements]: angle_deg: -0.5 must be positive"),
    "requirement text": ('[requirements]\nfield_error_nT = "150"\n',
                         "[requirements]: field_error_nT: '150' is not a finite number"),
}


@pytest.mark.parametrize("case", list(BAD_TABLES))
def test_orbit_and_requirements_faults(tmp_path, case):
    extra, fragment = BAD_TABLES[case]
    p = _write(tmp_path, "u.toml", UNIT + "\n" + extra)
    with pytest.raises(InputError) as e:
        load_unit(p)
    assert str(e.value).startswith(str(p)) and fragment in str(e.value), str(e.value)


# --------------------------------------------------------------------------- telemetry

def _tel(tmp_path, rows, header="time_s,ist_x,ist_y,ist_z,mmc_x,mmc_y,mmc_z,mmc_temp_C"):
    unit = load_unit(_write(tmp_path, "u.toml", UNIT))
    p = _write(tmp_path, "t.csv", header + "\n" + "\n".join(rows) + "\n")
    return unit, p


def test_physical_units_and_no_temperature(tmp_path):
    unit, p = _tel(tmp_path, ["0,20.5,-3.25,45.125,33768,32768,32000,21.0",
                              "1,1600,0,0,33768,32768,32000,21.0",       # at the IST8310 full scale
                              "2,,1,1,33768,32768,32000,21.0"])          # a missing cell
    tel = read_telemetry(p, unit)
    d = preprocess(tel, unit)["ist"]
    np.testing.assert_array_equal(d.field_frame_nT[0], [20500.0, -3250.0, 45125.0])
    assert list(d.usable) == [True, False, False]
    assert (d.n_saturated, d.n_missing) == (1, 1)
    assert not d.has_temperature and np.isnan(d.temp_C).all()
    np.testing.assert_array_equal(d.temp_or(25.0), [25.0, 25.0, 25.0])
    m = preprocess(tel, unit)["mmc"]
    assert m.has_temperature and list(m.temp_C) == [21.0] * 3
    np.testing.assert_array_equal(m.temp_or(25.0), m.temp_C)
    np.testing.assert_array_equal(m.field_frame_nT[0], [25000.0, 0.0, -19200.0])


def test_temperature_column_required_only_where_reported(tmp_path):
    unit, p = _tel(tmp_path, ["0,1,1,1,1,1,1"], header="time_s,ist_x,ist_y,ist_z,mmc_x,mmc_y,mmc_z")
    with pytest.raises(InputError) as e:
        read_telemetry(p, unit)
    assert "column 'mmc_temp_C'" in str(e.value)


@pytest.mark.parametrize("column,value", [("lat_deg", "91"), ("lon_deg", "-181"),
                                          ("kp_index", "9.5"), ("alt_km", "-3")])
def test_position_columns_checked(tmp_path, column, value):
    unit, p = _tel(tmp_path, ["0,1,1,1,1,1,1,20,0", f"1,1,1,1,1,1,1,20,{value}"],
                   header=f"time_s,ist_x,ist_y,ist_z,mmc_x,mmc_y,mmc_z,mmc_temp_C,{column}")
    with pytest.raises(InputError) as e:
        read_telemetry(p, unit)
    assert str(e.value).startswith(f"{p}:3: column '{column}'")


def test_position_columns_kept_as_channels(tmp_path):
    unit, p = _tel(tmp_path, ["0,1,1,1,1,1,1,20,52.5,13.3,0.05,3"],
                   header="time_s,ist_x,ist_y,ist_z,mmc_x,mmc_y,mmc_z,mmc_temp_C,"
                          "lat_deg,lon_deg,alt_km,kp_index")
    tel = read_telemetry(p, unit)
    assert tel.columns["kp_index"][0] == 3.0 and tel.columns["lat_deg"][0] == 52.5


# --------------------------------------------------------------------------- field model

def test_igrf_dipole_against_the_published_2020_coefficients():
    """IGRF-13 at 2020.0: g10 = -29404.8, g11 = -1450.9, h11 = 4652.5 nT (Alken et al. 2021,
    Earth Planets Space 73:49, table of coefficients). The dipole field on the equator at
    longitude 0 (geodetic = geocentric there, r = 6378.137 km) in closed form:
    N = -g10 (a/r)^3, E = -h11 (a/r)^3, D = -2 g11 (a/r)^3, a = 6371.2 km."""
    from generator.io.geomag import field_ned_nT, ppigrf_coefficient_file
    f = field_ned_nT(0.0, 0.0, 0.0, "2020-01-01T00:00:00Z", max_degree=1,
                     coeff_file=ppigrf_coefficient_file("IGRF13.shc"))
    s = (6371.2 / 6378.137) ** 3
    np.testing.assert_allclose(f[0], [29404.8 * s, -4652.5 * s, 2 * 1450.9 * s], rtol=0, atol=1e-6)
    # at longitude 90 E: N = -g10 s, E = g11 s, D = -2 h11 s
    f = field_ned_nT(0.0, 90.0, 0.0, dt.datetime(2020, 1, 1), max_degree=1,
                     coeff_file=ppigrf_coefficient_file("IGRF13.shc"))
    np.testing.assert_allclose(f[0], [29404.8 * s, -1450.9 * s, -2 * 4652.5 * s], rtol=0, atol=1e-6)


def test_field_model_vectorised_over_positions_and_days():
    from generator.io.geomag import field_ned_nT
    lat, lon, alt = [52.5, -30.0, 80.0], [13.3, -50.0, 0.0], [0.0, 400.0, 0.0]
    days = np.array(["2024-01-01T03:00", "2024-01-01T23:00", "2024-06-01T00:00"],
                    dtype="datetime64[us]")
    f = field_ned_nT(lat, lon, alt, days)
    assert f.shape == (3, 3)
    for k in range(3):
        np.testing.assert_allclose(f[k], field_ned_nT(lat[k], lon[k], alt[k], days[k])[0])
    # the total field lies between the weakest (South Atlantic, ~22,000 nT) and the
    # strongest (near the magnetic poles, ~67,000 nT) values the main field has at the
    # surface, times (a / (a + h))^3 at height h (the dipole falls as 1/r^3)
    shrink = (6371.2 / (6371.2 + np.asarray(alt))) ** 3
    B = np.linalg.norm(f, axis=1)
    assert np.all((20000 * shrink < B) & (B < 68000 * shrink))
    # inclination: down at 80 N, up over southern Brazil (south of the dip equator)
    assert f[2, 2] > 0 and f[1, 2] < 0


# --------------------------------------------------------------------------- PX4 pieces

def test_ned_to_body():
    from generator.io.px4_ulog import ned_to_body
    v = np.array([[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(ned_to_body(np.array([[1.0, 0, 0, 0]]), v), v)
    c = math.cos(math.radians(45)); q = np.array([[c, 0, 0, c]])     # yaw +90 deg
    # nose points east: body x = east, body y = south (FRD: right of east), z = down
    np.testing.assert_allclose(ned_to_body(q, v), [[2.0, -1.0, 3.0]], atol=1e-12)


def _px4_folder(tmp_path, devid=0x061E09, temp="nan"):
    d = tmp_path / "log"
    d.mkdir()
    rows = ["timestamp,x,y,z,temperature,device_id"]
    rows += [f"{1000000 + 20000 * k},0.2,0.01,0.45,{temp},{devid}" for k in range(50)]
    (d / "sensor_mag_0.csv").write_text("\n".join(rows) + "\n")
    out = ["timestamp,output[0],output[1]"] + [f"{1000000 + 100000 * k},{1000 + 10 * k},1500"
                                               for k in range(10)]
    (d / "actuator_outputs_0.csv").write_text("\n".join(out) + "\n")
    return d


def test_px4_csv_folder_import(tmp_path):
    assert main(["import", "px4", str(_px4_folder(tmp_path)), "--reference", "none",
                 "-o", str(tmp_path / "o"), "-q"]) == 0
    u = load_unit(tmp_path / "o" / "unit.toml")
    s = u.sensor("mag0")
    assert (s.part, s.input, s.temperature) == ("IST8310", "G", False)
    tel = read_telemetry(tmp_path / "o" / "log.csv", u)
    assert tel.n == 50 and "act0_out0" in tel.columns and "act0_out1" not in tel.columns
    assert tel.columns["act0_out0"][0] == 1000 and tel.columns["act0_out0"][-1] == 1090
    d = preprocess(tel, u)["mag0"]
    np.testing.assert_allclose(d.field_frame_nT[0], [20000.0, 1000.0, 45000.0])


def test_px4_unknown_devtype_is_generic_and_as_counts_states_its_stand_ins(tmp_path):
    assert main(["import", "px4", str(_px4_folder(tmp_path, devid=0x7F0009)),
                 "--reference", "none", "--as-counts", "10", "-o", str(tmp_path / "o"),
                 "-q"]) == 0
    text = (tmp_path / "o" / "unit.toml").read_text()
    assert "not in the catalogue" in text and "constant stand-in" in text
    u = load_unit(tmp_path / "o" / "unit.toml")
    s = u.sensor("mag0")
    assert (s.part, s.input, s.lsb_nT, s.temperature) == ("generic", "counts", 10.0, True)
    tel = read_telemetry(tmp_path / "o" / "log.csv", u)
    np.testing.assert_array_equal(tel.columns["mag0_x"][:2], [2000.0, 2000.0])


def test_px4_reference_needs_gnss(tmp_path, capsys):
    rc = main(["import", "px4", str(_px4_folder(tmp_path)), "-o", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--reference none" in err[0]
    assert not (tmp_path / "o" / "unit.toml").exists()


# --------------------------------------------------------------------------- generic import

def test_csv_import_with_map_and_time_scale(tmp_path):
    src = _write(tmp_path, "rec.csv", "t_ms,bx,by,bz,temp\n0,10,20,30,21.5\n20,11,21,31,21.5\n")
    assert main(["import", "csv", str(src), "--map",
                 "time_s=t_ms,mag_x=bx,mag_y=by,mag_z=bz,mag_temp_C=temp",
                 "--input", "mG", "--part", "QMC5883L", "--time-scale", "1e-3",
                 "-o", str(tmp_path / "o"), "-q"]) == 0
    u = load_unit(tmp_path / "o" / "unit.toml")
    s = u.sensor("mag")
    assert (s.part, s.input, s.temperature) == ("QMC5883L", "mG", True)
    tel = read_telemetry(tmp_path / "o" / "rec.csv", u)
    np.testing.assert_array_equal(tel.time_s, [0.0, 0.02])
    np.testing.assert_array_equal(preprocess(tel, u)["mag"].field_frame_nT[1], [1100, 2100, 3100])


def test_hdf5_import_components(tmp_path):
    h5py = pytest.importorskip("h5py")
    p = tmp_path / "rec.h5"
    with h5py.File(p, "w") as f:
        f["mag"] = np.arange(12.0).reshape(4, 3)          # (N, 3)
        f["buf"] = np.arange(8.0).reshape(2, 4)           # (k, N)
    assert main(["import", "csv", str(p), "--map", "m_x=mag:0,m_y=mag:1,m_z=mag:2,ch=buf:1",
                 "--input", "nT", "--rate-hz", "10", "--range-nT", "1e5",
                 "-o", str(tmp_path / "o"), "-q"]) == 0
    u = load_unit(tmp_path / "o" / "unit.toml")
    tel = read_telemetry(tmp_path / "o" / "rec.csv", u)
    np.testing.assert_array_equal(tel.columns["m_y"], [1, 4, 7, 10])
    np.testing.assert_array_equal(tel.columns["ch"], [4, 5, 6, 7])
    np.testing.assert_array_equal(tel.time_s, [0.0, 0.1, 0.2, 0.3])


@pytest.mark.parametrize("args,fragment", [
    (["--map", "mag_x=bx,mag_y=by"], "sensor 'mag' has mag_x but no mag_z"),
    (["--map", "mag_x=bx,mag_y=by,mag_z=nope"], "no column 'nope'"),
    (["--map", "mag_x=bx;mag_y=by"], "not TARGET=SOURCE"),
    (["--map", "mag_x=bx,mag_y=by,mag_z=bz", "--part", "XYZ"], "'XYZ' is not a known part"),
    (["--map", "mag_x=bx,mag_y=by,mag_z=bz", "--part", "generic"], "needs --range-nT"),
])
def test_csv_import_faults_exit_2(tmp_path, capsys, args, fragment):
    src = _write(tmp_path, "rec.csv", "bx,by,bz\n1,2,3\n")
    rc = main(["import", "csv", str(src), "--rate-hz", "1", "--part", "LIS3MDL", *args,
               "-o", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and fragment in err[0], err
    assert not (tmp_path / "o" / "unit.toml").exists()


def test_px4_attitude_reference_known_answer(tmp_path):
    """Level and facing east (yaw +90 deg): body x = east, y = south, z = down, so the
    body-frame reference is (E, -N, D) of the field model at the logged position and time;
    PX4 v1.14+ GNSS fields (sensor_gps, degrees and metres)."""
    from generator.io.geomag import field_ned_nT
    d = _px4_folder(tmp_path)
    t0 = 1_000_000
    utc0 = 1_700_000_000_000_000                       # 2023-11-14T22:13:20Z
    gps = ["timestamp,time_utc_usec,latitude_deg,longitude_deg,altitude_ellipsoid_m,fix_type"]
    gps += [f"{t0 + 200000 * k},{utc0 + 200000 * k},52.5,13.3,100.0,3" for k in range(6)]
    (d / "sensor_gps_0.csv").write_text("\n".join(gps) + "\n")
    c = math.cos(math.radians(45))
    att = ["timestamp,q[0],q[1],q[2],q[3]"] + [f"{t0 + 10000 * k},{c},0,0,{c}" for k in range(100)]
    (d / "vehicle_attitude_0.csv").write_text("\n".join(att) + "\n")
    assert main(["import", "px4", str(d), "-o", str(tmp_path / "o"), "-q"]) == 0
    u = load_unit(tmp_path / "o" / "unit.toml")
    tel = read_telemetry(tmp_path / "o" / "log.csv", u)
    assert tel.meta["utc_at_time_0"] == "2023-11-14T22:13:20.000000Z"
    ned = field_ned_nT(52.5, 13.3, 0.1, dt.datetime(2023, 11, 14, 22, 13, 20))[0]  # the sample's UTC
    ref = np.stack([tel.columns[f"ref_{a}_nT"] for a in "xyz"], axis=1)
    np.testing.assert_allclose(ref[0], [ned[1], -ned[0], ned[2]], rtol=0, atol=1e-4)
    np.testing.assert_allclose(tel.columns["ref_norm_nT"][0], np.linalg.norm(ned), atol=1e-4)
    np.testing.assert_array_equal(tel.columns["lat_deg"][:3], [52.5] * 3)


@pytest.mark.parametrize("args,fragment", [
    (["--unit-id", "Bad Id"], "id: 'Bad Id' does not match"),
    (["--map", "Mag_x=bx,Mag_y=by,Mag_z=bz"], "name: 'Mag' does not match"),
])
def test_import_never_leaves_files_the_toolchain_refuses(tmp_path, capsys, args, fragment):
    src = _write(tmp_path, "rec.csv", "bx,by,bz\n1,2,3\n")
    base = ["import", "csv", str(src), "--rate-hz", "1", "--part", "LIS3MDL",
            "--map", "mag_x=bx,mag_y=by,mag_z=bz", "-o", str(tmp_path / "o")]
    rc = main(base + args)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and fragment in err[0] and "nothing written" in err[0], err
    assert not (tmp_path / "o").exists()     # not even the folder the import would make
