"""A table manager that `<unit>_table_init` never completed on (mgr14).

Flight software that forgets init, or runs before it (an interrupt, a task started early),
holds a `<unit>_table_mgr_t` that is zero-filled (static storage) or filled with whatever
the memory held. Before this change such a manager handed out its zeros as the
coefficients in use: every correction returned a zero field, and where the temperature
check passed (a sensor without a temperature; 0 degC, the zeroed range) status 0, VALID.

Now init stores `<UNIT>_TABLE_INIT_MARK` as its last step and every manager function
tests it (docs/table_format.md, *A manager never initialised*). Here, through the flight
C built on the host (cffi, table_host.TableHost), for managers filled with 0x00, 0xFF and
other bytes: load / receive_part / commit return NOT_INITIALISED and change no byte,
abort changes no byte, info reports the state, active / prepared hand out the all-NaN
sets, every correction on them is flagged IMPLAUSIBLE and select finds no sensor; the
Python model (table_manager.TableManager(spec)) says the same; after init everything is
as before (the corrections on the manager's prepared set are the HostUnit corrections,
bit for bit); and only the exact mark counts as initialised (every single-bit flip of
it, and random mark bytes through hypothesis). The Cortex-M4F run is in
test_arm_tables.py (the same operations on the target, host and Python, compared).
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from chain_fixtures import (EXAMPLE_COEFFS, bits, random_coeffs, random_inputs, samsat_unit,
                            with_float)
from ci import require, require_gcc
from generator.flight import chain, tables
from generator.flight.coeffs import CoefficientSet
from generator.flight.host import HostUnit
from generator.flight.table_host import TableHost
from generator.flight.table_manager import (TableManager, poisoned_prepared, poisoned_values,
                                            prepared_values)
from generator.flight.tables import (MANAGER_INIT_MARK, NO_INDEX, TableStatus, chunk_table,
                                     encode_table)
from generator.io.unit import SensorSpec, Unit

S = TableStatus
COILS = ("coil_x_A", "coil_y_A", "coil_z_A")
# 0x00: static storage; 0xFF: erased flash / a debugger's fill; 0xA5, 0x49: other patterns
# (0x49 is the mark's own first and third byte: a single-byte fill never makes all four)
FILLS = (0x00, 0xFF, 0xA5, 0x49)


def _physical_unit() -> Unit:
    """A unit with a sensor WITHOUT a temperature (constant model): on a zeroed manager it
    was flagged valid at any temperature, the worst case of the fault."""
    return Unit("uninitphys", (
        SensorSpec("ist", "generic", "body", ("+y", "-x", "+z"), 1.0, 0, False, 100.0,
                   input="uT", temperature=False, range_nT=1.6e6),
        SensorSpec("mmc", "MMC5883MA", "body", ("+x", "+y", "-z"), 25.0, 32768, True, 40.0)),
        lab_field_nT=50000.0)


@functools.lru_cache(maxsize=None)
def _unit(label):
    require_gcc()
    if label == "example":
        require(EXAMPLE_COEFFS.exists(), f"no committed example unit at {EXAMPLE_COEFFS}")
        cs = CoefficientSet.load(EXAMPLE_COEFFS)
    elif label == "f64":
        rng = np.random.default_rng(1414)
        cs = with_float(random_coeffs(rng, samsat_unit("uninit64", "float64"), coils=COILS),
                        "float64")
    else:
        cs = random_coeffs(np.random.default_rng(1415), _physical_unit())
    return cs, TableHost(cs)


UNITS = ("example", "f64", "physical")


def _mgr_bytes(h, mgr) -> bytes:
    return bytes(h.ffi.buffer(mgr))


def _readings(rng, s, n):
    """n readings of sensor s (counts, or real numbers in its input unit) and temperatures,
    0 degC first (the zeroed manager's temperature range)."""
    if s.input == "counts":
        raw, temp, _ = random_inputs(rng, s, n)
        raw[0] = s.zero_count          # a zero field at 0 degC: what zeros called valid
    else:
        lim = chain.saturation_limit(s)
        raw = rng.uniform(-lim, lim, (n, 6 if s.set_reset else 3))
        raw[0] = 0.0
        temp = rng.uniform(-40.0, 95.0, n)
    temp = np.asarray(temp, dtype=np.float64)
    temp[0] = 0.0
    return raw, temp


def _samples(cs, n, seed):
    """[(raw per sensor, temp_C per sensor)] for n cycles."""
    rng = np.random.default_rng(seed)
    per = [_readings(rng, s, n) for s in cs.unit.sensors]
    return [([r[j] for r, _ in per], np.array([t[j] for _, t in per])) for j in range(n)]


def _assert_not_initialised(h, mgr, cs):
    """What every entry point of a manager not initialised must do (and the Python model
    with it)."""
    info = h.info(mgr)
    assert info == {"active_serial": 0, "active_buffer": 0, "transfer_open": 0,
                    "parts_received": 0, "part_count": 0, "transfer_serial": 0,
                    "last_status": S.NOT_INITIALISED, "last_bad_value": NO_INDEX,
                    "coeffs_valid": 0}
    py = TableManager(cs.spec)
    assert (py.last_status, py.last_bad, int(py.coeffs_valid), py.active_serial) == \
        (info["last_status"], info["last_bad_value"], info["coeffs_valid"],
         info["active_serial"])
    # nothing handed out is a coefficient: all NaN, the same bits as the Python model's
    np.testing.assert_array_equal(bits(h.active_flat(mgr)), bits(poisoned_values(cs.spec)))
    np.testing.assert_array_equal(bits(h.active_flat(mgr)), bits(py.active_values))
    np.testing.assert_array_equal(bits(h.prepared_flat(mgr)), bits(poisoned_prepared(cs.spec)))
    np.testing.assert_array_equal(bits(h.prepared_flat(mgr)), bits(py.prepared))
    # nothing changes it: a valid table, its parts, commit, abort
    before = _mgr_bytes(h, mgr)
    table = encode_table(cs, 1, 0)
    assert h.load(mgr, table) == S.NOT_INITIALISED == py.load(table)
    assert _mgr_bytes(h, mgr) == before
    for part in chunk_table(table, 200):
        assert h.receive_part(mgr, part) == S.NOT_INITIALISED == py.receive_part(part)
        assert _mgr_bytes(h, mgr) == before
    assert h.commit(mgr) == S.NOT_INITIALISED == py.commit()[0]
    h.abort(mgr)
    py.abort()
    assert _mgr_bytes(h, mgr) == before
    assert h.info(mgr) == info
    assert (py.last_status, py.initialised) == (S.NOT_INITIALISED, False)
    # a NULL part or manager is still NULL_ARGUMENT, checked first
    assert h._fn("receive_part")(mgr, h.ffi.NULL, 0) == S.NULL_ARGUMENT
    assert h._fn("load")(h.ffi.NULL, table, len(table)) == S.NULL_ARGUMENT


@pytest.mark.parametrize("fill", FILLS, ids=[f"0x{f:02X}" for f in FILLS])
@pytest.mark.parametrize("label", UNITS)
def test_a_filled_manager_is_not_initialised(label, fill):
    cs, h = _unit(label)
    mgr = h.uninitialised(fill)
    assert int(mgr.init_mark) == int.from_bytes(bytes([fill]) * 4, "little")
    _assert_not_initialised(h, mgr, cs)


@pytest.mark.parametrize("fill", (0x00, 0xFF))
@pytest.mark.parametrize("label", UNITS)
def test_no_correction_on_it_is_valid_and_nothing_is_selected(label, fill):
    """Every correction on the prepared set of a manager not initialised is flagged
    IMPLAUSIBLE (NaN fails the |B| band check), whatever the reading and temperature,
    the zero field at 0 degC included; select on those outputs finds no sensor.

    Select takes the validity from the statuses it is given (the corrections'). Told that
    every sensor is valid and agrees, it still finds none on the NaN set when the unit has
    3 or more sensors (each valid sensor is compared with at least two others and the
    NaN agreement tolerance makes every comparison fail: DISAGREE); with 1 or 2 sensors
    there is no majority to check and select follows the statuses it was given."""
    cs, h = _unit(label)
    mgr = h.uninitialised(fill)
    for raw, temp in _samples(cs, 40, 20 + fill):
        out = h.correct_all(mgr, raw, temp)
        assert np.all(out["status"] & chain.STATUS_IMPLAUSIBLE), out["status"]
        assert np.all(np.isnan(out["field_body_nT"]))
        assert (out["sel_sensor"], out["sel_reason"]) == (-1, chain.SELECT_NONE)
    n = len(cs.unit.sensors)
    if n < 3:
        return
    agree = np.tile([20000.0, -5000.0, 40000.0], (n, 1))
    sel = h.select(mgr, agree, np.zeros(n))
    assert (sel["sel_sensor"], sel["sel_reason"]) == (-1, chain.SELECT_NONE)
    # the same call on an initialised manager selects (the check above can fail)
    good = h.manager()
    assert h.select(good, agree, np.zeros(n))["sel_reason"] != chain.SELECT_NONE


@pytest.mark.parametrize("label", UNITS)
def test_a_null_manager_hands_out_nan_never_null(label):
    cs, h = _unit(label)
    null = h.ffi.NULL
    assert h._fn("active")(null) != h.ffi.NULL and h._fn("prepared")(null) != h.ffi.NULL
    np.testing.assert_array_equal(bits(h.active_flat(null)), bits(poisoned_values(cs.spec)))
    np.testing.assert_array_equal(bits(h.prepared_flat(null)),
                                  bits(poisoned_prepared(cs.spec)))
    assert h._fn("commit")(null) == S.NULL_ARGUMENT
    h._fn("abort")(null)    # no crash


@pytest.mark.parametrize("fill", (0x00, 0xFF))
@pytest.mark.parametrize("label", UNITS)
def test_after_init_everything_is_as_before(label, fill):
    """init on a filled manager: OK, the defaults in use and prepared, and the corrections
    and select on the manager's prepared set are HostUnit's (which prepares the same
    defaults itself), bit for bit; then a table loads as always."""
    cs, h = _unit(label)
    mgr = h.uninitialised(fill)
    mgr2, st = h.init(mgr=mgr)
    assert mgr2 is mgr and st == S.OK
    assert int(mgr.init_mark) == MANAGER_INIT_MARK
    info = h.info(mgr)
    assert (info["last_status"], info["coeffs_valid"], info["active_serial"]) == (S.OK, 1, 0)
    defaults = h.default_flat()
    np.testing.assert_array_equal(bits(h.active_flat(mgr)), bits(defaults))
    np.testing.assert_array_equal(bits(h.prepared_flat(mgr)),
                                  bits(prepared_values(cs.spec, defaults)))
    py = TableManager(cs.spec)
    assert py.init(defaults) == S.OK and py.initialised
    np.testing.assert_array_equal(bits(py.prepared), bits(h.prepared_flat(mgr)))
    hu = HostUnit(cs)
    statuses = []
    for raw, temp in _samples(cs, 60, 40 + fill):
        out = h.correct_all(mgr, raw, temp)
        for k, s in enumerate(cs.unit.sensors):
            want = hu.correct(s.name, np.asarray(raw[k])[None, :], temp[k:k + 1])
            np.testing.assert_array_equal(bits(out["field_body_nT"][k]),
                                          bits(want["field_body_nT"][0]), err_msg=s.name)
            assert out["status"][k] == want["status"][0], s.name
        sel = hu.select(out["field_body_nT"][None], out["status"][None])
        assert (out["sel_sensor"], out["sel_reason"]) == (sel["sensor"][0], sel["reason"][0])
        np.testing.assert_array_equal(bits(out["sel_field_body_nT"]),
                                      bits(sel["field_body_nT"][0]))
        statuses.append(out["status"])
    # the comparison covered valid and flagged outputs (not only one kind)
    statuses = np.concatenate(statuses)
    assert np.any(statuses == 0) and np.any(statuses != 0)
    table = encode_table(cs, 0, 0)     # serial 0 and the defaults' coefficients
    assert h.load(mgr, table) == S.ALREADY_ACTIVE == py.load(table)
    vals = tables.flat_values(cs).copy()     # the defaults with one offset 1 nT higher
    i = next(v.index for v in tables.value_layout(cs.spec) if v.block.name == "b_poly_nT")
    vals[i] += 1.0
    other = encode_table(tables.coefficient_set(cs.spec, vals), 2, 0)
    assert h.load(mgr, other) == S.OK == py.load(other)
    np.testing.assert_array_equal(bits(h.prepared_flat(mgr)), bits(py.prepared))
    assert h.info(mgr)["active_serial"] == 2


def test_the_init_fallback_hands_out_the_same_nan_sets():
    """Defaults that fail their checks at init: the manager is initialised (the mark is
    set, load works) but holds the NaN sets a manager not initialised hands out."""
    cs, h = _unit("example")
    vals = h.default_flat().copy()
    vals[0] = np.nan
    mgr, st = h.init(vals)
    assert st == S.NONFINITE_VALUE and int(mgr.init_mark) == MANAGER_INIT_MARK
    np.testing.assert_array_equal(bits(h.prepared_flat(mgr)), bits(poisoned_prepared(cs.spec)))
    np.testing.assert_array_equal(bits(h.active_flat(mgr)), bits(poisoned_values(cs.spec)))
    py = TableManager(cs.spec, vals)
    np.testing.assert_array_equal(bits(py.prepared), bits(h.prepared_flat(mgr)))
    raw, temp = _samples(cs, 1, 5)[0]
    out = h.correct_all(mgr, raw, temp)
    assert np.all(out["status"] & chain.STATUS_IMPLAUSIBLE) and out["sel_sensor"] == -1
    assert h.commit(mgr) == S.NOTHING_STAGED     # initialised: the usual answer
    assert h.load(mgr, encode_table(cs, 1, 0)) == S.OK and h.info(mgr)["coeffs_valid"] == 1


def _initialised_with_mark(h, mark: int):
    mgr = h.manager()
    mgr.init_mark = mark
    return mgr


def _looks_initialised(h, mgr) -> bool:
    """Initialised as every entry point sees it; asserts the entry points agree."""
    st_commit = h.commit(mgr)       # nothing staged: NOTHING_STAGED when initialised
    info = h.info(mgr)
    nan = bool(np.all(np.isnan(h.prepared_flat(mgr))))
    answers = {st_commit == S.NOTHING_STAGED, info["last_status"] != S.NOT_INITIALISED,
               info["coeffs_valid"] == 1, not nan}
    assert len(answers) == 1, (st_commit, info, nan)
    return answers.pop()


def test_only_the_exact_mark_counts_every_bit_flip_does_not():
    cs, h = _unit("example")
    assert _looks_initialised(h, _initialised_with_mark(h, MANAGER_INIT_MARK))
    for bit in range(32):
        assert not _looks_initialised(h, _initialised_with_mark(h, MANAGER_INIT_MARK ^ (1 << bit)))
    # its bytes are not all equal: no single-byte fill makes it
    assert len(set(MANAGER_INIT_MARK.to_bytes(4, "little"))) > 1
    assert not any(int.from_bytes(bytes([b]) * 4, "little") == MANAGER_INIT_MARK
                   for b in range(256))


@settings(max_examples=300, deadline=None, derandomize=True, database=None)
@given(mark=st.binary(min_size=4, max_size=4))
@example(mark=MANAGER_INIT_MARK.to_bytes(4, "little"))
@example(mark=b"\x00\x00\x00\x00")
@example(mark=b"\xff\xff\xff\xff")
@example(mark=b"TINI")
def test_random_mark_bytes_count_only_when_they_are_the_mark(mark):
    """An otherwise complete manager with random bytes in init_mark (little-endian, as the
    target stores it): initialised exactly when they are the mark."""
    cs, h = _unit("example")
    value = int.from_bytes(mark, "little")
    assert _looks_initialised(h, _initialised_with_mark(h, value)) == \
        (value == MANAGER_INIT_MARK)


@settings(max_examples=60, deadline=None, derandomize=True, database=None)
@given(seed=st.integers(0, 2**64 - 1))
def test_random_manager_bytes_are_not_initialised(seed):
    """A manager holding random bytes (what RAM holds at power-up; ~10 kB, drawn from a
    seed) whose mark is not the mark: not initialised, whatever the other fields say."""
    cs, h = _unit("example")
    n = h.ffi.sizeof(f"{h.unit}_table_mgr_t")
    blob = np.random.default_rng(seed).integers(0, 256, n, dtype=np.uint8).tobytes()
    mgr = h.uninitialised(0)
    h.ffi.memmove(mgr, blob, n)
    if int(mgr.init_mark) == MANAGER_INIT_MARK:      # 1 in 2^32: not a manager never inited
        mgr.init_mark = 0
    _assert_not_initialised(h, mgr, cs)


# ---- the same on the emulated Cortex-M4F (qemu mps2-an386) --------------------------------


def _assert_same_cycle(a: bytes, b: bytes, dt, n, where):
    """Two answers of the runner's op 10 (arm_tables.correct_bytes): the same bytes, except
    that a NaN field may differ in sign and payload. IEEE 754 leaves the sign and payload
    of an arithmetic NaN result unspecified, and they do differ: the float64 (soft-float,
    libgcc) corrections on the NaN set give negative quiet NaNs on the target where the
    host (x86-64 SSE2) gives positive ones. Every finite value, status, the selection: bit
    for bit."""
    assert len(a) == len(b), where
    k = 3 * n * dt.itemsize
    fa, fb = np.frombuffer(a[:k], dt), np.frombuffer(b[:k], dt)
    both_nan = np.isnan(fa) & np.isnan(fb)
    np.testing.assert_array_equal(bits(fa)[~both_nan], bits(fb)[~both_nan], err_msg=str(where))
    assert a[k:] == b[k:], where


@pytest.mark.arm
@pytest.mark.parametrize("label", ("example", "f64"))
def test_not_initialised_on_the_target(label):
    """The manager built for the target with the flight flags (arm_tables: the runner's
    table extension): managers filled with 0x00 / 0xFF / 0xA5, every entry point on them,
    corrections and select on the prepared set they hand out, then init and tables,
    compared result by result (statuses, info, the bytes of the coefficients and prepared
    coefficients handed out, the corrections' outputs) with the host build, and all but
    the corrections with the Python model."""
    from generator.flight import target as ta
    from generator.flight.arm_tables import ArmTables, host_results, python_results

    missing = ta.missing_tools()
    require(not missing, f"missing {', '.join(missing)}: install the Debian packages "
                         f"{' '.join(ta.DEBIAN_PACKAGES)}")
    cs, h = _unit(label)
    table = encode_table(cs, 1, 0)
    vals = tables.flat_values(cs).copy()
    vals[next(v.index for v in tables.value_layout(cs.spec)
              if v.block.name == "b_poly_nT")] += 1.0
    other = encode_table(tables.coefficient_set(cs.spec, vals), 2, 0)
    parts = chunk_table(table, 500)
    # cycles: the zero field at 0 degC, and three with valid outputs after init (picked on
    # the host build, so the target's comparison covers valid and flagged outputs)
    samples = _samples(cs, 200, 60)
    good = h.manager()
    with_valid = [x for x in samples[1:] if np.any(h.correct_all(good, *x)["status"] == 0)]
    cycles = [("correct", raw, temp) for raw, temp in [samples[0]] + with_valid[:3]]
    ops = [("fill", 0x00), ("active",), ("prepared",), *cycles, ("load", table)]
    ops += [("receive_part", p) for p in parts] + [("commit",), ("abort",), ("prepared",)]
    ops += [("fill", 0xFF), ("load", table), ("receive_part", parts[0]), ("commit",),
            ("active",), ("prepared",), *cycles, ("fill", 0xA5), ("prepared",), ("commit",)]
    ops += [("init",), ("prepared",), *cycles, ("commit",), ("load", other), ("prepared",),
            ("active",), *cycles]
    flat = tables.flat_values(cs).astype(tables.value_dtype(cs.spec))
    got = ArmTables(cs).run(ops)
    want_host = host_results(h, ops)
    want_py = python_results(cs.spec, flat, ops)
    assert len(got) == len(want_host) == len(want_py) == len(ops)
    dt = np.dtype(tables.value_dtype(cs.spec)).newbyteorder("<")
    n = len(cs.unit.sensors)
    for i, (op, a, w, p) in enumerate(zip(ops, got, want_host, want_py)):
        if op[0] == "correct":
            assert p is None
            _assert_same_cycle(a, w, dt, n, (i, op[0]))
        else:
            assert a == w == p, (i, op[0], a, w, p)
    filled, valid_outputs = True, 0
    for op, r in zip(ops, got):
        if op[0] in ("fill", "init"):
            filled = op[0] == "fill"
        elif op[0] in ("active", "prepared"):
            assert bool(np.all(np.isnan(np.frombuffer(r, dt)))) == filled, op
        elif op[0] == "correct":
            field = np.frombuffer(r, dt, 3 * n)
            status = np.frombuffer(r, "<u2", n, 3 * n * dt.itemsize)
            sensor, reason = np.frombuffer(r[-2:], np.int8)[0], r[-1]
            if filled:
                assert np.all(np.isnan(field)) and np.all(status & chain.STATUS_IMPLAUSIBLE)
                assert (sensor, reason) == (-1, chain.SELECT_NONE)
            valid_outputs += int(np.sum(status == 0))
        elif op[0] != "abort":
            assert (r[0] == S.NOT_INITIALISED) == filled, (op[0], r)
            assert r[4] == S.NOT_INITIALISED or not filled, (op[0], r)
    assert valid_outputs > 0        # the cycles after init reach valid outputs
    after_init = ops.index(("init",))
    assert got[after_init][0] == S.OK
    after_cycles = after_init + 2 + len(cycles)
    assert got[after_cycles][0] == S.NOTHING_STAGED        # commit: the usual answer again
    assert got[after_cycles + 1][0] == S.OK                # load of the other table
