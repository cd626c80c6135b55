"""Input reading and preprocessing (ICD sections 1 and 2).

Bad files are small texts written to tmp_path; each fault must raise InputError naming the
file, the line and the column (or TOML key). Expected numbers are written out by hand from
the files, not recomputed with the code under test.
"""

from __future__ import annotations


import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from generator.io import telemetry_csv as telemetry_io
from generator.errors import InputError
from generator.io.telemetry_csv import preprocess, read_telemetry
from generator.io.unitfile import load_unit

# =========================================================================== unit file

UNIT_TOML = """\
# test unit
[unit]
id = "testsat"
lab_field_nT = 50000.0

[boom]
reference = "mmc1"

[[sensor]]
name = "mmc1"
part = "MMC5883MA"
frame = "body"
axes = ["+z", "+y", "+x"]
lsb_nT = 25.0
zero_count = 32768
set_reset = true

[[sensor]]
name = "mpu1"
part = "MPU-9255"
frame = "body"
axes = ["-z", "-y", "-x"]
lsb_nT = 150.0
zero_count = 0

[[sensor]]
name = "mpu3"
part = "MPU-9255"
frame = "boom"
axes = ["-y", "-z", "+x"]
lsb_nT = 150
zero_count = 0
noise_nT = 250.0
"""


def write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def line_of(text, line_text):
    """1-based line number of the first line equal to line_text (independent of the code)."""
    return text.splitlines().index(line_text) + 1


def test_unit_good_file_and_defaults(tmp_path):
    u = load_unit(write(tmp_path, "unit.toml", UNIT_TOML))
    assert u.id == "testsat"
    assert u.lab_field_nT == 50000.0
    assert u.float_type == "float32"                       # default
    assert u.boom_reference == "mmc1"
    assert u.sensor_names == ("mmc1", "mpu1", "mpu3")
    mmc1, mpu1, mpu3 = u.sensors
    assert mmc1.set_reset is True and mpu1.set_reset is False   # default false
    assert mmc1.noise_nT is None and mpu3.noise_nT == 250.0      # optional
    assert mpu3.lsb_nT == 150.0 and isinstance(mpu3.lsb_nT, float)  # TOML integer accepted
    assert mpu3.axes == ("-y", "-z", "+x") and mpu3.frame == "boom"
    assert mmc1.zero_count == 32768 and mmc1.part == "MMC5883MA"
    assert u.extra == {}


def test_unit_float64_and_unknown_keys_kept(tmp_path):
    text = (UNIT_TOML.replace('id = "testsat"', 'id = "testsat"\nfloat = "float64"\ncolour = "blue"')
            .replace('name = "mpu1"', 'name = "mpu1"\nserial = "A123"')
            + '\n[thermal]\nheater = true\n')
    u = load_unit(write(tmp_path, "unit.toml", text))
    assert u.float_type == "float64"
    assert u.extra == {"unit": {"colour": "blue"}, "sensor": {"mpu1": {"serial": "A123"}},
                       "thermal": {"heater": True}}


