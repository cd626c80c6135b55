"""Review 20e on the telemetry reader (io/telemetry_csv.py, io/telemetry_parquet.py):

* F2: RFC 4180 quoting as pyarrow.csv.write_csv (and pandas QUOTE_NONNUMERIC) write it:
  quoted header names ("" escapes), quoted numbers (the number), a quoted empty cell
  (missing), quoted text holding commas in a column the chain does not read. A quoted
  cell with a line break inside is refused naming its line.
* F7: a column that neither the ICD nor the unit file names and that holds text is left
  out of the telemetry with a note (Telemetry.meta["text_columns"]); a named column of
  text stays an error; a column numeric in its first filled chunk stays numeric (a later
  non-number is an error naming line and column). Parquet: a string column by its type.
* F9a: old-Mac CR-only line endings read as LF.

Each through read_telemetry / iter_telemetry and through the CLI (generator.cli.main):
exit 0 with the same output as the plain file, or exit 2 with one line on stderr.
"""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pyarrow.csv as pcsv
import pyarrow.parquet as pq
import pytest

from generator.cli import main
from generator.errors import InputError
from generator.flight.coeffs import CoefficientSet
from generator.io.telemetry_csv import (TEXT_COLUMNS_KEY, concat_chunks, iter_telemetry,
                                        read_telemetry, text_column_notes)
from generator.io.unitfile import load_unit
from generator.trace.samples import candidate_channels

from conftest import REPO

COEFFS = REPO / "generated" / "samsat_fm1" / "coefficients.json"
ROWS = 3000                     # rows of the shared thermal file the small cases use


@pytest.fixture(scope="module")
def unit():
    return CoefficientSet.load(COEFFS).with_boom_stowed().unit


@pytest.fixture(scope="module")
def plain(fm1_dir, tmp_path_factory):
    """The first ROWS data rows of the shared thermal file (its comment lines kept)."""
    lines = (fm1_dir / "thermal_12pos.csv").read_text().split("\n")
    n_head = sum(1 for ln in lines[:10] if ln.startswith("#")) + 1
    p = tmp_path_factory.mktemp("plain") / "thermal.csv"
    p.write_text("\n".join(lines[:n_head + ROWS]) + "\n")
    return p


def _lines(path):
    return path.read_text().split("\n")


def _header_at(lines) -> int:
    return next(i for i, ln in enumerate(lines) if ln and not ln.startswith("#"))


def _quoted_copy(src, dst):
    """src as pyarrow.csv.write_csv writes it (every name and text quoted; the numbers
    as arrow prints them), the comment lines skipped as the review's reproduction does."""
    skip = _header_at(_lines(src))
    table = pcsv.read_csv(src, parse_options=pcsv.ParseOptions(ignore_empty_lines=True),
                          read_options=pcsv.ReadOptions(skip_rows=skip))
    pcsv.write_csv(table, dst)
    return dst


def _same_columns(a, b):
    assert list(a.columns) == list(b.columns)
    for k in a.columns:
        assert np.array_equal(a.columns[k], b.columns[k], equal_nan=True), k
        # bit for bit (equal_nan compares values): the float64 patterns themselves
        assert np.array_equal(a.columns[k].view(np.uint64), b.columns[k].view(np.uint64)), k


def _apply(tmp_path, data, name):
    out = tmp_path / name
    rc = main(["apply", str(COEFFS), str(data), "-o", str(out), "--boom-stowed",
               "--coils-off", "--at-rest", "--quiet"])
    return rc, out


def _data_lines(path):
    """apply's output without its comment lines (they name the source file)."""
    return [ln for ln in _lines(path) if not ln.startswith("#")]


def _refused(capsys, argv, *fragments):
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.count("\n") == 1, err
    for f in fragments:
        assert f in err, (f, err)
    return err


def _apply_refused(tmp_path, capsys, data, *fragments):
    out = tmp_path / "refused.csv"
    _refused(capsys, ["apply", str(COEFFS), str(data), "-o", str(out), "--boom-stowed",
                      "--coils-off", "--at-rest", "--quiet"], str(data), *fragments)
    assert not out.exists()


# --------------------------------------------------------------------------- F2 quoting

