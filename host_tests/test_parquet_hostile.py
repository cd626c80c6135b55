"""Issue 20: hostile Parquet telemetry is bad input, never a traceback or a wrong number.

Files are written with pyarrow: integers beyond what a float64 holds exactly (uint64 above
int64's maximum, int64 beyond 2^53), values outside a column's range, columns of types
that are no telemetry numbers (string, bool, timestamp, dictionary-encoded, all-null,
nested list, ...), and damaged bytes. Each gives exit status 2 and one line on stderr
naming the file and the column (and the 1-based data row where a value is at fault), and
no output file; integer types that hold the values exactly read as the CSV does.
"""

from __future__ import annotations

import datetime
import decimal
import random

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from generator.cli import main
from generator.errors import InputError
from generator.flight.coeffs import CoefficientSet
from generator.io.telemetry_csv import read_telemetry

from conftest import REPO

COEFFS = REPO / "generated" / "samsat_fm1" / "coefficients.json"
ROWS = 400


@pytest.fixture(scope="module")
def base(fm1_dir):
    """The first ROWS rows of the shared thermal campaign: {column: pa.Array} with the
    types a writer would choose (counts int64, the others float64, empty cells null)."""
    import pyarrow.csv as pcsv

    unit = CoefficientSet.load(COEFFS).with_boom_stowed().unit
    src = fm1_dir / "thermal_12pos.csv"
    table = pcsv.read_csv(src, read_options=pcsv.ReadOptions(skip_rows=2))
    table = table.slice(0, ROWS)
    return unit, {name: table.column(name).combine_chunks() for name in table.column_names}


def _write(tmp_path, cols: dict, name="bad.parquet", **kw):
    p = tmp_path / name
    pq.write_table(pa.table(cols), p, **kw)
    return p


