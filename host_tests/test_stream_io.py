"""Issue 20: telemetry of any length, `apply` at I/O speed.

* the vectorised cell formatter writes exactly Python's repr(float(v)) (the text apply
  wrote before it streamed), on values of every magnitude;
* pyarrow's CSV parser, tried first, accepts only cells the cell-by-cell parser accepts,
  with the same values (else the slow path decides and names the cell);
* reading in chunks gives the same columns, line numbers and messages as one chunk,
  across comment lines, blank lines, empty cells and a fault at a chunk boundary;
* apply in small chunks writes the same bytes as in one chunk, and as the row-by-row
  writer it replaced; the chain state carries over chunk boundaries (the same bits as
  one batch over the whole file).
"""

from __future__ import annotations

import csv
import io

import numpy as np
import pytest

from generator import pipeline
from generator.errors import InputError
from generator.flight.chain import SELECT_REASONS, STATUS_BITS
from generator.flight.coeffs import CoefficientSet
from generator.io import telemetry_csv
from generator.io.outputs import csv_lines, float_cells, int_cells
from generator.io.telemetry_csv import concat_chunks, iter_telemetry, read_telemetry

from conftest import REPO

COEFFS = REPO / "generated" / "samsat_fm1" / "coefficients.json"


# ---- the cell formatter -------------------------------------------------------------------

def _repr_cells(x):
    return [repr(v) if np.isfinite(v) else None for v in np.asarray(x, np.float64).tolist()]


def test_float_cells_are_repr_on_every_magnitude():
    rng = np.random.default_rng(20)
    n = 200_000
    mags = 10.0 ** rng.integers(-30, 30, n)
    edges = [0.0, -0.0, 1e-4, 9.999999999999999e-05, 1e16, 9999999999999998.0, 1e15,
             1234567890123456.0, 5e-324, 2.2250738585072014e-308, 1.7976931348623157e308,
             0.1, 1.0, -1.0, 123456789.0, np.nan, np.inf, -np.inf]
    x = np.concatenate([rng.normal(size=n) * mags,                       # float64
                        (rng.normal(size=n) * 5e4).astype(np.float32),   # fields in nT
                        np.round(rng.normal(size=n) * 3e4),              # whole numbers
                        np.arange(n) * 0.01,                             # time stamps
                        edges])
    assert float_cells(x).to_pylist() == _repr_cells(x)


def test_float32_cells_round_trip():
    """Every finite float32 bit pattern class: the cell reads back as the same float32."""
    rng = np.random.default_rng(21)
    bits = rng.integers(0, 2**32, 300_000, dtype=np.uint64).astype(np.uint32)
    x = bits.view(np.float32)
    cells = float_cells(x).to_pylist()
    ok = np.isfinite(x)
    back = np.array([float(c) for c, k in zip(cells, ok) if k], dtype=np.float64)
    assert np.array_equal(back.astype(np.float32).view(np.uint32), x[ok].view(np.uint32))
    assert all(c is None for c, k in zip(cells, ok) if not k)


def test_float_cells_present_mask_and_lines():
    cells = float_cells([1.0, 2.0, np.nan], present=[True, False, True])
    assert cells.to_pylist() == ["1.0", None, None]
    text = bytes(csv_lines([cells, int_cells([3, 4, 5])])).decode()
    assert text == "1.0,3\n,4\n,5\n"
    assert bytes(csv_lines([float_cells([]), int_cells([])])) == b""


# ---- the parsers --------------------------------------------------------------------------

CELLS = ["1.5", " 1.5", "1.5 ", "+1.5", "1.", ".5", "1e5", "1E+5", "0x10", "1_000", "--1",
         "1e", "e5", "1.5.2", '"1.5"', "\u0663", "1d5", "1e400", "1e-400", "  ", "-", "+",
         "00012", "-0", ".", "1e+", "\t1", "+.5e-3", "4.9e-324", "1.7976931348623157e308",
         "123456789012345678901234567890", "9007199254740993", "", "1,5", "'1'", "1 2"]


@pytest.mark.parametrize("cell", CELLS)
def test_arrow_parser_accepts_a_subset_of_the_slow_parser(cell):
    rows = [f"0,{cell}", "1,2"]
    fast = telemetry_csv._parse_arrow("\n".join(rows), 2, 2)
    try:
        slow = telemetry_csv._parse_slow("x.csv", ["a", "b"], rows, [2, 3])
    except InputError:
        slow = None
    if fast is not None:
        assert slow is not None, f"pyarrow accepted {cell!r}, the slow parser does not"
        assert np.array_equal(fast, slow, equal_nan=True), cell