def test_pyarrow_quoted_file_reads_as_the_plain_file(tmp_path, plain, unit):
    q = _quoted_copy(plain, tmp_path / "q.csv")
    assert _lines(q)[0].startswith('"time_s","position",')       # the writer did quote
    a, b = read_telemetry(plain, unit), read_telemetry(q, unit)
    _same_columns(a, b)
    # streamed in small chunks: the same values, every chunk boundary between lines
    chunks = list(iter_telemetry(q, unit, chunk_bytes=4096))
    assert len(chunks) > 10
    _same_columns(a, concat_chunks(chunks))


def test_quoted_cells_header_escapes_and_text_with_commas(tmp_path, unit, plain):
    lines = _lines(plain)
    h = _header_at(lines)
    names = lines[h].split(",")
    rows = [ln.split(",") for ln in lines[h + 1:h + 6]]
    # every cell quoted; a quoted empty cell in row 2's mpu1_temp_C: missing
    j_temp = names.index("mpu1_temp_C")
    rows[2][j_temp] = ""
    head = ",".join(f'"{n}"' for n in names) + ',"note ""a"""'
    body = [",".join(f'"{c}"' for c in r) + f',"x, y, {i}"' for i, r in enumerate(rows)]
    p = tmp_path / "cells.csv"
    p.write_text("\n".join([head, *body]) + "\n")
    tel = read_telemetry(p, unit)
    assert 'note "a"' not in tel.columns             # its cells are text: left out
    note = tel.meta[TEXT_COLUMNS_KEY]['note "a"']
    assert note == "column 'note \"a\"': text (first non-number 'x, y, 0' at line 2): not used"
    want = read_telemetry(plain, unit)
    for k in tel.columns:
        v = want.columns[k][:5].copy()
        if k == "mpu1_temp_C":
            v[2] = np.nan
        assert np.array_equal(tel.columns[k], v, equal_nan=True), k


def test_quoted_number_in_a_named_column_that_is_no_number(tmp_path, capsys, unit, plain):
    lines = _lines(plain)
    h = _header_at(lines)
    j = lines[h].split(",").index("mpu1_temp_C")
    cells = lines[h + 3].split(",")
    cells[j] = '"25,5"'                                # a decimal comma, quoted
    lines[h + 3] = ",".join(cells)
    p = tmp_path / "comma.csv"
    p.write_text("\n".join(lines))
    with pytest.raises(InputError, match=rf":{h + 4}: column 'mpu1_temp_C': not a number: "
                                         r"'25,5'"):
        read_telemetry(p, unit)
    _apply_refused(tmp_path, capsys, p, f":{h + 4}: column 'mpu1_temp_C': not a number")


def test_line_break_inside_quotes_is_refused_naming_the_line(tmp_path, capsys, unit, plain):
    lines = _lines(plain)
    h = _header_at(lines)
    lines[h] += ",note"
    for i in range(h + 1, h + ROWS + 1):
        lines[i] += ",ok"
    lines[h + 100] = lines[h + 100][:-2] + '"two\nlines"'
    p = tmp_path / "newline.csv"
    p.write_text("\n".join(lines))
    for chunk_bytes in (1 << 20, 512):               # wherever the chunk boundary falls
        with pytest.raises(InputError, match=rf":{h + 101}: a quoted cell runs past the end "
                                             r"of the line"):
            concat_chunks(iter_telemetry(p, unit, chunk_bytes=chunk_bytes))
    _apply_refused(tmp_path, capsys, p, f":{h + 101}: a quoted cell runs past the end")


def test_malformed_quoting_in_the_header_names_the_line(tmp_path, capsys, unit, plain):
    lines = _lines(plain)
    h = _header_at(lines)
    lines[h] = lines[h].replace("time_s", '"time_s"x', 1)
    p = tmp_path / "badquote.csv"
    p.write_text("\n".join(lines))
    with pytest.raises(InputError, match=rf":{h + 1}: malformed quoting"):
        read_telemetry(p, unit)
    _apply_refused(tmp_path, capsys, p, f":{h + 1}: malformed quoting")


