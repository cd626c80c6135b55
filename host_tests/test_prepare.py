"""The prepare step (issue 20 item 5): the kernels read coefficients folded once per table.

`<unit>_table_prepare` (C loops in templates/magcal.c.j2: a second writing of
chain.fold_sensor_coeffs, since CasADi's straight-line emission of it took ~8 kB of code)
and chain.prepare_sensor (fold_sensor_coeffs on float32/float64 values) must give the
same bits;
the compiled-in `<unit>_table_prepared_default` (written at generate time) must be what
the C computes from `<unit>_coeffs_default`; the table manager prepares a table when it
activates it and keeps the old table AND its prepared copy when a table is refused.
Everything here is compared bit for bit: there is no tolerance.
"""

from __future__ import annotations

import numpy as np
import pytest

from chain_fixtures import bits, random_coeffs, samsat_unit, with_float, with_options
from generator.flight import tables
from generator.flight.chain import SensorOptions, n_prepared, prepare_sensor
from generator.flight.host import HostUnit
from generator.flight.table_host import TableHost
from generator.flight.tables import TableStatus, encode_table
from generator.io.unit import SensorSpec, Unit

COILS = ("coil_x_A", "coil_y_A", "coil_z_A")


def _physical_unit() -> Unit:
    return Unit("prepphys", (
        SensorSpec("ist", "generic", "body", ("+y", "-x", "+z"), 1.0, 0, False, 100.0,
                   input="uT", temperature=False, range_nT=1.6e6),
        SensorSpec("hmg", "generic", "boom", ("-z", "+y", "+x"), 1.0, 0, True, 100.0,
                   input="G", temperature=True, range_nT=8e5),
        SensorSpec("mmc", "MMC5883MA", "body", ("+x", "+y", "-z"), 25.0, 32768, True, 40.0)),
        lab_field_nT=50000.0, boom_reference="mmc")


def _cases() -> dict:
    rng = np.random.default_rng(2020)
    opts = {"mmc1": SensorOptions(channels=("heater_A",), nonlinear=True, sr_compensation=True,
                                  channel_scale=True, lagged_channels=("bus_V",)),
            "mpu3": SensorOptions(channels=("heater_A", "bus_V"), thermal_lag=True),
            "mmc2": SensorOptions(sr_compensation=True)}
    return {
        "f32_coils": random_coeffs(rng, samsat_unit("prepsat"), coils=COILS),
        "f64": with_float(random_coeffs(rng, samsat_unit("prep64", "float64"), coils=COILS),
                          "float64"),
        "options": with_options(rng, random_coeffs(rng, samsat_unit("prepopt"), coils=COILS),
                                opts, poly_degree=4),
        "physical": random_coeffs(rng, _physical_unit(), coils=COILS),
    }


CASES = _cases()


def _python_prepared(cs) -> np.ndarray:
    """The C struct `<unit>_table_prepared_t` as flat values, from chain.prepare_sensor:
    per sensor its table coefficients, its kernel's prepared vector, the SET-only
    kernel's (SET/RESET sensors)."""
    spec = cs.spec
    dt = np.float32 if spec.unit.float_type == "float32" else np.float64
    parts = []
    for s in spec.unit.sensors:
        parts.append(np.asarray(cs.flat_sensor(s.name), dtype=dt))
        for set_only in ((False, True) if s.set_reset else (False,)):
            p = prepare_sensor(spec, s, cs.flat_sensor(s.name), cs.flat_unit(), set_only)
            assert p.size == n_prepared(spec, s, set_only)
            parts.append(p)
    return np.concatenate(parts)


@pytest.fixture(scope="module", params=list(CASES))
def built(request):
    cs = CASES[request.param]
    return request.param, cs, HostUnit(cs)


def _c_prepare(host, flat) -> np.ndarray:
    out = np.zeros(int(host._lib.host_prepared_size()), dtype=host.dtype)
    flat = np.ascontiguousarray(flat, dtype=host.dtype)
    host._lib.host_prepare(host._ptr(flat), host._ptr(out))
    return out


def test_c_prepare_is_the_python_prepare(built):
    label, cs, host = built
    want = _python_prepared(cs)
    got = _c_prepare(host, host.flat_coeffs())
    assert got.size == want.size, label
    np.testing.assert_array_equal(bits(got), bits(want.astype(host.dtype)), err_msg=label)


def test_compiled_in_prepared_defaults_are_the_c_prepare(built):
    """`<unit>_table_prepared_default`, written at generate time from Python, holds the bits
    `<unit>_table_prepare(&<unit>_coeffs_default)` computes on the machine."""
    label, cs, host = built
    out = np.zeros(int(host._lib.host_prepared_size()), dtype=host.dtype)
    host._lib.host_default_prepared(host._ptr(out))
    np.testing.assert_array_equal(bits(out), bits(_c_prepare(host, host.default_coeffs())),
                                  err_msg=label)


def test_random_tables_prepare_the_same_in_c_and_python():
    """Many coefficient sets through one build: the C prepare follows the values (no
    constant of the build leaks in) and equals the Python prepare bit for bit."""
    cs0 = CASES["options"]
    host = HostUnit(cs0)
    rng = np.random.default_rng(7)
    for k in range(20):
        cs = with_options(np.random.default_rng(100 + k), random_coeffs(rng, cs0.unit,
                                                                         coils=COILS),
                          dict(cs0.spec.sensor_options), poly_degree=4)
        got = _c_prepare(host, host.flat_coeffs(cs))
        np.testing.assert_array_equal(bits(got), bits(_python_prepared(cs)), err_msg=str(k))


@pytest.fixture(scope="module")
def table_pair():
    rng = np.random.default_rng(31)
    default = random_coeffs(rng, samsat_unit("preptbl"), coils=COILS)
    new = random_coeffs(rng, samsat_unit("preptbl"), coils=COILS)
    return default, new, TableHost(default)


def test_manager_prepares_what_it_activates_and_keeps_both_on_a_fault(table_pair):
    default, new, h = table_pair
    mgr = h.manager()   # init with the compiled-in defaults
    np.testing.assert_array_equal(bits(h.prepared_flat(mgr)), bits(_python_prepared(default)))
    # init with defaults given as a plain coefficient struct: init prepares them
    other, st = h.init(tables.flat_values(new).astype(h.dtype))
    assert st == TableStatus.OK
    np.testing.assert_array_equal(bits(h.prepared_flat(other)), bits(_python_prepared(new)))
    good = encode_table(new, 5, 0)
    assert h.load(mgr, good) == TableStatus.OK
    after_load = h.prepared_flat(mgr)
    np.testing.assert_array_equal(bits(after_load), bits(_python_prepared(new)))
    # refused: a rollback, and a corrupt table; the prepared copy in use stays as it was
    assert h.load(mgr, encode_table(default, 4, 0)) == TableStatus.SERIAL_ROLLBACK
    bad = bytearray(encode_table(default, 6, 0))
    bad[tables.HEADER_BYTES + 3] ^= 0x40
    assert h.load(mgr, bytes(bad)) != TableStatus.OK
    np.testing.assert_array_equal(bits(h.prepared_flat(mgr)), bits(after_load))
    np.testing.assert_array_equal(bits(h.active_flat(mgr)),
                                  bits(tables.flat_values(new).astype(h.dtype)))
