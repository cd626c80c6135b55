"""Issue 15: uplink tables of units with sensors that have no temperature (ICD section 4,
`temperature = false`): such a sensor has no t_min_C/t_max_C and takes no part in the
header temperature range; a unit none of whose sensors has one has the whole plausible
range, tables.NO_TEMP_RANGE_C, in its header. The flight validator (C) and the ground
decoder (Python) agree on every check, and `magcal generate` / `magcal table` work on
such units.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

from chain_fixtures import bits, random_coeffs
from generator.cli import main
from generator.flight import tables
from generator.flight.table_host import TableHost
from generator.flight.tables import (HEADER_FIELDS, HEADER_OFFSETS, TableStatus, check_table,
                                     encode_table, reseal)
from generator.io.unit import SensorSpec, Unit
from test_tables import _flips, _header_expectation, _set_field, _set_value, _status

S = TableStatus
XYZ = ("+x", "+y", "+z")


def _units() -> dict:
    """label -> (unit, coils). notemp: no sensor has a temperature (counts and uT);
    mixed: one MMC5883MA with a temperature beside two without (G with SET/RESET on the
    boom, counts), float64, coils."""
    notemp = Unit("tnotemp", (
        SensorSpec("mpu", "MPU-9255", "body", XYZ, 150.0, 0, False, 250.0, temperature=False),
        SensorSpec("ist", "generic", "body", ("-y", "+x", "+z"), 1.0, 0, False, 100.0,
                   input="uT", temperature=False, range_nT=1.6e6)))
    mixed = Unit("tmixed", (
        SensorSpec("mmc", "MMC5883MA", "body", XYZ, 25.0, 32768, True, 40.0),
        SensorSpec("phg", "generic", "boom", ("+z", "-x", "+y"), 1.0, 0, True, 100.0,
                   input="G", temperature=False, range_nT=8e5),
        SensorSpec("mpu", "MPU-9255", "body", XYZ, 150.0, 0, False, 250.0, temperature=False)),
        lab_field_nT=50000.0, float_type="float64", boom_reference="mmc")
    return {"notemp": (notemp, ()), "mixed": (mixed, ("mtq_x_A",))}


UNITS = _units()


@functools.lru_cache(maxsize=None)
def pair(label):
    """(compiled-in default set, another set of the same chain to upload)."""
    unit, coils = UNITS[label]
    return tuple(random_coeffs(np.random.default_rng(seed), unit, coils=coils)
                 for seed in (31, 32))


@functools.lru_cache(maxsize=None)
def host(label) -> TableHost:
    return TableHost(pair(label)[0])


def _expected_range(cs) -> tuple:
    with_t = [s for s in cs.unit.sensors if s.temperature]
    if not with_t:
        return tables.NO_TEMP_RANGE_C
    dt = tables.value_dtype(cs.spec).type
    return (np.float32(min(dt(cs.sensors[s.name]["t_min_C"]) for s in with_t)),
            np.float32(max(dt(cs.sensors[s.name]["t_max_C"]) for s in with_t)))


@pytest.mark.parametrize("label", list(UNITS))
def test_header_range_and_round_trip(label):
    default, new = pair(label)
    h = host(label)
    table = encode_table(new, serial=3, created_s=0)
    head, _ = check_table(table, new.spec)
    assert (head["t_min_C"], head["t_max_C"]) == _expected_range(new)
    if label == "notemp":
        assert (head["t_min_C"], head["t_max_C"]) == (-100.0, 150.0)
    else:   # the header is the one sensor with a temperature, not the plausible range
        assert (head["t_min_C"], head["t_max_C"]) == (-20.0, 55.0)
        assert len(tables._temp_indices(new.spec)) == 1
    # the compiled-in default table is the encoder's, and the C accepts both
    assert h.default_table() == encode_table(default, serial=0, created_s=0)
    assert h.validate(h.default_table()) == S.OK
    mgr = h.manager()
    assert h.load(mgr, table) == S.OK and h.info(mgr)["active_serial"] == 3
    want = tables.flat_values(new).astype(np.dtype(tables.value_dtype(new.spec)).newbyteorder("="))
    np.testing.assert_array_equal(bits(h.active_flat(mgr)), bits(want))


@pytest.mark.parametrize("label", list(UNITS))
def test_header_range_checks_agree_in_c_and_python(label):
    default, new = pair(label)
    h, spec = host(label), default.spec
    dt = np.dtype(tables.value_dtype(spec))
    table = encode_table(new, serial=9, created_s=0)
    lo, hi = _expected_range(new)
    hdr = (HEADER_FIELDS, HEADER_OFFSETS)
    trials = [
        (reseal(_set_field(table, *hdr, "t_min_C", float("nan"))), S.BAD_TEMP_RANGE),
        (reseal(_set_field(table, *hdr, "t_min_C", float(hi))), S.BAD_TEMP_RANGE),  # empty
        (reseal(_set_field(table, *hdr, "t_max_C", 151.0)), S.BAD_TEMP_RANGE),
        (reseal(_set_field(table, *hdr, "t_min_C", float(lo) + 1.0)), S.TEMP_RANGE_MISMATCH),
        (reseal(_set_field(table, *hdr, "t_max_C", float(hi) - 1.0)), S.TEMP_RANGE_MISMATCH),
    ]
    if label == "mixed":
        i_min, i_max = tables._temp_indices(spec)[0]
        trials += [(_set_value(table, i_min, -30.0, dt), S.TEMP_RANGE_MISMATCH),
                   (_set_value(table, i_max, -20.0, dt), S.EMPTY_RANGE)]
    # another value of the first sensor (its lsb_nT, 0.01 % off, inside its plausible
    # range) with a resealed CRC: no range involved, accepted
    trials.append((_set_value(table, 0, np.frombuffer(table, dt, 1, tables.HEADER_BYTES)[0]
                              * dt.type(1.0001), dt), S.OK))
    for t, want in trials:
        st, bad = h.validate_detail(t)
        assert st == want and (st, bad) == _status(t, spec), (label, want, st)


@pytest.mark.parametrize("label", list(UNITS))
def test_every_single_bit_flip_is_rejected_with_the_right_code(label):
    default, new = pair(label)
    h = host(label)
    table = encode_table(new, serial=5, created_s=1_790_000_000)
    flips = _flips(table)
    mgr = h.manager()
    res, codes = h.fuzz(mgr, flips)
    assert res == 0, f"invariant broken at flip {-res - 1}"
    want = np.array([_header_expectation(k // 8) for k in range(len(flips))])
    np.testing.assert_array_equal(codes[:, 0], want)
    np.testing.assert_array_equal([_status(x, default.spec)[0] for x in flips], want)


def test_generate_and_table_commands(tmp_path, capsys):
    """`magcal generate --compile` and `magcal table` (encode, decode, flight check) on a
    unit none of whose sensors has a temperature."""
    default, new = pair("notemp")
    cj = tmp_path / "coefficients.json"
    new.save(cj)
    out = tmp_path / "c"
    assert main(["generate", str(cj), "-o", str(out), "--compile", "-q"]) == 0
    assert (out / "tnotemp_table.c").is_file() and (out / "tnotemp_magcal.c").is_file()
    tb = tmp_path / "TABLE.bin"
    assert main(["table", str(cj), "-o", str(tb), "--serial", "4", "--created-s", "0",
                 "-q"]) == 0
    assert tb.read_bytes() == encode_table(new, 4, 0)
    capsys.readouterr()
    assert main(["table", "--decode", str(tb), "--coeffs", str(cj)]) == 0
    text = capsys.readouterr().out
    assert "t_min_C          -100.0 degC" in text and "t_max_C          150.0 degC" in text
    assert main(["table", "--check", str(tb), "--coeffs", str(cj)]) == 0
    assert "accepted by the flight validator" in capsys.readouterr().out