# (old text, new text, fragment expected in the message, expect the line of `new`)
UNIT_FAULTS = {
    "toml syntax": ('lsb_nT = 25.0', 'lsb_nT = 25.0.0', "TOML syntax", True),
    "no [unit]": ('[unit]\nid = "testsat"\nlab_field_nT = 50000.0\n', '', "[unit]: table missing", False),
    "id missing": ('id = "testsat"\n', '', "[unit]: id: missing", False),
    "id pattern": ('id = "testsat"', 'id = "TestSat"', "[unit]: id: 'TestSat' does not match", True),
    "id digit first": ('id = "testsat"', 'id = "1sat"', "[unit]: id: '1sat' does not match", True),
    "id not a string": ('id = "testsat"', 'id = 7', "[unit]: id: 7 does not match", True),
    "lab field negative": ('lab_field_nT = 50000.0', 'lab_field_nT = -1.0',
                           "[unit]: lab_field_nT: -1.0 must be positive", True),
    "lab field text": ('lab_field_nT = 50000.0', 'lab_field_nT = "50 uT"',
                       "[unit]: lab_field_nT: '50 uT' is not a finite number", True),
    "float type": ('id = "testsat"', 'id = "testsat"\nfloat = "float16"',
                   "[unit]: float: 'float16' is not one of float32, float64", False),
    "name pattern": ('name = "mpu1"', 'name = "MPU 1"', "[[sensor]] #2: name: 'MPU 1' does not match", True),
    "name missing": ('name = "mpu1"\n', '', "[[sensor]] #2: name: missing", False),
    "unknown part": ('part = "MPU-9255"', 'part = "HMC5884"',
                     "[[sensor]] #2 'mpu1': part: 'HMC5884' is not a known part; known parts: "
                     "MMC5883MA, MMC5983MA, MPU-9255 (MPU-9250, AK8963)", True),
    "unknown frame": ('frame = "boom"', 'frame = "deck"',
                      "[[sensor]] #3 'mpu3': frame: 'deck' is not one of body, boom", True),
    "axes token": ('axes = ["-y", "-z", "+x"]', 'axes = ["-y", "-z", "+w"]',
                   "[[sensor]] #3 'mpu3': axes: '+w' is not one of +x,-x,+y,-y,+z,-z", True),
    "axes unsigned": ('axes = ["-y", "-z", "+x"]', 'axes = ["-y", "-z", "x"]',
                      "[[sensor]] #3 'mpu3': axes: 'x' is not one of", True),
    "axes not a permutation": ('axes = ["-y", "-z", "+x"]', 'axes = ["+x", "+x", "+z"]',
                               "[[sensor]] #3 'mpu3': axes: ['+x', '+x', '+z'] is not a permutation of x, y, z", True),
    "axes two entries": ('axes = ["-y", "-z", "+x"]', 'axes = ["-y", "-z"]',
                         "[[sensor]] #3 'mpu3': axes: ['-y', '-z'] must be a list of three", True),
    "axes a string": ('axes = ["-y", "-z", "+x"]', 'axes = "-y-z+x"',
                      "[[sensor]] #3 'mpu3': axes: '-y-z+x' must be a list of three", True),
    "lsb zero": ('lsb_nT = 150\n', 'lsb_nT = 0\n', "[[sensor]] #3 'mpu3': lsb_nT: 0 must be positive", True),
    "lsb negative": ('lsb_nT = 25.0', 'lsb_nT = -25.0', "[[sensor]] #1 'mmc1': lsb_nT: -25.0 must be positive", True),
    "lsb nan": ('lsb_nT = 25.0', 'lsb_nT = nan', "[[sensor]] #1 'mmc1': lsb_nT: nan is not a finite number", True),
    "lsb text": ('lsb_nT = 25.0', 'lsb_nT = "25"', "[[sensor]] #1 'mmc1': lsb_nT: '25' is not a finite number", True),
    "lsb missing": ('lsb_nT = 150\n', '', "[[sensor]] #3 'mpu3': lsb_nT: missing", False),
    "zero count fraction": ('zero_count = 32768', 'zero_count = 32768.5',
                            "[[sensor]] #1 'mmc1': zero_count: 32768.5 is not an integer", True),
    "zero count outside range": ('zero_count = 32768', 'zero_count = 70000',
                                 "[[sensor]] #1 'mmc1': zero_count: 70000 is not inside the MMC5883MA raw range", True),
    "set_reset on MPU": ('name = "mpu1"', 'name = "mpu1"\nset_reset = true',
                         "[[sensor]] #2 'mpu1': set_reset: the MPU-9255 has no SET/RESET", False),
    "set_reset not bool": ('set_reset = true', 'set_reset = 1',
                           "[[sensor]] #1 'mmc1': set_reset: 1 is not true or false", True),
    "noise negative": ('noise_nT = 250.0', 'noise_nT = -3.0',
                       "[[sensor]] #3 'mpu3': noise_nT: -3.0 must be positive", True),
    "duplicate name": ('name = "mpu3"', 'name = "mpu1"',
                       "[[sensor]] #3 'mpu1': name: duplicate sensor name 'mpu1'", False),
    "column clash": ('name = "mpu1"', 'name = "mmc1_set"',
                     "[[sensor]] #2 'mmc1_set': name: telemetry column 'mmc1_set_x' would also belong to sensor 'mmc1'", True),
    "boom reference missing": ('reference = "mmc1"', 'ref = "mmc1"', "[boom]: reference: missing", False),
    "boom reference is boom": ('reference = "mmc1"', 'reference = "mpu3"',
                               "[boom]: reference: 'mpu3' is a boom-frame sensor; it must name a body-frame sensor", True),
    "boom reference unknown": ('reference = "mmc1"', 'reference = "mmc9"',
                               "[boom]: reference: 'mmc9' is not a sensor of this unit", True),
}


@pytest.mark.parametrize("case", list(UNIT_FAULTS))
def test_unit_faults(tmp_path, case):
    old, new, fragment, expect_line = UNIT_FAULTS[case]
    assert old in UNIT_TOML
    text = UNIT_TOML.replace(old, new, 1)
    path = write(tmp_path, "unit.toml", text)
    with pytest.raises(InputError) as exc:
        load_unit(path)
    msg = str(exc.value)
    assert msg.startswith(str(path)), msg
    assert fragment in msg, msg
    assert "\n" not in msg
    if expect_line:
        expected = line_of(text, new.strip().split("\n")[-1])
        assert exc.value.line == expected, msg
        assert msg.startswith(f"{path}:{expected}: "), msg


def test_unit_sensor_written_as_single_table(tmp_path):
    text = UNIT_TOML.split("\n[[sensor]]")[0] + '\n[sensor]\nname = "mmc1"\n'
    path = write(tmp_path, "unit.toml", text)
    with pytest.raises(InputError) as exc:
        load_unit(path)
    assert exc.value.line == line_of(text, "[sensor]")
    assert "sensor: must be an array of tables, written [[sensor]]" in str(exc.value)


