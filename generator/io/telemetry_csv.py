"""Telemetry CSV (ICD section 2): reading, validation, and preprocessing to raw frame-axis fields.

read_telemetry checks the whole file before returning anything; the first fault raises
InputError naming the file, the 1-based line and the column, e.g.

    thermal.csv:17: column 'mmc1_set_x': not a number: 'abc'

The file is read in chunks of whole lines (iter_telemetry, about CHUNK_BYTES each), so
memory is bounded by the chunk, not the file: `apply` streams chunk by chunk,
read_telemetry joins the chunks' columns. A Parquet file (io/telemetry_parquet.py) is
read the same way and passes the same checks.

Parsing has three paths that accept the same cells. A block of data lines without
comments or blank lines goes as it is to pyarrow's C CSV parser (float64 columns, RFC 4180
quoting only where the block has a '"', only empty cells missing); lines that pyarrow
refuses go to numpy's C parser (no quotes, no text column); whenever neither can be sure
(a parse failure, a row of the wrong width, letters of nan/inf in the data), the lines are
parsed cell by cell in Python, which finds and names the exact faulty cell. Old-Mac
CR-only line endings (a first block with CR and no LF) are read as LF.

Text columns (ICD section 2 "anything else"): a column that named_columns(unit) does not
name is judged on the first chunk where it has a non-empty cell: text when a cell there is
not a number (nor a nan/inf literal), numeric otherwise; once numeric, a later non-number
is bad input as in any numeric column. A text column is left out, its note in
Telemetry.meta["text_columns"] (text_column_notes: a line for the verbs). The columns of
a stream are fixed at its first chunk: a column still empty there and found text later is
carried by the stream as empty cells and left out by read_telemetry (concat_chunks).

preprocess_sensors turns counts into nT in the sensor's frame axes (not calibrated):
    SET/RESET: field = (set - reset)/2 * lsb_nT,  chip offset = ((set + reset)/2 - zero_count) * lsb_nT
    otherwise: field = (count - zero_count) * lsb_nT
    frame[k] = sign[k] * sensor[idx[k]]   (SensorSpec.axis_map, seed 000 eq. 1)
"""

from __future__ import annotations

import csv
import io
import math
import re

import numpy as np

from generator.errors import InputError
from generator.io import coil_study
from generator.io.arrow_np import to_bool, to_float64
from generator.io.telemetry import SensorData, Telemetry
from generator.io.telemetry_parquet import ParquetTelemetry, is_parquet

TIME_COLUMN = "time_s"
POSITION_COLUMN = "position"

# '# key: value' (the value is stripped in code: a lazy group before \s*$ is quadratic)
_META_RE = re.compile(r"#\s*([A-Za-z_][A-Za-z0-9_.-]*)\s*:(.*)")
# linear: no two adjacent runs of digits that could share a digit (\d+\.?\d* backtracks
# quadratically on a long cell of digits that ends in a letter)
_NUMBER_RE = re.compile(r"[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?", re.ASCII)

# Physical bounds of cells (bad input beyond them, exit 2 naming the row):
# * temperatures: the parts are rated -40..+85/+125 degC (automotive grade 0: 150 degC);
#   a reported temperature outside -150..+200 degC is a corrupted cell, not a temperature
#   the sensor worked at;
# * reference field: a reference is a field the sensor measured, and the parts saturate
#   below 5e6 nT (AK8963: 4912 uT full scale), so |ref| beyond 1e7 nT is not a reference;
# * any other cell: beyond 1e15 in the units the columns carry (s, A, V, deg/s, ...) there
#   is no physical meaning, and squares must stay far from float64 overflow.
TEMP_RANGE_C = (-150.0, 200.0)
ABSOLUTE_ZERO_C = -273.15
REF_LIMIT_nT = 1e7
CELL_LIMIT = 1e15
_NONFINITE_RE = re.compile(r"[+-]?(nan|inf|infinity)", re.IGNORECASE)

# Telemetry.meta key of the text columns left out: {column: one-line note} (ICD section 2
# "anything else: further telemetry": a column no part of the chain reads may hold text)
TEXT_COLUMNS_KEY = "text_columns"
# prefixes of columns the ICD gives a meaning (section 2): numeric whatever their name goes on
NAMED_PREFIXES = ("coil_", "ref_", "rate_")
# the lab's field magnitude as a column (ICD section 2 beside ref_norm_nT; import --field-nT)
LAB_FIELD_COLUMN = "lab_field_nT"


def named_columns(unit) -> set:
    """Columns the ICD or the unit file names, which must hold numbers wherever they are:
    time_s, position, lab_field_nT, the sensors' count and temperature columns, the
    coil study's columns, the ICD section 4 position columns, the inputs of the unit's
    regressors ([[trace.regressor]]); with them any coil_*, ref_*, rate_* column
    (is_named_column). Any other column whose cells are not numbers is text: left out
    (TEXT_COLUMNS_KEY)."""
    from generator.io.orbit import ECEF_COLUMNS, GEODETIC_COLUMNS
    named = {TIME_COLUMN, POSITION_COLUMN, LAB_FIELD_COLUMN, coil_study.DISTANCE_COLUMN,
             coil_study.PANEL_COLUMN, *GEODETIC_COLUMNS, *ECEF_COLUMNS, *GEO_LIMITS}
    for spec in unit.sensors:
        named.update(spec.count_columns)
        named.add(spec.temp_column)
    for reg in (unit.extra or {}).get("trace_regressors", ()):
        named.update(reg.get("inputs", ()))
    return named