def test_apply_and_fit_on_the_quoted_file_equal_the_plain_file(tmp_path, fm1_dir):
    """The review's reproduction on the whole shared thermal file: apply's output bit for
    bit (its numbers as printed), fit's coefficients.json identical but for the path."""
    src = fm1_dir / "thermal_12pos.csv"
    qdir = tmp_path / "quoted"
    qdir.mkdir()
    q = _quoted_copy(src, qdir / src.name)
    rc, out_plain = _apply(tmp_path, src, "plain_out.csv")
    assert rc == 0
    rc, out_q = _apply(tmp_path, q, "quoted_out.csv")
    assert rc == 0
    assert _data_lines(out_plain) == _data_lines(out_q)
    unit_file = fm1_dir / "unit.toml"
    for data, folder in ((src, "fit_plain"), (q, "fit_quoted")):
        assert main(["fit", str(unit_file), str(data), "-o", str(tmp_path / folder),
                     "--no-report", "--quiet"]) == 0
    a = (tmp_path / "fit_plain" / "coefficients.json").read_text()
    b = (tmp_path / "fit_quoted" / "coefficients.json").read_text()
    assert json.loads(a.replace(str(src), "SRC")) == json.loads(b.replace(str(q), "SRC"))


# --------------------------------------------------------------------------- F7 text

def _with_column(plain, dst, name, cell_of_row):
    """plain with a last column `name`, cell_of_row(i) in data row i (0-based)."""
    lines = _lines(plain)
    h = _header_at(lines)
    out = lines[:h] + [lines[h] + "," + name]
    for i, ln in enumerate(lines[h + 1:]):
        out.append(ln + "," + cell_of_row(i) if ln else ln)
    dst.write_text("\n".join(out))
    return dst, h


def test_text_column_is_left_out_with_a_note(tmp_path, capsys, unit, plain):
    p, h = _with_column(plain, tmp_path / "mode.csv", "mode",
                        lambda i: "SAFE" if i < 7 else "NOMINAL")
    want = read_telemetry(plain, unit)
    tel = read_telemetry(p, unit)
    assert "mode" not in tel.columns
    _same_columns(want, tel)
    # 'SAFE' is the first cell that is not a number, on the first data line
    assert tel.meta[TEXT_COLUMNS_KEY] == {
        "mode": f"column 'mode': text (first non-number 'SAFE' at line {h + 2}): not used"}
    assert text_column_notes(tel) == [f"{p}: column 'mode': text (first non-number 'SAFE' "
                                      f"at line {h + 2}): not used"]
    assert text_column_notes(want) == []
    # streamed: no chunk carries it
    chunks = list(iter_telemetry(p, unit, chunk_bytes=4096))
    assert all("mode" not in c.columns for c in chunks)
    # the trace: not a candidate channel
    names, _ = candidate_channels(unit, [tel])
    assert "mode" not in names
    # the CLI: apply's output is the plain file's
    rc, out_plain = _apply(tmp_path, plain, "plain_out.csv")
    rc2, out_mode = _apply(tmp_path, p, "mode_out.csv")
    assert (rc, rc2) == (0, 0), capsys.readouterr().err
    assert _data_lines(out_plain) == _data_lines(out_mode)


def test_numbers_with_text_in_the_same_first_chunk_are_text(tmp_path, unit, plain):
    """An extra column whose first filled chunk holds a non-number is text, even where
    most cells are numbers (a flag column 0/1/on): left out, the note names that cell."""
    p, h = _with_column(plain, tmp_path / "flag.csv", "heater_flag",
                        lambda i: "on" if i == 5 else str(i % 2))
    tel = read_telemetry(p, unit)
    assert "heater_flag" not in tel.columns
    assert "'on' at line" in tel.meta[TEXT_COLUMNS_KEY]["heater_flag"]
    assert f"at line {h + 7}" in tel.meta[TEXT_COLUMNS_KEY]["heater_flag"]


def test_numeric_column_with_a_later_non_number_is_an_error(tmp_path, capsys, unit, plain):
    """Numeric in its first filled chunk: a non-number in a later chunk is a typo named
    by line and column, not a reason to drop the column mid-file."""
    late = ROWS - 10
    p, h = _with_column(plain, tmp_path / "late.csv", "heater_A",
                        lambda i: "abc" if i == late else "0.5")
    want = read_telemetry(plain, unit)
    # one chunk: the non-number is in the column's first filled chunk: text
    tel = read_telemetry(p, unit)
    assert "heater_A" not in tel.columns
    _same_columns(want, tel)
    # small chunks: numeric in the first, the typo later is an error
    with pytest.raises(InputError, match=rf":{h + late + 2}: column 'heater_A': not a "
                                         r"number: 'abc'"):
        concat_chunks(iter_telemetry(p, unit, chunk_bytes=4096))


