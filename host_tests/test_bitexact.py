"""The core promise: the generated flight C and the Python reference agree bit for bit.

C is compiled by cffi (-std=c99 -O2 -ffp-contract=off; wrappers -Wall -Wextra -Werror
-pedantic); the Python reference is chain.reference_sensor (float32 elementwise, same
operation order). Outputs are compared as bit patterns, never with a tolerance.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from chain_fixtures import (EXAMPLE_COEFFS, assert_bit_identical, bits, random_coeffs,
                            random_inputs, samsat_unit, with_float)
from generator.flight import chain
from generator.flight.chain import reference_sensor
from generator.flight.coeffs import CoefficientSet
from generator.flight.host import HostUnit

COILS = ("coil_x_A", "coil_y_A", "coil_z_A")
N_RANDOM = 100_000


def _cases():
    """(label, coefficient set) pairs: the committed example unit, and random sets with
    and without coils, in float32 and float64."""
    rng = np.random.default_rng(20261121)
    cases = []
    if EXAMPLE_COEFFS.exists():
        cases.append(("example", CoefficientSet.load(EXAMPLE_COEFFS)))
    cases.append(("random", random_coeffs(rng, samsat_unit("rnd32"))))
    cases.append(("random_coils", random_coeffs(rng, samsat_unit("rndcoil"), coils=COILS)))
    cases.append(("random_f64", with_float(random_coeffs(rng, samsat_unit("rnd64"), coils=COILS),
                                           "float64")))
    return cases


CASES = _cases()


@pytest.fixture(scope="module", params=CASES, ids=[c[0] for c in CASES])
def built(request):
    label, cs = request.param
    return label, cs, HostUnit(cs)


def _both(cs, host, sensor, raw, temp, coil, coeffs_flat=None):
    spec = cs.spec
    s = spec.unit.sensor(sensor)
    c_out = host.correct(sensor, raw, temp, coil, coeffs_flat=coeffs_flat)
    if coeffs_flat is None:
        cs_flat, cu_flat = cs.flat_sensor(sensor), cs.flat_unit()
    else:
        cs_flat, cu_flat = _split(spec, sensor, coeffs_flat)
    py_out = reference_sensor(spec, s, cs_flat, cu_flat, raw, temp, coil)
    return c_out, py_out


def _split(spec, sensor, flat):
    k = 0
    for s in spec.unit.sensors:
        n = spec.n_sensor_coeffs(s)
        if s.name == sensor:
            mine = flat[k:k + n]
        k += n
    return mine, flat[k:]


def test_random_inputs_bit_identical(built):
    label, cs, host = built
    rng = np.random.default_rng(1)
    for s in cs.unit.sensors:
        t = (cs.sensors[s.name]["t_min_C"], cs.sensors[s.name]["t_max_C"])
        raw, temp, coil = random_inputs(rng, s, N_RANDOM, len(cs.spec.coils), t)
        c_out, py_out = _both(cs, host, s.name, raw, temp, coil)
        assert_bit_identical(c_out, py_out, f"{label}/{s.name}")
        # the comparison is not vacuous: outputs vary and most samples are valid
        assert np.unique(bits(c_out["field_body_nT"][:, 0])).size > N_RANDOM // 2
        st_ = c_out["status"]
        assert np.mean((st_ & ~np.uint16(chain.STATUS_IMPLAUSIBLE)) == 0) > 0.3
        assert 0.01 < np.mean(st_ & chain.STATUS_IMPLAUSIBLE) / chain.STATUS_IMPLAUSIBLE < 0.99


def test_edge_cases_bit_identical(built):
    label, cs, host = built
    for s in cs.unit.sensors:
        t_min = float(cs.sensors[s.name]["t_min_C"])
        t_max = float(cs.sensors[s.name]["t_max_C"])
        f32 = np.float32
        temps = [t_min, t_max, np.nextafter(f32(t_min), f32(-np.inf)),
                 np.nextafter(f32(t_max), f32(np.inf)), np.nextafter(f32(t_min), f32(np.inf)),
                 -273.15, 1e30, -1e30, 0.0, -0.0, 25.0, np.inf, -np.inf, np.nan]
        k = 6 if s.set_reset else 3
        counts = [s.count_min, s.count_min + 1, s.zero_count, s.count_max - 1, s.count_max]
        raws = [np.full(k, c) for c in counts]
        raws.append(np.resize([s.count_min, s.count_max], k))
        if s.set_reset:   # zero field with a bridge offset: set == reset
            raws.append(np.array([40000, 30000, 20000, 40000, 30000, 20000]))
        rows, trows = [], []
        for r in raws:
            for t in temps:
                rows.append(r)
                trows.append(t)
        raw = np.array(rows)
        temp = np.array(trows, dtype=np.float32)
        coil = None
        if cs.spec.coils:
            coil = np.zeros((raw.shape[0], len(cs.spec.coils)))
            coil[::7] = 0.1
            coil[3::11, 0] = np.nan
            coil[5::13, 1] = np.inf
        c_out, py_out = _both(cs, host, s.name, raw, temp, coil)
        assert_bit_identical(c_out, py_out, f"{label}/{s.name} edges")
        st_ = c_out["status"]
        nonfinite = ~np.isfinite(temp)
        assert np.all(st_[nonfinite] & chain.STATUS_NONFINITE)
        assert np.all(c_out["field_body_nT"][nonfinite] == 0)
        beyond = np.isfinite(temp) & ((temp < np.float32(t_min)) | (temp > np.float32(t_max)))
        if coil is not None:
            beyond &= np.all(np.isfinite(coil), axis=1)
        assert np.all(st_[beyond] & chain.STATUS_TEMP_CLAMPED)
        at_rail = np.any((raw <= s.count_min) | (raw >= s.count_max), axis=1)
        assert np.all(st_[at_rail] & chain.STATUS_SATURATED)
        assert np.all((st_[~at_rail & ~nonfinite & ~beyond] & chain.STATUS_SATURATED) == 0)
        if coil is None:
            # zero field: a clamped temperature must give exactly the value at the range end
            clamped_lo = temp == np.float32(-1e30)
            at_lo = temp == np.float32(t_min)
            np.testing.assert_array_equal(bits(c_out["field_body_nT"][clamped_lo]),
                                          bits(c_out["field_body_nT"][at_lo]))


def test_coils_null_equals_zero_currents(built):
    label, cs, host = built
    if not cs.spec.coils:
        pytest.skip("no coils in this chain")
    rng = np.random.default_rng(3)
    s = cs.unit.sensors[0]
    raw, temp, _ = random_inputs(rng, s, 1000)
    a = host.correct(s.name, raw, temp, None)
    b = host.correct(s.name, raw, temp, np.zeros((1000, len(cs.spec.coils))))
    np.testing.assert_array_equal(bits(a["field_body_nT"]), bits(b["field_body_nT"]))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_property_any_single_sample(data):
    """Hypothesis: any counts in range, any float32 temperature (inf/nan included), any
    currents: C and Python agree bit for bit."""
    label, cs = CASES[-2]   # random coefficient set with coils, float32
    if label not in _HOSTS:
        _HOSTS[label] = HostUnit(cs)
    host = _HOSTS[label]
    s = data.draw(st.sampled_from(cs.unit.sensors))
    k = 6 if s.set_reset else 3
    raw = np.array([data.draw(st.lists(st.integers(s.count_min, s.count_max), min_size=k,
                                       max_size=k))])
    temp = np.array([data.draw(st.floats(width=32, allow_nan=True, allow_infinity=True))],
                    dtype=np.float32)
    coil = np.array([data.draw(st.lists(st.floats(-1.0, 1.0, width=32), min_size=3,
                                        max_size=3))])
    c_out, py_out = _both(cs, host, s.name, raw, temp, coil)
    assert_bit_identical(c_out, py_out, f"hypothesis/{s.name}")


_HOSTS: dict = {}


def test_the_comparison_catches_a_perturbed_coefficient(built):
    """The smallest change of one matrix coefficient that reaches the kernel, in the
    reference only: the suite must notice. The kernel reads M folded with the count scale
    (chain.prepare_sensor, rounded once), so one ulp of the table's M can round to the
    same prepared value; the coefficient is stepped ulp by ulp until its prepared value
    changes (a few steps: the scale is at most a binade away)."""
    label, cs, host = built
    rng = np.random.default_rng(7)
    s = cs.unit.sensors[0]
    t = (cs.sensors[s.name]["t_min_C"], cs.sensors[s.name]["t_max_C"])
    raw, temp, coil = random_inputs(rng, s, 20_000, len(cs.spec.coils), t)
    c_out = host.correct(s.name, raw, temp, coil)
    flat = cs.flat_sensor(s.name).astype(host.dtype)
    k = cs.spec.offsets(cs.spec.sensor_blocks(s))["M_poly"]  # m0_00
    before = chain.prepare_sensor(cs.spec, s, flat, cs.flat_unit())
    for _ in range(4):
        flat[k] = np.nextafter(flat[k], host.dtype(np.inf))
        if not np.array_equal(chain.prepare_sensor(cs.spec, s, flat, cs.flat_unit()), before):
            break
    else:
        raise AssertionError("four ulps of M did not reach the prepared coefficients")
    py_out = reference_sensor(cs.spec, s, flat, cs.flat_unit(), raw, temp, coil)
    with pytest.raises(AssertionError, match="samples differ"):
        assert_bit_identical(c_out, py_out)


def test_the_comparison_catches_a_reordered_operation(built, monkeypatch):
    """Summing the matrix row in another order is the same maths, not the same bits."""
    label, cs, host = built
    rng = np.random.default_rng(8)
    s = cs.unit.sensors[1]
    t = (cs.sensors[s.name]["t_min_C"], cs.sensors[s.name]["t_max_C"])
    raw, temp, coil = random_inputs(rng, s, 20_000, len(cs.spec.coils), t)
    c_out = host.correct(s.name, raw, temp, coil)
    monkeypatch.setattr(chain, "_dot3", lambda row, v: row[2] * v[2] + row[1] * v[1] + row[0] * v[0])
    py_out = reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(), raw, temp, coil)
    with pytest.raises(AssertionError, match="samples differ"):
        assert_bit_identical(c_out, py_out)


def test_compiled_in_defaults_are_the_coefficients(built):
    label, cs, host = built
    np.testing.assert_array_equal(bits(host.default_coeffs()), bits(host.flat_coeffs()))


def test_set_only_readings_bit_identical(built):
    """SET-only readings with a stored offset: C == Python, and with the offset of the same
    pair the field equals the pair's bit for bit."""
    label, cs, host = built
    rng = np.random.default_rng(11)
    for s in cs.unit.sensors:
        if not s.set_reset:
            continue
        t = (cs.sensors[s.name]["t_min_C"], cs.sensors[s.name]["t_max_C"])
        raw, temp, coil = random_inputs(rng, s, 20_000, len(cs.spec.coils), t)
        pair = host.correct(s.name, raw, temp, coil)
        py_pair = reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(), raw,
                                   temp, coil)
        assert_bit_identical(pair, py_pair, f"{label}/{s.name} pair")
        stored = pair["offset_counts"].copy()
        # the state keeps the last unsaturated pair's offset
        own = (pair["status"] & (chain.STATUS_SATURATED | chain.STATUS_NONFINITE)) == 0
        assert 0 < own.sum() < own.size
        stored[rng.random(stored.shape[0]) < 0.05] = np.nan      # no offset stored yet
        c_out = host.correct_set(s.name, raw[:, :3], temp, stored, coil)
        py_out = reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(),
                                  raw[:, :3], temp, coil, set_only=True, offset_counts=stored)
        assert_bit_identical(c_out, py_out, f"{label}/{s.name} set-only")
        fresh = own & np.all(np.isfinite(stored), axis=1)
        np.testing.assert_array_equal(bits(c_out["field_body_nT"][fresh]),
                                      bits(pair["field_body_nT"][fresh]))
        missing = ~np.all(np.isfinite(stored), axis=1) & np.isfinite(temp)
        if coil is not None:
            missing &= np.all(np.isfinite(coil), axis=1)
        assert missing.any() and np.all(c_out["status"][missing] & chain.STATUS_NO_OFFSET)
        assert np.all(c_out["field_body_nT"][missing] == 0)
        # an offset kept from another pair (the satellite turned): C == Python still
        shifted = np.roll(stored, 1, axis=0)
        c2 = host.correct_set(s.name, raw[:, :3], temp, shifted, coil)
        p2 = reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(), raw[:, :3],
                              temp, coil, set_only=True, offset_counts=shifted)
        assert_bit_identical(c2, p2, f"{label}/{s.name} set-only, old offset")