def test_unit_no_sensor(tmp_path):
    path = write(tmp_path, "unit.toml", '[unit]\nid = "testsat"\n')
    with pytest.raises(InputError, match=r"unit\.toml: \[\[sensor\]\]: no sensor"):
        load_unit(path)


def test_unit_file_unreadable_or_not_utf8(tmp_path):
    with pytest.raises(InputError, match=r"nowhere\.toml: cannot read unit file"):
        load_unit(tmp_path / "nowhere.toml")
    p = tmp_path / "unit.toml"
    p.write_bytes(UNIT_TOML.replace("# test unit", "# test unit \xb5T").encode("latin-1"))
    with pytest.raises(InputError) as exc:
        load_unit(p)
    assert exc.value.line == 1 and "not UTF-8" in str(exc.value)


# ICD section 1 table: SamSat-ION mounting, frame axes X, Y, Z in terms of sensor axes.
ICD_AXES = {
    "mmc1": ("body", ("+z", "+y", "+x")),
    "mpu1": ("body", ("-z", "-y", "-x")),
    "mpu2": ("body", ("-z", "+y", "+x")),
    "mmc2": ("boom", ("-y", "-z", "-x")),
    "mpu3": ("boom", ("-y", "-z", "+x")),
}


def test_fm1_unit_matches_icd(fm1_dir):
    u = load_unit(fm1_dir / "unit.toml")
    assert u.id == "samsat_fm1" and u.boom_reference == "mmc1" and u.float_type == "float32"
    assert {s.name: (s.frame, s.axes) for s in u.sensors} == ICD_AXES
    assert [s.set_reset for s in u.sensors] == [True, False, False, True, False]


# =========================================================================== telemetry

SMALL_UNIT = """\
[unit]
id = "testsat"

[[sensor]]
name = "mmc1"
part = "MMC5883MA"
frame = "body"
axes = ["+z", "+y", "+x"]
lsb_nT = 25.0
zero_count = 32768
set_reset = true

[[sensor]]
name = "mpu1"
part = "MPU-9255"
frame = "body"
axes = ["-z", "-y", "-x"]
lsb_nT = 150.0
zero_count = 0
"""

COLUMNS = ["time_s", "position",
           "mmc1_set_x", "mmc1_reset_x", "mmc1_set_y", "mmc1_reset_y", "mmc1_set_z", "mmc1_reset_z",
           "mmc1_temp_C", "mpu1_x", "mpu1_y", "mpu1_z", "mpu1_temp_C", "heater_on"]
ROWS = [
    ["0", "1", "34000", "31000", "33000", "32000", "32900", "32500", "25.0", "-300", "-40", "-130", "24.5", "0"],
    ["1", "1", "34001", "31001", "33001", "32001", "32901", "32501", "25.1", "-301", "-41", "-131", "24.6", "1"],
    ["2", "1", "34002", "31002", "33002", "32002", "32902", "32502", "25.2", "-302", "-42", "-132", "24.7", "1"],
    ["2", "0", "34003", "31003", "33003", "32003", "32903", "32503", "25.3", "-303", "-43", "-133", "24.8", "0"],
]
PREAMBLE = ["# bench test of the flight computer board", "# operator: ada", "#unit: testsat"]
FIRST_DATA_LINE = len(PREAMBLE) + 2          # header on line 4, row 0 on line 5


def csv_text(rows=ROWS, columns=COLUMNS, preamble=PREAMBLE):
    return "\n".join([*preamble, ",".join(columns), *(",".join(r) for r in rows)]) + "\n"


def with_cell(row, column, value, rows=ROWS):
    rows = [list(r) for r in rows]
    rows[row][COLUMNS.index(column)] = value
    return rows


@pytest.fixture
def small_unit(tmp_path):
    return load_unit(write(tmp_path, "unit.toml", SMALL_UNIT))


def read_text(tmp_path, unit, text, **kw):
    return read_telemetry(write(tmp_path, "data.csv", text), unit, **kw)


def test_csv_good_file(tmp_path, small_unit):
    tel = read_text(tmp_path, small_unit, csv_text())
    assert list(tel.columns) == COLUMNS                      # file order kept
    assert tel.n == 4
    assert tel.line_numbers.tolist() == [5, 6, 7, 8]
    assert tel.meta == {"operator": "ada", "unit": "testsat"}
    assert tel.comments == ["# bench test of the flight computer board"]
    assert tel.time_s.tolist() == [0.0, 1.0, 2.0, 2.0]       # equal times are allowed
    assert tel.columns["mmc1_reset_y"].tolist() == [32000, 32001, 32002, 32003]
    assert tel.columns["mpu1_temp_C"].tolist() == [24.5, 24.6, 24.7, 24.8]
    assert tel.columns["heater_on"].tolist() == [0, 1, 1, 0]  # extra column kept as a channel
    assert all(c.dtype == np.float64 for c in tel.columns.values())


