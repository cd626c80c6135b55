"""Read and validate a unit file (ICD section 1) into generator.io.unit.Unit.

Every fault raises InputError naming the file, the table and the key, and the line where
the key (or its table) is written when that can be found, e.g.

    unit.toml:34: [[sensor]] #3 'mpu2': axes: '+w' is not one of +x,-x,+y,-y,+z,-z

Unknown tables and keys are not errors: they are kept in Unit.extra so that a newer file
still loads in an older toolchain (the ICD allows accepting more).
"""

from __future__ import annotations

import math
import re
import sys
from pathlib import Path

from generator.errors import InputError

if sys.version_info >= (3, 11):
    import tomllib
else:                                   # Python 3.10: the same parser, as a package
    import tomli as tomllib
from generator.io import parts as P
from generator.io.names import name_fault, prefix_collision
from generator.io.unit import FLOAT_TYPES, FRAMES, SensorSpec, Unit

AXIS_TOKENS = ("+x", "-x", "+y", "-y", "+z", "-z")
MAX_UNIT_FILE_BYTES = 2 ** 20   # a unit file of 8 sensors is a few kB
MAX_SENSORS = 8           # the flight chain's fixed size (flight/chain.py checks it too)

UNIT_KEYS = ("id", "lab_field_nT", "float")
BOOM_KEYS = ("reference",)
SENSOR_KEYS = ("name", "part", "frame", "axes", "lsb_nT", "zero_count", "set_reset", "noise_nT",
               "input", "temperature", "range_nT")                 # the last three: ICD section 4
ORBIT_KEYS = ("epoch_utc", "tle")
REQUIREMENT_KEYS = ("field_error_nT", "angle_deg")
_EPOCH_RE = re.compile(r"\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}(\.\d+)?(Z|[+-]\d{2}:\d{2})")

# A field, field step or noise beyond 1e7 nT (10 mT, twice the largest full scale among
# the parts, AK8963 4912 uT) describes no magnetometer: the arithmetic would overflow.
FIELD_LIMIT_nT = 1e7

_TABLE_HEADER_RE = re.compile(r"^\s*(\[\[?)\s*([A-Za-z0-9_-]+)\s*\]\]?\s*(#.*)?$")
_KEY_RE = re.compile(r"^\s*([A-Za-z0-9_-]+)\s*=")
_TOML_POS_RE = re.compile(r"\s*\(at line (\d+), column (\d+)\)$")
_MISSING = object()


def load_unit(path) -> Unit:
    """Read and validate a unit TOML file (ICD section 1).

    Raises generator.errors.InputError naming the file (and the key / [[sensor]] index)
    on any fault: TOML syntax, missing key, bad id or name pattern, unknown part (the
    message lists the catalogue, generator/io/parts.toml), unknown frame, input not one of
    counts/nT/uT/mG/G, generic part without range_nT, [orbit] epoch_utc / tle and
    [requirements] values malformed (ICD section 4), axes that are not a signed permutation of x, y, z, non-positive
    lsb_nT, set_reset on a part that cannot, duplicate sensor names, boom.reference
    that is not a body-frame sensor, float not in FLOAT_TYPES.
    """
    try:
        if Path(path).is_file() and Path(path).stat().st_size > MAX_UNIT_FILE_BYTES:
            raise InputError(path, f"larger than any unit file ({MAX_UNIT_FILE_BYTES} bytes "
                                   "at most)")
        raw = Path(path).read_bytes()
    except OSError as e:
        raise InputError(path, f"cannot read unit file: {e.strerror or e}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise InputError(path, f"not UTF-8 (byte 0x{raw[e.start]:02x})",
                         line=raw.count(b"\n", 0, e.start) + 1) from None
    try:
        doc = tomllib.loads(text)
    except RecursionError:
        raise InputError(path, "TOML syntax: nested too deeply") from None
    except tomllib.TOMLDecodeError as e:
        msg = str(e)
        m = _TOML_POS_RE.search(msg)
        line = int(m.group(1)) if m else None
        raise InputError(path, f"TOML syntax: {_TOML_POS_RE.sub('', msg)}", line=line) from None
    except ValueError as e:              # an integer of more than 4300 digits
        raise InputError(path, f"TOML: {e}") from None
    return unit_from_doc(path, doc, text)