def _select_inputs(rng, cs, n):
    """Sensor fields around one true field, with outliers and invalid sensors (the exact
    ties are test_select_ties_are_agreement)."""
    S = len(cs.unit.sensors)
    truth = rng.normal(0, 30000, (n, 1, 3))
    agree = np.array([cs.sensors[s.name]["agree_nT"] for s in cs.unit.sensors])
    fields = truth + rng.normal(0, 1, (n, S, 3)) * agree[None, :, None] / 8
    outlier = rng.random((n, S)) < 0.15
    fields[outlier] += rng.normal(0, 1, (outlier.sum(), 3)) * 5 * agree.max()
    statuses = np.where(rng.random((n, S)) < 0.15, rng.integers(1, 64, (n, S)), 0)
    return fields, statuses.astype(np.uint16)


def test_select_bit_identical_and_sensible(built):
    label, cs, host = built
    rng = np.random.default_rng(12)
    fields, statuses = _select_inputs(rng, cs, 20_000)
    c_out = host.select(fields, statuses)
    flat = {s.name: cs.flat_sensor(s.name) for s in cs.unit.sensors}
    py_out = chain.reference_select(cs.spec, flat, fields, statuses)
    for k in ("status", "sensor", "rank", "reason"):
        np.testing.assert_array_equal(c_out[k], py_out[k], err_msg=k)
    np.testing.assert_array_equal(bits(c_out["field_body_nT"]), bits(py_out["field_body_nT"]))
    # every reason occurs, the first choice is taken when it is fine, NONE gives zeros
    assert set(np.unique(c_out["reason"])) == {0, 1, 2, 3} or len(cs.unit.sensors) < 3
    order = cs.spec.fallback_order()
    first_ok = c_out["status"][:, order[0]] == 0
    assert np.all(c_out["sensor"][first_ok] == order[0])
    none = c_out["reason"] == chain.SELECT_NONE
    assert np.all(c_out["field_body_nT"][none] == 0) and np.all(c_out["sensor"][none] == -1)
    # a lone outlier among agreeing sensors is flagged
    f = np.repeat(fields[:1, :1, :], len(cs.unit.sensors), axis=1).copy()
    f[0, order[0]] += 10 * max(cs.sensors[s.name]["agree_nT"] for s in cs.unit.sensors)
    one = host.select(f, np.zeros((1, len(cs.unit.sensors)), np.uint16))
    assert one["status"][0, order[0]] & chain.STATUS_DISAGREE
    assert one["sensor"][0] == order[1] and one["reason"][0] == chain.SELECT_CONFIRMED