def test_csv_empty_cells_are_nan_wherever_they_are(tmp_path, small_unit):
    rows = with_cell(0, "position", "")                      # second cell
    rows = with_cell(1, "heater_on", "", rows)               # last cell of a row
    rows = with_cell(2, "mmc1_set_x", "", rows)              # two empty cells side by side
    rows = with_cell(2, "mmc1_reset_x", "", rows)
    rows = with_cell(2, "mmc1_set_y", "", rows)              # ... three
    rows = with_cell(3, "mpu1_temp_C", "", rows)
    rows = with_cell(3, "heater_on", "", rows)               # last row ends with an empty cell
    tel = read_text(tmp_path, small_unit, csv_text(rows))
    empty = {(r, c) for r, row in enumerate(rows) for c, v in enumerate(row) if v == ""}
    got = {(r, c) for c, name in enumerate(COLUMNS) for r in np.flatnonzero(np.isnan(tel.columns[name]))}
    assert got == empty
    assert tel.columns["mmc1_set_z"].tolist() == [32900, 32901, 32902, 32903]


def test_csv_blank_cell_whitespace_crlf_bom_and_late_comments(tmp_path, small_unit):
    rows = with_cell(1, "mpu1_y", "  ")                       # blank cell: missing value
    rows = with_cell(2, "mpu1_z", " -132 ", rows)             # blanks around a number
    lines = csv_text(rows).splitlines()
    lines.insert(FIRST_DATA_LINE, "# heater on")              # comment after the header
    lines.insert(FIRST_DATA_LINE + 2, "")                     # blank line
    text = "\ufeff" + "\r\n".join(lines) + "\r\n"
    tel = read_text(tmp_path, small_unit, text)
    assert tel.n == 4
    assert tel.line_numbers.tolist() == [5, 7, 9, 10]
    assert np.isnan(tel.columns["mpu1_y"][1])
    assert tel.columns["mpu1_z"][2] == -132.0
    assert tel.meta["operator"] == "ada"


def test_fast_and_slow_parsers_agree():
    """Empty cells at every kind of place stay on numpy's fast path and give the same array."""
    rows = with_cell(0, "time_s", "")                 # first cell of the file
    rows = with_cell(0, "position", "", rows)
    rows = with_cell(1, "heater_on", "", rows)        # last cell of a line inside the file
    rows = with_cell(2, "time_s", "", rows)           # first cell of a line inside the file
    rows = with_cell(1, "mmc1_set_x", "", rows)
    rows = with_cell(1, "mmc1_reset_x", "", rows)
    rows = with_cell(3, "heater_on", "", rows)        # last cell of the file
    lines = [",".join(r) for r in rows]
    fast = telemetry_io._parse_fast(lines, len(COLUMNS))
    slow = telemetry_io._parse_slow("x.csv", COLUMNS, lines, [5, 6, 7, 8])
    assert fast is not None
    np.testing.assert_array_equal(fast, slow)
    assert np.isnan(slow).sum() == 7
    assert slow[2, COLUMNS.index("mpu1_z")] == -132.0


_cell = st.one_of(st.just(""), st.integers(-70000, 70000).map(str),
                  st.floats(-1e6, 1e6, allow_nan=False).map(repr),
                  st.floats(-1e6, 1e6, allow_nan=False).map(lambda x: f"{x:.3e}"))


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 5).flatmap(lambda ncol: st.lists(st.lists(_cell, min_size=ncol, max_size=ncol),
                                                         min_size=1, max_size=6)))
def test_fast_parser_matches_slow_parser(rows):
    ncol = len(rows[0])
    lines = [",".join(r) for r in rows]
    if ncol == 1 and "" in lines:
        return                      # an empty line is a blank line, never a row
    slow = telemetry_io._parse_slow("x.csv", [f"c{j}" for j in range(ncol)], lines,
                                    list(range(1, len(lines) + 1)))
    fast = telemetry_io._parse_fast(lines, ncol)
    assert fast is not None
    np.testing.assert_array_equal(fast, slow)
    assert np.isnan(slow).sum() == sum(c == "" for r in rows for c in r)


