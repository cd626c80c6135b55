"""Issue 15: `magcal apply` on a unit with physical-input sensors (ICD section 4).

Telemetry whose <s>_x.. columns hold real numbers in uT or G goes through the compiled
flight C (HostUnit passes them as the flight float type) and agrees bit for bit with the
Python reference, selection included; the output CSV holds those bits. A sensor without
a temperature needs no <s>_temp_C column in the apply path.

apply reads the file with the full ICD reader (io.telemetry_csv.iter_telemetry, every
check, section 4 included); `test_apply_command_reads_physical_telemetry` also runs the
real command.
"""

from __future__ import annotations

import csv

import numpy as np

from chain_fixtures import bits, random_coeffs, random_inputs
from generator import pipeline
from generator.cli import main
from generator.flight import chain
from generator.flight.chain import (NULL_STATE, SensorState, reference_select,
                                    reference_sensor)
from generator.flight.host import HostUnit
from generator.io.unit import SensorSpec, Unit
from test_any_unit import physical_inputs
from test_cli import read_apply_csv

N = 600


def _unit() -> Unit:
    """An IST8310-like uT sensor without temperature, a G sensor with SET/RESET and a
    temperature on the boom, and an MMC5883MA in counts (the boom reference)."""
    return Unit("physapp", (
        SensorSpec("ist", "generic", "body", ("+y", "-x", "+z"), 1.0, 0, False, 100.0,
                   input="uT", temperature=False, range_nT=1.6e6),
        SensorSpec("hmg", "generic", "boom", ("-z", "+y", "+x"), 1.0, 0, True, 100.0,
                   input="G", temperature=True, range_nT=8e5),
        SensorSpec("mmc", "MMC5883MA", "body", ("+x", "+y", "+z"), 25.0, 32768, True, 40.0)),
        lab_field_nT=50000.0, boom_reference="mmc")


def _coeffs():
    return random_coeffs(np.random.default_rng(41), _unit())


def _text(v) -> str:
    """Readings as a logger writes them: a few decimals, so the value is not exact in
    float32 and the text -> float64 -> float type rounding is part of what is compared."""
    return f"{v:.5f}" if np.isfinite(v) else ""


def _write_telemetry(path, cs, rng, n=N):
    """The ICD CSV of n samples; returns {column: float64 values as written} (NaN where
    the cell is empty: a few missing readings and temperatures)."""
    cols = {"time_s": np.arange(n) * 0.1}
    fmt = {"time_s": repr}
    for s in cs.unit.sensors:
        t = (-20.0, 55.0)
        if chain.is_physical(s):
            raw, temp, _ = physical_inputs(rng, s, np.float64, n, 0, t)
            raw = np.array([[float(_text(v)) for v in row] for row in raw])
        else:
            raw, temp, _ = random_inputs(rng, s, n, 0, t)
        raw = raw.astype(np.float64)
        raw[rng.random(n) < 0.02, rng.integers(0, raw.shape[1])] = np.nan
        for k, c in enumerate(s.count_columns):
            cols[c] = raw[:, k]
            fmt[c] = _text if chain.is_physical(s) else (lambda v: str(int(v)))
        if s.temperature:
            temp = np.round(np.asarray(temp, np.float64), 2)
            temp[rng.random(n) < 0.02] = np.nan
            cols[s.temp_column] = temp
            fmt[s.temp_column] = repr
    with open(path, "w", newline="") as f:
        f.write(f"# unit: {cs.unit.id}\n")
        w = csv.writer(f, lineterminator="\n")
        w.writerow(list(cols))
        for i in range(n):
            w.writerow([fmt[c](float(v[i])) if np.isfinite(v[i]) else ""
                        for c, v in cols.items()])
    return cols



def _expected(cs, cols):
    """The reference of `apply`: per sensor reference_sensor over the rows (missing cells
    as zeros, rows with one not present), then reference_select with ABSENT statuses."""
    n = cols["time_s"].size
    out, present = {}, {}
    for s in cs.unit.sensors:
        raw = np.stack([cols[c] for c in s.count_columns], axis=1)
        temp = cols[s.temp_column] if s.temperature else np.zeros(n)
        present[s.name] = np.all(np.isfinite(raw), axis=1) & np.isfinite(temp)
        fill = 0.0 if chain.is_physical(s) else s.zero_count
        raw = np.where(np.isfinite(raw), raw, fill)
        if not chain.is_physical(s):
            raw = raw.astype(np.int64)
        out[s.name] = reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(),
                                       raw, np.where(np.isfinite(temp), temp, 0.0))
    fields = np.stack([out[s.name]["field_body_nT"] for s in cs.unit.sensors], axis=1)
    st = np.stack([np.where(present[s.name], out[s.name]["status"], pipeline.STATUS_ABSENT)
                   for s in cs.unit.sensors], axis=1).astype(np.uint16)
    flat = {s.name: cs.flat_sensor(s.name) for s in cs.unit.sensors}
    sel = reference_select(cs.spec, flat, fields, st)
    for k, s in enumerate(cs.unit.sensors):
        # a sample missing from the file carries the ABSENT bit (valid = status 0)
        out[s.name]["status"] = np.where(present[s.name], sel["status"][:, k],
                                         np.asarray(out[s.name]["status"], dtype=np.uint16)
                                         | pipeline.STATUS_ABSENT)
    return out, present, sel