def test_optional_stages_bit_identical():
    """The flight forms of traced effects (channel coupling, thermal lag, cubic
    nonlinearity, SET/RESET rate compensation, degree 5): C == Python, pair, SET-only
    and the lag recursion over a sequence of calls."""
    from chain_fixtures import random_aux, with_options
    from generator.flight.chain import SensorOptions

    rng = np.random.default_rng(21)
    base = random_coeffs(rng, samsat_unit("optsat"), coils=COILS)
    cs = with_options(rng, base, {
        "mmc1": SensorOptions(channels=("heater_A",), thermal_lag=True, sr_compensation=True),
        "mpu1": SensorOptions(nonlinear=True),
        "mmc2": SensorOptions(channels=("sa_current_A", "heater_A"), nonlinear=True,
                              sr_compensation=True),
        "mpu3": SensorOptions(thermal_lag=True),
    }, poly_degree=5)
    host = HostUnit(cs)
    n = 30_000
    for s in cs.unit.sensors:
        t = (cs.sensors[s.name]["t_min_C"], cs.sensors[s.name]["t_max_C"])
        raw, temp, coil = random_inputs(rng, s, n, len(COILS), t)
        temp[rng.random(n) < 0.01] = np.nan
        channels, rate, dt = random_aux(rng, cs.spec, n, nan_fraction=0.01)
        kw = dict(channels=channels, rate_dps=rate, dt_s=dt)
        c_out = host.correct(s.name, raw, temp, coil, **kw)
        py_out = reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(), raw,
                                  temp, coil, **kw)
        assert_bit_identical(c_out, py_out, f"options/{s.name}")
        assert np.mean(c_out["status"] == 0) > 0.05
        if s.set_reset:
            c_set = host.correct_set(s.name, raw[:, :3], temp, c_out["offset_counts"], coil, **kw)
            py_set = reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(),
                                      raw[:, :3], temp, coil, set_only=True,
                                      offset_counts=c_out["offset_counts"], **kw)
            assert_bit_identical(c_set, py_set, f"options/{s.name} set-only")
        # a null aux is zeros everywhere: still identical
        c0 = host.correct(s.name, raw[:1000], temp[:1000])
        p0 = reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(), raw[:1000],
                              temp[:1000])
        assert_bit_identical(c0, p0, f"options/{s.name} null aux")
    # the stages change the output (the test is not vacuous): lag on vs off
    s = cs.unit.sensor("mpu3")
    raw, temp, _ = random_inputs(rng, s, 2000, 0, (-20, 55))
    _, _, dt = random_aux(rng, cs.spec, 2000)
    lag = host.correct(s.name, raw, temp, dt_s=dt)["field_body_nT"]
    nolag = HostUnit(base).correct(s.name, raw, temp)["field_body_nT"]
    assert np.mean(bits(lag) != bits(nolag)) > 0.5