def is_named_column(name: str, named: set) -> bool:
    """True for a column of named_columns(unit) (given as named) or of an ICD family."""
    return name in named or name.startswith(NAMED_PREFIXES)


def text_column_notes(tel: Telemetry) -> list:
    """The file's note on its text columns left out ("<path>: column 'mode': text (first
    non-number 'NOMINAL' at line 5): not used"; several columns joined by '; '), as a list
    of one line, or [] when it has none: for the verbs' progress lines and notes."""
    notes = tel.meta.get(TEXT_COLUMNS_KEY)
    return [f"{tel.path}: " + "; ".join(notes.values())] if notes else []


def _short(cell: str, limit: int = 40) -> str:
    """repr of a cell for a one-line note (a long cell cut)."""
    r = repr(cell)
    return r if len(r) <= limit else r[:limit] + "...'"


# --------------------------------------------------------------------------- reading

# text read per chunk: whole lines adding up to about this many bytes (a few 10^4 rows of
# telemetry); memory while reading is bounded by it, not by the file's length
CHUNK_BYTES = 2 << 20


def read_telemetry(path, unit, *, require_sensors: bool = True) -> Telemetry:
    """Read and validate one telemetry CSV against the unit (ICD section 2).

    Raises InputError (file, line, column, fault) on: unreadable file, no header, missing
    `time_s`, a sensor column the unit requires missing (require_sensors), a cell that is
    not a number, a literal NaN/inf cell, time going backwards, a row with the wrong
    number of cells, a count outside the part's raw range. Empty cells are missing values
    (NaN) and are allowed. Extra columns are kept as channels.

    A coil study (a coil_distance_cm column, docs/coil_study.md) is checked against its
    rules here (io/coil_study.py), before any fit: its test sensors, distances, panel flags,
    two or more distances per panel state, a current that steps at each distance.

    ICD section 4: a file with a position (columns, or the unit's [orbit] TLE) and no ref_*
    column gets ref_norm_nT from the field model along its track (io/orbit.py; its
    provenance in meta["field_reference"]).
    The file is read in chunks (iter_telemetry) and the columns joined at the end: the
    peak memory is the columns themselves plus one chunk, not copies of the whole text.
    """
    tel = concat_chunks(iter_telemetry(path, unit, require_sensors=require_sensors),
                        rows=_rows_at_most(path))
    coil_study.check_file(tel)           # a coil study's whole-file rules (io/coil_study.py)
    # ICD section 4: a position and no ref_* column -> ref_norm_nT from the field model
    from generator.io.orbit import attach_field_reference
    return attach_field_reference(tel, unit)


def concat_chunks(chunks, rows: int | None = None) -> Telemetry:
    """One Telemetry from consecutive chunks of one file. rows (an upper bound on the
    file's data rows, e.g. _rows_at_most): the columns are allocated once at that length
    and filled in place, then cut to the rows read (a shrinking realloc moves nothing), so
    the peak is the columns themselves plus one chunk, as for numpy.loadtxt; pages never
    written are never resident. Without it (or beyond it) the columns grow by half
    (ndarray.resize)."""
    cols, lines, n, first = None, None, 0, None
    for c in chunks:
        if cols is None:
            first = c
            cap = max(c.n, rows or 0, 1)
            cols = {name: np.empty(cap) for name in c.columns}
            lines = np.empty(cap, dtype=np.int64)
        if n + c.n > lines.shape[0]:
            cap = max(n + c.n, int(lines.shape[0] * 1.5))
            for a in (*cols.values(), lines):
                a.resize(cap, refcheck=False)
        for name, v in c.columns.items():
            cols[name][n:n + c.n] = v
        lines[n:n + c.n] = c.line_numbers
        n += c.n
    for a in (*cols.values(), lines):
        a.resize(n, refcheck=False)
    for name in first.meta.get(TEXT_COLUMNS_KEY, ()):   # text found after the first chunk
        cols.pop(name, None)          # (the stream carried it as empty cells): left out
    return Telemetry(path=first.path, columns=cols, line_numbers=lines, meta=first.meta,
                     comments=first.comments)


def _rows_at_most(path) -> int | None:
    """An upper bound on the data rows of a telemetry file, or None when it cannot be
    told cheaply: Parquet's row count from its footer; a CSV's line breaks + 1 (every
    data row is a line; comments and the header only make the bound looser), counted in
    blocks of CHUNK_BYTES (the file is read twice; the second time from the page cache)."""
    if is_parquet(path):
        try:
            return ParquetTelemetry(path, is_named=lambda _name: False).num_rows
        except InputError:
            return None                  # the reader names the fault
    try:
        with open(path, "rb") as f:
            blocks = iter(lambda: f.read(CHUNK_BYTES), b"")      # LF, or CR (old Mac)
            return sum(block.count(b"\n") or block.count(b"\r") for block in blocks) + 1
    except OSError:
        return None