def unit_from_doc(path, doc: dict, text: str = "") -> Unit:
    """Validate a parsed unit document (the TOML tables as dicts) into a Unit; the same
    checks as load_unit. text: the file's text, for line numbers in messages (optional)."""
    lines = _LineFinder(text)
    extra: dict = {}

    unit_tbl = _Table.top(path, lines, doc, "unit", required=True)
    unit_id = unit_tbl.name("id", kind="unit")
    lab_field_nT = unit_tbl.number("lab_field_nT", required=False, positive=True,
                                   at_most=FIELD_LIMIT_nT)
    float_type = unit_tbl.choice("float", FLOAT_TYPES, default="float32")
    unit_tbl.keep_unknown(UNIT_KEYS, extra, "unit")

    sensor_list = doc.get("sensor", _MISSING)
    if sensor_list is _MISSING:
        raise InputError(path, "[[sensor]]: no sensor (at least one [[sensor]] table is needed)")
    if not isinstance(sensor_list, list) or not all(isinstance(s, dict) for s in sensor_list):
        raise InputError(path, "sensor: must be an array of tables, written [[sensor]]",
                         line=lines.table("sensor", 1))
    if not sensor_list:
        raise InputError(path, "[[sensor]]: no sensor (at least one [[sensor]] table is needed)")
    if len(sensor_list) > MAX_SENSORS:
        raise InputError(path, f"[[sensor]]: {len(sensor_list)} sensors; a unit has 1 to "
                               f"{MAX_SENSORS} (the flight code's fixed size)",
                         line=lines.table("sensor", MAX_SENSORS + 1))

    sensors = []
    sensor_extra = {}
    for i, d in enumerate(sensor_list, start=1):
        spec, unknown = _read_sensor(_Table(path, lines, d, "sensor", i), float_type)
        sensors.append(spec)
        if unknown:
            sensor_extra[spec.name] = unknown
    if sensor_extra:
        extra["sensor"] = sensor_extra

    _check_unique_names_and_columns(path, lines, sensors)

    boom_reference = None
    boom_sensors = [s.name for s in sensors if s.frame == "boom"]
    body_sensors = [s.name for s in sensors if s.frame == "body"]
    boom_tbl = _Table.top(path, lines, doc, "boom", required=False)
    # boom sensors and no [boom] reference (or no body-frame sensor to name): nothing to
    # align them to, H is the identity and the coefficients, the header and the report
    # say so (ICD section 1 names the reference where there is one)
    if boom_tbl is not None:
        boom_reference = boom_tbl.name("reference", required=bool(boom_sensors and body_sensors))
        if boom_reference is not None:
            body = [s.name for s in sensors if s.frame == "body"]
            if boom_reference not in body:
                what = ("is a boom-frame sensor" if boom_reference in boom_sensors
                        else "is not a sensor of this unit")
                boom_tbl.fail("reference", f"'{boom_reference}' {what}; it must name a "
                                           f"body-frame sensor (one of {', '.join(body) or 'none'})")
        boom_tbl.keep_unknown(BOOM_KEYS, extra, "boom")

    orbit = _read_orbit(_Table.top(path, lines, doc, "orbit", required=False), extra)
    requirements = _read_requirements(
        _Table.top(path, lines, doc, "requirements", required=False), extra)

    for key, value in doc.items():
        if key not in ("unit", "boom", "sensor", "orbit", "requirements"):
            extra[key] = value
    if "trace" in doc:     # [[trace.regressor]]: user-declared regressors (io/formula.py)
        from generator.io.formula import read_regressors
        regs = read_regressors(path, doc["trace"],
                               lambda i, _k: lines.table("trace.regressor", i))
        if regs:
            extra["trace_regressors"] = [{k: r[k] for k in ("name", "formula", "inputs")}
                                         for r in regs]
    # ICD section 4 tables, validated, in plain form (the Unit dataclass is shared and
    # frozen; Unit.extra carries them to whoever needs them: orbit work, the report)
    if orbit:
        extra["orbit"] = orbit
    if requirements:
        extra["requirements"] = requirements

    return Unit(id=unit_id, sensors=tuple(sensors), lab_field_nT=lab_field_nT,
                float_type=float_type, boom_reference=boom_reference, path=str(path), extra=extra)