def test_select_ties_are_agreement(built):
    """Two sensors exactly agree_i + agree_j apart (margin exactly 0) agree, in C and in
    Python alike; one float step further they do not. Tolerances set to exact values."""
    label, cs, host = built
    spec = cs.spec
    S = len(cs.unit.sensors)
    flat = host.flat_coeffs().copy()
    k0, agree = 0, []
    for s in cs.unit.sensors:
        off = spec.offsets(spec.sensor_blocks(s))["agree_nT"]
        flat[k0 + off] = 40.0 if s.part == "MMC5883MA" else 250.0
        agree.append(flat[k0 + off])
        k0 += spec.n_sensor_coeffs(s)
    order = spec.fallback_order()
    a, b = order[0], order[1]
    rows = []
    tie = np.float32(1000.0) + np.float32(agree[a] + agree[b])      # exact in float32
    for x_b in (tie, np.nextafter(tie, np.float32(np.inf))):
        f = np.zeros((S, 3), np.float32)
        f[:, 2] = 30000.0
        f[a, 0] = 1000.0
        f[b, 0] = x_b
        rows.append(f)
    fields = np.array(rows)
    statuses = np.zeros((2, S), np.uint16)
    statuses[:, [i for i in range(S) if i not in (a, b)]] = 1     # only a and b valid
    c_out = host.select(fields, statuses, coeffs_flat=flat)
    flat_by = {}
    k0 = 0
    for s in cs.unit.sensors:
        n = spec.n_sensor_coeffs(s)
        flat_by[s.name] = flat[k0:k0 + n]
        k0 += n
    py_out = chain.reference_select(spec, flat_by, fields, statuses)
    for key in ("status", "sensor", "rank", "reason"):
        np.testing.assert_array_equal(c_out[key], py_out[key], err_msg=key)
    assert list(c_out["reason"]) == [chain.SELECT_CONFIRMED, chain.SELECT_UNCONFIRMED]


