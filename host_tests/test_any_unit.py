"""Issue 15 (flight side): any unit of 1 to 8 sensors, in any mix of parts, frames, input
kinds and temperature, through chain -> C -> host build (and a few on the Cortex-M4F),
bit for bit against the Python reference.

Random units come from hypothesis: MMC5883MA with and without SET/RESET, MPU-9255,
physical-unit inputs (nT, uT, mG, G; ICD section 4) with and without SET/RESET, random
axis permutations and signs, body and boom frames (with or without a body reference),
with and without temperature, with and without coils, float32 and float64. Each unit is
generated, compiled with cffi (-Wall -Wextra -Werror -pedantic on the wrappers) and fed
random samples plus edge cases: rails and full scale, one ulp either side, non-finite
readings, temperatures and currents, the ends of the temperature range.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from chain_fixtures import (assert_bit_identical, bits, random_coeffs, random_inputs)
from generator.fit.calibration import SensorCalibration
from generator.flight import chain
from generator.flight.chain import (ChainSpec, reference_select, reference_sensor,
                                    saturation_limit)
from generator.flight.codegen import render
from generator.flight.coeffs import NO_BOOM_ALIGNMENT, CoefficientSet
from generator.flight.host import HostUnit
from generator.io.unit import SensorSpec, Unit

N = 3000                 # random samples per sensor and unit (plus the edge cases)
PHYSICAL = ("nT", "uT", "mG", "G")
KINDS = ("mmc_sr", "mmc", "mpu", "physical", "physical_sr")
COILS = ("mtq_x_A", "mtq_y_A")


# ---- units -----------------------------------------------------------------------------


def make_sensor(i, kind, frame, axes, temperature, inp="uT", range_nT=1.6e6):
    name = f"m{i}"
    if kind in ("mmc_sr", "mmc"):
        return SensorSpec(name, "MMC5883MA", frame, axes, 25.0, 32768, kind == "mmc_sr",
                          40.0, temperature=temperature)
    if kind == "mpu":
        return SensorSpec(name, "MPU-9255", frame, axes, 150.0, 0, False, 250.0,
                          temperature=temperature)
    # physical input: lsb_nT and zero_count are not used (ICD section 4)
    return SensorSpec(name, "generic", frame, axes, 1.0, 0, kind == "physical_sr", 100.0,
                      input=inp, temperature=temperature, range_nT=range_nT)


def make_unit(sensors, float_type="float32", unit_id="anyu") -> Unit:
    body = [s.name for s in sensors if s.frame == "body"]
    boom = any(s.frame == "boom" for s in sensors)
    return Unit(unit_id, tuple(sensors), lab_field_nT=50000.0, float_type=float_type,
                boom_reference=body[0] if body and boom else None)


@st.composite
def units(draw, max_sensors=8):
    n = draw(st.integers(1, max_sensors))
    sensors = []
    for i in range(n):
        kind = draw(st.sampled_from(KINDS))
        perm = draw(st.permutations("xyz"))
        signs = draw(st.lists(st.sampled_from("+-"), min_size=3, max_size=3))
        sensors.append(make_sensor(
            i, kind, draw(st.sampled_from(("body", "boom"))),
            tuple(sg + a for sg, a in zip(signs, perm)), draw(st.booleans()),
            draw(st.sampled_from(PHYSICAL)), draw(st.sampled_from((8e5, 1.6e6, 4.9e6)))))
    float_type = draw(st.sampled_from(("float32", "float32", "float64")))
    coils = draw(st.sampled_from(((), COILS)))
    return make_unit(sensors, float_type), coils, draw(st.integers(0, 2**32 - 1))


def host_build(cs: CoefficientSet) -> HostUnit:
    """The unit's generated C compiled on the host: every generated file, the uplink-table
    validator included (sensors without a temperature take no part in its header range)."""
    return HostUnit(cs)


# ---- inputs ----------------------------------------------------------------------------


def _t_range(cs, s):
    if not s.temperature:
        return -20.0, 55.0
    return float(cs.sensors[s.name]["t_min_C"]), float(cs.sensors[s.name]["t_max_C"])


def physical_inputs(rng, s: SensorSpec, ft, n, n_coils, t_range):
    """Readings in the sensor's unit: three quarters a plausible field (20,000-60,000 nT
    in a random direction), the rest anywhere up to 1.2 x full scale; temperatures and
    currents as random_inputs draws them."""
    scale = chain.input_scale_nT(s)
    k = 6 if s.set_reset else 3
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    field = direction * rng.uniform(20000, 60000, (n, 1)) / scale
    if s.set_reset:   # SET reads +field, RESET -field, both plus the bridge offset
        off = rng.normal(0, 3000 / scale, (n, 3))
        raw = np.concatenate([field + off, -field + off], axis=1)
    else:
        raw = field
    wide = rng.random(n) < 0.25
    lim = saturation_limit(s)
    raw[wide] = rng.uniform(-1.2 * lim, 1.2 * lim, (wide.sum(), k))
    temp = rng.uniform(t_range[0] - 20, t_range[1] + 20, n)
    coil = rng.uniform(-0.2, 0.2, (n, n_coils)) if n_coils else None
    return raw.astype(ft), temp, coil


def edge_inputs(s: SensorSpec, ft, n_coils, t_range, base_raw):
    """Edge rows on a base sample: each reading at and one ulp beyond its limits,
    non-finite readings, temperatures and currents, the range ends and one ulp outside."""
    k = base_raw.size
    rows, temps, coils = [], [], []
    t_mid = 0.5 * (t_range[0] + t_range[1])

    def add(raw, temp=t_mid, coil=0.0):
        rows.append(raw)
        temps.append(temp)
        coils.append(np.full(n_coils, coil))

    if chain.is_physical(s):
        lim = ft(saturation_limit(s))
        inf = ft(np.inf)
        for j in range(k):
            for v in (lim, -lim, np.nextafter(lim, inf), -np.nextafter(lim, inf), np.nan,
                      np.inf, -np.inf, ft(0), -ft(0)):
                r = base_raw.copy()
                r[j] = v
                add(r)
    else:
        for j in range(k):
            for v in (s.count_min, s.count_min + 1, s.count_max - 1, s.count_max,
                      s.zero_count):
                r = base_raw.copy()
                r[j] = v
                add(r)
    t32 = [np.float32(t) for t in t_range]
    for t in (t32[0], t32[1], np.nextafter(t32[0], np.float32(-np.inf)),
              np.nextafter(t32[1], np.float32(np.inf)), np.nan, np.inf, -np.inf, -1e30, 1e30):
        add(base_raw.copy(), float(t))
    if n_coils:
        for c in (np.nan, np.inf, -np.inf, 0.0, 1e3):
            add(base_raw.copy(), t_mid, c)
    raw = np.array(rows)
    return raw, np.array(temps), (np.array(coils) if n_coils else None)


def sensor_inputs(rng, cs, s, n):
    ft = chain.np_dtype(cs.unit)
    nc = len(cs.spec.coils)
    t = _t_range(cs, s)
    if chain.is_physical(s):
        raw, temp, coil = physical_inputs(rng, s, ft, n, nc, t)
    else:
        raw, temp, coil = random_inputs(rng, s, n, nc, t)
    e_raw, e_temp, e_coil = edge_inputs(s, ft, nc, t, raw[0].copy())
    raw = np.concatenate([raw, e_raw.astype(raw.dtype)])
    temp = np.concatenate([temp, e_temp])
    coil = None if coil is None else np.concatenate([coil, e_coil])
    return raw, temp, coil


def py_correct(cs, s, raw, temp, coil):
    return reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(), raw, temp,
                            coil)


def select_inputs(rng, cs, n):
    """Fields around one true field, with outliers and invalid sensors."""
    S = len(cs.unit.sensors)
    truth = rng.normal(0, 30000, (n, 1, 3))
    agree = np.array([float(cs.sensors[s.name]["agree_nT"]) for s in cs.unit.sensors])
    fields = truth + rng.normal(0, 1, (n, S, 3)) * agree[None, :, None] / 8
    outlier = rng.random((n, S)) < 0.2
    fields[outlier] += rng.normal(0, 1, (outlier.sum(), 3)) * 5 * agree.max()
    statuses = np.where(rng.random((n, S)) < 0.2, rng.integers(1, 64, (n, S)), 0)
    return fields, statuses.astype(np.uint16)


def check_unit(cs: CoefficientSet, host: HostUnit, seed: int):
    """Every sensor and the selection: C bits == Python bits; the status bits obey the
    unit's declarations (no clamp without temperature, rails/full scale as declared)."""
    rng = np.random.default_rng(seed)
    for s in cs.unit.sensors:
        raw, temp, coil = sensor_inputs(rng, cs, s, N)
        c_out = host.correct(s.name, raw, temp, coil)
        assert_bit_identical(c_out, py_correct(cs, s, raw, temp, coil),
                             f"{cs.unit.id}/{s.name} ({s.part}, {s.input})")
        status = c_out["status"]
        # not vacuous: the outputs vary
        assert np.unique(bits(c_out["field_body_nT"][:, 0])).size > N // 4
        if not s.temperature:
            assert not np.any(status & chain.STATUS_TEMP_CLAMPED)
            # the temperature is ignored: any value gives the same bits
            other = host.correct(s.name, raw, np.full(temp.shape, np.nan), coil)
            assert_bit_identical(other, c_out, f"{s.name} with NaN temperatures")
        else:
            assert np.any(status & chain.STATUS_TEMP_CLAMPED)
        assert np.any(status & chain.STATUS_SATURATED)
        assert np.any(status & chain.STATUS_NONFINITE) == (
            s.temperature or chain.is_physical(s) or bool(cs.spec.coils))
        if s.set_reset:   # SET-only readings with the pairs' stored offsets, some missing
            offs = c_out["offset_counts"].copy()
            offs[rng.random(offs.shape[0]) < 0.05] = np.nan
            c_set = host.correct_set(s.name, raw[:, :3], temp, offs, coil)
            p_set = reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(),
                                     raw[:, :3], temp, coil, set_only=True, offset_counts=offs)
            assert_bit_identical(c_set, p_set, f"{cs.unit.id}/{s.name} SET-only")
            assert np.any(c_set["status"] & chain.STATUS_NO_OFFSET)
            assert np.any(c_set["status"] == 0)
    fields, statuses = select_inputs(rng, cs, 2000)
    c_sel = host.select(fields, statuses)
    flat = {s.name: cs.flat_sensor(s.name) for s in cs.unit.sensors}
    p_sel = reference_select(cs.spec, flat, fields, statuses)
    for k in ("status", "sensor", "rank", "reason"):
        np.testing.assert_array_equal(c_sel[k], p_sel[k], err_msg=k)
    np.testing.assert_array_equal(bits(c_sel["field_body_nT"]), bits(p_sel["field_body_nT"]))
    c_sel["added"] = c_sel["status"] & ~statuses   # the bits select set
    return c_sel