def _apply_fails(tmp_path, capsys, path, *expected):
    """`magcal apply` on path: exit 2, one line on stderr naming the file and every
    expected fragment, no output file."""
    out = tmp_path / "out.csv"
    rc = main(["apply", str(COEFFS), str(path), "-o", str(out), "--boom-stowed",
               "--coils-off", "--at-rest", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.count("\n") == 1 and str(path) in err, err
    for frag in expected:
        assert frag in err, (frag, err)
    assert not out.exists()
    return err


def _replace(cols, name, arr):
    cols = dict(cols)
    cols[name] = arr
    return cols


def _with_value(arr: pa.Array, row: int, value, type_):
    """arr cast to type_ (values kept), with `value` at 0-based `row`."""
    v = arr.to_pylist()
    v[row] = value
    return pa.array(v, type=type_)


def test_uint64_beyond_int64_names_row_and_column(tmp_path, capsys, base):
    _, cols = base
    big = 2**64 - 1
    # a channel column (no raw range to check): the reader itself must refuse the value
    col = _with_value(pa.array([0] * ROWS, type=pa.uint64()), 10, big, pa.uint64())
    p = _write(tmp_path, _replace(cols, "extra_ch", col))
    _apply_fails(tmp_path, capsys, p, ":11: column 'extra_ch'", str(big))
    # a count column: uint64 above int64's maximum at 0-based row 300
    v = [abs(x) for x in cols["mpu1_x"].to_pylist()]
    v[300] = 2**63 + 5
    p = _write(tmp_path, _replace(cols, "mpu1_x", pa.array(v, type=pa.uint64())), "c.parquet")
    _apply_fails(tmp_path, capsys, p, ":301: column 'mpu1_x'", str(2**63 + 5))


def test_int64_beyond_float64_exactness_names_row_and_column(tmp_path, capsys, base):
    _, cols = base
    for value in (2**53 + 1, -(2**63)):
        col = _with_value(pa.array([1] * ROWS, type=pa.int64()), 57, value, pa.int64())
        p = _write(tmp_path, _replace(cols, "ch", col), f"i{value}.parquet")
        _apply_fails(tmp_path, capsys, p, ":58: column 'ch'", str(value))


def test_values_outside_the_columns_range_name_row_and_column(tmp_path, capsys, base):
    _, cols = base
    cases = [("mmc1_set_x", 70000, pa.int32(), "count 70000 is outside"),
             ("mpu2_y", -40000, pa.int32(), "count -40000 is outside"),
             ("mmc1_set_y", 2**40, pa.uint64(), f"count {2**40} is outside"),
             ("mmc1_temp_C", -300.0, pa.float32(), "physical range"),
             ("ref_norm_nT", 2e7, pa.float64(), "physical range"),
             ("ch", 1e300, pa.float64(), "physical range"),
             ("ch", 2 * 10**15, pa.int64(), "physical range")]
    for k, (name, value, type_, what) in enumerate(cases):
        vals = cols[name].to_pylist() if name in cols else [0] * ROWS
        vals[199] = value
        p = _write(tmp_path, _replace(cols, name, pa.array(vals, type=type_)), f"r{k}.parquet")
        _apply_fails(tmp_path, capsys, p, f":200: column '{name}'", what)


def test_small_integer_types_read_as_the_csv(tmp_path, base):
    """int8..uint64 and float32 columns holding the values exactly give the values of the
    int64 / float64 file; so do dictionary-encoded numbers (a storage detail)."""
    unit, cols = base
    ref = read_telemetry(_write(tmp_path, cols, "ref.parquet"), unit)
    narrow = dict(cols)
    narrow["position"] = cols["position"].cast(pa.uint8())
    narrow["mpu1_x"] = cols["mpu1_x"].cast(pa.int16())
    narrow["mpu1_y"] = cols["mpu1_y"].cast(pa.int32())
    narrow["mmc1_set_x"] = cols["mmc1_set_x"].cast(pa.uint16())
    narrow["mmc1_set_y"] = cols["mmc1_set_y"].cast(pa.uint32())
    narrow["mmc1_set_z"] = cols["mmc1_set_z"].cast(pa.uint64())
    narrow["mpu1_temp_C"] = cols["mpu1_temp_C"].cast(pa.float32())
    narrow["mpu1_z"] = cols["mpu1_z"].dictionary_encode()     # a storage detail, read as ints
    narrow["mpu2_temp_C"] = cols["mpu2_temp_C"].dictionary_encode()
    tel = read_telemetry(_write(tmp_path, narrow, "narrow.parquet"), unit)
    for k in ref.columns:
        want = ref.columns[k]
        if k == "mpu1_temp_C":
            want = want.astype(np.float32).astype(np.float64)
        assert np.array_equal(tel.columns[k], want, equal_nan=True), k


def _bad_types(n):
    t0 = datetime.datetime(2026, 1, 1)
    return {
        "string": pa.array([str(i) for i in range(n)]),
        "large_string": pa.array([str(i) for i in range(n)], type=pa.large_string()),
        "binary": pa.array([b"\x00\x01"] * n),
        "bool": pa.array([i % 2 == 0 for i in range(n)]),
        "timestamp": pa.array([t0 + datetime.timedelta(seconds=i) for i in range(n)]),
        "date": pa.array([datetime.date(2026, 1, 1)] * n),
        "duration": pa.array([datetime.timedelta(seconds=i) for i in range(n)]),
        "decimal": pa.array([decimal.Decimal(i) for i in range(n)], type=pa.decimal128(10, 2)),
        "dictionary": pa.array([str(i % 3) for i in range(n)]).dictionary_encode(),
        "null": pa.nulls(n),
        "list": pa.array([[i, i + 1] for i in range(n)]),
        "struct": pa.array([{"a": i, "b": 1.0} for i in range(n)]),
        "map": pa.array([[("k", i)] for i in range(n)], type=pa.map_(pa.string(), pa.int64())),
    }


@pytest.mark.parametrize("kind", sorted(_bad_types(1)))
def test_columns_of_unexpected_type_name_the_column(tmp_path, capsys, base, kind):
    _, cols = base
    bad = _bad_types(ROWS)[kind]
    # as an extra channel and in place of a count column the unit needs; any type but
    # integers and floats in an extra channel is left out with a note, not refused (ICD 2
    # "anything else", as a CSV's text column: host_tests/test_csv_quoting_text.py,
    # test_parquet_unused_types.py), in a named column refused
    for name in ("odd_ch", "mpu1_z"):
        p = _write(tmp_path, _replace(cols, name, bad), f"{kind}_{name}.parquet")
        if name == "odd_ch":
            out = tmp_path / "text_left_out.csv"
            rc = main(["apply", str(COEFFS), str(p), "-o", str(out), "--boom-stowed",
                       "--coils-off", "--at-rest", "--quiet"])
            assert rc == 0, capsys.readouterr().err
            continue
        _apply_fails(tmp_path, capsys, p, f"column '{name}'", "Parquet column of type")


def test_hostile_metadata_and_names(tmp_path, capsys, base):
    """A bad value in a column whose name holds a line break, a key-value 'unit' of
    another unit: one line each; metadata that is not UTF-8 is ignored (writers'
    bookkeeping)."""
    unit, cols = base
    weird = dict(cols)
    vals = cols["ref_x_nT"].to_pylist()
    vals[3] = 1e300
    weird["a\nb"] = pa.array(vals)
    err = _apply_fails(tmp_path, capsys, _write(tmp_path, weird, "nl.parquet"), ":4: ",
                       "physical range")
    assert err.count("\n") == 1
    t = pa.table(cols).replace_schema_metadata({b"unit": b"\xff\xfe", "x": "y"})
    p = tmp_path / "meta.parquet"
    pq.write_table(t, p)
    assert read_telemetry(p, unit).n == ROWS
    t = pa.table(cols).replace_schema_metadata({"unit": "another_unit"})
    pq.write_table(t, p)
    _apply_fails(tmp_path, capsys, p, "another_unit")


def test_damaged_files_are_one_line_exit_2(tmp_path, capsys, base):
    """Truncated files and files with bytes overwritten (seeded): exit 2 with one line,
    or, where the damage leaves a valid file, exit 0; never an internal error."""
    _, cols = base
    good = _write(tmp_path, cols, "good.parquet", row_group_size=100)
    raw = good.read_bytes()
    for cut in (4, 8, len(raw) // 3, len(raw) - 9, len(raw) - 1):
        p = tmp_path / f"cut{cut}.parquet"
        p.write_bytes(raw[:cut])
        _apply_fails(tmp_path, capsys, p)
    rng = random.Random(20)
    outcomes = {0: 0, 2: 0}
    for k in range(60):
        b = bytearray(raw)
        for _ in range(rng.choice((1, 4, 32))):
            b[rng.randrange(4, len(b) - 4)] = rng.randrange(256)
        p = tmp_path / f"flip{k}.parquet"
        p.write_bytes(bytes(b))
        out = tmp_path / f"flip{k}.csv"
        rc = main(["apply", str(COEFFS), str(p), "-o", str(out), "--boom-stowed",
                   "--coils-off", "--at-rest", "--quiet"])
        err = capsys.readouterr().err
        assert rc in (0, 2), err
        assert (rc == 0) == out.exists(), err
        if rc == 2:
            assert err.count("\n") == 1 and str(p) in err, err
        outcomes[rc] += 1
    assert outcomes[2] > 0