# (rows or header change, line, column, fragment). Row i is on line FIRST_DATA_LINE + i.
def csv_fault_cases():
    L = FIRST_DATA_LINE
    cells = {  # (row, column, cell): line, fragment
        "non-numeric count": (1, "mmc1_set_y", "abc", "not a number: 'abc'"),
        # an extra column of text is left out (test_csv_quoting_text.py); a named one is not
        "non-numeric named column": (2, "position", "on", "not a number: 'on'"),
        "underscore number": (0, "mpu1_temp_C", "2_5", "not a number: '2_5'"),
        "decimal comma": (3, "mmc1_temp_C", "25;3", "not a number: '25;3'"),
        "literal nan": (2, "mpu1_temp_C", "nan",
                        "'nan': NaN is not allowed; leave the cell empty for a missing value"),
        "literal NaN in a count": (1, "mpu1_x", "NaN", "NaN is not allowed; leave the cell empty"),
        "literal inf": (0, "heater_on", "inf", "'inf': infinity is not allowed; leave the cell empty"),
        "literal -Infinity": (3, "position", "-Infinity", "infinity is not allowed"),
        "overflow": (1, "mmc1_temp_C", "1e999", "'1e999' is too large for a 64-bit float"),
        "time empty": (2, "time_s", "", "empty; every sample needs a time"),
        "time backwards": (2, "time_s", "0.5", "time goes backwards: 0.5 s after 1 s on line 6"),
        "count not whole": (1, "mpu1_y", "-41.5", "count -41.5 is not a whole number"),
        "MMC count above range": (3, "mmc1_reset_z", "65536",
                                  "count 65536 is outside the MMC5883MA raw range [0, 65535]"),
        "MMC count below range": (0, "mmc1_set_x", "-1",
                                  "count -1 is outside the MMC5883MA raw range [0, 65535]"),
        "MPU count above range": (2, "mpu1_z", "32761",
                                  "count 32761 is outside the MPU-9255 raw range [-32760, 32760]"),
        "MPU count below range": (1, "mpu1_x", "-32761", "outside the MPU-9255 raw range"),
        "position negative": (1, "position", "-1", "-1 is not a static position number"),
        "position fraction": (1, "position", "1.5", "1.5 is not a static position number"),
    }
    for name, (row, column, cell, fragment) in cells.items():
        yield pytest.param(csv_text(with_cell(row, column, cell)), L + row, column, fragment, id=name)

    short = [list(r) for r in ROWS]
    del short[1][-2:]
    yield pytest.param(csv_text(short), L + 1, "mpu1_temp_C",
                       "row has 12 cells, the header has 14 columns", id="row too short")
    long = [list(r) for r in ROWS]
    long[3].append("7")
    yield pytest.param(csv_text(long), L + 3, None,
                       "row has 15 cells, the header has 14 columns (extra cells after the last "
                       "column 'heater_on')", id="row too long")
    yield pytest.param(csv_text(columns=[*COLUMNS[:-1], "mpu1_x"]), L - 1, "mpu1_x",
                       "appears twice in the header (columns 10 and 14)", id="duplicate column")
    yield pytest.param(csv_text(columns=["t", *COLUMNS[1:]]), L - 1, "time_s",
                       "missing from the header", id="time_s missing")
    yield pytest.param(csv_text(columns=[*COLUMNS[:5], "", *COLUMNS[6:]]), L - 1, None,
                       "header: column 6 has no name", id="empty column name")
    renamed = [c.replace("mmc1_reset_y", "mmc1_rst_y") for c in COLUMNS]
    yield pytest.param(csv_text(columns=renamed), L - 1, "mmc1_reset_y",
                       "missing from the header; sensor 'mmc1' (MMC5883MA, with SET/RESET) needs "
                       "mmc1_reset_y", id="set/reset column missing")
    renamed = [c.replace("mpu1_temp_C", "mpu1_temp") for c in COLUMNS]
    yield pytest.param(csv_text(columns=renamed), L - 1, "mpu1_temp_C",
                       "sensor 'mpu1' (MPU-9255, without SET/RESET) needs mpu1_temp_C",
                       id="temperature column missing")
    plain = [c.replace("_set_", "_").replace("_reset_", "_r") for c in COLUMNS]
    yield pytest.param(csv_text(columns=plain), L - 1, "mmc1_set_x",
                       "(the file has 'mmc1_x': is set_reset right in the unit file?)",
                       id="set_reset mismatch")
    lines = csv_text(with_cell(3, "mpu1_y", "x")).splitlines()
    lines.insert(L, "# a comment after the header")
    lines.insert(L + 2, "")
    yield pytest.param("\n".join(lines), L + 5, "mpu1_y", "not a number: 'x'",
                       id="line number counts comments and blank lines")


@pytest.mark.parametrize("text,line,column,fragment", list(csv_fault_cases()))
def test_csv_faults(tmp_path, small_unit, text, line, column, fragment):
    path = write(tmp_path, "data.csv", text)
    with pytest.raises(InputError) as exc:
        read_telemetry(path, small_unit)
    err, msg = exc.value, str(exc.value)
    assert err.path == str(path)
    assert err.line == line, msg
    assert err.column == column, msg
    where = f"{path}:{line}: " + (f"column '{column}': " if column else "")
    assert msg.startswith(where), msg
    assert fragment in msg, msg
    assert "\n" not in msg