def test_calls_of_every_kind_on_one_state():
    """Pair and SET-only calls interleaved on one state, some with state NULL (no filter,
    nothing stored, no offset for SET-only), with thermal lag: C == Python, bit for bit."""
    from chain_fixtures import random_aux, with_options
    from generator.flight.chain import NULL_STATE, SensorOptions, SensorState

    rng = np.random.default_rng(31)
    base = random_coeffs(rng, samsat_unit("mixsat"), coils=COILS)
    cs = with_options(rng, base, {"mmc1": SensorOptions(thermal_lag=True),
                                  "mpu3": SensorOptions(thermal_lag=True)})
    host = HostUnit(cs)
    n = 1500
    for name in ("mmc1", "mmc2", "mpu3"):
        s = cs.unit.sensor(name)
        raw, temp, coil = random_inputs(rng, s, n, len(COILS), (-20.0, 55.0))
        if not s.set_reset:
            raw = np.hstack([raw, np.zeros_like(raw)])
        channels, rate, dt = random_aux(rng, cs.spec, n, nan_fraction=0.01)
        mode = rng.integers(0, 4 if s.set_reset else 3, n).astype(np.uint8)
        if not s.set_reset:
            mode &= 2
        mode[:5] = 0                    # start with pairs on the state
        c_out = host.correct_mixed(name, raw if s.set_reset else raw[:, :3], temp, mode, coil,
                                   channels=channels, rate_dps=rate, dt_s=dt)
        state = SensorState()
        field = np.zeros((n, 3), np.float32)
        status = np.zeros(n, np.uint16)
        for j in range(n):
            one = slice(j, j + 1)
            kw = dict(coil_A=coil[one], set_only=bool(mode[j] & 1),
                      state=NULL_STATE if mode[j] & 2 else state,
                      dt_s=None if dt is None else dt[one],
                      rate_dps=None if rate is None else rate[one],
                      channels=None if channels is None else
                      {k: v[one] for k, v in channels.items()})
            r = raw[one, :3] if mode[j] & 1 or not s.set_reset else raw[one]
            out = reference_sensor(cs.spec, s, cs.flat_sensor(name), cs.flat_unit(), r,
                                   temp[one], **kw)
            field[j], status[j] = out["field_body_nT"][0], out["status"][0]
        np.testing.assert_array_equal(c_out["status"], status)
        np.testing.assert_array_equal(bits(c_out["field_body_nT"]), bits(field))
        if s.set_reset:   # every kind occurred, and the NULL-state SET-only had no offset
            assert set(np.unique(mode)) == {0, 1, 2, 3}
            m3 = status[mode == 3]
            assert np.all((m3 & (chain.STATUS_NO_OFFSET | chain.STATUS_NONFINITE)) != 0)
            assert np.mean((m3 & chain.STATUS_NO_OFFSET) != 0) > 0.9