def iter_telemetry(path, unit, *, require_sensors: bool = True, chunk_bytes: int = CHUNK_BYTES):
    """The telemetry file as consecutive validated Telemetry chunks (same checks and
    messages as read_telemetry; at least one chunk, maybe empty). Each chunk holds the
    rows of about chunk_bytes of text; time order is checked across chunk boundaries.
    A fault is raised when its chunk is reached: a caller writing output must write it
    atomically (io.outputs.atomic_file).

    A Parquet file (io.telemetry_parquet, recognised by its magic bytes) is read the same
    way: its blocks of values pass the same checks; its faults name the data row."""
    if is_parquet(path):
        yield from _iter_parquet(path, unit, require_sensors, chunk_bytes)
        return
    try:
        f = open(path, "rb")
    except OSError as e:
        raise InputError(path, f"cannot read telemetry file: {e.strerror or e}") from None
    with f:
        st = _SplitState()
        names = None
        prev = None                     # (time_s, line) of the last row of the last chunk
        yielded = False
        next_line = 1
        for raw in _line_blocks(path, f, chunk_bytes):
            first_no = next_line
            next_line += raw.count(b"\n")
            if names is None:                  # the lines up to the header, one by one
                raw, first_no = _up_to_header(path, raw, first_no, st)
                if st.header is None:
                    continue
                if "unit" in st.meta and st.meta["unit"] != unit.id:
                    raise InputError(path, f"'# unit: {st.meta['unit']}' but the unit file is "
                                           f"for '{unit.id}': telemetry of another unit?")
                names = _check_header(path, st.header, st.header_line, unit, require_sensors)
                coil_study.check_meta(path, names, st.meta, unit)
                named = named_columns(unit)
                st.kinds = ["num" if is_named_column(n, named) else None for n in names]
            values, row_lines = _parse_chunk(path, names, raw, first_no, st)
            del raw
            tel = _validated(path, names, values, row_lines, unit, st, prev)
            del values
            if tel.n:
                prev = (float(tel.time_s[-1]), int(tel.line_numbers[-1]))
            if tel.n or not yielded:
                yielded = True
                yield tel
        if st.header is None:
            raise InputError(path, "no header line (the file is empty or holds only comments)")


def _up_to_header(path, raw: bytes, first_no: int, st):
    """Splits the lines of raw into st (meta, comments, the header) until the header is
    found; returns the bytes after the header line and the line number they start at."""
    pos, no = 0, first_no
    while st.header is None and pos < len(raw):
        end = raw.find(b"\n", pos)
        end = len(raw) if end < 0 else end
        line = raw[pos:end]
        if line.endswith(b"\r"):
            line = line[:-1]
        _split_chunk(path, _decode(path, line, no, first=no == 1), no, st)
        pos, no = end + 1, no + 1
    return raw[pos:], no


def _line_blocks(path, f, chunk_bytes: int):
    """The file's bytes in blocks of whole lines, about chunk_bytes each (a line longer
    than that is one block). Old-Mac line endings (a first block with CR and no LF: CR
    only) are read as LF, block by block."""
    rest = b""
    cr_only = None
    while True:
        try:
            block = f.read(chunk_bytes)
        except OSError as e:
            raise InputError(path, f"cannot read telemetry file: {e.strerror or e}") from None
        if cr_only is None and block:
            cr_only = b"\r" in block and b"\n" not in block
        if cr_only:
            block = block.replace(b"\r", b"\n")
        if not block:
            if rest:
                yield rest
            return
        cut = block.rfind(b"\n")
        if cut < 0:
            rest += block
            continue
        raw = rest + block[:cut + 1] if rest else block[:cut + 1]
        rest = block[cut + 1:]
        del block
        yield raw


def _read_text(path) -> str:
    """The whole file as text (importers of small files; telemetry is read in chunks)."""
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as e:
        raise InputError(path, f"cannot read telemetry file: {e.strerror or e}") from None
    return _decode(path, raw, 1, first=True)