def test_csv_file_level_faults(tmp_path, small_unit):
    with pytest.raises(InputError, match=r"nothing\.csv: cannot read telemetry file"):
        read_telemetry(tmp_path / "nothing.csv", small_unit)
    with pytest.raises(InputError, match=r": cannot read telemetry file: Is a directory"):
        read_telemetry(tmp_path, small_unit)
    for text in ("", "\n\n", "# only\n# comments\n"):
        with pytest.raises(InputError, match=r"data\.csv: no header line"):
            read_text(tmp_path, small_unit, text)
    p = tmp_path / "latin1.csv"
    p.write_bytes(csv_text(with_cell(2, "heater_on", "\xb0")).encode("latin-1"))
    with pytest.raises(InputError) as exc:
        read_telemetry(p, small_unit)
    assert exc.value.line == FIRST_DATA_LINE + 2
    assert str(exc.value).startswith(f"{p}:{FIRST_DATA_LINE + 2}: not UTF-8")


def test_csv_header_only_is_zero_samples(tmp_path, small_unit):
    tel = read_text(tmp_path, small_unit, csv_text(rows=[]))
    assert tel.n == 0 and tel.columns["time_s"].shape == (0,)
    data = preprocess(tel, small_unit)
    assert data["mmc1"].field_frame_nT.shape == (0, 3) and data["mmc1"].n_missing == 0


def test_csv_partial_sensor_columns_only_without_require_sensors(tmp_path, small_unit):
    keep = [j for j, c in enumerate(COLUMNS) if c not in ("mpu1_y", "mpu1_temp_C")]
    text = csv_text(rows=[[r[j] for j in keep] for r in ROWS], columns=[COLUMNS[j] for j in keep])
    with pytest.raises(InputError, match="column 'mpu1_y': missing from the header"):
        read_text(tmp_path, small_unit, text)
    tel = read_text(tmp_path, small_unit, text, require_sensors=False)
    assert "mpu1_y" not in tel.columns and tel.columns["mpu1_x"].tolist() == [-300, -301, -302, -303]
    data = preprocess(tel, small_unit)
    assert data["mpu1"].missing_columns == ("mpu1_y", "mpu1_temp_C")
    assert data["mpu1"].n_missing == 4 and not data["mpu1"].usable.any()
    assert set(data["mpu1"].counts) == {"mpu1_x", "mpu1_z"}
    assert data["mmc1"].usable.all() and data["mmc1"].missing_columns == ()
    # the count checks still apply to the columns that are there
    bad = text.replace("-302", "-40000")
    with pytest.raises(InputError, match="column 'mpu1_x': count -40000 is outside"):
        read_text(tmp_path, small_unit, bad, require_sensors=False)


def test_missing_and_saturated_samples(tmp_path, small_unit):
    base = ROWS[0]
    rows = [list(base) for _ in range(8)]
    for i, r in enumerate(rows):
        r[0] = str(i)
    rows = with_cell(1, "mmc1_set_y", "", rows)          # mmc1 missing
    rows = with_cell(2, "mmc1_reset_z", "65535", rows)   # mmc1 at the upper rail
    rows = with_cell(3, "mmc1_set_x", "0", rows)         # mmc1 at the lower rail ...
    rows = with_cell(3, "mmc1_temp_C", "", rows)         # ... and missing: counted once, as missing
    rows = with_cell(4, "mpu1_x", "-32760", rows)        # mpu1 at the lower rail
    rows = with_cell(5, "mpu1_z", "32760", rows)         # mpu1 at the upper rail ...
    rows = with_cell(5, "mpu1_y", "", rows)              # ... and missing
    rows = with_cell(6, "mpu1_temp_C", "", rows)         # mpu1 missing temperature
    rows = with_cell(7, "mmc1_set_x", "65534", rows)     # one count inside the rails: usable
    rows = with_cell(7, "mmc1_reset_x", "1", rows)
    rows = with_cell(7, "mpu1_y", "32759", rows)
    tel = read_text(tmp_path, small_unit, csv_text(rows))
    data = preprocess(tel, small_unit)
    mmc1, mpu1 = data["mmc1"], data["mpu1"]
    assert mmc1.usable.tolist() == [True, False, False, False, True, True, True, True]
    assert (mmc1.n_missing, mmc1.n_saturated) == (2, 1)
    assert mpu1.usable.tolist() == [True, True, True, True, False, False, False, True]
    assert (mpu1.n_missing, mpu1.n_saturated) == (2, 1)
    for sd in (mmc1, mpu1):
        assert np.isnan(sd.field_frame_nT[~sd.usable]).all()      # never a silent wrong number
        assert np.isfinite(sd.field_frame_nT[sd.usable]).all()
    assert np.isnan(mmc1.chip_offset_sensor_nT[~mmc1.usable]).all()
    assert mmc1.counts["mmc1_reset_z"][2] == 65535                # raw counts kept as read
    assert mpu1.counts["mpu1_x"][4] == -32760
    # row 7, by hand: mmc1 x = (65534 - 1)/2 * 25 = 819162.5 nT -> frame Z (axes +z,+y,+x)
    assert mmc1.field_frame_nT[7, 2] == 819162.5
    # mpu1 y = 32759 * 150 = 4913850 nT -> frame Y = -4913850 (axes -z,-y,-x)
    assert mpu1.field_frame_nT[7, 1] == -4913850.0


