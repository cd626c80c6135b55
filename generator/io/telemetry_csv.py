"""Telemetry CSV (ICD section 2): reading, validation, and preprocessing to raw frame-axis fields.

read_csv checks the whole file before returning anything; the first fault raises InputError
naming the file, the 1-based line and the column, e.g.

    thermal.csv:17: column 'mmc1_set_x': not a number: 'abc'

Reading has two paths that accept the same files. The fast path hands the data lines to
numpy's C parser (36,000 rows x 35 columns in well under 0.5 s). Whenever it cannot be sure
(a parse failure, a row of the wrong width, letters of nan/inf in the data), the file is
parsed again cell by cell in Python, which finds and names the exact faulty cell.

preprocess_sensors turns counts into nT in the sensor's frame axes (not calibrated):
    SET/RESET: field = (set - reset)/2 * lsb_nT,  chip offset = ((set + reset)/2 - zero_count) * lsb_nT
    otherwise: field = (count - zero_count) * lsb_nT
    frame[k] = sign[k] * sensor[idx[k]]   (SensorSpec.axis_map, seed 000 eq. 1)
"""

from __future__ import annotations

import io
import math
import re

import numpy as np

from generator.errors import InputError
from generator.io.telemetry import SensorData, Telemetry

TIME_COLUMN = "time_s"
POSITION_COLUMN = "position"

# '# key: value' (the value is stripped in code: a lazy group before \s*$ is quadratic)
_META_RE = re.compile(r"#\s*([A-Za-z_][A-Za-z0-9_.-]*)\s*:(.*)")
# linear: no two adjacent runs of digits that could share a digit (\d+\.?\d* backtracks
# quadratically on a long cell of digits that ends in a letter)
_NUMBER_RE = re.compile(r"[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?")

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


# --------------------------------------------------------------------------- reading

def read_telemetry(path, unit, *, require_sensors: bool = True) -> Telemetry:
    """Read and validate one telemetry CSV against the unit (ICD section 2).

    Raises InputError (file, line, column, fault) on: unreadable file, no header, missing
    `time_s`, a sensor column the unit requires missing (require_sensors), a cell that is
    not a number, a literal NaN/inf cell, time going backwards, a row with the wrong
    number of cells, a count outside the part's raw range. Empty cells are missing values
    (NaN) and are allowed. Extra columns are kept as channels.

    ICD section 4: a file with a position (columns, or the unit's [orbit] TLE) and no ref_*
    column gets ref_norm_nT from the field model along its track (io/orbit.py; its
    provenance in meta["field_reference"]).
    """
    text = _read_text(path)
    header, header_line, rows, row_lines, meta, comments = _split_lines(path, text)
    if "unit" in meta and meta["unit"] != unit.id:
        raise InputError(path, f"'# unit: {meta['unit']}' but the unit file is for "
                               f"'{unit.id}': telemetry of another unit?")
    names = _check_header(path, header, header_line, unit, require_sensors)

    values = _parse_fast(rows, len(names))
    if values is None:
        values = _parse_slow(path, names, rows, row_lines)
    columns = {name: np.ascontiguousarray(values[:, j]) for j, name in enumerate(names)}
    line_numbers = np.asarray(row_lines, dtype=np.int64)

    _check_time(path, columns[TIME_COLUMN], line_numbers)
    _check_counts(path, columns, line_numbers, unit)
    _check_position(path, columns, line_numbers)
    _check_geo(path, columns, line_numbers)
    _check_physical(path, columns, line_numbers)
    tel = Telemetry(path=str(path), columns=columns, line_numbers=line_numbers,
                    meta=meta, comments=comments)
    # ICD section 4: a position and no ref_* column -> ref_norm_nT from the field model
    from generator.io.orbit import attach_field_reference
    return attach_field_reference(tel, unit)


def _read_text(path) -> str:
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as e:
        raise InputError(path, f"cannot read telemetry file: {e.strerror or e}") from None
    try:
        text = raw.decode("utf-8-sig")          # a leading byte-order mark is tolerated
    except UnicodeDecodeError as e:
        line = raw.count(b"\n", 0, e.start) + 1
        raise InputError(path, f"not UTF-8 (byte 0x{raw[e.start]:02x})", line=line) from None
    return text.replace("\r\n", "\n")