def test_apply_physical_unit_bit_identical(tmp_path):
    cs = _coeffs()
    rng = np.random.default_rng(42)
    data = tmp_path / "tel.csv"
    cols = _write_telemetry(data, cs, rng)
    out_csv = tmp_path / "out.csv"
    res = pipeline.apply(cs, data, out_csv, host=HostUnit(cs))
    want, present, sel = _expected(cs, cols)
    got = read_apply_csv(out_csv)
    for s in cs.unit.sensors:
        p = present[s.name]
        assert 0 < np.sum(~p) < N // 10        # some rows missing, most present
        np.testing.assert_array_equal(res[s.name]["present"], p)
        np.testing.assert_array_equal(res[s.name]["status"], want[s.name]["status"])
        f_c, f_py = res[s.name]["field_body_nT"][p], want[s.name]["field_body_nT"][p]
        np.testing.assert_array_equal(bits(f_c), bits(f_py), err_msg=s.name)
        # the output file holds the same float32 values
        f_csv = np.stack([got[f"{s.name}_{a}_nT"] for a in "xyz"], axis=1)[p]
        np.testing.assert_array_equal(bits(f_csv.astype(np.float32)), bits(f_c))
        assert np.all(np.isnan(np.stack([got[f"{s.name}_{a}_nT"] for a in "xyz"], 1)[~p]))
        np.testing.assert_array_equal(got[f"{s.name}_status"], res[s.name]["status"])
        # not vacuous: valid and flagged samples both occur (a quarter of the physical
        # readings are drawn up to 1.2 x full scale, so some saturate)
        valid = res[s.name]["valid"]
        assert np.any(valid) and np.any(~valid & p)
        if chain.is_physical(s):
            assert np.any(res[s.name]["status"] & chain.STATUS_SATURATED)
    for k in ("sensor", "reason"):
        np.testing.assert_array_equal(res["selected"][k], sel[k])
    np.testing.assert_array_equal(bits(res["selected"]["field_body_nT"]),
                                  bits(sel["field_body_nT"]))


def test_apply_scales_physical_readings_to_nT(tmp_path):
    """Independent of the reference: the temperature-free uT sensor's valid outputs are
    M (A x_uT * 1000 - b) of its constant calibration (A: the axis map), within float32
    rounding: a dozen roundings of 2^-24 relative each, so 1e-5 of |B| is ample, while a
    wrong scale (x 1 or x 1e6) or a lost axis sign is off by far more."""
    cs = _coeffs()
    rng = np.random.default_rng(43)
    data = tmp_path / "tel.csv"
    cols = _write_telemetry(data, cs, rng)
    res = pipeline.apply(cs, data, tmp_path / "out.csv", host=HostUnit(cs))
    s = cs.unit.sensor("ist")
    valid = res["ist"]["valid"]
    x = np.stack([cols[c] for c in s.count_columns], axis=1)[valid] * 1000.0
    idx, sign = s.axis_map()
    frame = x[:, list(idx)] * np.array(sign)
    b, M = cs.sensors["ist"]["b_poly_nT"][0], cs.sensors["ist"]["M_poly"][0]
    want = (frame - b) @ M.T
    got = res["ist"]["field_body_nT"][valid].astype(np.float64)
    err = np.linalg.norm(got - want, axis=1)
    assert np.all(err <= 1e-5 * np.linalg.norm(want, axis=1)), err.max()


def test_mixed_calls_on_a_physical_set_reset_sensor(tmp_path):
    """HostUnit.correct_mixed with real-typed readings: pairs, SET-only readings and calls
    with state NULL interleaved on one state, against the reference call by call."""
    cs = _coeffs()
    host = HostUnit(cs)
    s = cs.unit.sensor("hmg")
    rng = np.random.default_rng(44)
    n = 400
    raw, temp, _ = physical_inputs(rng, s, np.float32, n, 0, (-20.0, 55.0))
    mode = rng.integers(0, 4, n).astype(np.uint8)
    c_out = host.correct_mixed(s.name, raw, temp, mode)
    state = SensorState()
    field = np.zeros((n, 3), np.float32)
    status = np.zeros(n, np.uint16)
    for j in range(n):
        one = slice(j, j + 1)
        r = raw[one, :3] if mode[j] & 1 else raw[one]
        o = reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(), r, temp[one],
                             set_only=bool(mode[j] & 1),
                             state=NULL_STATE if mode[j] & 2 else state)
        field[j], status[j] = o["field_body_nT"][0], o["status"][0]
    np.testing.assert_array_equal(c_out["status"], status)
    np.testing.assert_array_equal(bits(c_out["field_body_nT"]), bits(field))
    assert set(np.unique(mode)) == {0, 1, 2, 3}
    # not vacuous: SET-only calls after a stored offset are valid, NULL-state ones never
    assert np.any(status[mode == 1] == 0)
    assert np.all(status[mode == 3] & (chain.STATUS_NO_OFFSET | chain.STATUS_NONFINITE
                                       | chain.STATUS_SATURATED))


def test_apply_command_reads_physical_telemetry(tmp_path):
    """`magcal apply` itself, with the real reader: same output as above."""
    cs = _coeffs()
    cj = tmp_path / "coefficients.json"
    cs.save(cj)
    data = tmp_path / "tel.csv"
    cols = _write_telemetry(data, cs, np.random.default_rng(42))
    out_csv = tmp_path / "out.csv"
    assert main(["apply", str(cj), str(data), "-o", str(out_csv), "-q"]) == 0
    want, present, _ = _expected(cs, cols)
    got = read_apply_csv(out_csv)
    for s in cs.unit.sensors:
        p = present[s.name]
        f_csv = np.stack([got[f"{s.name}_{a}_nT"] for a in "xyz"], axis=1)[p]
        np.testing.assert_array_equal(bits(f_csv.astype(np.float32)),
                                      bits(want[s.name]["field_body_nT"][p]))