def test_axis_mapping_every_icd_sensor(tmp_path, fm1_dir):
    """Counts that read (100, 200, 300) counts of field along sensor x, y, z."""
    unit = load_unit(fm1_dir / "unit.toml")
    columns, row = ["time_s"], ["0"]
    for s in unit.sensors:
        z = s.zero_count
        if s.set_reset:   # SET = zero + field, RESET = zero - field
            cells = {f"{s.name}_set_{a}": z + f for a, f in zip("xyz", (100, 200, 300))}
            cells |= {f"{s.name}_reset_{a}": z - f for a, f in zip("xyz", (100, 200, 300))}
        else:
            cells = {f"{s.name}_{a}": z + f for a, f in zip("xyz", (100, 200, 300))}
        cells[f"{s.name}_temp_C"] = 20
        columns += list(cells)
        row += [str(v) for v in cells.values()]
    tel = read_text(tmp_path, unit, csv_text(rows=[row], columns=columns, preamble=[]))
    data = preprocess(tel, unit)
    # sensor axes in nT: MMC (2500, 5000, 7500), MPU (15000, 30000, 45000); ICD table by hand:
    expected = {
        "mmc1": [7500, 5000, 2500],        # +z, +y, +x
        "mpu1": [-45000, -30000, -15000],  # -z, -y, -x
        "mpu2": [-45000, 30000, 15000],    # -z, +y, +x
        "mmc2": [-5000, -7500, -2500],     # -y, -z, -x
        "mpu3": [-30000, -45000, 15000],   # -y, -z, +x
    }
    assert set(data) == set(expected)
    for name, frame in expected.items():
        assert data[name].field_frame_nT[0].tolist() == frame, name
        assert data[name].usable[0]
    for name in ("mmc1", "mmc2"):  # SET/RESET symmetric about zero_count: no chip offset
        assert data[name].chip_offset_sensor_nT[0].tolist() == [0, 0, 0]


# =========================================================================== shared files

FM1_FILES = {  # name: (samples, columns) counted from the files
    "thermal_12pos.csv": (36000, 32),
    "rotation.csv": (4000, 32),
    "coils.csv": (1020, 35),
    "flight_6h.csv": (10800, 36),
}


@pytest.mark.parametrize("name", list(FM1_FILES))
def test_fm1_files_load(fm1_dir, name):
    unit = load_unit(fm1_dir / "unit.toml")
    tel = read_telemetry(fm1_dir / name, unit)
    assert (tel.n, len(tel.columns)) == FM1_FILES[name]
    assert tel.meta == {"unit": "samsat_fm1"}
    assert len(tel.comments) == 1 and tel.comments[0].startswith("# ")
    assert tel.line_numbers[0] == 4 and tel.line_numbers[-1] == tel.n + 3
    assert np.isfinite(tel.time_s).all() and (np.diff(tel.time_s) >= 0).all()
    data = preprocess(tel, unit)
    assert list(data) == ["mmc1", "mpu1", "mpu2", "mmc2", "mpu3"]
    for sd in data.values():
        assert sd.field_frame_nT.shape == (tel.n, 3) and sd.field_frame_nT.dtype == np.float64
        assert sd.usable.all() and sd.n_missing == 0 and sd.n_saturated == 0
        # a magnetometer in the Earth's field: tens of uT, never zero, never hundreds of uT
        norm = np.linalg.norm(sd.field_frame_nT, axis=1)
        assert 15_000 < norm.min() and norm.max() < 70_000


def test_fm1_extra_columns_kept(fm1_dir):
    unit = load_unit(fm1_dir / "unit.toml")
    tel = read_telemetry(fm1_dir / "flight_6h.csv", unit)
    assert list(tel.columns)[-3:] == ["ref_norm_nT", "sa_current_A", "bus_voltage_V"]
    # first data row of flight_6h.csv: ..., 23297.8, 0.385, 7.998
    assert tel.columns["sa_current_A"][0] == 0.385
    assert tel.columns["bus_voltage_V"][0] == 7.998
    assert tel.columns["coil_y_A"][1] == 0.0064


