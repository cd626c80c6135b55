"""Issue 14, flight tables: monotonic serials, physical validation, the compiled-in
default checked at init with a defined fallback, and a non-finite thermal-lag state
cleared by the next finite sample.

Every rule is tried on hand-built coefficient sets whose verdict is known without running
either validator (exact determinants, exact H^T H entries, serial orders), and the same
input goes through the flight C (generator.flight.table_host.TableHost, cffi) and the
Python ground code (tables.check_table, table_manager.TableManager): both must give the expected
status and name the same bad value.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

from chain_fixtures import (edit_coeffs, m_poly, assert_bit_identical, bits, random_coeffs, random_inputs,
                            random_rotation, samsat_unit, with_float, with_options)
from generator.flight import chain, tables
from generator.flight.chain import SensorOptions, SensorState, reference_sensor
from generator.flight.coeffs import CoefficientSet
from generator.flight.host import HostUnit
from generator.flight.table_host import TableHost
from generator.flight.table_manager import TableManager, init_status
from generator.flight.tables import (NO_INDEX, TableError, TableStatus,
                                     check_table, chunk_table, encode_table)

S = TableStatus


def _base(unit_id="rulesat", float_type="float32", seed=14):
    cs = random_coeffs(np.random.default_rng(seed), samsat_unit(unit_id, float_type))
    return with_float(cs, float_type) if float_type == "float64" else cs




BASE = {"f32": _base(), "f64": _base("rule64", "float64")}


@functools.lru_cache(maxsize=None)
def host(label) -> TableHost:
    return TableHost(BASE[label])


def _python_status(table, spec):
    try:
        check_table(table, spec)
        return S.OK, NO_INDEX
    except TableError as e:
        return e.status, (NO_INDEX if e.bad_value_index is None else e.bad_value_index)


def _verdict(label, cs, serial=3):
    """(status, bad index) of the flight C and of the ground validator, which must agree."""
    table = encode_table(cs, serial, 0, check=False)
    c = host(label).validate_detail(table)
    py = _python_status(table, cs.spec)
    assert c == py, (c, py)
    return c


def _m_index(spec, sensor):
    return next(m.m_poly for m in tables._matrix_indices(spec) if m.sensor == sensor)


# ---- physical validation ------------------------------------------------------------------

# M0 with an exact determinant (small integers and products of the diagonal)
DET_CASES = [
    ("identity", np.eye(3), S.OK),
    ("all zero", np.zeros((3, 3)), S.BAD_DETERMINANT),
    ("reflected axis", np.diag([1.0, 1.0, -1.0]), S.BAD_DETERMINANT),
    ("two axes swapped", np.array([[0, 1, 0], [1, 0, 0], [0, 0, 1.0]]), S.BAD_DETERMINANT),
    ("rank 2", np.array([[1, 0, 0], [0, 1, 0], [1, 1, 0.0]]), S.BAD_DETERMINANT),
    ("gains 0.3: det 0.027 < 1/27", np.diag([0.3, 0.3, 0.3]), S.BAD_DETERMINANT),
    ("gains 0.34: det 0.0393 > 1/27", np.diag([0.34, 0.34, 0.34]), S.OK),
    ("gains 3: det 27, the bound", np.diag([3.0, 3.0, 3.0]), S.OK),
    # every element within the matrix_poly range [-3, 3], det 3 * 9 + 1 * 3 = 30 > 27
    ("det 30 from in-range elements", np.array([[3, -1, 0], [1, 3, 0], [0, 0, 3.0]]),
     S.BAD_DETERMINANT),
]


@pytest.mark.parametrize("label", list(BASE))
@pytest.mark.parametrize("name,m0,want", DET_CASES, ids=[c[0] for c in DET_CASES])
def test_determinant_of_the_constant_term(label, name, m0, want):
    base = BASE[label]
    for sensor in ("mmc1", "mpu3"):      # a body and a boom sensor
        cs = edit_coeffs(base, sensor, M_poly=m_poly(m0))
        st, bad = _verdict(label, cs)
        assert st == want, (name, sensor, st)
        if want != S.OK:
            assert bad == _m_index(cs.spec, sensor)


@pytest.mark.parametrize("label", list(BASE))
def test_determinant_at_the_ends_of_the_temperature_range(label):
    """M(T) = I + M1 (T - t_ref): singular at t_max_C (or t_min_C) although M0 = I.
    t_ref 25, range [-20, 55]: M1 = -I/30 puts M(55) at 0; M1 = +I/45 puts M(-20) at 0;
    M1 = -I/60 leaves M(55) = I/2 (det 1/8) and M(-20) = 1.75 I (det 5.36): plausible."""
    base = BASE[label]
    cases = [(-np.eye(3) / 30.0, S.BAD_DETERMINANT), (np.eye(3) / 45.0, S.BAD_DETERMINANT),
             (-np.eye(3) / 60.0, S.OK)]
    for m1, want in cases:
        cs = edit_coeffs(base, "mpu1", M_poly=m_poly(np.eye(3), m1), t_ref_C=25.0, t_min_C=-20.0,
                   t_max_C=55.0)
        st, bad = _verdict(label, cs)
        assert st == want, (m1[0, 0], st)
        if want != S.OK:
            assert bad == _m_index(cs.spec, "mpu1")
    # the values computed are those expected: det M(55) = (1 - 30/60)^3 = 1/8, exactly
    cs = edit_coeffs(base, "mpu1", M_poly=m_poly(np.eye(3), -np.eye(3) / 60.0), t_ref_C=25.0,
               t_min_C=-20.0, t_max_C=55.0)
    vals = tables.flat_values(cs).astype(tables.value_dtype(cs.spec))
    dets = dict(tables.physical_values(cs.spec, vals)["det_M"])["mpu1"]
    assert dets[0] == 1.0 and abs(float(dets[2]) - 0.125) < 1e-6 \
        and abs(float(dets[1]) - 1.75 ** 3) < 1e-5


H_CASES = [
    # (name, H, expected status, index (i, j) of the bad element of H)
    ("identity", np.eye(3), S.OK, None),
    ("a fitted rotation", None, S.OK, None),
    ("scaled by 1.0005", 1.0005 * np.eye(3), S.NOT_A_ROTATION, (0, 0)),
    ("scaled by 1.2 (out of the element range first)", 1.2 * np.eye(3),
     S.VALUE_OUT_OF_RANGE, None),
    ("sheared by 1e-4", np.eye(3) + np.array([[0, 1e-4, 0], [0, 0, 0], [0, 0, 0]]),
     S.NOT_A_ROTATION, (0, 1)),
    ("sheared by 5e-6, within the allowance", np.eye(3) +
     np.array([[0, 5e-6, 0], [0, 0, 0], [0, 0, 0]]), S.OK, None),
    ("a reflection (orthogonal, det -1)", np.diag([1.0, -1.0, 1.0]), S.NOT_A_ROTATION, (0, 0)),
    ("all zero", np.zeros((3, 3)), S.NOT_A_ROTATION, (0, 0)),
]


@pytest.mark.parametrize("label", list(BASE))
@pytest.mark.parametrize("name,H,want,where", H_CASES, ids=[c[0] for c in H_CASES])
def test_boom_alignment_must_be_a_rotation(label, name, H, want, where):
    base = BASE[label]
    if H is None:
        H = random_rotation(np.random.default_rng(5), max_angle_rad=0.5)
    cs = edit_coeffs(base, H_boom_to_body=H)
    st, bad = _verdict(label, cs)
    assert st == want, (name, st)
    h0 = tables._rotation_index(cs.spec)
    if want == S.NOT_A_ROTATION:
        assert bad == h0 + 3 * where[0] + where[1]
    if want == S.VALUE_OUT_OF_RANGE:
        assert bad == h0


@pytest.mark.parametrize("label", list(BASE))
def test_rotation_tolerance_is_the_stated_one(label):
    """H = I with H[0][1] = x: (H^T H - I)[0][1] is x exactly and the diagonal stays 0
    (x^2 is below half an ulp of 1), so x = tol passes and the next float fails."""
    base = BASE[label]
    dt = tables.value_dtype(base.spec)
    tol = dt.type(tables.PHYSICAL_LIMITS.rotation_tol)
    for x, want in ((tol, S.OK), (np.nextafter(tol, dt.type(1)), S.NOT_A_ROTATION),
                    (-tol, S.OK), (np.nextafter(-tol, dt.type(-1)), S.NOT_A_ROTATION)):
        H = np.eye(3)
        H[0, 1] = float(x)
        st, bad = _verdict(label, edit_coeffs(base, H_boom_to_body=H))
        assert st == want, (x, st)
    # 1e-5 < tol < 1.1e-5: the allowance plus 2^-21
    assert 1.0e-5 < float(tol) < 1.1e-5


def test_a_unit_without_boom_has_no_rotation_check():
    unit = samsat_unit("noboom")
    from dataclasses import replace
    unit = replace(unit, sensors=unit.sensors[:3], boom_reference=None)
    cs = random_coeffs(np.random.default_rng(2), unit)
    assert tables._rotation_index(cs.spec) is None
    h = TableHost(cs)
    table = encode_table(cs, 1, 0)
    assert h.validate(table) == S.OK
    bad = edit_coeffs(cs, "mpu2", M_poly=m_poly(np.zeros((3, 3))))
    t = encode_table(bad, 1, 0, check=False)
    assert h.validate_detail(t) == _python_status(t, cs.spec) == \
        (S.BAD_DETERMINANT, _m_index(cs.spec, "mpu2"))


def test_order_of_the_physical_checks():
    """Range before determinant before rotation: a table failing all three says range;
    without the range fault, det; the first sensor in unit order is named."""
    base = BASE["f32"]
    cs = edit_coeffs(edit_coeffs(edit_coeffs(base, "mpu2", M_poly=m_poly(np.zeros((3, 3)))), "mmc2",
                     M_poly=m_poly(-np.eye(3))), H_boom_to_body=1.0005 * np.eye(3))
    assert _verdict("f32", cs) == (S.BAD_DETERMINANT, _m_index(cs.spec, "mpu2"))
    cs2 = edit_coeffs(cs, "mpu1", lsb_nT=0.0)
    assert _verdict("f32", cs2)[0] == S.VALUE_OUT_OF_RANGE


def test_encoder_refuses_physically_wrong_coefficients():
    base = BASE["f32"]
    with pytest.raises(TableError) as e:
        encode_table(edit_coeffs(base, H_boom_to_body=1.0005 * np.eye(3)), 1, 0)
    assert e.value.status == S.NOT_A_ROTATION and "H^T H - I" in str(e.value)
    with pytest.raises(TableError) as e:
        encode_table(edit_coeffs(base, "mmc1", M_poly=m_poly(np.zeros((3, 3)))), 1, 0)
    assert e.value.status == S.BAD_DETERMINANT and "mmc1 det M at t_ref_C = 0" in str(e.value)


def test_example_unit_passes_the_physical_checks():
    from chain_fixtures import EXAMPLE_COEFFS

    if not EXAMPLE_COEFFS.exists():
        pytest.skip("no committed example unit")
    cs = CoefficientSet.load(EXAMPLE_COEFFS)
    vals = tables.flat_values(cs).astype(np.float32)
    phys = tables.physical_values(cs.spec, vals)
    for name, dets in phys["det_M"]:
        assert all(0.5 < float(d) < 2 for d in dets), (name, dets)   # gains near 1
    assert max(abs(float(g)) for g in phys["HtH_minus_I"]) < 1e-6    # rounding only
    assert init_status(cs.spec, vals) == (S.OK, None)


# ---- monotonic serials ---------------------------------------------------------------------


def _tables(label):
    base = BASE[label]
    other = random_coeffs(np.random.default_rng(99), base.unit)
    if base.unit.float_type == "float64":
        other = with_float(other, "float64")
    return base, other


def _both(h, mgr, py, method, *args):
    c = getattr(h, method)(mgr, *args) if args else getattr(h, method)(mgr)
    p = getattr(py, method)(*args)
    p = p[0] if isinstance(p, tuple) else p
    assert c == p, (method, c, p)
    return c


@pytest.mark.parametrize("label", list(BASE))
@pytest.mark.parametrize("via", ["load", "parts"])
def test_serials_refuse_rollback_and_replay(label, via):
    base, other = _tables(label)
    h = host(label)
    mgr = h.manager()
    py = TableManager(base.spec, tables.flat_values(base))

    def send(cs, serial):
        t = encode_table(cs, serial, 1_790_000_000 + serial)
        if via == "load":
            return _both(h, mgr, py, "load", t)
        for p in chunk_table(t, 300):
            assert _both(h, mgr, py, "receive_part", p) == S.OK
        return _both(h, mgr, py, "commit")

    def active():
        return bits(h.active_flat(mgr)).copy(), h.info(mgr)["active_serial"]

    # first boot: the compiled-in default is serial 0
    assert h.info(mgr)["active_serial"] == 0 and h.info(mgr)["coeffs_valid"] == 1
    assert send(other, 0) == S.SERIAL_REPLAY        # serial 0 with other contents
    assert send(base, 0) == S.ALREADY_ACTIVE        # serial 0, the defaults themselves
    assert send(other, 5) == S.OK
    assert h.info(mgr)["active_serial"] == 5
    np.testing.assert_array_equal(bits(h.active_flat(mgr)),
                                  bits(tables.flat_values(other).astype(h.dtype)))
    before = active()
    assert send(base, 1) == S.SERIAL_ROLLBACK       # older serial, valid table
    assert send(other, 4) == S.SERIAL_ROLLBACK      # older serial, same contents
    assert send(base, 5) == S.SERIAL_REPLAY         # same serial, other contents
    assert send(other, 5) == S.ALREADY_ACTIVE       # same serial, same contents
    assert h.info(mgr)["last_status"] == S.ALREADY_ACTIVE
    after = active()
    np.testing.assert_array_equal(after[0], before[0])
    assert after[1] == before[1] == 5
    assert send(base, 6) == S.OK                    # newer: accepted
    assert send(other, 2 ** 32 - 1) == S.OK         # the last serial there is
    assert send(base, 2 ** 32 - 1) == S.SERIAL_REPLAY
    np.testing.assert_array_equal(py.active_values.view(f"u{py.active_values.itemsize}"),
                                  bits(h.active_flat(mgr)))


def test_created_time_is_not_contents():
    """Same serial and coefficients, another created_s: nothing to change."""
    base, other = _tables("f32")
    h = host("f32")
    mgr = h.manager()
    assert h.load(mgr, encode_table(other, 7, 100)) == S.OK
    assert h.load(mgr, encode_table(other, 7, 200)) == S.ALREADY_ACTIVE


def test_a_refused_table_checks_before_the_serial():
    """A table with a lower serial that is also corrupt says what is wrong with it."""
    base, other = _tables("f32")
    h = host("f32")
    mgr = h.manager()
    assert h.load(mgr, encode_table(other, 9, 0)) == S.OK
    bad = encode_table(edit_coeffs(base, H_boom_to_body=1.0005 * np.eye(3)), 3, 0, check=False)
    assert h.load(mgr, bad) == S.NOT_A_ROTATION


# ---- the compiled-in default, validated at init -------------------------------------------


BAD_DEFAULTS = [
    ("H scaled by 1.2", dict(H_boom_to_body=1.2 * np.eye(3)), None, S.VALUE_OUT_OF_RANGE),
    ("H scaled by 1.0005", dict(H_boom_to_body=1.0005 * np.eye(3)), None, S.NOT_A_ROTATION),
    ("mpu2 M all zero", dict(M_poly=m_poly(np.zeros((3, 3)))), "mpu2", S.BAD_DETERMINANT),
]


@functools.lru_cache(maxsize=None)
def _bad_default_unit(i):
    name, blocks, sensor, want = BAD_DEFAULTS[i]
    cs = edit_coeffs(_base(f"baddef{i}"), sensor, **blocks)
    return cs, TableHost(cs)


@pytest.mark.parametrize("i", range(len(BAD_DEFAULTS)), ids=[c[0] for c in BAD_DEFAULTS])
def test_a_default_that_fails_its_checks_is_not_used(i):
    """A unit built with a broken default (the C of coeffs_default.c holds it): init
    reports the failing check and the first bad value, marks the coefficients invalid and
    puts NaN in use, so every correction is flagged IMPLAUSIBLE and select finds no
    sensor; a valid table then restores the chain."""
    name, blocks, sensor, want = BAD_DEFAULTS[i]
    cs, h = _bad_default_unit(i)
    mgr, st = h.init()
    assert st == want, (name, st)
    info = h.info(mgr)
    assert info["last_status"] == want and info["coeffs_valid"] == 0
    assert info["active_serial"] == 0
    py = TableManager(cs.spec, tables.flat_values(cs))
    assert py.init_status == want and not py.coeffs_valid
    assert info["last_bad_value"] == py.init_bad
    active = h.active_flat(mgr)
    assert np.all(np.isnan(active))
    np.testing.assert_array_equal(bits(active), bits(py.active_values))
    # the fallback: every correction flagged, nothing selected
    hu = HostUnit(cs)
    rng = np.random.default_rng(3)
    fields, statuses = [], []
    for s in cs.unit.sensors:
        raw, temp, coil = random_inputs(rng, s, 500, 0, (-20.0, 55.0))
        out = hu.correct(s.name, raw, temp, coil, coeffs_flat=active)
        assert np.all(out["status"] & chain.STATUS_IMPLAUSIBLE), s.name
        fields.append(out["field_body_nT"])
        statuses.append(out["status"])
    fields, statuses = np.stack(fields, axis=1), np.stack(statuses, axis=1)
    sel = hu.select(fields, statuses, coeffs_flat=active)
    assert np.all(sel["reason"] == chain.SELECT_NONE) and np.all(sel["sensor"] == -1)
    # a valid table restores it (serial >= 1; serial 0 is the default's and refused)
    good = _base("good", seed=15)
    good = CoefficientSet(cs.spec, good.sensors, good.unit_values)
    assert h.load(mgr, encode_table(good, 0, 0)) == S.SERIAL_REPLAY
    assert h.load(mgr, encode_table(good, 1, 0)) == S.OK
    assert h.info(mgr)["coeffs_valid"] == 1
    assert py.load(encode_table(good, 1, 0)) == S.OK and py.coeffs_valid


def test_init_with_valid_defaults_and_with_a_bad_struct():
    """init on the fixture's own defaults is OK; the same TableHost given a bad struct
    (flat values) reports it the same way as a build with that default."""
    h = host("f32")
    mgr, st = h.init()
    assert st == S.OK and h.info(mgr)["coeffs_valid"] == 1
    assert h.info(mgr)["last_bad_value"] == NO_INDEX
    vals = tables.flat_values(BASE["f32"]).astype(np.float32)
    vals[_m_index(BASE["f32"].spec, "mmc1") + 4] = -1.0     # M0[1][1] of mmc1 negative
    mgr, st = h.init(vals)
    assert st == S.BAD_DETERMINANT and h.info(mgr)["coeffs_valid"] == 0
    assert h.info(mgr)["last_bad_value"] == _m_index(BASE["f32"].spec, "mmc1")
    assert init_status(BASE["f32"].spec, vals) == \
        (S.BAD_DETERMINANT, _m_index(BASE["f32"].spec, "mmc1"))
    vals[3] = np.nan
    assert h.init(vals)[1] == S.NONFINITE_VALUE


# ---- a non-finite thermal-lag state ------------------------------------------------------


@functools.lru_cache(maxsize=None)
def _lag_unit():
    rng = np.random.default_rng(8)
    cs = with_options(rng, random_coeffs(rng, samsat_unit("lagsat")),
                      {"mpu1": SensorOptions(thermal_lag=True),
                       "mmc1": SensorOptions(thermal_lag=True)})
    return cs, HostUnit(cs)


@pytest.mark.parametrize("sensor", ["mpu1", "mmc1"])
def test_a_nonfinite_lag_state_is_cleared_by_the_next_finite_sample(sensor):
    """Two finite but extreme temperatures, +3.4e38 then -3.4e38 with dt = 0, drive the
    element temperature to 3.4e38 + 0 * (-inf) = NaN. The filter must restart from that
    sample, as on a first call: from sample 1 on, the outputs equal a fresh run started at
    sample 1 (an expectation that needs neither implementation), and the C equals the
    Python reference bit for bit. Before the fix, every later output was NaN."""
    cs, hu = _lag_unit()
    s = cs.unit.sensor(sensor)
    rng = np.random.default_rng(1)
    n = 400
    raw, temp, _ = random_inputs(rng, s, n, 0, (-20.0, 55.0))
    temp = temp.astype(np.float32)
    temp[0], temp[1] = 3.4e38, -3.4e38
    dt = rng.uniform(0.5, 2.0, n)
    dt[1] = 0.0
    # later the state goes non-finite once more in the middle of the run
    temp[200], temp[201], dt[201] = 3.4e38, -3.4e38, 0.0
    full = hu.correct(sensor, raw, temp, dt_s=dt)
    state = SensorState()
    ref = reference_sensor(cs.spec, s, cs.flat_sensor(sensor), cs.flat_unit(), raw, temp,
                           dt_s=dt, state=state)
    assert_bit_identical(full, ref, f"{sensor} NaN lag state")
    assert np.isfinite(state.temp_el_C)
    fresh = hu.correct(sensor, raw[1:201], temp[1:201], dt_s=dt[1:201])
    np.testing.assert_array_equal(bits(full["field_body_nT"][1:201]),
                                  bits(fresh["field_body_nT"]))
    np.testing.assert_array_equal(full["status"][1:201], fresh["status"])
    fresh2 = hu.correct(sensor, raw[201:], temp[201:], dt_s=dt[201:])
    np.testing.assert_array_equal(bits(full["field_body_nT"][201:]),
                                  bits(fresh2["field_body_nT"]))
    # the outputs are numbers again (the restarted filter holds an extreme temperature
    # for a while, so they are clamped to the range: finite, flagged TEMP_CLAMPED)
    assert np.all(np.isfinite(full["field_body_nT"]))
    assert not np.any(full["status"] & chain.STATUS_IMPLAUSIBLE & ~ref["status"])


def test_check_command_names_the_physical_fault(tmp_path, capsys):
    """`magcal table --check` (the flight validator on the host) exits 2 naming the new
    check and the bad value."""
    import argparse

    from generator.errors import InputError
    from generator.verbs import table as verbs_table

    base = BASE["f32"]
    coeffs = tmp_path / "coefficients.json"
    base.save(coeffs)
    bad = tmp_path / "bad.bin"
    bad.write_bytes(encode_table(edit_coeffs(base, H_boom_to_body=1.0005 * np.eye(3)), 2, 0,
                                 check=False))
    p = argparse.ArgumentParser()
    verbs_table.add_table_args(p)
    args = p.parse_args(["--check", str(bad), "--coeffs", str(coeffs)])
    with pytest.raises(InputError) as e:
        verbs_table.cmd_table(args)
    msg = str(e.value)
    assert f"error {int(S.NOT_A_ROTATION)} NOT_A_ROTATION" in msg
    assert "unit H_boom_to_body[0][0]" in msg and "bad.bin" in msg