def _split_lines(path, text: str):
    """Header, data lines with their 1-based line numbers, '# key: value' meta, other comments.

    Comment lines ('#' first, leading blanks allowed) and blank lines are skipped anywhere;
    only those before the header are collected into meta / comments.
    """
    header = header_line = None
    rows, row_lines, meta, comments = [], [], {}, []
    for no, line in enumerate(text.split("\n"), start=1):
        first = line[:1]
        if first in ("", " ", "\t"):
            stripped = line.strip()
            if not stripped:
                continue                          # blank line
            first = stripped[0]
        if first == "#":
            if header is None:
                m = _META_RE.match(line.strip())
                if m:
                    meta[m.group(1)] = m.group(2).strip()
                else:
                    comments.append(line)
            continue
        if header is None:
            header, header_line = line, no
        else:
            rows.append(line)
            row_lines.append(no)
    if header is None:
        raise InputError(path, "no header line (the file is empty or holds only comments)")
    return header, header_line, rows, row_lines, meta, comments


def _check_header(path, header: str, line: int, unit, require_sensors: bool) -> list:
    names = [c.strip() for c in header.split(",")]
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


def _parse_slow(path, names: list, rows: list, row_lines: list) -> np.ndarray:
    """Cell by cell; raises InputError at the first faulty cell."""
    ncol = len(names)
    values = np.empty((len(rows), ncol))
    for r, (row, line) in enumerate(zip(rows, row_lines)):
        cells = row.split(",")
        if len(cells) < ncol:
            raise InputError(path, f"row has {len(cells)} cells, the header has {ncol} columns "
                                   "(this and later columns have no cell)",
                             line=line, column=names[len(cells)])
        if len(cells) > ncol:
            raise InputError(path, f"row has {len(cells)} cells, the header has {ncol} columns "
                                   f"(extra cells after the last column '{names[-1]}')", line=line)
        for j, cell in enumerate(cells):
            s = cell.strip()
            if not s:
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

def preprocess(tel: Telemetry, unit) -> dict:
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
    return {spec.name: _sensor_data(tel, spec) for spec in unit.sensors}


def _sensor_data(tel: Telemetry, spec) -> SensorData:
    absent_cells = np.full(tel.n, np.nan)
    counts = {c: tel.columns[c] for c in spec.count_columns if c in tel.columns}
    missing_columns = tuple(c for c in spec.required_columns if c not in tel.columns)
    raw = np.column_stack([np.asarray(tel.columns.get(c, absent_cells), dtype=np.float64)
                           for c in spec.count_columns])          # (N, 3) or (N, 6) counts
    if spec.temperature:
        temp_C = np.array(tel.columns.get(spec.temp_column, absent_cells), dtype=np.float64)
        missing = ~np.isfinite(raw).all(axis=1) | ~np.isfinite(temp_C)
    else:
        temp_C = np.full(tel.n, np.nan)          # documented: no temperature, not missing
        missing = ~np.isfinite(raw).all(axis=1)
    if spec.counts:
        at_rail = ((raw <= spec.count_min) | (raw >= spec.count_max)).any(axis=1)
    else:
        with np.errstate(invalid="ignore"):
            at_rail = (np.abs(raw) * spec.nT_per_input >= spec.full_scale_nT).any(axis=1)
    saturated = at_rail & ~missing              # missing and saturated counts once, as missing
    usable = ~missing & ~saturated

    chip_offset_sensor_nT = None
    if spec.set_reset:
        set_counts, reset_counts = raw[:, :3], raw[:, 3:]
        field_sensor_nT = (set_counts - reset_counts) / 2.0 * spec.lsb_nT
        chip_offset_sensor_nT = ((set_counts + reset_counts) / 2.0 - spec.zero_count) * spec.lsb_nT
        chip_offset_sensor_nT[~usable] = np.nan
    else:
        field_sensor_nT = (raw - spec.zero_count) * spec.lsb_nT

    idx, sign = spec.axis_map()
    field_frame_nT = field_sensor_nT[:, list(idx)] * np.asarray(sign, dtype=np.float64)
    field_frame_nT[~usable] = np.nan

    return SensorData(
        name=spec.name, field_frame_nT=field_frame_nT, temp_C=temp_C, usable=usable,
        n_missing=int(missing.sum()), n_saturated=int(saturated.sum()),
        chip_offset_sensor_nT=chip_offset_sensor_nT, counts=counts,
        missing_columns=missing_columns, has_temperature=spec.temperature,
    )