def test_fm1_thermal_row1_by_hand(fm1_dir):
    unit = load_unit(fm1_dir / "unit.toml")
    tel = read_telemetry(fm1_dir / "thermal_12pos.csv", unit)
    data = preprocess(tel, unit)
    # thermal_12pos.csv line 4 (row 1): time 0, position 1,
    # mmc1 set/reset x 34701/30570, y 33026/32540, z 33349/32020, 25.8 degC;
    # mpu1 -336, -40, -133, 25.8 degC; mmc2 set/reset x 31074/34985, y 32357/33814, z 32646/32891.
    mmc1 = data["mmc1"]
    # sensor axes: x (34701-30570)/2*25 = 51637.5, y (33026-32540)/2*25 = 6075,
    #              z (33349-32020)/2*25 = 16612.5; frame = (+z, +y, +x)
    assert mmc1.field_frame_nT[0].tolist() == [16612.5, 6075.0, 51637.5]
    # chip offset: x (34701+30570)/2 - 32768 = -132.5 -> -3312.5 nT; y 32783 - 32768 = 15 -> 375;
    #              z 32684.5 - 32768 = -83.5 -> -2087.5 nT (sensor axes)
    assert mmc1.chip_offset_sensor_nT[0].tolist() == [-3312.5, 375.0, -2087.5]
    assert mmc1.temp_C[0] == 25.8
    assert mmc1.counts["mmc1_set_x"][0] == 34701 and mmc1.counts["mmc1_reset_z"][0] == 32020
    mpu1 = data["mpu1"]
    # sensor axes: (-336, -40, -133) * 150 = (-50400, -6000, -19950); frame = (-z, -y, -x)
    assert mpu1.field_frame_nT[0].tolist() == [19950.0, 6000.0, 50400.0]
    assert mpu1.chip_offset_sensor_nT is None
    assert mpu1.temp_C[0] == 25.8
    mmc2 = data["mmc2"]
    # sensor axes: x -3911/2*25 = -48887.5, y -1457/2*25 = -18212.5, z -245/2*25 = -3062.5;
    # frame = (-y, -z, -x)
    assert mmc2.field_frame_nT[0].tolist() == [18212.5, 3062.5, 48887.5]


def test_fm1_axis_mapping_agrees_with_reference_field(fm1_dir):
    """In the jig (boom board not deployed) every sensor's frame axes are the body axes, so in
    each of the 12 static positions each sensor's raw frame field points along ref_*_nT
    (uncalibrated: a few percent off). A wrong sign or swapped axis fails some position."""
    unit = load_unit(fm1_dir / "unit.toml")
    tel = read_telemetry(fm1_dir / "thermal_12pos.csv", unit)
    data = preprocess(tel, unit)
    ref_nT = np.column_stack([tel.columns[f"ref_{a}_nT"] for a in "xyz"])
    position = tel.columns["position"]
    assert set(position) == set(range(1, 13))
    for name, sd in data.items():
        for p in range(1, 13):
            at = position == p
            b = np.median(sd.field_frame_nT[at], axis=0)
            r = ref_nT[at][0]
            cosine = b @ r / np.linalg.norm(b) / np.linalg.norm(r)
            assert cosine > 0.99, (name, p, cosine)


def test_telemetry_of_another_unit_is_refused(tmp_path, fm1_dir):
    unit = load_unit(fm1_dir / "unit.toml")
    text = (fm1_dir / "coils.csv").read_text().replace("# unit: samsat_fm1", "# unit: samsat_fm2")
    p = tmp_path / "other.csv"
    p.write_text(text)
    with pytest.raises(InputError, match="another unit"):
        read_telemetry(p, unit)


def test_boom_sensors_without_a_boom_table_are_accepted(tmp_path):
    """Issue 15: a boom sensor with no [boom] reference is accepted (H is then the
    identity, and the coefficients and header say so: test_any_unit.py)."""
    text = UNIT_TOML.replace('[boom]\nreference = "mmc1"\n', '')
    assert text != UNIT_TOML
    p = tmp_path / "u.toml"
    p.write_text(text)
    unit = load_unit(p)
    assert unit.boom_reference is None and any(s.frame == "boom" for s in unit.sensors)


def test_more_than_eight_sensors_is_refused_at_the_unit_file(tmp_path):
    block = UNIT_TOML[UNIT_TOML.index("[[sensor]]"):UNIT_TOML.index("[[sensor]]", UNIT_TOML.index("[[sensor]]") + 1)]
    extra = "".join(block.replace('name = "mmc1"', f'name = "extra{i}"') for i in range(9))
    p = tmp_path / "u.toml"
    p.write_text(UNIT_TOML + "\n" + extra)
    with pytest.raises(InputError, match="1 to 8"):
        load_unit(p)


def test_readings_in_the_wrong_unit_are_refused_before_the_fit(tmp_path, fm1_dir, capsys):
    """lsb_nT 1000x too small: the fit would 'succeed' with a meaningless calibration."""
    from generator.cli import main
    text = (fm1_dir / "unit.toml").read_text()
    assert "lsb_nT = 25.0" in text
    unit = tmp_path / "unit.toml"
    unit.write_text(text.replace("lsb_nT = 25.0", "lsb_nT = 0.025", 1))
    rows = (fm1_dir / "thermal_12pos.csv").read_text().splitlines()
    data = tmp_path / "d.csv"
    data.write_text("\n".join(rows[:400]) + "\n")
    rc = main(["fit", str(unit), str(data), "-o", str(tmp_path / "out"), "-q"])
    assert rc == 2 and not (tmp_path / "out").exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not match the data" in err[0] and "lsb_nT = 0.025" in err[0]