# The largest raw count magnitude a chain holds exactly: the flight code takes counts as
# int32_t and converts them to its float type, where every integer up to 2^24 (float32's
# 24-bit significand) or up to int32's range (float64) is exact; the folded chain's
# count - zero_count rests on that (docs/flight_target.md, "The flop bound").
EXACT_COUNT_LIMIT = {"float32": 2 ** 24, "float64": 2 ** 31 - 1}


def _read_sensor(t: "_Table", float_type: str = "float32") -> tuple[SensorSpec, dict]:
    name = t.name("name")
    t.label = f"[[sensor]] #{t.index} '{name}'"
    part_name = t.get("part")
    part = P.find(part_name)
    if part is None:
        t.fail("part", f"{part_name!r} is not a known part; known parts: {P.known_text()} "
                       "(\"generic\" needs range_nT)")
    frame = t.choice("frame", FRAMES)
    axes = _read_axes(t)
    inp = t.choice("input", P.INPUTS, default="counts")
    range_nT = t.number("range_nT", required=part.generic, positive=True,
                        at_most=FIELD_LIMIT_nT)
    # default from the part: a part without a temperature sensor (IST8310, HMC5883L, ...)
    # has no <s>_temp_C column unless the unit file says otherwise
    temperature = t.boolean("temperature", default=part.temperature)
    if inp == "counts":
        lsb_nT = t.number("lsb_nT", positive=True, at_most=FIELD_LIMIT_nT)
        zero_count = t.integer("zero_count")
        lo, hi = P.count_range(part, lsb_nT, zero_count, range_nT)
        if not lo < zero_count < hi:
            t.fail("zero_count", f"{zero_count} is not inside the {part_name} raw range "
                                 f"({lo}, {hi})")
        limit = EXACT_COUNT_LIMIT[float_type]
        if lo < -limit or hi > limit:
            key = ("zero_count" if abs(zero_count) > limit else
                   "range_nT" if part.generic else "lsb_nT")
            t.fail(key, f"the raw range ({lo}, {hi}) reaches beyond +-{limit:,}, the "
                        f"largest count the {float_type} flight chain holds exactly (counts "
                        "are int32 converted to the chain's float type): give the readings "
                        "in a physical unit (input = \"nT\", \"uT\" or \"G\")"
                        + (" or use float = \"float64\" in [unit]"
                           if float_type == "float32" else ""))
    else:
        # ICD section 4: the columns hold real numbers in `input`; lsb_nT and zero_count
        # are not used (written, they are ignored). The spec carries the unit's nT factor
        # as lsb_nT and 0 as zero_count, so (value - zero_count) * lsb_nT is still the field.
        if "lsb_nT" in t.d:
            t.number("lsb_nT", positive=True)          # a present key is still well-formed
        lsb_nT, zero_count = P.INPUT_UNITS_nT[inp], 0
    set_reset = t.boolean("set_reset", default=False)
    if set_reset and not part.set_reset:
        t.fail("set_reset", f"the {part_name} has no SET/RESET; set_reset must be false")
    noise_nT = t.number("noise_nT", required=False, positive=True, at_most=FIELD_LIMIT_nT)
    unknown = {k: v for k, v in t.d.items() if k not in SENSOR_KEYS}
    spec = SensorSpec(name=name, part=part_name, frame=frame, axes=axes, lsb_nT=lsb_nT,
                      zero_count=zero_count, set_reset=set_reset, noise_nT=noise_nT,
                      input=inp, temperature=temperature, range_nT=range_nT)
    return spec, unknown