def test_text_after_empty_chunks_is_left_out(tmp_path, unit, plain):
    """A column empty in the first chunks and text later: text. The stream carried it as
    empty cells (every chunk has the same columns); read_telemetry leaves it out."""
    late = ROWS - 10
    p, h = _with_column(plain, tmp_path / "late_text.csv", "comment",
                        lambda i: "door opened" if i == late else "")
    want = read_telemetry(plain, unit)
    chunks = list(iter_telemetry(p, unit, chunk_bytes=4096))
    assert len({tuple(c.columns) for c in chunks}) == 1
    assert all(np.isnan(c.columns["comment"]).all() for c in chunks)
    assert "door opened" in chunks[0].meta[TEXT_COLUMNS_KEY]["comment"]
    tel = concat_chunks(iter_telemetry(p, unit, chunk_bytes=4096))
    _same_columns(want, tel)
    assert f"at line {h + late + 2}" in tel.meta[TEXT_COLUMNS_KEY]["comment"]


@pytest.mark.parametrize("column", ["position", "coil_x_A", "ref_norm_nT", "rate_x_dps",
                                    "lat_deg", "ecef_x_km", "kp_index", "panel",
                                    "mpu1_temp_C", "lab_field_nT"])
def test_text_in_a_column_the_icd_names_is_an_error(tmp_path, capsys, unit, plain, column):
    lines = _lines(plain)
    h = _header_at(lines)
    names = lines[h].split(",")
    if column in names:
        j = names.index(column)
        cells = lines[h + 2].split(",")
        cells[j] = "NOMINAL"
        lines[h + 2] = ",".join(cells)
    else:
        lines[h] += "," + column
        for i in range(h + 1, len(lines)):
            if lines[i]:
                lines[i] += ",NOMINAL" if i == h + 2 else ",0"
    p = tmp_path / f"{column}.csv"
    p.write_text("\n".join(lines))
    with pytest.raises(InputError, match=rf":{h + 3}: column '{column}': not a number: "
                                         r"'NOMINAL'"):
        read_telemetry(p, unit)
    _apply_refused(tmp_path, capsys, p, f"column '{column}': not a number: 'NOMINAL'")


def test_text_in_a_regressor_input_is_an_error(tmp_path, capsys, fm1_dir, plain):
    unit_file = tmp_path / "unit.toml"
    unit_file.write_text((fm1_dir / "unit.toml").read_text() + '\n[[trace.regressor]]\n'
                         'name = "heater_w"\nformula = "v_heater * i_heater"\n')
    u = load_unit(unit_file)
    p, h = _with_column(plain, tmp_path / "reg.csv", "v_heater",
                        lambda i: "high" if i == 1 else "5")
    with pytest.raises(InputError, match=rf":{h + 3}: column 'v_heater': not a number: "
                                         r"'high'"):
        read_telemetry(p, u)
    # the shared unit does not name it: text, left out
    assert "v_heater" not in read_telemetry(p, load_unit(fm1_dir / "unit.toml")).columns
    _refused(capsys, ["fit", str(unit_file), str(p), "-o", str(tmp_path / "fit"),
                      "--no-report", "--quiet"], f"column 'v_heater': not a number: 'high'")


