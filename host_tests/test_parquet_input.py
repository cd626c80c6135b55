"""Issue 20: Parquet telemetry beside CSV, for apply, fit and trace.

The same columns read from a Parquet file give the same Telemetry as from the CSV, pass
the same checks (the CSV reader's, fed with the Parquet columns) and give the same
outputs; bad Parquet input is one line naming the file, the row and the column.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from generator import pipeline
from generator.cli import main
from generator.errors import InputError
from generator.flight.coeffs import CoefficientSet
from generator.io.telemetry_csv import iter_telemetry, read_telemetry

from conftest import REPO

COEFFS = REPO / "generated" / "samsat_fm1" / "coefficients.json"
ROWS = 3000


def _cs():
    return CoefficientSet.load(COEFFS).with_boom_stowed()


@pytest.fixture()
def csv_path(tmp_path, fm1_dir):
    lines = (fm1_dir / "thermal_12pos.csv").read_text().split("\n")
    p = tmp_path / "part.csv"
    p.write_text("\n".join(lines[:ROWS + 3]) + "\n")
    return p


def _to_parquet(tel, path, unit_id=None, change=None, row_group_size=700):
    """The telemetry's columns in Parquet: whole-number columns as int32 (nulls where the
    CSV cell was empty), the others float64; `change(name, values) -> array` edits."""
    arrays, names = [], []
    for name, v in tel.columns.items():
        v = np.array(v)
        if change:
            v = change(name, v)
        whole = np.all(np.isnan(v) | (v == np.round(v))) and np.nanmax(np.abs(v)) < 2**31
        if whole and not name.endswith("_temp_C") and name != "time_s":
            arrays.append(pa.array(np.where(np.isnan(v), 0, v).astype(np.int32),
                                   mask=np.isnan(v)))
        else:
            arrays.append(pa.array(v, mask=np.isnan(v)))
        names.append(name)
    table = pa.table(arrays, names=names)
    if unit_id:
        table = table.replace_schema_metadata({"unit": unit_id})
    pq.write_table(table, path, row_group_size=row_group_size)
    return path


def test_parquet_reads_as_the_csv(tmp_path, csv_path):
    cs = _cs()
    tel = read_telemetry(csv_path, cs.unit)
    pqp = _to_parquet(tel, tmp_path / "part.parquet", unit_id=cs.unit.id)
    back = read_telemetry(pqp, cs.unit)
    assert list(back.columns) == list(tel.columns)
    for k in tel.columns:
        assert np.array_equal(back.columns[k], tel.columns[k], equal_nan=True), k
    assert back.meta["unit"] == cs.unit.id
    assert np.array_equal(back.line_numbers, np.arange(1, tel.n + 1))
    assert len(list(iter_telemetry(pqp, cs.unit, chunk_bytes=20_000))) > 5


def test_apply_on_parquet_writes_the_csv_rows(tmp_path, csv_path):
    cs = _cs()
    tel = read_telemetry(csv_path, cs.unit)
    pqp = _to_parquet(tel, tmp_path / "part.parquet")
    kw = dict(coils_off=True, at_rest=True)
    pipeline.apply(cs, csv_path, tmp_path / "a.csv", **kw)
    pipeline.apply(cs, pqp, tmp_path / "b.csv", chunk_bytes=30_000, **kw)
    a = (tmp_path / "a.csv").read_text().split("\n")
    b = (tmp_path / "b.csv").read_text().split("\n")
    assert a[0].endswith(str(csv_path)) and b[0].endswith(str(pqp))   # the source line
    assert a[1:] == b[1:] and len(a) == ROWS + 5
    rc = main(["apply", str(COEFFS), str(pqp), "-o", str(tmp_path / "c.csv"), "--boom-stowed",
               "--coils-off", "--at-rest", "--quiet"])
    assert rc == 0
    assert (tmp_path / "c.csv").read_text().split("\n")[1:] == b[1:]


def test_fit_and_trace_read_parquet(tmp_path, fm1_dir):
    """fit on the Parquet copy of the rotation campaign gives the same coefficients as on
    the CSV; trace reads its data files through the same reader."""
    from generator.io.unitfile import load_unit
    from generator.trace import tracer

    unit_path = fm1_dir / "unit.toml"
    unit = load_unit(unit_path)
    src = fm1_dir / "rotation.csv"
    pqp = _to_parquet(read_telemetry(src, unit), tmp_path / "rotation.parquet",
                      row_group_size=1500)
    a = pipeline.fit(unit_path, [src]).to_json_dict()
    b = pipeline.fit(unit_path, [pqp]).to_json_dict()
    assert a["sensors"] == b["sensors"] and a["unit_coefficients"] == b["unit_coefficients"]
    tel_csv, tel_pq = tracer._read(unit, [src, pqp])
    for k in tel_csv.columns:
        assert np.array_equal(tel_csv.columns[k], tel_pq.columns[k], equal_nan=True), k


def _raises(tmp_path, csv_path, match, **kw):
    cs = _cs()
    tel = read_telemetry(csv_path, cs.unit)
    p = _to_parquet(tel, tmp_path / "bad.parquet", **kw)
    with pytest.raises(InputError, match=match) as e:
        read_telemetry(p, cs.unit)
    assert "\n" not in str(e.value) and str(p) in str(e.value)
    return str(e.value)


def test_parquet_faults_name_row_and_column(tmp_path, csv_path):
    def count_out_of_range(name, v):
        if name == "mmc1_set_x":
            v[41] = 70000
        return v
    _raises(tmp_path, csv_path, r":42: column 'mmc1_set_x': count 70000 is outside",
            change=count_out_of_range)

    def time_back(name, v):
        if name == "time_s":
            v[100] = v[98]
        return v
    _raises(tmp_path, csv_path, r":101: column 'time_s': time goes backwards",
            change=time_back)
    _raises(tmp_path, csv_path, r"unit file is for", unit_id="another_unit")


def test_parquet_stored_nan_and_text_column(tmp_path, csv_path):
    cs = _cs()
    tel = read_telemetry(csv_path, cs.unit)
    cols = {k: pa.array(v) for k, v in tel.columns.items()}
    v = np.array(tel.columns["mpu1_x"])
    v[7] = np.nan                                   # a stored NaN, not a null
    cols["mpu1_x"] = pa.array(v, from_pandas=False)
    p = tmp_path / "nan.parquet"
    pq.write_table(pa.table(cols), p)
    with pytest.raises(InputError, match=r":8: column 'mpu1_x': NaN is not allowed"):
        read_telemetry(p, cs.unit)
    cols = {k: pa.array(v) for k, v in tel.columns.items()}
    # a string column the chain does not name is text, left out (ICD 2 "anything else";
    # host_tests/test_csv_quoting_text.py); a named column of string type stays an error
    cols["note"] = pa.array(["x"] * tel.n)
    cols["mmc1_temp_C"] = pa.array(["25"] * tel.n)
    p = tmp_path / "text.parquet"
    pq.write_table(pa.table(cols), p)
    with pytest.raises(InputError, match=r"column 'mmc1_temp_C': Parquet column of type string"):
        read_telemetry(p, cs.unit)
    cols["mmc1_temp_C"] = pa.array(tel.columns["mmc1_temp_C"])
    del cols["note"], cols["mmc1_set_y"]
    p = tmp_path / "missing.parquet"
    pq.write_table(pa.table(cols), p)
    with pytest.raises(InputError, match=r"column 'mmc1_set_y': missing from the header"):
        read_telemetry(p, cs.unit)
    p = tmp_path / "broken.parquet"
    p.write_bytes(b"PAR1" + b"\0" * 100)
    rc = main(["apply", str(COEFFS), str(p), "-o", str(tmp_path / "o.csv"), "--quiet"])
    assert rc == 2 and not (tmp_path / "o.csv").exists()