def _read_orbit(t, extra) -> dict:
    """[orbit] (ICD section 4): epoch_utc "YYYY-MM-DDThh:mm:ss[.f](Z|+hh:mm)", optional
    tle = [line 1, line 2] (69 characters each, starting "1 " and "2 ", checksums right)."""
    if t is None:
        return {}
    out = {}
    epoch = t.get("epoch_utc")
    if not isinstance(epoch, str) or not _EPOCH_RE.fullmatch(epoch):
        t.fail("epoch_utc", f"{epoch!r} is not a UTC time written like \"2026-03-01T00:00:00Z\"")
    from datetime import datetime
    try:
        datetime.fromisoformat(epoch.replace("Z", "+00:00"))
    except ValueError as e:
        t.fail("epoch_utc", f"{epoch!r}: {e}")
    out["epoch_utc"] = epoch
    tle = t.get("tle", required=False)
    if tle is not None:
        if (not isinstance(tle, list) or len(tle) != 2
                or not all(isinstance(x, str) for x in tle)):
            t.fail("tle", "must be a list of the two lines of a two-line element set")
        for k, line in enumerate(tle, start=1):
            if len(line) != 69 or not line.startswith(f"{k} "):
                t.fail("tle", f"line {k} must be 69 characters starting \"{k} \" "
                              f"(it has {len(line)}: {line[:20]!r}...)")
            if _tle_checksum(line) != line[68]:
                t.fail("tle", f"line {k}: checksum {line[68]!r}, the line sums to "
                              f"{_tle_checksum(line)!r}")
        if tle[0][2:7] != tle[1][2:7]:   # columns 3-7 of both lines: the catalogue number
            t.fail("tle", f"line 1 is catalogue number {tle[0][2:7].strip()!r} but line 2 is "
                          f"{tle[1][2:7].strip()!r}: the lines of two different element sets")
        out["tle"] = list(tle)
    t.keep_unknown(ORBIT_KEYS, extra, "orbit_unknown")
    return out


def _tle_checksum(line: str) -> str:
    """Last digit of the sum of the first 68 characters' digits, '-' counting 1."""
    return str(sum(int(c) if c.isdigit() else (1 if c == "-" else 0) for c in line[:68]) % 10)


def _read_requirements(t, extra) -> dict:
    """[requirements] (ICD section 4): field_error_nT, angle_deg, both positive, optional."""
    if t is None:
        return {}
    out = {}
    for key in REQUIREMENT_KEYS:
        v = t.number(key, required=False, positive=True)
        if v is not None:
            out[key] = v
    t.keep_unknown(REQUIREMENT_KEYS, extra, "requirements_unknown")
    return out


def _read_axes(t: "_Table") -> tuple:
    axes = t.get("axes")
    if not isinstance(axes, list) or len(axes) != 3:
        t.fail("axes", f"{axes!r} must be a list of three entries such as [\"+z\", \"+y\", \"+x\"]")
    for a in axes:
        if a not in AXIS_TOKENS:
            t.fail("axes", f"{a!r} is not one of {','.join(AXIS_TOKENS)}")
    if sorted(a[1] for a in axes) != ["x", "y", "z"]:
        t.fail("axes", f"{axes!r} is not a permutation of x, y, z")
    return tuple(axes)


def _check_unique_names_and_columns(path, lines, sensors) -> None:
    owner: dict = {}
    for i, s in enumerate(sensors, start=1):
        where = f"[[sensor]] #{i} '{s.name}'"
        line = lines.key("sensor", i, "name")
        if s.name in (o.name for o in sensors[: i - 1]):
            raise InputError(path, f"{where}: name: duplicate sensor name '{s.name}'", line=line)
        for col in (*s.count_columns, s.temp_column):   # temp even when temperature = false
            if col in owner:
                raise InputError(path, f"{where}: name: telemetry column '{col}' would also "
                                       f"belong to sensor '{owner[col]}'", line=line)
            owner[col] = s.name
    clash = prefix_collision(s.name for s in sensors)
    if clash:
        a, b = clash
        i = [s.name for s in sensors].index(b) + 1
        raise InputError(path, f"[[sensor]] #{i} '{b}': name: starts with the name of sensor "
                               f"'{a}' and an '_': their C identifiers could collide after "
                               "prefixing (docs/names.md)", line=lines.key("sensor", i, "name"))