def test_parquet_string_column(tmp_path, capsys, unit, plain):
    want = read_telemetry(plain, unit)
    cols = {k: pa.array(v) for k, v in want.columns.items()}
    cols["mode"] = pa.array(["SAFE", "NOMINAL"] * (want.n // 2) + ["SAFE"] * (want.n % 2))
    p = tmp_path / "mode.parquet"
    pq.write_table(pa.table(cols), p)
    tel = read_telemetry(p, unit)
    assert "mode" not in tel.columns
    _same_columns(want, tel)
    assert tel.meta[TEXT_COLUMNS_KEY] == {"mode": "column 'mode': text (Parquet type string): "
                                                  "not used"}
    assert all("mode" not in c.columns for c in iter_telemetry(p, unit, chunk_bytes=4096))
    rc, out_plain = _apply(tmp_path, plain, "plain_out.csv")
    rc2, out_pq = _apply(tmp_path, p, "pq_out.csv")
    assert (rc, rc2) == (0, 0), capsys.readouterr().err
    assert _data_lines(out_plain) == _data_lines(out_pq)
    # a named column of string type stays an error
    cols["coil_x_A"] = pa.array(["0"] * want.n)
    p2 = tmp_path / "coil_text.parquet"
    pq.write_table(pa.table(cols), p2)
    with pytest.raises(InputError, match=r"column 'coil_x_A': Parquet column of type string"):
        read_telemetry(p2, unit)
    _apply_refused(tmp_path, capsys, p2, "column 'coil_x_A': Parquet column of type string")


# --------------------------------------------------------------------------- F9a CR only

def test_cr_only_line_endings_read_as_lf(tmp_path, capsys, unit, plain):
    cr = tmp_path / "cr.csv"
    cr.write_bytes(plain.read_bytes().replace(b"\n", b"\r"))
    want = read_telemetry(plain, unit)
    tel = read_telemetry(cr, unit)
    _same_columns(want, tel)
    assert np.array_equal(tel.line_numbers, want.line_numbers)
    assert tel.meta == want.meta
    _same_columns(want, concat_chunks(iter_telemetry(cr, unit, chunk_bytes=4096)))
    rc, out_plain = _apply(tmp_path, plain, "plain_out.csv")
    rc2, out_cr = _apply(tmp_path, cr, "cr_out.csv")
    assert (rc, rc2) == (0, 0), capsys.readouterr().err
    assert _data_lines(out_plain) == _data_lines(out_cr)
    # a fault in a CR-only file names its line as in the LF file
    lines = _lines(plain)
    h = _header_at(lines)
    cells = lines[h + 50].split(",")
    cells[2] = "abc"
    lines[h + 50] = ",".join(cells)
    bad = tmp_path / "cr_bad.csv"
    bad.write_bytes("\r".join(lines).encode())
    name = lines[h].split(",")[2]
    with pytest.raises(InputError, match=rf":{h + 51}: column '{name}': not a number: 'abc'"):
        read_telemetry(bad, unit)
    _apply_refused(tmp_path, capsys, bad, f":{h + 51}: column '{name}'")


# --------------------------------------------------------------------------- fast path

def test_the_c_parser_takes_quoted_rows_and_skips_text_columns():
    """Quoted files and files with a text column stay on pyarrow's C parser (the slow
    path would give the same values, cell by cell in Python: apply's hot path), with the
    slow path's values."""
    from generator.io import telemetry_csv as tc

    rows = ['"1","2.5",""', '"3","-4e-3","7"']
    fast = tc._parse_arrow("\n".join(rows), 3, 2)
    assert fast is not None
    slow = tc._parse_slow("x.csv", ["a", "b", "c"], rows, [2, 3])
    assert np.array_equal(fast.view(np.uint64), slow.view(np.uint64))
    rows = ['1,"NOMINAL, since 3",2', '3,SAFE,4']
    kinds = ["num", "text", "num"]
    fast = tc._parse_arrow("\n".join(rows), 3, 2, kinds)
    assert fast is not None
    assert np.array_equal(fast, [[1, np.nan, 2], [3, np.nan, 4]], equal_nan=True)
    # a literal nan in a numeric column beside a text column: left to the slow path
    assert tc._parse_arrow("1,SAFE,nan\n", 3, 1, kinds) is None


def test_the_first_fault_is_named_first(tmp_path, unit, plain):
    """A bad number on one line and a quoted cell running past its line later in the same
    chunk: the earlier line is named (the slow path judges the rows in file order)."""
    p, h = _with_column(plain, tmp_path / "order.csv", "note",
                        lambda i: '"open' if i == 20 else "x")
    lines = _lines(p)
    cells = lines[h + 11].split(",")
    cells[3] = "12a"
    lines[h + 11] = ",".join(cells)
    p.write_text("\n".join(lines))
    name = lines[h].split(",")[3]
    with pytest.raises(InputError, match=rf":{h + 12}: column '{name}': not a number: '12a'"):
        read_telemetry(p, unit)


@pytest.mark.parametrize("cells, kind", [
    (["1", " 2 ", "", "-3.5e2"], "num"),
    (["", "  ", ""], None),                       # no cell yet: not judged
    (["1", "nan", ""], "num"),                    # a nan literal: refused later, as numbers
    (["1", "SAFE", "2"], "text"),
    (["", '"x, y"', "1"], "text"),
    (['"7"', '""', "1e3"], "num"),
    (["1_0"], "text"),
])
def test_the_c_parser_and_the_slow_path_judge_columns_alike(cells, kind):
    """_judge_arrow (pyarrow) and _parse_slow (Python) give a column the same kind and
    name the same first non-number (the slow path judges where pyarrow cannot read)."""
    from generator.io import telemetry_csv as tc

    names = ["a", "b"]
    rows = [f"{i},{c}" for i, c in enumerate(cells)]
    lines = list(range(10, 10 + len(rows)))
    results = []
    for judge in ("arrow", "slow"):
        st = tc._SplitState()
        st.kinds = ["num", None]
        if judge == "arrow":
            tc._judge_arrow("\n".join(rows), names, len(rows), st, lines.__getitem__)
        else:
            try:
                tc._parse_slow("x.csv", names, rows, lines, st)
            except InputError:
                pass                                  # the nan literal: judged first
        results.append((st.kinds[1], st.meta.get(TEXT_COLUMNS_KEY)))
    assert results[0] == results[1]
    assert results[0][0] == kind


def test_pandas_quote_nonnumeric(tmp_path, capsys, unit, plain):
    """pandas' QUOTE_NONNUMERIC: names and text quoted, numbers bare, a missing value as
    "" (quoted empty): read as the plain file, the text column left out."""
    pd = pytest.importorskip("pandas")
    import csv

    skip = _header_at(_lines(plain))
    df = pd.read_csv(plain, skiprows=skip)
    df.loc[4, "mpu1_temp_C"] = float("nan")
    df["mode"] = ["SAFE" if i % 2 else "NOMINAL" for i in range(len(df))]
    p = tmp_path / "pandas.csv"
    df.to_csv(p, index=False, quoting=csv.QUOTE_NONNUMERIC)
    assert '""' in p.read_text() and '"NOMINAL"' in p.read_text()   # the writer did quote
    want = read_telemetry(plain, unit)
    want.columns["mpu1_temp_C"][4] = np.nan
    tel = read_telemetry(p, unit)
    _same_columns(want, tel)
    assert set(tel.meta[TEXT_COLUMNS_KEY]) == {"mode"}
    rc, out = _apply(tmp_path, p, "pandas_out.csv")
    assert rc == 0, capsys.readouterr().err


def test_text_and_quoted_files_never_take_the_python_path(tmp_path, monkeypatch, unit, plain):
    """apply's hot path: a file with a text column and a quoted file are read on the C
    parsers alone (the cell-by-cell Python path is for faults only)."""
    from generator.io import telemetry_csv as tc

    mode, _ = _with_column(plain, tmp_path / "mode.csv", "mode",
                           lambda i: "SAFE" if i % 2 else '"NOMINAL, since 12:00"')
    q = _quoted_copy(mode, tmp_path / "q.csv")
    want = read_telemetry(plain, unit)

    def refuse(*_a, **_k):
        raise AssertionError("the cell-by-cell path was taken")

    monkeypatch.setattr(tc, "_parse_slow", refuse)
    for p in (mode, q):
        tel = concat_chunks(tc.iter_telemetry(p, unit, chunk_bytes=8192))
        assert "mode" not in tel.columns and "mode" in tel.meta[TEXT_COLUMNS_KEY]
        for k in want.columns:
            assert np.array_equal(tel.columns[k], want.columns[k], equal_nan=True), k


def test_a_quoted_header_with_a_space_after_each_comma(tmp_path):
    """`"time_s", "position", ...` (a writer's ", " separator; review 20f): the space
    before a quoted name is not part of the cell (csv skipinitialspace), so the names are
    the same as in `"time_s","position"`."""
    from generator.io.telemetry_csv import _split_row
    assert _split_row("f.csv", '"time_s", "position", "a ""q"""', 1) == \
        ["time_s", "position", 'a "q"']