def _iter_parquet(path, unit, require_sensors, chunk_bytes):
    named = named_columns(unit)
    pt = ParquetTelemetry(path, is_named=lambda name: is_named_column(name, named))
    st = _SplitState()
    st.meta = pt.meta
    for name, kind in pt.text.items():      # the type says text: left out, with a note
        st.meta.setdefault(TEXT_COLUMNS_KEY, {})[name] = (
            f"column '{name}': text (Parquet type {kind}): not used")
    if "unit" in st.meta and st.meta["unit"] != unit.id:
        raise InputError(path, f"metadata 'unit: {st.meta['unit']}' but the unit file is "
                               f"for '{unit.id}': telemetry of another unit?")
    names = _check_header(path, pt.names, None, unit, require_sensors)
    coil_study.check_meta(path, names, st.meta, unit)
    rows = max(1, chunk_bytes // (8 * len(names)))    # as many values as a CSV chunk's text
    prev, yielded = None, False
    for first, values in pt.blocks(rows):
        tel = _validated(path, names, values, np.arange(first, first + values.shape[0]),
                         unit, st, prev)
        if tel.n:
            prev = (float(tel.time_s[-1]), int(tel.line_numbers[-1]))
            yielded = True
            yield tel
    if not yielded:
        yield _validated(path, names, np.empty((0, len(names))), [], unit, st, None)


class _SplitState:
    """What the line splitter knows so far: the header and the comments before it."""

    def __init__(self):
        self.header = self.header_line = None
        self.meta, self.comments = {}, []
        # per column: "num" (a named column, or one decided numeric), "text", or None (no
        # non-empty cell yet); the column indices every chunk carries (set at the first)
        self.kinds = None
        self.emitted = None

    def text_column(self, name: str, j: int, cell: str, line: int) -> None:
        """Column j is text from now on; its note goes into meta["text_columns"]."""
        self.kinds[j] = "text"
        self.meta.setdefault(TEXT_COLUMNS_KEY, {})[name] = (
            f"column '{name}': text (first non-number {_short(cell)} at line {line}): "
            "not used")


def _decode(path, raw: bytes, first_line: int, first: bool) -> str:
    try:
        text = raw.decode("utf-8-sig" if first else "utf-8")   # a leading BOM is tolerated
    except UnicodeDecodeError as e:
        line = first_line + raw.count(b"\n", 0, e.start)
        raise InputError(path, f"not UTF-8 (byte 0x{raw[e.start]:02x})", line=line) from None
    return text.replace("\r\n", "\n")


def _validated(path, names, values, row_lines, unit, st, prev) -> Telemetry:
    if st.emitted is None:     # the columns every chunk carries: fixed at the first chunk
        st.emitted = [j for j, k in enumerate(st.kinds or [None] * len(names)) if k != "text"]
    columns = {names[j]: np.ascontiguousarray(values[:, j]) for j in st.emitted}
    line_numbers = np.asarray(row_lines, dtype=np.int64)
    if prev is not None and line_numbers.size:
        _check_time(path, np.concatenate([[prev[0]], columns[TIME_COLUMN]]),
                    np.concatenate([[prev[1]], line_numbers]))
    else:
        _check_time(path, columns[TIME_COLUMN], line_numbers)
    _check_counts(path, columns, line_numbers, unit)
    _check_position(path, columns, line_numbers)
    _check_geo(path, columns, line_numbers)
    _check_physical(path, columns, line_numbers)
    coil_study.check_cells(path, columns, line_numbers)
    return Telemetry(path=str(path), columns=columns, line_numbers=line_numbers,
                     meta=st.meta, comments=st.comments)


def _parse_chunk(path, names, raw: bytes, first_no: int, st):
    """(values, line numbers) of a block of data lines after the header. A block with no
    comment, blank or indented line and no CR but in CR LF goes to the C parser as it is, with
    consecutive line numbers; any other (or one the C parser refuses) is decoded and goes
    line by line (_split_chunk, _parse_rows). Text columns (st.kinds) come out NaN."""
    if not raw:
        return np.empty((0, len(names))), []
    clean = (b"#" not in raw and b"\n\n" not in raw and b"\n " not in raw
             and b"\n\t" not in raw and b"\n\r" not in raw
             and raw[:1] not in (b"\n", b" ", b"\t", b"\r")
             and raw.count(b"\r") == raw.count(b"\r\n"))     # CR only in CR LF endings
    if clean:        # no UTF-8 check needed: pyarrow accepts only ASCII number cells
        n = raw.count(b"\n") + (0 if raw.endswith(b"\n") else 1)
        values = _parse_arrow(raw, len(names), n, st.kinds)
        if values is not None:
            return values, np.arange(first_no, first_no + n, dtype=np.int64)
    text = _decode(path, raw, first_no, first=False)
    rows, row_lines = _split_chunk(path, text, first_no, st)
    return _parse_rows(path, names, rows, row_lines, st), row_lines


def _parse_rows(path, names, rows: list, row_lines: list, st=None) -> np.ndarray:
    """The data rows as (N, ncol) float64: the C parsers first, cell by cell (naming the
    faulty cell, deciding the columns without a kind yet: st.kinds) when they cannot be
    sure."""
    kinds = st.kinds if st is not None else None
    values = _parse_arrow("\n".join(rows), len(names), len(rows), kinds) if rows else None
    if (values is None and rows and kinds
            and _judge_arrow("\n".join(rows), names, len(rows), st, row_lines.__getitem__)):
        values = _parse_arrow("\n".join(rows), len(names), len(rows), kinds)
    if (values is None and all(r.isascii() and '"' not in r for r in rows)
            and not (kinds and "text" in kinds)):
        # numpy's float parser takes other scripts' digits ('１２' as 12): only ASCII rows
        values = _parse_fast(rows, len(names))
        if values is not None and kinds:
            _numeric_where_filled(values, kinds)
    if values is None:
        values = _parse_slow(path, names, rows, row_lines, st)
    return values


def _parse_arrow(body, ncol: int, nrows: int, kinds=None):
    """(nrows, ncol) float64 parsed by pyarrow's C CSV reader, or None when it is not sure
    (then the callers' slower paths decide and name the fault). It accepts a subset of what
    _parse_slow accepts, with the same values (host_tests/test_stream_io.py): RFC 4180
    quoting (only where the body has a '"'; a quoted number is that number, a quoted empty
    cell is missing), only empty cells are missing; nan/inf cells are left to the slow
    path. kinds (st.kinds): "text" columns are not converted (NaN); a column without a
    kind (None) that has a cell becomes "num"."""
    if nrows == 0:
        return np.empty((0, ncol))
    if isinstance(body, str):
        body = body.encode()
    text = [j for j in range(ncol) if kinds and kinds[j] == "text"]
    if not text and any(ch in body for ch in (b"n", b"N", b"i", b"I")):
        return None                      # nan/inf (or text): the slow path says which
    quoted = b'"' in body
    import pyarrow as pa
    import pyarrow.csv as pcsv

    cols = [f"c{j}" for j in range(ncol)]
    numeric = [c for j, c in enumerate(cols) if j not in text]
    try:
        table = pcsv.read_csv(
            pa.BufferReader(body),
            read_options=pcsv.ReadOptions(column_names=cols),
            parse_options=_arrow_parse_options(quoted),
            convert_options=pcsv.ConvertOptions(column_types={c: pa.float64() for c in numeric},
                                                null_values=[""], strings_can_be_null=False,
                                                quoted_strings_can_be_null=quoted,
                                                include_columns=numeric if text else None))
    except (pa.ArrowInvalid, pa.ArrowException, ValueError):
        return None
    if table.num_rows != nrows or table.num_columns != len(numeric):
        return None
    values = np.empty((nrows, ncol), order="F")    # columns contiguous: no copy per column
    for j in text:
        values[:, j] = np.nan
    for k, j in enumerate(j for j in range(ncol) if j not in text):
        col = table.column(k)
        values[:, j] = to_float64(col, copy=False)   # empty cell: NaN
        if text and np.count_nonzero(np.isnan(values[:, j])) != col.null_count:
            return None                  # a literal nan cell: the slow path says so
    if np.isinf(values).any():
        return None                      # a value too large for float64: the slow path says so
    if kinds:
        _numeric_where_filled(values, kinds)
    return values


def _arrow_parse_options(quoted: bool):
    """pyarrow's CSV parse options for a block of data lines: RFC 4180 quoting only where
    the block holds a quote (else none: a stray quote is then the slow path's to name), no
    escapes, no line break inside a cell, empty lines kept (the callers count rows)."""
    import pyarrow.csv as pcsv
    return pcsv.ParseOptions(quote_char='"' if quoted else False, double_quote=quoted,
                             escape_char=False, newlines_in_values=False,
                             ignore_empty_lines=False)


# a cell _parse_slow takes for a number (or a nan/inf literal, refused there), blanks around
_NUMBER_LIKE_RE2 = (r"^\s*([+-]?((\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?|(?i:nan|inf|infinity)))?\s*$")


def _judge_arrow(body, names, nrows: int, st, line_of) -> bool:
    """The columns without a kind judged on pyarrow's C parser (their cells read as
    strings): text where a non-empty cell is not a number (its note names the first such
    cell, line_of(row index) its line), numeric where a cell is one. True when some
    column was judged (the caller parses again); False when pyarrow cannot read the block
    or none has a cell, which leaves the judgement to _parse_slow (the same rule)."""
    kinds = st.kinds if st is not None else None
    open_ = [j for j, k in enumerate(kinds or ()) if k is None]
    if not open_ or nrows == 0:
        return False
    if isinstance(body, str):
        body = body.encode()
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.csv as pcsv

    quoted = b'"' in body
    cols = [f"c{j}" for j in range(len(names))]
    wanted = [cols[j] for j in open_]
    try:
        table = pcsv.read_csv(
            pa.BufferReader(body),
            read_options=pcsv.ReadOptions(column_names=cols),
            parse_options=_arrow_parse_options(quoted),
            convert_options=pcsv.ConvertOptions(column_types={c: pa.string() for c in wanted},
                                                include_columns=wanted))
    except (pa.ArrowInvalid, pa.ArrowException, ValueError):
        return False
    if table.num_rows != nrows:
        return False
    judged = False
    for k, j in enumerate(open_):
        col = table.column(k)
        filled = pc.not_equal(pc.utf8_trim_whitespace(col), "")
        if not pc.any(filled).as_py():
            continue
        number = pc.match_substring_regex(col, _NUMBER_LIKE_RE2)
        bad = np.flatnonzero(to_bool(pc.invert(number)))
        if bad.size:
            i = int(bad[0])
            cell = col[i].as_py().strip()
            if not cell or _NUMBER_RE.fullmatch(cell) or _NONFINITE_RE.fullmatch(cell):
                return judged        # the two disagree (exotic blanks): _parse_slow decides
            st.text_column(names[j], j, cell, int(line_of(i)))
        else:
            kinds[j] = "num"
        judged = True
    return judged


def _numeric_where_filled(values: np.ndarray, kinds: list) -> None:
    """Columns without a kind that hold a value in this chunk are numeric from now on."""
    for j, k in enumerate(kinds):
        if k is None and not np.isnan(values[:, j]).all():
            kinds[j] = "num"


def _split_lines(path, text: str):
    """Header, data lines with their 1-based line numbers, '# key: value' meta, other comments.

    Comment lines ('#' first, leading blanks allowed) and blank lines are skipped anywhere;
    only those before the header are collected into meta / comments.
    """
    st = _SplitState()
    rows, row_lines = _split_chunk(path, text, 1, st)
    if st.header is None:
        raise InputError(path, "no header line (the file is empty or holds only comments)")
    return st.header, st.header_line, rows, row_lines, st.meta, st.comments


def _split_chunk(path, text: str, first_no: int, st: _SplitState):
    """Data lines and their line numbers of a chunk of text starting at line first_no;
    the header and the comments before it go into st."""
    rows, row_lines = [], []
    for no, line in enumerate(text.split("\n"), start=first_no):
        first = line[:1]
        if first in ("", " ", "\t"):
            stripped = line.strip()
            if not stripped:
                continue                          # blank line
            first = stripped[0]
        if first == "#":
            if st.header is None:
                m = _META_RE.match(line.strip())
                if m:
                    st.meta[m.group(1)] = m.group(2).strip()
                else:
                    st.comments.append(line)
            continue
        if st.header is None:
            st.header, st.header_line = line, no
        else:
            rows.append(line)
            row_lines.append(no)
    return rows, row_lines


def _check_header(path, header, line, unit, require_sensors: bool) -> list:
    """The column names of a CSV header line (or a list of names: Parquet), checked. A
    header with a '"' is split by RFC 4180 (quoted names, "" for a quote in a name)."""
    names = (list(header) if isinstance(header, (list, tuple))
             else [c.strip() for c in _split_row(path, header, line)])
    first_at = {}
    for j, name in enumerate(names, start=1):
        if not name:
            raise InputError(path, f"header: column {j} has no name", line=line)
        if name in first_at:
            raise InputError(path, f"appears twice in the header (columns {first_at[name]} and {j})",
                             line=line, column=name)
        first_at[name] = j
    if TIME_COLUMN not in first_at:
        raise InputError(path, "missing from the header (every file needs it)",
                         line=line, column=TIME_COLUMN)
    if require_sensors:
        for spec in unit.sensors:
            needed = spec.required_columns       # no <s>_temp_C when temperature = false
            absent = [c for c in needed if c not in first_at]
            if absent:
                kind = "with SET/RESET" if spec.set_reset else "without SET/RESET"
                msg = (f"missing from the header; sensor '{spec.name}' ({spec.part}, {kind}) "
                       f"needs {', '.join(absent)}")
                other = (f"{spec.name}_x" if spec.set_reset else f"{spec.name}_set_x")
                if other in first_at:
                    msg += f" (the file has '{other}': is set_reset right in the unit file?)"
                raise InputError(path, msg, line=line, column=absent[0])
    return names


def _parse_fast(rows: list, ncol: int):
    """(N, ncol) float64 with NaN for empty cells, or None when the slow path must decide."""
    if not rows:
        return np.empty((0, ncol))
    body = "\n".join(rows)
    if any(ch in body for ch in "nNiI"):
        return None                      # nan/inf (or text): numpy would accept or misplace it
    if ",," in body or "\n," in body or ",\n" in body or body[0] == "," or body[-1] == ",":
        body = body.replace(",,", ",nan,").replace(",,", ",nan,")   # twice: ",,," needs both
        body = body.replace("\n,", "\nnan,").replace(",\n", ",nan\n")
        if body[0] == ",":
            body = "nan" + body
        if body[-1] == ",":
            body += "nan"
    try:
        values = np.loadtxt(io.StringIO(body), delimiter=",", comments=None,
                            dtype=np.float64, ndmin=2)
    except ValueError:
        return None
    if values.shape != (len(rows), ncol) or np.isinf(values).any():
        return None                      # wrong width, or a value too large for float64
    return values


def _parse_slow(path, names: list, rows: list, row_lines: list, st=None) -> np.ndarray:
    """Cell by cell; raises InputError at the first faulty cell. A row with a '"' is split
    by RFC 4180 (csv module: quoted cells, "" escapes). st (st.kinds): a column without a
    kind becomes text when one of its cells here is not a number, else numeric when one
    holds a number; text columns come out NaN."""
    ncol = len(names)
    kinds = st.kinds if st is not None else None
    values = np.empty((len(rows), ncol))
    split = []                # the cells of each row, or the fault of its quoting
    for row, line in zip(rows, row_lines):
        try:
            split.append(_split_row(path, row, line))
        except InputError as e:
            split.append(e)   # raised in row order below: the first fault is named
    if kinds:
        for j in [j for j, k in enumerate(kinds) if k is None]:
            for cells, line in zip(split, row_lines):
                if isinstance(cells, InputError) or len(cells) != ncol:
                    break     # the first fault comes first
                c = cells[j].strip()
                if c and not (_NUMBER_RE.fullmatch(c) or _NONFINITE_RE.fullmatch(c)):
                    st.text_column(names[j], j, c, line)
                    break
                if c:
                    kinds[j] = "num"
    text = {j for j, k in enumerate(kinds or ()) if k == "text"}
    for r, (cells, line) in enumerate(zip(split, row_lines)):
        if isinstance(cells, InputError):
            raise cells
        if len(cells) < ncol:
            raise InputError(path, f"row has {len(cells)} cells, the header has {ncol} columns "
                                   "(this and later columns have no cell)",
                             line=line, column=names[len(cells)])
        if len(cells) > ncol:
            raise InputError(path, f"row has {len(cells)} cells, the header has {ncol} columns "
                                   f"(extra cells after the last column '{names[-1]}')", line=line)
        for j, cell in enumerate(cells):
            s = cell.strip()
            if not s or j in text:
                values[r, j] = np.nan
            elif _NUMBER_RE.fullmatch(s):
                x = float(s)
                if math.isinf(x):
                    raise InputError(path, f"{s!r} is too large for a 64-bit float",
                                     line=line, column=names[j])
                values[r, j] = x
            elif _NONFINITE_RE.fullmatch(s):
                what = "NaN" if "nan" in s.lower() else "infinity"
                raise InputError(path, f"{s!r}: {what} is not allowed; leave the cell empty for "
                                       "a missing value", line=line, column=names[j])
            else:
                raise InputError(path, f"not a number: {s!r}", line=line, column=names[j])
    return values


def _split_row(path, row: str, line: int | None) -> list:
    """The cells of one CSV line: split at commas, or by RFC 4180 where it has a '"'
    (a quoted cell may hold commas and "" for a quote; it may not run past its line)."""
    if '"' not in row:
        return row.split(",")
    try:
        parsed = list(csv.reader([row], strict=True, skipinitialspace=True))
    except csv.Error as e:
        what = ("a quoted cell runs past the end of the line (a line break inside quotes is "
                "not supported)" if "end of data" in str(e).lower()
                else f"malformed quoting (RFC 4180: {e})")
        raise InputError(path, what, line=line) from None
    return parsed[0] if parsed else [""]


def _check_time(path, time_s: np.ndarray, line_numbers: np.ndarray) -> None:
    empty = np.flatnonzero(np.isnan(time_s))
    if empty.size:
        raise InputError(path, "empty; every sample needs a time",
                         line=int(line_numbers[empty[0]]), column=TIME_COLUMN)
    back = np.flatnonzero(np.diff(time_s) < 0)
    if back.size:
        i = back[0] + 1
        raise InputError(path, f"time goes backwards: {_fmt(time_s[i])} s after "
                               f"{_fmt(time_s[i - 1])} s on line {line_numbers[i - 1]}",
                         line=int(line_numbers[i]), column=TIME_COLUMN)


def _check_counts(path, columns: dict, line_numbers: np.ndarray, unit) -> None:
    """Count cells are whole numbers inside the part's raw range (at the rails = saturated,
    allowed). Sensors with a physical input (ICD section 4) hold real numbers: any finite
    value is accepted here; preprocess flags those at or beyond the full scale."""
    for spec in unit.sensors:
        if not spec.counts:
            continue
        lo, hi = spec.count_min, spec.count_max
        for name in spec.count_columns:
            v = columns.get(name)
            if v is None:
                continue
            with np.errstate(invalid="ignore"):
                not_whole = v != np.floor(v)          # False for NaN (empty cell)
            outside = (v < lo) | (v > hi)
            bad = np.flatnonzero((not_whole & ~np.isnan(v)) | outside)
            if bad.size:
                i = bad[0]
                if outside[i]:
                    msg = (f"count {_fmt(v[i])} is outside the {spec.part} raw range "
                           f"[{lo}, {hi}]: impossible sensor output")
                else:
                    msg = f"count {_fmt(v[i])} is not a whole number"
                raise InputError(path, msg, line=int(line_numbers[i]), column=name)


def _check_position(path, columns: dict, line_numbers: np.ndarray) -> None:
    v = columns.get(POSITION_COLUMN)
    if v is None:
        return
    bad = np.flatnonzero(~np.isnan(v) & ((v < 0) | (v != np.floor(v))))
    if bad.size:
        i = bad[0]
        raise InputError(path, f"{_fmt(v[i])} is not a static position number "
                               "(1..N, or 0 while moving)",
                         line=int(line_numbers[i]), column=POSITION_COLUMN)


# ICD section 4 position columns: kept as channels like any other, checked for range
GEO_LIMITS = {"lat_deg": (-90.0, 90.0), "lon_deg": (-180.0, 360.0),
              "alt_km": (-1.0, 100000.0), "kp_index": (0.0, 9.0)}


def _check_geo(path, columns: dict, line_numbers: np.ndarray) -> None:
    for name, (lo, hi) in GEO_LIMITS.items():
        v = columns.get(name)
        if v is None:
            continue
        bad = np.flatnonzero(~np.isnan(v) & ((v < lo) | (v > hi)))
        if bad.size:
            i = bad[0]
            raise InputError(path, f"{_fmt(v[i])} is outside [{_fmt(lo)}, {_fmt(hi)}]",
                             line=int(line_numbers[i]), column=name)


def _physical_bounds(name: str):
    """(low, high, unit) a cell of this column must lie within."""
    # a temperature below absolute zero is no reading at all (a broken column or unit):
    # bad input; above it the cell is bounded by CELL_LIMIT only: an impossible reading
    # (1e6 degC) is a fault of that sample, which the fits reject and count
    # (fit/samples.screen_temperatures) and the flight code clamps and flags
    if name.endswith("_temp_C"):
        return ABSOLUTE_ZERO_C, CELL_LIMIT, " degC"
    if name.startswith("ref_") and name.endswith("_nT"):
        return (0.0 if name == "ref_norm_nT" else -REF_LIMIT_nT), REF_LIMIT_nT, " nT"
    return -CELL_LIMIT, CELL_LIMIT, ""


def _check_physical(path, columns: dict, line_numbers: np.ndarray) -> None:
    """Every cell inside its column's physical bounds (_physical_bounds)."""
    for name, v in columns.items():
        lo, hi, unit = _physical_bounds(name)
        with np.errstate(invalid="ignore"):
            bad = np.flatnonzero((v < lo) | (v > hi))
        if bad.size:
            i = bad[0]
            raise InputError(path, f"{_fmt(v[i])}{unit} is outside the physical range "
                                   f"{_fmt(lo)}..{_fmt(hi)}{unit}",
                             line=int(line_numbers[i]), column=name)


def _fmt(x) -> str:
    x = float(x)
    return str(int(x)) if x.is_integer() and abs(x) < 1e15 else repr(x)


# --------------------------------------------------------------------------- preprocessing

def preprocess(tel: Telemetry, unit, sensors=None) -> dict:
    """Counts -> nT, SET/RESET -> field and chip offset, axis mapping -> frame axes.

    Per sensor: usable=False where any needed cell is missing or non-finite, or a count is at
    the part's rail (saturated); these are counted in n_missing / n_saturated, never used.

    Physical inputs (ICD section 4, input = nT | uT | mG | G): field = value * nT per unit
    (SensorSpec.nT_per_input; the unit reader stores it as lsb_nT with zero_count 0, so the
    formulas above hold as written); saturated where any axis reaches the sensor's full
    scale |value| * factor >= SensorSpec.full_scale_nT (the unit file's range_nT, else the
    catalogue's range of the part).

    temperature = false: SensorData.temp_C is all NaN and has_temperature is False; a
    missing temperature does not make the sample unusable. Fits that model temperature
    take SensorData.temp_or(t_C): the reported temperature, or the constant t_C for a
    sensor without one (a temperature-independent model).
    """
    return {spec.name: _sensor_data(tel, spec) for spec in unit.sensors
            if sensors is None or spec.name in sensors}


def _sensor_cells(tel: Telemetry, spec):
    """(raw, temp_C, missing, saturated) of one sensor: its count (or physical input)
    columns as float64 views, its temperature (all NaN without one), and per row whether a
    needed cell is missing or non-finite, or a count at the part's rail (saturated)."""
    n = tel.n
    absent_cells = None
    raw = []                          # the count (or physical input) columns, float64 views
    for c in spec.count_columns:
        v = tel.columns.get(c)
        if v is None:
            if absent_cells is None:
                absent_cells = np.full(n, np.nan)
            v = absent_cells
        raw.append(np.asarray(v, dtype=np.float64))
    missing = np.zeros(n, dtype=bool)
    at_rail = np.zeros(n, dtype=bool)
    for v in raw:
        missing |= ~np.isfinite(v)
        if spec.counts:
            at_rail |= (v <= spec.count_min) | (v >= spec.count_max)
        else:
            with np.errstate(invalid="ignore"):
                at_rail |= np.abs(v) * spec.nT_per_input >= spec.full_scale_nT
    if spec.temperature:
        col = tel.columns.get(spec.temp_column)
        temp_C = np.full(n, np.nan) if col is None else np.asarray(col, dtype=np.float64)
        missing |= ~np.isfinite(temp_C)
    else:
        temp_C = np.full(n, np.nan)          # documented: no temperature, not missing
    saturated = at_rail & ~missing              # missing and saturated counts once, as missing
    return raw, temp_C, missing, saturated


def usable_rows(tel: Telemetry, spec) -> np.ndarray:
    """(N,) bool: the rows whose readings of this sensor preprocess marks usable (none of
    its cells missing or non-finite, no count at the rail), without computing the fields
    (1 byte a row: what a capped trace keeps of the rows it does not trace)."""
    _, _, missing, saturated = _sensor_cells(tel, spec)
    return ~missing & ~saturated


def _sensor_data(tel: Telemetry, spec) -> SensorData:
    """One sensor's SensorData, column by column: no (N, 6) stack of the counts and no
    (N, 3) intermediate per step; the temperature is the file's column itself (a view:
    nothing writes into either). The same operations per element as on stacked arrays,
    so the same bits."""
    n = tel.n
    counts = {c: tel.columns[c] for c in spec.count_columns if c in tel.columns}
    missing_columns = tuple(c for c in spec.required_columns if c not in tel.columns)
    raw, temp_C, missing, saturated = _sensor_cells(tel, spec)
    usable = ~missing & ~saturated

    idx, sign = spec.axis_map()
    field_frame_nT = np.empty((n, 3))
    chip_offset_sensor_nT = None
    if spec.set_reset:
        chip_offset_sensor_nT = np.empty((n, 3))
        for k in range(3):
            set_counts, reset_counts = raw[k], raw[3 + k]
            chip_offset_sensor_nT[:, k] = ((set_counts + reset_counts) / 2.0
                                           - spec.zero_count) * spec.lsb_nT
        chip_offset_sensor_nT[~usable] = np.nan
        for k in range(3):           # frame[k] = sign[k] * sensor[idx[k]]
            j = idx[k]
            field_frame_nT[:, k] = (raw[j] - raw[3 + j]) / 2.0 * spec.lsb_nT * float(sign[k])
    else:
        for k in range(3):
            field_frame_nT[:, k] = (raw[idx[k]] - spec.zero_count) * spec.lsb_nT * float(sign[k])
    field_frame_nT[~usable] = np.nan

    return SensorData(
        name=spec.name, field_frame_nT=field_frame_nT, temp_C=temp_C, usable=usable,
        n_missing=int(missing.sum()), n_saturated=int(saturated.sum()),
        chip_offset_sensor_nT=chip_offset_sensor_nT, counts=counts,
        missing_columns=missing_columns, has_temperature=spec.temperature,
    )