class _LineFinder:
    """Where a table or key is written, for messages (None when it cannot be told)."""

    def __init__(self, text: str):
        self.lines = text.splitlines()

    def _sections(self, table):
        """(header line number, [(line number, text)...]) of each [table] / [[table]];
        table None: the root keys written before the first table header."""
        out, current = [], None
        if table is None:
            current = (None, [])
            out.append(current)
        for no, line in enumerate(self.lines, start=1):
            m = _TABLE_HEADER_RE.match(line)
            if m:
                current = (no, []) if m.group(2) == table else None
                if current:
                    out.append(current)
            elif current:
                current[1].append((no, line))
        return out

    def table(self, table: str, index: int):
        sections = self._sections(table)
        return sections[index - 1][0] if 0 < index <= len(sections) else None

    def key(self, table: str, index: int, key: str):
        sections = self._sections(table)
        if not 0 < index <= len(sections):
            return None
        header, body = sections[index - 1]
        for no, line in body:
            m = _KEY_RE.match(line)
            if m and m.group(1) == key:
                return no
        return header


class _Table:
    """One TOML table being validated: typed getters that fail with file, line, table, key."""

    def __init__(self, path, lines: _LineFinder, d: dict, table: str, index: int):
        self.path, self.lines, self.d, self.table, self.index = path, lines, d, table, index
        self.label = f"[[{table}]] #{index}" if table == "sensor" else f"[{table}]"

    @staticmethod
    def top(path, lines, doc, table, required):
        d = doc.get(table, _MISSING)
        if d is _MISSING:
            if required:
                raise InputError(path, f"[{table}]: table missing")
            return None
        if not isinstance(d, dict):
            raise InputError(path, f"{table}: must be a table, written [{table}]",
                             line=lines.key(None, 1, table))
        return _Table(path, lines, d, table, 1)

    def fail(self, key, message):
        raise InputError(self.path, f"{self.label}: {key}: {message}",
                         line=self.lines.key(self.table, self.index, key))

    def get(self, key, required=True):
        if key not in self.d:
            if required:
                self.fail(key, "missing")
            return None
        return self.d[key]

    def name(self, key, required=True, kind="sensor"):
        v = self.get(key, required)
        if v is None:
            return None
        fault = name_fault(v, kind)
        if fault:
            self.fail(key, fault)
        return v

    def choice(self, key, allowed, default=None):
        v = self.get(key, required=default is None)
        if v is None:
            return default
        if v not in allowed:
            self.fail(key, f"{v!r} is not one of {', '.join(allowed)}")
        return v

    def number(self, key, required=True, positive=False, at_most=None):
        v = self.get(key, required)
        if v is None:
            return None
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            self.fail(key, f"{v!r} is not a finite number")
        if positive and not v > 0:
            self.fail(key, f"{v!r} must be positive")
        if at_most is not None and abs(v) > at_most:
            self.fail(key, f"{v!r} is beyond the plausible {at_most:g}")
        return float(v)

    def integer(self, key):
        v = self.get(key)
        if isinstance(v, float) and math.isfinite(v) and v.is_integer():
            v = int(v)
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail(key, f"{v!r} is not an integer")
        return v

    def boolean(self, key, default):
        v = self.get(key, required=False)
        if v is None:
            return default
        if not isinstance(v, bool):
            self.fail(key, f"{v!r} is not true or false")
        return v

    def keep_unknown(self, known, extra, into):
        unknown = {k: v for k, v in self.d.items() if k not in known}
        if unknown:
            extra[into] = unknown