# ---- reading in chunks --------------------------------------------------------------------

def _unit():
    return CoefficientSet.load(COEFFS).unit


def _telemetry_text(unit, n, rng, extras=True) -> str:
    cols = ["time_s"]
    for s in unit.sensors:
        cols += list(s.required_columns)
    lines = ["# unit: " + unit.id, "# a comment before the header", ",".join(cols)]
    for i in range(n):
        cells = [repr(i * 0.5)]
        for s in unit.sensors:
            for c in s.required_columns:
                if c.endswith("_temp_C"):
                    cells.append(f"{20 + rng.normal():.3f}")
                else:
                    cells.append(str(int(s.zero_count + rng.integers(-2000, 2000))))
        if extras and i % 97 == 5:
            cells[3] = ""                                       # an empty cell
        lines.append(",".join(cells))
        if extras and i % 131 == 7:
            lines.append("# a comment between rows")
        if extras and i % 173 == 11:
            lines.append("")
    return "\n".join(lines) + "\n"


def _same(a, b):
    assert list(a.columns) == list(b.columns)
    for k in a.columns:
        assert np.array_equal(a.columns[k], b.columns[k], equal_nan=True), k
    assert np.array_equal(a.line_numbers, b.line_numbers)
    assert a.meta == b.meta and a.comments == b.comments


@pytest.mark.parametrize("extras", [False, True])
def test_chunks_read_the_same_as_one(tmp_path, extras):
    unit = _unit()
    p = tmp_path / "t.csv"
    p.write_text(_telemetry_text(unit, 3000, np.random.default_rng(3), extras))
    whole = concat_chunks(iter_telemetry(p, unit, chunk_bytes=1 << 30))
    chunks = list(iter_telemetry(p, unit, chunk_bytes=5000))
    assert len(chunks) > 20
    _same(concat_chunks(chunks), whole)
    _same(read_telemetry(p, unit), whole)
    assert whole.n == 3000


def test_fault_at_a_chunk_boundary_names_its_line(tmp_path):
    unit = _unit()
    text = _telemetry_text(unit, 400, np.random.default_rng(4), extras=False)
    lines = text.split("\n")
    k = 250                                 # a data line: time set before its predecessor
    cells = lines[k].split(",")
    cells[0] = "0.25"
    lines[k] = ",".join(cells)
    p = tmp_path / "back.csv"
    p.write_text("\n".join(lines))
    messages = set()
    for chunk_bytes in (1 << 30, 300, 1000, 7777):
        with pytest.raises(InputError) as e:
            list(iter_telemetry(p, unit, chunk_bytes=chunk_bytes))
        messages.add(str(e.value))
    assert len(messages) == 1, messages
    assert f":{k + 1}:" in messages.pop()


def test_bad_utf8_line_in_a_later_chunk(tmp_path):
    unit = _unit()
    raw = _telemetry_text(unit, 300, np.random.default_rng(5), extras=False).encode()
    lines = raw.split(b"\n")
    lines[200] = lines[200] + b"\xff"
    p = tmp_path / "bad.csv"
    p.write_bytes(b"\n".join(lines))
    with pytest.raises(InputError, match=":201: not UTF-8"):
        list(iter_telemetry(p, unit, chunk_bytes=2000))


# ---- apply in chunks ----------------------------------------------------------------------

def _old_apply_csv(tel, unit, results) -> str:
    """The row-by-row writer apply used before it streamed (csv.writer, repr of each
    value), kept here as the reference for the text."""
    def fmt(v):
        return str(v.item() if hasattr(v, "item") else v) if np.isfinite(v) else ""

    names = [s.name for s in unit.sensors]
    reasons = {v: k for k, v in SELECT_REASONS.items()}
    out = io.StringIO()
    out.write(f"# magcal apply: calibrated field in the body frame, from {tel.path}\n")
    out.write("# <s>_status: bits " + " ".join(f"{k}={v}" for k, v in STATUS_BITS.items())
              + f" ABSENT={pipeline.STATUS_ABSENT}; valid = no bit but TEMP_EXTRAPOLATED\n")
    out.write("# sel_*: the vector for attitude control (fallback order "
              + " > ".join(names[i] for i in results["fallback_order"]) + ")\n")
    w = csv.writer(out, lineterminator="\n")
    header = ["time_s"]
    for s in unit.sensors:
        header += [f"{s.name}_x_nT", f"{s.name}_y_nT", f"{s.name}_z_nT", f"{s.name}_valid",
                   f"{s.name}_status"]
    w.writerow(header + ["sel_x_nT", "sel_y_nT", "sel_z_nT", "sel_sensor", "sel_reason"])
    sel = results["selected"]
    for i in range(tel.n):
        row = [fmt(tel.time_s[i])]
        for s in unit.sensors:
            r = results[s.name]
            row += ([fmt(r["field_body_nT"][i, k]) for k in range(3)] if r["present"][i]
                    else ["", "", ""])
            row += ["1" if r["valid"][i] else "0", str(int(r["status"][i]))]
        k = int(sel["sensor"][i])
        row += ([fmt(sel["field_body_nT"][i, j]) for j in range(3)] + [names[k]] if k >= 0
                else ["", "", "", ""])
        row.append(reasons[int(sel["reason"][i])])
        w.writerow(row)
    return out.getvalue()