# ---- hypothesis: random units ------------------------------------------------------------


@settings(max_examples=12, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(units())
def test_random_units_bit_identical(drawn):
    unit, coils, seed = drawn
    cs = random_coeffs(np.random.default_rng(seed), unit, coils=coils)
    check_unit(cs, host_build(cs), seed)


# ---- 1, 2 and 8 sensors ------------------------------------------------------------------


def _unit_of(kinds, temperature=True, frames=None, float_type="float32", coils=(), seed=5):
    rng = np.random.default_rng(seed)
    frames = frames or ["body"] * len(kinds)
    sensors = [make_sensor(i, k, frames[i], ("+x", "+y", "+z"), temperature)
               for i, k in enumerate(kinds)]
    unit = make_unit(sensors, float_type, unit_id=f"u{len(kinds)}")
    return random_coeffs(rng, unit, coils=coils)


def test_one_sensor_unit_compiles_and_selects_itself():
    """The unit that failed to compile (unused 'coeffs' in select): builds with -Werror,
    and select has nothing to cross-check: its own vector when valid (SINGLE), zeros
    when not (NONE), status untouched."""
    for kind in KINDS:
        cs = _unit_of([kind], temperature=kind != "mpu")
        host = host_build(cs)
        sel = check_unit(cs, host, 7)
        fields = np.array([[[1000.0, -2000.0, 3000.0]]] * 3)
        st_in = np.array([[0], [chain.STATUS_IMPLAUSIBLE], [chain.STATUS_SATURATED]], np.uint16)
        out = host.select(fields, st_in)
        assert list(out["reason"]) == [chain.SELECT_SINGLE, chain.SELECT_NONE,
                                       chain.SELECT_NONE]
        assert list(out["sensor"]) == [0, -1, -1]
        np.testing.assert_array_equal(out["status"], st_in)
        np.testing.assert_array_equal(out["field_body_nT"][0], fields[0, 0].astype(np.float32))
        assert np.all(out["field_body_nT"][1:] == 0)
        assert set(np.unique(sel["reason"])) == {chain.SELECT_SINGLE, chain.SELECT_NONE}
        assert not np.any(sel["added"])
        assert "a single sensor" in render(cs, tables=False)["u1_magcal.c"]


def test_two_sensors_never_outvote_each_other():
    """With two valid sensors nobody has two others to be outvoted by: no DISAGREE; the
    first choice is CONFIRMED when they agree, UNCONFIRMED when not."""
    cs = _unit_of(["mmc_sr", "physical"], frames=["body", "boom"])
    host = host_build(cs)
    sel = check_unit(cs, host, 8)
    assert not np.any(sel["added"])
    assert {chain.SELECT_CONFIRMED, chain.SELECT_UNCONFIRMED} <= set(np.unique(sel["reason"]))


def test_eight_sensors_outlier_is_flagged_and_skipped():
    kinds = ["mmc_sr", "mmc", "mpu", "physical", "physical_sr", "mpu", "mmc", "physical"]
    frames = ["body", "boom"] * 4
    cs = _unit_of(kinds, frames=frames, coils=COILS)
    host = host_build(cs)
    check_unit(cs, host, 9)
    order = cs.spec.fallback_order()
    f = np.tile(np.array([20000.0, -30000.0, 10000.0]), (1, 8, 1))
    f[0, order[0]] += 10 * max(float(cs.sensors[s.name]["agree_nT"]) for s in cs.unit.sensors)
    out = host.select(f, np.zeros((1, 8), np.uint16))
    assert out["status"][0, order[0]] & chain.STATUS_DISAGREE
    assert out["sensor"][0] == order[1] and out["reason"][0] == chain.SELECT_CONFIRMED


def test_sensor_count_limits():
    one = make_sensor(0, "mpu", "body", ("+x", "+y", "+z"), True)
    with pytest.raises(ValueError, match="1 to 8 sensors"):
        ChainSpec(Unit("none", ()))
    nine = tuple(make_sensor(i, "mpu", "body", ("+x", "+y", "+z"), True) for i in range(9))
    with pytest.raises(ValueError, match="1 to 8 sensors"):
        ChainSpec(Unit("nine", nine))
    ChainSpec(Unit("ok", (one,)))


# ---- frames: boom sensors without a body reference -------------------------------------------


def test_boom_only_unit_gets_identity_and_says_so():
    """No body-frame sensor: nothing to align the boom to. H is the identity, the
    coefficients say why, and so does the generated header."""
    sensors = (make_sensor(0, "mmc_sr", "boom", ("-y", "-z", "+x"), True),
               make_sensor(1, "physical", "boom", ("+z", "+x", "+y"), False))
    unit = make_unit(sensors, unit_id="boomonly")
    assert unit.boom_reference is None
    cals = {s.name: SensorCalibration(s.name, np.zeros((4, 3)),
                                      np.concatenate([np.eye(3)[None], np.zeros((3, 3, 3))]),
                                      25.0, -20.0, 55.0) for s in sensors}
    cs = CoefficientSet.from_calibrations(unit, cals)
    np.testing.assert_array_equal(cs.unit_values["H_boom_to_body"], np.eye(3))
    assert cs.fit_info["boom_alignment"] == NO_BOOM_ALIGNMENT
    assert CoefficientSet.from_json_dict(cs.to_json_dict()).fit_info["boom_alignment"] == \
        NO_BOOM_ALIGNMENT
    header = render(cs, tables=False)["boomonly_magcal.h"]
    assert f"H_boom_to_body: {NO_BOOM_ALIGNMENT}" in header
    check_unit(cs, host_build(cs), 10)


# ---- physical inputs and temperature-free sensors ------------------------------------------


def test_physical_units_scale_to_nT():
    """The same field given in nT, uT, mG and G gives the same calibrated field when the
    readings are exact in each unit (b, M identical; constant model): C and Python bit
    for bit per unit, and across units equal up to the rounding of the folded constants.

    The kernels read M scale and b / scale (chain.fold_sensor_coeffs, rounded once each
    when the table is prepared) instead of scaling every reading, so the units no longer
    give the same bits: per output, both forms are the same 3-term dot product of M with
    (field - b) under a handful of roundings each (the fold's 2, the subtraction, 3
    products, 2 sums), so they differ by at most ~8 units of 2^-24 relative to
    sum_j |M_ij| (|field_j| + |b_j|), the size of the terms summed."""
    sensors = [make_sensor(i, "physical", "body", ("+x", "+y", "+z"), False, inp=u,
                           range_nT=4.9e6) for i, u in enumerate(PHYSICAL)]
    unit = make_unit(sensors, unit_id="scales")
    b = np.array([[120.0, -340.0, 56.0]])
    M = np.array([[[1.01, 0.002, -0.003], [0.001, 0.99, 0.004], [0.0, -0.002, 1.003]]])
    cals = {s.name: SensorCalibration(s.name, b, M, 25.0, -20.0, 55.0) for s in sensors}
    cs = CoefficientSet.from_calibrations(unit, cals)
    host = host_build(cs)
    field_nT = np.array([[25000.0, -12000.0, 40000.0], [100000.0, 0.0, -300000.0]])
    outs = []
    for s in sensors:   # field_nT / scale is exact in float32 for these values
        raw = field_nT / chain.input_scale_nT(s)
        assert np.all(raw.astype(np.float32) * np.float32(chain.input_scale_nT(s)) == field_nT)
        out = host.correct(s.name, raw, np.zeros(2), None)
        assert_bit_identical(out, py_correct(cs, s, raw, np.zeros(2), None), s.input)
        outs.append(out["field_body_nT"])
    size = (np.abs(M[0]) @ (np.abs(field_nT) + np.abs(b[0])).T).T   # (2, 3)
    tol = 8 * 2.0 ** -24 * size
    for o in outs[1:]:
        assert np.all(np.abs(o.astype(np.float64) - outs[0]) <= tol), (o, outs[0], tol)
    # and it is M (x - b)
    want = (M[0] @ (field_nT - b[0]).T).T
    np.testing.assert_allclose(outs[0], want, rtol=1e-6)


def test_physical_saturation_at_full_scale():
    s = make_sensor(0, "physical", "body", ("+x", "+y", "+z"), True, inp="G", range_nT=8e5)
    assert saturation_limit(s) == 8.0          # 800,000 nT = 8 G
    cs = random_coeffs(np.random.default_rng(3), make_unit([s], unit_id="satg"))
    host = host_build(cs)
    v = np.array([8.0, -8.0, np.nextafter(np.float32(8), np.float32(9)), -8.000001, 0.3])
    raw = np.stack([np.full(5, 0.2), v, np.full(5, -0.1)], axis=1)
    out = host.correct(s.name, raw, np.full(5, 25.0), None)
    assert_bit_identical(out, py_correct(cs, s, raw, np.full(5, 25.0), None))
    sat = (out["status"] & chain.STATUS_SATURATED) != 0
    assert list(sat) == [False, False, True, True, False]


def test_physical_input_needs_a_range():
    s = SensorSpec("x", "generic", "body", ("+x", "+y", "+z"), 1.0, 0, False, input="mG")
    with pytest.raises(ValueError, match="range_nT"):
        ChainSpec(Unit("norange", (s,)))
    s = SensorSpec("x", "generic", "body", ("+x", "+y", "+z"), 1.0, 0, False, input="kG",
                   range_nT=1e6)
    with pytest.raises(ValueError, match="input 'kG'"):
        ChainSpec(Unit("badinput", (s,)))


def test_temperature_free_sensor_is_constant_and_unclamped():
    s = make_sensor(0, "mpu", "body", ("-z", "+x", "-y"), False)
    cs = random_coeffs(np.random.default_rng(4), make_unit([s], unit_id="notemp"))
    names = [b.name for b in cs.spec.sensor_blocks(s)]
    assert "t_min_C" not in names and "t_ref_C" not in names
    assert cs.sensors[s.name]["b_poly_nT"].shape == (1, 3)
    assert cs.sensors[s.name]["M_poly"].shape == (1, 3, 3)
    src = render(cs, tables=False)
    assert "IGNORED: this sensor has no temperature" in src["notemp_magcal.h"]
    assert "T_MIN_C" not in src["notemp_magcal.c"]
    with pytest.raises(ValueError, match="no thermal lag"):
        ChainSpec(cs.unit, sensor_options=(("m0", chain.SensorOptions(thermal_lag=True)),))


def test_table_of_a_temperature_free_unit():
    """No sensor has a temperature: the table C is generated and the default table has
    the whole plausible temperature range in its header (host_tests/test_tables_any_unit.py
    checks such tables in C and Python)."""
    from generator.flight import tables
    s = make_sensor(0, "mpu", "body", ("+x", "+y", "+z"), False)
    cs = random_coeffs(np.random.default_rng(4), make_unit([s], unit_id="notab"))
    assert "notab_table.c" in render(cs)
    head, _ = tables.check_table(tables.encode_table(cs, 1, 0), cs.spec)
    assert (head["t_min_C"], head["t_max_C"]) == tables.NO_TEMP_RANGE_C == (-100.0, 150.0)


def test_version_1_structure_unchanged():
    """A unit without version-2 keys keeps its layout hash: the example's committed C is
    byte-identical (test_generated), and counts/temperature sensors hash as before."""
    from chain_fixtures import EXAMPLE_COEFFS
    if not EXAMPLE_COEFFS.exists():
        pytest.skip("no committed example")
    cs = CoefficientSet.load(EXAMPLE_COEFFS)   # checks the stored layout_hash
    for s in cs.spec.structure()["sensors"]:
        assert "input" not in s and "temperature" not in s


# ---- on the emulated Cortex-M4F --------------------------------------------------------------


def _arm_units():
    """A handful of units: 1 sensor without temperature, 2 sensors boom/body, 8 sensors
    with coils, and physical inputs (the runner's real-typed readings): uT without
    temperature beside G with SET/RESET and temperature and a counts sensor, with coils;
    one float64 mG SET/RESET sensor without temperature."""
    phys = [make_sensor(0, "physical", "body", ("+y", "-x", "+z"), False, inp="uT"),
            make_sensor(1, "physical_sr", "boom", ("-z", "+y", "+x"), True, inp="G",
                        range_nT=8e5),
            make_sensor(2, "mmc_sr", "body", ("+x", "+y", "+z"), True)]
    phys64 = [make_sensor(0, "physical_sr", "body", ("+x", "-y", "-z"), False, inp="mG",
                          range_nT=4.9e6)]
    return [
        ("one_notemp", _unit_of(["mpu"], temperature=False, seed=11)),
        ("two", _unit_of(["mmc_sr", "mpu"], frames=["body", "boom"], seed=12)),
        ("eight", _unit_of(["mmc_sr", "mmc", "mpu", "mmc", "mpu", "mmc_sr", "mpu", "mmc"],
                           frames=["body", "boom"] * 4, coils=COILS, seed=13)),
        ("physical", random_coeffs(np.random.default_rng(16),
                                   make_unit(phys, unit_id="armphys"), coils=COILS)),
        ("physical64", random_coeffs(np.random.default_rng(17),
                                     make_unit(phys64, "float64", unit_id="armphys64"))),
    ]


@pytest.mark.arm
@pytest.mark.parametrize("label,cs", _arm_units(), ids=[u[0] for u in _arm_units()])
def test_arm_units_bit_identical(label, cs):
    from generator.flight import target as ta
    if ta.missing_tools():
        pytest.skip(f"missing {', '.join(ta.missing_tools())}")
    arm = ta.ArmUnit(cs)   # every generated file, the table validator included
    rng = np.random.default_rng(14)
    calls, refs = [], []
    for s in cs.unit.sensors:
        raw, temp, coil = sensor_inputs(rng, cs, s, 500)
        calls.append(("correct", s.name, raw, temp, coil))
        refs.append((s.name, py_correct(cs, s, raw, temp, coil)))
        if s.set_reset:   # SET-only readings with the pairs' stored offsets, some missing
            offs = refs[-1][1]["offset_counts"].copy()
            offs[rng.random(offs.shape[0]) < 0.05] = np.nan
            calls.append(("correct_set", s.name, raw[:, :3], temp, offs, coil))
            refs.append((f"{s.name} SET-only", reference_sensor(
                cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(), raw[:, :3], temp, coil,
                set_only=True, offset_counts=offs)))
    fields, statuses = select_inputs(rng, cs, 500)
    calls.append(("select", fields, statuses))
    outs = arm.run(calls)
    for (name, ref), got in zip(refs, outs):
        assert_bit_identical(got, ref, f"{label}/{name}")
    flat = {s.name: cs.flat_sensor(s.name) for s in cs.unit.sensors}
    p_sel = reference_select(cs.spec, flat, fields, statuses)
    for k in ("status", "sensor", "rank", "reason"):
        np.testing.assert_array_equal(outs[-1][k], p_sel[k], err_msg=k)
    np.testing.assert_array_equal(bits(outs[-1]["field_body_nT"]),
                                  bits(p_sel["field_body_nT"]))


def test_degree_comes_from_the_sensors_with_temperature():
    """A unit whose first sensor has no temperature (a constant calibration) still gets
    the cubic of its other sensors; a unit with no temperature at all is constant."""
    a = make_sensor(0, "physical", "body", ("+x", "+y", "+z"), False)
    b = make_sensor(1, "mpu", "body", ("+x", "+y", "+z"), True)
    eye = np.eye(3)[None]
    cals = {"m0": SensorCalibration("m0", np.zeros((1, 3)), eye, 0.0, -np.inf, np.inf),
            "m1": SensorCalibration("m1", np.zeros((4, 3)),
                                    np.concatenate([eye, np.zeros((3, 3, 3))]), 25.0, -20.0,
                                    55.0)}
    cs = CoefficientSet.from_calibrations(make_unit([a, b], unit_id="deg"), cals)
    assert cs.spec.poly_degree == 3
    assert cs.sensors["m0"]["M_poly"].shape == (1, 3, 3)
    assert cs.sensors["m1"]["M_poly"].shape == (4, 3, 3)
    cs0 = CoefficientSet.from_calibrations(make_unit([a], unit_id="deg0"), {"m0": cals["m0"]})
    assert cs0.spec.poly_degree == 0
    check_unit(cs, host_build(cs), 15)


def _static_units():
    """The new shapes of the generated C: one sensor without temperature, physical inputs
    (plain and SET/RESET, with and without temperature), eight sensors with coils."""
    phys = [make_sensor(0, "physical", "body", ("-y", "+x", "+z"), False, inp="G"),
            make_sensor(1, "physical_sr", "boom", ("+z", "-x", "+y"), True, inp="mG"),
            make_sensor(2, "mmc", "boom", ("+x", "+y", "-z"), False)]
    return [("one_notemp", _unit_of(["mpu"], temperature=False, seed=21)),
            ("physical", random_coeffs(np.random.default_rng(22),
                                       make_unit(phys, unit_id="physw"), coils=COILS)),
            ("eight", _unit_of(KINDS + ("mpu", "mmc", "physical"),
                               frames=["boom", "body"] * 4, coils=COILS, seed=23))]


@pytest.mark.arm
@pytest.mark.slow   # cppcheck on three units: about a minute on the shared 2-core machine
@pytest.mark.parametrize("label,cs", _static_units(), ids=[u[0] for u in _static_units()])
def test_new_shapes_pass_the_static_checks(label, cs, tmp_path):
    """The flight flags plus -Wdouble-promotion -Wconversion -Wshadow (-Werror), on the
    Cortex-M4F compiler, and cppcheck: clean, as test_arm requires of the example."""
    from generator.flight import target as ta
    if ta.missing_tools():
        pytest.skip(f"missing {', '.join(ta.missing_tools())}")
    msgs, work = ta.warning_check(cs, workdir=tmp_path)   # the table validator included
    assert msgs and all(m == "" for m in msgs.values()), msgs
    if ta.cppcheck_available():
        p = ta.cppcheck(sorted(work.glob("*.c")), work)
        assert p.returncode == 0, p.stdout + p.stderr