def test_apply_in_chunks_writes_the_same_bytes(tmp_path, fm1_dir):
    cs = CoefficientSet.load(COEFFS).with_boom_stowed()
    src = (fm1_dir / "thermal_12pos.csv").read_text().split("\n")
    data = tmp_path / "part.csv"
    data.write_text("\n".join(src[:4000]) + "\n")          # a few thousand rows
    from generator.flight.host import HostUnit
    host = HostUnit(cs)
    one = pipeline.apply(cs, data, tmp_path / "one.csv", host=host, coils_off=True,
                         at_rest=True, chunk_bytes=1 << 30)
    many = pipeline.apply(cs, data, tmp_path / "many.csv", host=host, coils_off=True,
                          at_rest=True, chunk_bytes=20_000)
    text = (tmp_path / "one.csv").read_bytes()
    assert (tmp_path / "many.csv").read_bytes() == text
    tel = read_telemetry(data, cs.unit)
    assert text.decode() == _old_apply_csv(tel, cs.unit, one)
    for s in cs.unit.sensors:             # the same bits as one batch over the whole file
        for k in ("field_body_nT", "status", "valid"):
            a, b = np.asarray(one[s.name][k]), np.asarray(many[s.name][k])
            assert a.tobytes() == b.tobytes(), (s.name, k)
    # the state matters here: SET/RESET sensors keep their offset from call to call
    assert any(s.set_reset for s in cs.unit.sensors)
    summary = pipeline.apply(cs, data, tmp_path / "s.csv", host=host, coils_off=True,
                             at_rest=True, collect=False, chunk_bytes=20_000)
    assert summary["n"] == tel.n
    assert summary["n_valid"] == {s.name: int(one[s.name]["valid"].sum())
                                  for s in cs.unit.sensors}


def test_fault_in_a_late_chunk_leaves_no_output(tmp_path, fm1_dir):
    """Chunks before the fault were already corrected and written to the temporary file:
    the output must still not appear (atomic), and the message names the line."""
    cs = CoefficientSet.load(COEFFS).with_boom_stowed()
    lines = (fm1_dir / "thermal_12pos.csv").read_text().split("\n")[:3000]
    k = 2500
    cells = lines[k].split(",")
    cells[3] = "abc"
    lines[k] = ",".join(cells)
    data = tmp_path / "late.csv"
    data.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out.csv"
    with pytest.raises(InputError, match=f":{k + 1}: column .*not a number: 'abc'"):
        pipeline.apply(cs, data, out, coils_off=True, at_rest=True, chunk_bytes=20_000)
    assert not out.exists() and list(tmp_path.iterdir()) == [data]


@pytest.mark.parametrize("extras", [False, True])
def test_crlf_file_reads_as_lf(tmp_path, extras):
    """CR LF line ends take the C parser's path too, with the same values and lines; a
    lone CR in a cell goes the cell-by-cell way (which strips it, as before)."""
    unit = _unit()
    text = _telemetry_text(unit, 2000, np.random.default_rng(6), extras)
    lf, crlf = tmp_path / "lf.csv", tmp_path / "crlf.csv"
    lf.write_bytes(text.encode())
    crlf.write_bytes(text.replace("\n", "\r\n").encode())
    _same(concat_chunks(iter_telemetry(crlf, unit, chunk_bytes=7000)), read_telemetry(lf, unit))
    lines = text.split("\n")
    k = next(i for i in range(1500, 1600) if lines[i] and not lines[i].startswith("#"))
    cells = lines[k].split(",")
    cells[2] += "\r"                                      # a lone CR inside a line
    lines[k] = ",".join(cells)
    lone = tmp_path / "lone.csv"
    lone.write_bytes("\n".join(lines).encode())
    _same(concat_chunks(iter_telemetry(lone, unit, chunk_bytes=7000)), read_telemetry(lf, unit))
