"""Uplink coefficient tables: the format, the ground tools, the flight C's context.

After launch the ground recalibrates and sends coefficients up a slow, lossy link. A
table that is corrupt, cut short, meant for another unit or another build of the chain
must never reach the correction code, and the table in use must stay in use. The design
follows NASA cFS table services in spirit: a table file header, a validation function
run on the inactive buffer, a double buffer switched only after validation.

Everything that knows the table format reads it from this module, from ONE definition:

* ``HEADER_FIELDS`` / ``PART_FIELDS`` (the header layouts), ``ERRORS`` (the status codes,
  never renumbered) and ``CHECK_ORDER`` (the order the table checks run),
  ``PLAUSIBLE_RANGES`` (per Block.kind, per polynomial order), ``PHYSICAL_LIMITS``
  (table_physics.py: det M, H a rotation) and the chain's blocks (``ChainSpec``, chain.py);
* the flight manager's serial rule and init fallback, modelled in table_manager.py;
* the encoder (:func:`encode_table`), the ground validator/decoder (:func:`check_table`,
  :func:`decode_table`) and the reassembler (:class:`Reassembler`);
* the flight C: ``templates/table.h.j2`` and ``table.c.j2`` are rendered with
  :func:`table_context` (offsets, sizes, codes, ranges, the default table's bytes);
* the docs: ``docs/table_format.md`` is :func:`format_doc` (a test keeps them equal).

Layout of a table (all little-endian): header (72 bytes), payload (the coefficients as
IEEE float32 or float64 per unit.float_type, in layout order: exactly the flat
``<unit>_coeffs_t`` contents), CRC-32 (IEEE 802.3, ``zlib.crc32``) of everything before it.

Size: one module on purpose. The table format is ONE definition (header fields, status
codes in check order, plausible ranges), and the encoder, the ground validator (which
must run the flight checks in the flight order, bit for bit), the diff, the parts and
the dump all read it; splitting them would put the order of the checks in two places.
The host build, the physics of the checks and the manager model live beside it
(table_host.py, table_physics.py, table_manager.py).
"""

from __future__ import annotations

import datetime
import enum
import functools
import hashlib
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from generator.flight.chain import Block, ChainSpec, n_prepared, np_dtype
from generator.flight.coeffs import CoefficientSet
from generator.errors import InputError
from generator.flight.c_syntax import c_literal
from generator.flight.table_physics import (PHYSICAL_LIMITS, MatrixIndex, evaluate,
                                             first_fault)


MAGIC = b"MGCT"            # a magcal coefficient table
PART_MAGIC = b"mgcp"       # one part of a chunked table (5 bits away from MAGIC)
FORMAT_VERSION = 1         # bump when the meaning of a header field changes
UNIT_ID_FIELD_BYTES = 32   # unit id, ASCII, NUL-padded (at most 31 characters)
CRC_BYTES = 4
NO_INDEX = 0xFFFFFFFF      # "no coefficient" in bad_value_index
# <unit>_table_mgr_t.init_mark after a completed <unit>_table_init (its last store): the
# bytes "INIT" in a little-endian memory dump. Its bytes are not all equal, so no
# single-byte fill (zeroed static storage, erased flash's 0xFF, any memset) makes a
# manager look initialised; every manager function tests it.
MANAGER_INIT_MARK = 0x54494E49
MAX_U16 = 0xFFFF

# Table files for the flight build; same shape as codegen.TEMPLATES entries.


# ---- the header layouts ------------------------------------------------------------------


@dataclass(frozen=True)
class Field:
    """One header field. code: its struct code (little-endian, no padding)."""

    name: str
    code: str
    doc: str
    check: str | None = None   # status of the check on this field that runs BEFORE the CRC

    @property
    def size(self) -> int:
        return struct.calcsize("<" + self.code)

    @property
    def type_name(self) -> str:
        return {"H": "uint16", "I": "uint32", "Q": "uint64", "f": "float32"}.get(
            self.code, f"uint8[{self.size}]")


HEADER_FIELDS = (
    Field("magic", "4s", 'the bytes "MGCT"', "BAD_MAGIC"),
    Field("format_version", "H", f"table format version ({FORMAT_VERSION})", "BAD_VERSION"),
    Field("value_bytes", "H", "bytes per coefficient: 4 (float32) or 8 (float64), "
                              "the unit's float type", "BAD_VALUE_BYTES"),
    Field("unit_id_hash", "I", "first 4 bytes, little-endian, of SHA-256 of the unit id",
          "WRONG_UNIT"),
    Field("unit_id", f"{UNIT_ID_FIELD_BYTES}s", "unit id, ASCII, padded with NUL bytes",
          "WRONG_UNIT"),
    Field("layout_hash", "I", "ChainSpec.layout_hash(): the chain structure it is for",
          "WRONG_LAYOUT"),
    Field("payload_bytes", "I", "bytes of coefficients that follow the header",
          "BAD_PAYLOAD_LENGTH"),
    Field("table_serial", "I", "serial number given by the ground (0: compiled-in default)"),
    Field("created_s", "Q", "creation time, s since 1970-01-01 UTC, given explicitly "
                            "(0: not given)"),
    Field("t_min_C", "f", "lowest calibrated temperature, degC: min over sensors of t_min_C"),
    Field("t_max_C", "f", "highest calibrated temperature, degC: max over sensors of t_max_C"),
)

PART_FIELDS = (
    Field("magic", "4s", 'the bytes "mgcp"', "PART_BAD_MAGIC"),
    Field("table_serial", "I", "table_serial of the table this part belongs to"),
    Field("table_bytes", "I", "length of the whole table (header + payload + CRC)"),
    Field("part_index", "H", "0 .. part_count - 1"),
    Field("part_count", "H", "number of parts: ceil(table_bytes / chunk_bytes)"),
    Field("chunk_bytes", "H", "table bytes in every part but the last; this part's bytes "
                              "go at offset part_index * chunk_bytes"),
    Field("part_bytes", "H", "table bytes in this part (before its CRC)", "PART_BAD_LENGTH"),
)


def _offsets(fields) -> dict:
    out, k = {}, 0
    for f in fields:
        out[f.name] = k
        k += f.size
    return out


HEADER_STRUCT = struct.Struct("<" + "".join(f.code for f in HEADER_FIELDS))
PART_STRUCT = struct.Struct("<" + "".join(f.code for f in PART_FIELDS))
HEADER_BYTES = HEADER_STRUCT.size
PART_HEADER_BYTES = PART_STRUCT.size
HEADER_OFFSETS = _offsets(HEADER_FIELDS)
PART_OFFSETS = _offsets(PART_FIELDS)
PART_OVERHEAD = PART_HEADER_BYTES + CRC_BYTES


# ---- status codes: the order of the checks -----------------------------------------------

# (name, reason), value = position. The table checks run in this order, the first that
# fails decides the status; identity and length checks of the header come before the CRC
# (so a table for another unit says so), the content checks after it.
ERRORS = (
    ("OK", "accepted"),
    ("NULL_ARGUMENT", "a pointer argument is NULL"),
    ("TRUNCATED", "shorter than the header, or than header + payload + CRC"),
    ("BAD_MAGIC", "not a magcal coefficient table (magic)"),
    ("BAD_VERSION", "table format version not supported by this build"),
    ("BAD_VALUE_BYTES", "coefficient width (float32/float64) differs from this build"),
    ("WRONG_UNIT", "table is for another unit (unit id)"),
    ("WRONG_LAYOUT", "table is for another chain structure (layout hash)"),
    ("BAD_PAYLOAD_LENGTH", "payload length differs from this build's coefficient layout"),
    ("TOO_LONG", "longer than header + payload + CRC"),
    ("BAD_CRC", "CRC-32 does not match: table corrupted"),
    ("BAD_TEMP_RANGE", "header temperature range not inside the plausible range, or empty"),
    ("NONFINITE_VALUE", "a coefficient is NaN or infinite"),
    ("VALUE_OUT_OF_RANGE", "a coefficient is outside its plausible range"),
    ("EMPTY_RANGE", "a lower limit is not below its upper limit (t_min_C, t_max_C; "
                    "field_min_nT, field_max_nT)"),
    ("TEMP_RANGE_MISMATCH", "header temperature range is not the sensors' range"),
    # one part (receive_part), in check order
    ("PART_TRUNCATED", "part shorter than its header + CRC"),
    ("PART_BAD_MAGIC", "not a part of a magcal coefficient table (magic)"),
    ("PART_BAD_LENGTH", "part length differs from header + part_bytes + CRC"),
    ("PART_BAD_CRC", "part CRC-32 does not match: part corrupted"),
    ("PART_TABLE_SIZE", "part of a table whose length differs from this build's tables"),
    ("PART_NUMBERING", "part index, part count and chunk size do not fit together"),
    ("PART_SIZE", "part_bytes differs from what its index and the chunk size imply"),
    ("PART_FOREIGN_SERIAL", "part of another table while a transfer is in progress"),
    ("PART_COUNT_CHANGED", "part count or chunk size differs from the transfer in progress"),
    ("PART_REPEATED", "part already received (identical; nothing stored)"),
    ("PART_CONFLICT", "part already received with other contents (nothing stored)"),
    # commit
    ("NOTHING_STAGED", "commit without a transfer in progress"),
    ("PARTS_MISSING", "commit before every part has arrived"),
    ("SERIAL_MISMATCH", "reassembled table's serial differs from its parts' serial"),
    # Added later. A code is never renumbered (ground tools and telemetry decoders keep
    # their meaning): new checks get the next free code, and the check order is stated
    # in CHECK_ORDER below, not by the code values.
    # physical checks of the content, after TEMP_RANGE_MISMATCH (PHYSICAL_LIMITS)
    ("BAD_DETERMINANT", "det M(T) of a sensor (at t_ref_C, t_min_C or t_max_C) is outside "
                        "its plausible range: singular, reflected or an implausible gain"),
    ("NOT_A_ROTATION", "H_boom_to_body is not a rotation: an element of H^T H - I beyond "
                       "the tolerance, or det H <= 0"),
    # the serial of an accepted table against the active one (load, commit), last
    ("SERIAL_ROLLBACK", "table serial below the active table's: rollback refused"),
    ("SERIAL_REPLAY", "table serial equal to the active table's, with other coefficients"),
    ("ALREADY_ACTIVE", "table serial and coefficients equal the active table's: "
                       "nothing changed"),
    # a manager never initialised (load, receive_part, commit; info's last_status), first
    ("NOT_INITIALISED", "table manager not initialised (table_init never completed on "
                        "it): nothing changed, NaN coefficients handed out"),
)

# The table checks of <unit>_table_validate, in the order they run.
CHECK_ORDER = ("NULL_ARGUMENT", "TRUNCATED", "BAD_MAGIC", "BAD_VERSION", "BAD_VALUE_BYTES",
               "WRONG_UNIT", "WRONG_LAYOUT", "BAD_PAYLOAD_LENGTH", "TOO_LONG", "BAD_CRC",
               "BAD_TEMP_RANGE", "NONFINITE_VALUE", "VALUE_OUT_OF_RANGE", "EMPTY_RANGE",
               "TEMP_RANGE_MISMATCH", "BAD_DETERMINANT", "NOT_A_ROTATION")
# The checks of the coefficients alone (no header): what <unit>_table_init runs on the
# compiled-in defaults.
CONTENT_CHECKS = ("NONFINITE_VALUE", "VALUE_OUT_OF_RANGE", "EMPTY_RANGE", "BAD_DETERMINANT",
                  "NOT_A_ROTATION")
# The serial rule, after every table check (and after SERIAL_MISMATCH in commit).
SERIAL_CHECKS = ("SERIAL_ROLLBACK", "SERIAL_REPLAY", "ALREADY_ACTIVE")

TableStatus = enum.IntEnum("TableStatus", [(n, i) for i, (n, _) in enumerate(ERRORS)],
                           module=__name__)
REASONS = {TableStatus[n]: r for n, r in ERRORS}


class TableError(InputError):
    """A table or part the flight code would reject; .status is the flight status code."""

    def __init__(self, status, detail="", path=None, bad_value_index=None):
        self.status = TableStatus(status)
        self.detail = detail
        self.bad_value_index = bad_value_index
        text = f"error {int(self.status)} {self.status.name}: {REASONS[self.status]}"
        super().__init__(path, text + (f" ({detail})" if detail else ""))

    def at(self, path) -> "TableError":
        return TableError(self.status, self.detail, path, self.bad_value_index)


def _fail(name, detail="", bad_value_index=None):
    raise TableError(TableStatus[name], detail, bad_value_index=bad_value_index)


# ---- plausible ranges, per kind of coefficient -------------------------------------------


@dataclass(frozen=True)
class KindRange:
    """Plausible values of one kind of coefficient (Block.kind).

    poly_span_C: a polynomial block (first axis = order k): the order-k coefficients are
    bounded by [lo, hi] / poly_span_C**k, i.e. every term c_k dT^k stays within [lo, hi]
    for |dT| <= poly_span_C. part_counts: the range is the sensor part's raw output range.
    """

    kind: str
    lo: float | None
    hi: float | None
    why: str
    poly_span_C: float | None = None
    part_counts: bool = False

    def bounds(self, sensor=None, order=0) -> tuple:
        if self.part_counts:
            return float(sensor.count_min), float(sensor.count_max)
        if self.poly_span_C is not None:
            scale = self.poly_span_C ** order
            return self.lo / scale, self.hi / scale
        return self.lo, self.hi


PLAUSIBLE_RANGES = {r.kind: r for r in (
    KindRange("lsb", 1e-3, 1e4, "nT per count, positive (the parts: 25 and 150)"),
    KindRange("zero_count", None, None, "count at zero field: inside the part's raw range",
              part_counts=True),
    KindRange("temp", -100.0, 150.0, "degC, beyond any qualification range of the parts"),
    KindRange("temp_margin", 0.0, 250.0, "degC, not negative, at most the plausible span"),
    KindRange("offset_poly", -2e5, 2e5, "nT: each term b_k dT^k within 4x the Earth's field",
              poly_span_C=50.0),
    KindRange("matrix_poly", -3.0, 3.0, "each term M_k dT^k within +-3 (scale factors ~1)",
              poly_span_C=50.0),
    KindRange("coupling", -1e6, 1e6, "nT per A of magnetorquer current, or per unit of a "
                                      "telemetry channel"),
    KindRange("rotation", -1.001, 1.001, "elements of an orthogonal matrix, rounding margin"),
    KindRange("tolerance", 0.1, 1e5, "nT, positive: expected scatter between sensors"),
    KindRange("field_band", 0.0, 2e5, "nT: limits of a plausible |B| (LEO: 18 000-55 000)"),
    KindRange("time_constant", 1e-3, 1e5, "s, positive (so dt / (tau + dt) is defined at "
                                          "dt = 0), at most about a day"),
    KindRange("nonlinearity", -1e-10, 1e-10, "1/nT^2: the cubic n x^3 stays below the "
                                             "reading x up to 100 000 nT"),
    KindRange("sr_delay", -0.01, 0.01, "s rad/deg: a SET->RESET delay of at most ~1 s"),
    KindRange("scale_coupling", -1.0, 1.0, "per unit of a telemetry channel: a unit of the "
                                           "channel changes the scale by less than 100 %"),
)}

# The header temperature range of a unit none of whose sensors has a temperature: the
# whole plausible range (its constant model holds at any temperature; the header check
# t_min_C < t_max_C inside the plausible range passes unchanged).
NO_TEMP_RANGE_C = PLAUSIBLE_RANGES["temp"].bounds()

# Lower and upper limits that must be strictly ordered, by block name, wherever both
# are blocks of the same sensor (or of the unit).
ORDERED_PAIRS = (("t_min_C", "t_max_C"), ("field_min_nT", "field_max_nT"))


@dataclass(frozen=True)
class Segment:
    """Consecutive payload values that share one plausible range."""

    first: int
    count: int
    lo: float
    hi: float
    owner: str         # sensor name or "unit"
    block: Block
    order: int | None  # polynomial order k, or None


@dataclass(frozen=True)
class ValueInfo:
    """What one payload value is."""

    index: int
    owner: str
    block: Block
    element: tuple

    @property
    def label(self) -> str:
        return f"{self.owner} {self.block.name}" + "".join(f"[{i}]" for i in self.element)

    @property
    def unit(self) -> str:
        """Physical unit with the polynomial order filled in: nT/degC^k, k=1 -> nT/degC."""
        u = self.block.unit
        if "^k" in u:
            k = self.element[0]
            u = u.replace("/degC^k", "") if k == 0 else \
                u.replace("degC^k", "degC" if k == 1 else f"degC^{k}")
        return "" if u == "1" else u


def _per_spec(fn):
    """Memoise a function of a ChainSpec by identity (hashing a spec walks the whole unit,
    which the validator would otherwise do on every call)."""
    memo = {}

    @functools.wraps(fn)
    def wrapper(spec):
        hit = memo.get(id(spec))
        if hit is not None and hit[0] is spec:
            return hit[1]
        value = fn(spec)
        if len(memo) >= 256:
            memo.clear()
        memo[id(spec)] = (spec, value)
        return value
    return wrapper


def _kind_range(block: Block) -> KindRange:
    try:
        return PLAUSIBLE_RANGES[block.kind]
    except KeyError:
        raise KeyError(f"no plausible range for coefficient kind {block.kind!r} (block "
                       f"{block.name}): add it to tables.PLAUSIBLE_RANGES") from None


def _owners(spec: ChainSpec):
    """(owner name, sensor or None, blocks) in payload order."""
    for s in spec.unit.sensors:
        yield s.name, s, spec.sensor_blocks(s)
    if spec.unit_blocks():
        yield "unit", None, spec.unit_blocks()


@_per_spec
def segments(spec: ChainSpec) -> tuple:
    out, k = [], 0
    for owner, sensor, blocks in _owners(spec):
        for b in blocks:
            r = _kind_range(b)
            if r.poly_span_C is not None:
                step = b.size // b.shape[0]
                for order in range(b.shape[0]):
                    lo, hi = r.bounds(sensor, order)
                    out.append(Segment(k, step, lo, hi, owner, b, order))
                    k += step
            else:
                lo, hi = r.bounds(sensor)
                out.append(Segment(k, b.size, lo, hi, owner, b, None))
                k += b.size
    return tuple(out)


@_per_spec
def value_layout(spec: ChainSpec) -> tuple:
    """ValueInfo of every payload value, in payload order."""
    out = []
    for owner, _, blocks in _owners(spec):
        for b in blocks:
            for element in np.ndindex(*b.shape) if b.shape else [()]:
                out.append(ValueInfo(len(out), owner, b, tuple(int(i) for i in element)))
    return tuple(out)


@_per_spec
def n_values(spec: ChainSpec) -> int:
    return sum(spec.n_sensor_coeffs(s) for s in spec.unit.sensors) + spec.n_unit_coeffs()


def n_prepared_values(spec: ChainSpec) -> int:
    """Reals in `<unit>_table_prepared_t` (templates/magcal.h.j2): per sensor its table
    coefficients and its kernels' prepared vectors (the SET-only one of a SET/RESET
    sensor too)."""
    return sum(spec.n_sensor_coeffs(s) + n_prepared(spec, s)
               + (n_prepared(spec, s, set_only=True) if s.set_reset else 0)
               for s in spec.unit.sensors)


@_per_spec
def layout_hash(spec: ChainSpec) -> int:
    """spec.layout_hash(), cached (it serialises the whole structure)."""
    return spec.layout_hash()


def value_dtype(spec_or_bytes) -> np.dtype:
    vb = spec_or_bytes if isinstance(spec_or_bytes, int) else \
        np.dtype(np_dtype(spec_or_bytes.unit)).itemsize
    return np.dtype("<f4" if vb == 4 else "<f8")


def table_bytes(spec: ChainSpec) -> int:
    return HEADER_BYTES + n_values(spec) * value_dtype(spec).itemsize + CRC_BYTES


@_per_spec
def _ordered_pairs(spec: ChainSpec) -> tuple:
    """(lower index, upper index) of every ORDERED_PAIRS pair in the payload."""
    out, base = [], 0
    for _, _, blocks in _owners(spec):
        off = spec.offsets(blocks)
        for lo, hi in ORDERED_PAIRS:
            if lo in off and hi in off:
                out.append((base + off[lo], base + off[hi]))
        base += sum(b.size for b in blocks)
    return tuple(out)


@_per_spec
def _temp_indices(spec: ChainSpec) -> tuple:
    """(t_min index, t_max index) of every sensor with a temperature, in payload order
    (a sensor with none has no temperature range: ICD section 4, temperature = false)."""
    out, base = [], 0
    for s in spec.unit.sensors:
        off = spec.offsets(spec.sensor_blocks(s))
        if "t_min_C" in off:
            out.append((base + off["t_min_C"], base + off["t_max_C"]))
        base += spec.n_sensor_coeffs(s)
    return tuple(out)


def _temp_sensors(spec: ChainSpec) -> tuple:
    """The sensors _temp_indices covers, in the same order."""
    return tuple(s for s in spec.unit.sensors
                 if "t_min_C" in spec.offsets(spec.sensor_blocks(s)))


@_per_spec
def _matrix_indices(spec: ChainSpec) -> tuple:
    """MatrixIndex of every sensor, in unit order."""
    out, base = [], 0
    for s in spec.unit.sensors:
        blocks = spec.sensor_blocks(s)
        off = spec.offsets(blocks)
        m = next(b for b in blocks if b.name == "M_poly")
        temps = [base + off[k] if k in off else None for k in ("t_ref_C", "t_min_C", "t_max_C")]
        out.append(MatrixIndex(s.name, base + off["M_poly"], m.shape[0], *temps))
        base += spec.n_sensor_coeffs(s)
    return tuple(out)


@_per_spec
def _rotation_index(spec: ChainSpec):
    """Payload index of H_boom_to_body[0][0], or None when the unit has no boom."""
    base = sum(spec.n_sensor_coeffs(s) for s in spec.unit.sensors)
    off = spec.offsets(spec.unit_blocks())
    return base + off["H_boom_to_body"] if "H_boom_to_body" in off else None


def physical_values(spec: ChainSpec, values) -> dict:
    """What the physical checks compute (table_physics.evaluate) for these payload values,
    in the unit's float type."""
    return evaluate(np.asarray(values).astype(value_dtype(spec), copy=False),
                    _matrix_indices(spec), _rotation_index(spec))


def _check_physics(spec: ChainSpec, values):
    """BAD_DETERMINANT, NOT_A_ROTATION (table_physics.first_fault), as TableError."""
    fault = first_fault(np.asarray(values).astype(value_dtype(spec), copy=False),
                        _matrix_indices(spec), _rotation_index(spec))
    if fault is not None:
        _fail(*fault)


@_per_spec
def _bound_arrays(spec: ChainSpec) -> tuple:
    """Plausible [lo, hi] of every value, rounded to the flight type as the C literals are."""
    dt = value_dtype(spec)
    lo = np.empty(n_values(spec), dtype=dt)
    hi = np.empty_like(lo)
    for seg in segments(spec):
        lo[seg.first:seg.first + seg.count] = seg.lo
        hi[seg.first:seg.first + seg.count] = seg.hi
    return lo, hi


# ---- identity ----------------------------------------------------------------------------


@functools.lru_cache(maxsize=256)
def unit_id_hash(unit_id: str) -> int:
    return int.from_bytes(hashlib.sha256(unit_id.encode("utf-8")).digest()[:4], "little")


@functools.lru_cache(maxsize=256)
def unit_id_field(unit_id: str) -> bytes:
    raw = unit_id.encode("ascii", errors="replace")
    if len(raw) >= UNIT_ID_FIELD_BYTES:
        raise InputError(None, f"unit id {unit_id!r} is too long for the table header "
                               f"(at most {UNIT_ID_FIELD_BYTES - 1} characters)")
    return raw.ljust(UNIT_ID_FIELD_BYTES, b"\0")


def crc32(data) -> int:
    return zlib.crc32(bytes(data)) & 0xFFFFFFFF


def reseal(table) -> bytes:
    """The table with its CRC recomputed: for tests and tools that edit a table on purpose."""
    body = bytes(table[:-CRC_BYTES])
    return body + struct.pack("<I", crc32(body))


def unpack_header(data) -> dict:
    vals = HEADER_STRUCT.unpack_from(bytes(data[:HEADER_BYTES]))
    h = {f.name: v for f, v in zip(HEADER_FIELDS, vals)}
    h["unit_id_text"] = h["unit_id"].rstrip(b"\0").decode("ascii", errors="replace")
    return h


def pack_header(h: dict) -> bytes:
    return HEADER_STRUCT.pack(*(h[f.name] for f in HEADER_FIELDS))


# ---- encoder -----------------------------------------------------------------------------


def flat_values(cs: CoefficientSet) -> np.ndarray:
    """The payload values in float64: sensor by sensor in unit order, then the unit blocks."""
    parts = [cs.flat_sensor(s.name) for s in cs.unit.sensors] + [cs.flat_unit()]
    return np.concatenate(parts)


def _temp_range(spec: ChainSpec, values) -> tuple:
    """Header range from the flight-type values, computed as the flight C does: min of
    t_min_C and max of t_max_C over the sensors with a temperature. A unit none of whose
    sensors has a temperature has a constant model that holds at every temperature: its
    header range is the whole plausible `temp` range, NO_TEMP_RANGE_C."""
    idx = _temp_indices(spec)
    if not idx:
        return tuple(np.float32(v) for v in NO_TEMP_RANGE_C)
    lo, hi = values[idx[0][0]], values[idx[0][1]]
    for i_min, i_max in idx[1:]:
        if values[i_min] < lo:
            lo = values[i_min]
        if values[i_max] > hi:
            hi = values[i_max]
    return np.float32(lo), np.float32(hi)


def _uint(name, value, bits):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) \
            or not 0 <= int(value) < 2 ** bits:
        raise InputError(None, f"{name} must be an integer in 0 .. 2^{bits}-1, not {value!r}")
    return int(value)


def encode_table(cs: CoefficientSet, serial: int, created_s: int, *, check=True) -> bytes:
    """The uplink table of a coefficient set.

    serial: table serial (u32; 0 is the compiled-in default); created_s: creation time in
    seconds (u64), given explicitly so the output is reproducible. With check (default)
    the table is run through the ground validator, which applies the flight checks, and
    a table the flight code would reject raises TableError.
    """
    spec = cs.spec
    serial = _uint("serial", serial, 32)
    created_s = _uint("created_s", created_s, 64)
    dt = value_dtype(spec)
    with np.errstate(over="ignore", invalid="ignore"):
        values = flat_values(cs).astype(dt)
    t_min, t_max = _temp_range(spec, values)
    header = pack_header({
        "magic": MAGIC, "format_version": FORMAT_VERSION, "value_bytes": dt.itemsize,
        "unit_id_hash": unit_id_hash(spec.unit.id), "unit_id": unit_id_field(spec.unit.id),
        "layout_hash": spec.layout_hash(), "payload_bytes": values.nbytes,
        "table_serial": serial, "created_s": created_s, "t_min_C": t_min, "t_max_C": t_max,
    })
    body = header + values.tobytes()
    table = body + struct.pack("<I", crc32(body))
    if check:
        check_table(table, spec)
    return table


# ---- ground validator and decoder: the flight checks, in the flight order ----------------


def check_table(data, spec: ChainSpec | None = None) -> tuple:
    """Validate a table as the flight code does; returns (header dict, values ndarray).

    With spec: every flight check, in the flight order (the status codes of ERRORS).
    Without: what the table alone allows (format, length, CRC, header temperature range,
    finite values). Raises TableError with the flight status code.
    """
    if isinstance(spec, CoefficientSet):
        spec = spec.spec
    data = bytes(data)
    n = len(data)
    if n < HEADER_BYTES + CRC_BYTES:
        _fail("TRUNCATED", f"{n} bytes; header and CRC alone take {HEADER_BYTES + CRC_BYTES}")
    h = unpack_header(data)
    if h["magic"] != MAGIC:
        _fail("BAD_MAGIC", f"{h['magic']!r}, expected {MAGIC!r}")
    if h["format_version"] != FORMAT_VERSION:
        _fail("BAD_VERSION", f"version {h['format_version']}, this is {FORMAT_VERSION}")
    if spec is not None:
        vb = value_dtype(spec).itemsize
        if h["value_bytes"] != vb:
            _fail("BAD_VALUE_BYTES", f"{h['value_bytes']}-byte values, this build has {vb}")
        uid = spec.unit.id
        if h["unit_id_hash"] != unit_id_hash(uid) or h["unit_id"] != unit_id_field(uid):
            _fail("WRONG_UNIT", f"table for {h['unit_id_text']!r} "
                                f"(hash 0x{h['unit_id_hash']:08x}), this is {uid!r}")
        if h["layout_hash"] != layout_hash(spec):
            _fail("WRONG_LAYOUT", f"table layout 0x{h['layout_hash']:08x}, this build "
                                  f"0x{layout_hash(spec):08x}")
        if h["payload_bytes"] != n_values(spec) * vb:
            _fail("BAD_PAYLOAD_LENGTH", f"{h['payload_bytes']} bytes, this build "
                                        f"{n_values(spec) * vb}")
    else:
        vb = h["value_bytes"]
        if vb not in (4, 8):
            _fail("BAD_VALUE_BYTES", f"{vb}-byte values")
        if h["payload_bytes"] % vb:
            _fail("BAD_PAYLOAD_LENGTH", f"{h['payload_bytes']} bytes is not a whole number "
                                        f"of {vb}-byte values")
    total = HEADER_BYTES + h["payload_bytes"] + CRC_BYTES
    if n < total:
        _fail("TRUNCATED", f"{n} bytes of {total}")
    if n > total:
        _fail("TOO_LONG", f"{n} bytes, expected {total}")
    stored = struct.unpack_from("<I", data, total - CRC_BYTES)[0]
    h["crc32"] = stored
    if crc32(data[:total - CRC_BYTES]) != stored:
        _fail("BAD_CRC", f"stored 0x{stored:08x}, computed "
                         f"0x{crc32(data[:total - CRC_BYTES]):08x}")
    t_lo, t_hi = (np.float32(v) for v in PLAUSIBLE_RANGES["temp"].bounds())
    a, b = np.float32(h["t_min_C"]), np.float32(h["t_max_C"])
    if not (a >= t_lo and a <= t_hi and b >= t_lo and b <= t_hi and a < b):
        _fail("BAD_TEMP_RANGE", f"[{a}, {b}] degC, plausible within [{t_lo}, {t_hi}]")
    dt = value_dtype(vb)
    values = np.frombuffer(data, dtype=dt, count=h["payload_bytes"] // vb, offset=HEADER_BYTES)
    check_values(values, spec, (a, b))
    return h, values


def check_values(values, spec: ChainSpec | None = None, header_range=None) -> None:
    """The content checks, in the flight order: finite; with spec also every plausible
    range, the ordered pairs, the header range (header_range (t_min_C, t_max_C), when
    given) and the physical checks. Raises TableError. Without header_range this is what
    `<unit>_table_init` runs on the compiled-in defaults (CONTENT_CHECKS)."""
    spec = _spec_of(spec)
    values = np.asarray(values)
    names = value_layout(spec) if spec is not None else None

    def label(i):
        return names[i].label if names else f"value[{i}]"

    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        i = int(bad[0])
        _fail("NONFINITE_VALUE", f"{label(i)} = {values[i]}", i)
    if spec is None:
        return
    lo, hi = _bound_arrays(spec)
    bad = np.flatnonzero(~((values >= lo) & (values <= hi)))
    if bad.size:
        i = int(bad[0])
        _fail("VALUE_OUT_OF_RANGE", f"{label(i)} = {values[i]} {names[i].unit}, plausible "
                                    f"within [{lo[i]}, {hi[i]}]", i)
    for i_lo, i_hi in _ordered_pairs(spec):
        if not values[i_lo] < values[i_hi]:
            _fail("EMPTY_RANGE", f"{label(i_lo)} = {values[i_lo]}, "
                                 f"{label(i_hi)} = {values[i_hi]}", i_lo)
    if header_range is not None:
        a, b = header_range
        t_min, t_max = _temp_range(spec, values)
        if t_min != a or t_max != b:
            _fail("TEMP_RANGE_MISMATCH", f"header [{a}, {b}] degC, sensors [{t_min}, {t_max}]")
    _check_physics(spec, values)


def default_refusal(cs: CoefficientSet) -> str | None:
    """Why `<unit>_table_init` would refuse these coefficients as its compiled-in default
    (the content checks, CONTENT_CHECKS, as `magcal table` applies them: it then serves
    all-NaN coefficients, every correction IMPLAUSIBLE), or None when it accepts them."""
    with np.errstate(over="ignore", invalid="ignore"):
        values = flat_values(cs).astype(value_dtype(cs.spec))
    try:
        check_values(values, cs.spec)
    except TableError as e:
        return e.message
    return None


def _spec_of(spec):
    return spec.spec if isinstance(spec, CoefficientSet) else spec


def coefficient_set(spec: ChainSpec, values, header=None) -> CoefficientSet:
    """A CoefficientSet (float64) holding the flight-type payload values."""
    vals = np.asarray(values, dtype=np.float64)
    sensors, unit_values, k = {}, {}, 0
    for owner, _, blocks in _owners(spec):
        d = unit_values if owner == "unit" else sensors.setdefault(owner, {})
        for b in blocks:
            d[b.name] = vals[k:k + b.size].reshape(b.shape).copy()
            k += b.size
    info = {}
    if header is not None:
        info["table"] = {"serial": header["table_serial"], "created_s": header["created_s"]}
    return CoefficientSet(spec, sensors, unit_values, {}, info)


def decode_table(data, spec=None) -> tuple:
    """(header dict, CoefficientSet) with spec (ChainSpec or CoefficientSet), else
    (header dict, flat values ndarray). Raises TableError as check_table does."""
    spec = _spec_of(spec)
    h, values = check_table(data, spec)
    if spec is None:
        return h, values
    return h, coefficient_set(spec, values, h)


# ---- diff --------------------------------------------------------------------------------


def _fmt(v, dtype) -> str:
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    return str(np.dtype(dtype).type(v)) if np.dtype(dtype) == np.float32 else repr(float(v))


@dataclass(frozen=True)
class Change:
    """One difference between two tables, in physical terms."""

    name: str          # "mmc1 b_poly_nT[0][1]" or "header table_serial"
    old: object
    new: object
    unit: str = ""
    dtype: str = "float32"
    block: str | None = None
    index: int | None = None   # flat payload index

    def __str__(self) -> str:
        u = f" {self.unit}" if self.unit else ""
        if not isinstance(self.old, (float, np.floating)):     # serial, time, id, hashes
            return f"{self.name}: {self.old} -> {self.new}{u}"
        delta = float(self.new) - float(self.old)
        return (f"{self.name}: {_fmt(self.old, self.dtype)} -> {_fmt(self.new, self.dtype)}"
                f"{u} ({delta:+.6g}{u})")


def _as_table(x, spec):
    if isinstance(x, CoefficientSet):
        return encode_table(x, 0, 0, check=False), x.spec
    return bytes(x), spec


def diff_tables(a, b, spec=None) -> list:
    """Changes from table a to table b: header fields, then coefficients by name.

    a, b: table bytes or CoefficientSets (rounded to the flight type first: what changes
    on board). spec (ChainSpec or CoefficientSet) names the values when a and b are bytes;
    without it values are named value[i]. Both must decode (TableError otherwise).
    """
    spec = _spec_of(spec)
    ta, spec_a = _as_table(a, spec)
    tb, spec_b = _as_table(b, spec)
    spec = spec_a or spec_b
    ha, va = check_table(ta, None)
    hb, vb = check_table(tb, None)
    changes = []
    for f in HEADER_FIELDS:
        if f.name in ("magic",):
            continue
        if ha[f.name] != hb[f.name]:
            old, new = ha[f.name], hb[f.name]
            if f.name == "unit_id":
                old, new = ha["unit_id_text"], hb["unit_id_text"]
            elif f.code == "f":
                old, new = np.float32(old), np.float32(new)
            elif f.name.endswith("hash"):
                old, new = f"0x{old:08x}", f"0x{new:08x}"
            unit = "degC" if f.code == "f" else ("s" if f.name == "created_s" else "")
            changes.append(Change(f"header {f.name}", old, new, unit))
    if ha["layout_hash"] != hb["layout_hash"] or ha["value_bytes"] != hb["value_bytes"] \
            or va.size != vb.size:
        return changes      # different structures: the values do not correspond
    names = None
    if spec is not None:
        check_table(ta, spec)    # the names are only right for the chain they are for
        check_table(tb, spec)
        names = value_layout(spec)
    differ = np.flatnonzero(va.view(f"<u{va.itemsize}") != vb.view(f"<u{vb.itemsize}"))
    dt = "float32" if va.dtype == np.float32 else "float64"
    for i in differ:
        i = int(i)
        if names:
            info = names[i]
            changes.append(Change(info.label, va[i], vb[i], info.unit, dt, info.block.name, i))
        else:
            changes.append(Change(f"value[{i}]", va[i], vb[i], "", dt, None, i))
    return changes


# ---- parts -------------------------------------------------------------------------------


def chunk_table(data, max_bytes: int) -> list:
    """Split a table into numbered parts of at most max_bytes each (part header, a run
    of table bytes, the part's own CRC-32). Parts may be sent in any order."""
    data = bytes(data)
    if len(data) < HEADER_BYTES + CRC_BYTES or data[:4] != MAGIC:
        raise InputError(None, "not a table: nothing to chunk")
    if len(data) > MAX_U16:
        raise InputError(None, f"table of {len(data)} bytes: parts address at most {MAX_U16}")
    chunk = min(int(max_bytes) - PART_OVERHEAD, len(data), MAX_U16)
    if chunk < 1:
        raise InputError(None, f"parts of {max_bytes} bytes cannot hold any table bytes "
                               f"(part header and CRC take {PART_OVERHEAD})")
    serial = unpack_header(data)["table_serial"]
    count = -(-len(data) // chunk)
    parts = []
    for i in range(count):
        piece = data[i * chunk:(i + 1) * chunk]
        head = PART_STRUCT.pack(PART_MAGIC, serial, len(data), i, count, chunk, len(piece))
        parts.append(head + piece + struct.pack("<I", crc32(head + piece)))
    return parts


def unpack_part(part) -> dict:
    return dict(zip((f.name for f in PART_FIELDS),
                    PART_STRUCT.unpack_from(bytes(part[:PART_HEADER_BYTES]))))


class Reassembler:
    """The flight reassembly and commit, in Python (the same checks, codes and order as
    `<unit>_table_receive_part` / `_commit`): ground tooling and the differential tests."""

    def __init__(self, spec: ChainSpec):
        self.spec = _spec_of(spec)
        self.table_bytes = table_bytes(self.spec)
        self.staging = bytearray(self.table_bytes)
        self.abort()

    def abort(self):
        self.open = False
        self.serial = self.count = self.chunk = 0
        self.seen = set()

    def receive(self, part) -> TableStatus:
        part = bytes(part)
        S = TableStatus
        if len(part) < PART_OVERHEAD:
            return S.PART_TRUNCATED
        if part[:4] != PART_MAGIC:
            return S.PART_BAD_MAGIC
        p = unpack_part(part)
        if len(part) != PART_OVERHEAD + p["part_bytes"]:
            return S.PART_BAD_LENGTH
        if crc32(part[:-CRC_BYTES]) != struct.unpack_from("<I", part, len(part) - 4)[0]:
            return S.PART_BAD_CRC
        if p["table_bytes"] != self.table_bytes:
            return S.PART_TABLE_SIZE
        chunk, count, index = p["chunk_bytes"], p["part_count"], p["part_index"]
        if chunk == 0 or count != -(-self.table_bytes // chunk) or index >= count:
            return S.PART_NUMBERING
        offset = index * chunk
        if p["part_bytes"] != min(chunk, self.table_bytes - offset):
            return S.PART_SIZE
        piece = part[PART_HEADER_BYTES:-CRC_BYTES]
        if self.open:
            if p["table_serial"] != self.serial:
                return S.PART_FOREIGN_SERIAL
            if count != self.count or chunk != self.chunk:
                return S.PART_COUNT_CHANGED
            if index in self.seen:
                same = self.staging[offset:offset + len(piece)] == piece
                return S.PART_REPEATED if same else S.PART_CONFLICT
        else:
            self.open, self.serial, self.count, self.chunk = True, p["table_serial"], count, chunk
            self.seen = set()
        self.staging[offset:offset + len(piece)] = piece
        self.seen.add(index)
        return S.OK

    def commit(self) -> tuple:
        """(status, table bytes or None)."""
        S = TableStatus
        if not self.open:
            return S.NOTHING_STAGED, None
        if len(self.seen) != self.count:
            return S.PARTS_MISSING, None
        table = bytes(self.staging)
        self.open = False
        try:
            h, _ = check_table(table, self.spec)
        except TableError as e:
            return e.status, None
        if h["table_serial"] != self.serial:
            return S.SERIAL_MISMATCH, None
        return S.OK, table


def join_parts(parts, spec: ChainSpec) -> bytes:
    """Reassemble parts (any order) into the table, or raise TableError."""
    r = Reassembler(spec)
    for i, p in enumerate(parts):
        st = r.receive(p)
        if st != TableStatus.OK:
            raise TableError(st, f"part #{i} of the list")
    st, table = r.commit()
    if st != TableStatus.OK:
        raise TableError(st)
    return table


# ---- readable dump -----------------------------------------------------------------------


def _time_text(s: int) -> str:
    if s == 0:
        return "0 (not given)"
    try:
        t = datetime.datetime.fromtimestamp(s, tz=datetime.timezone.utc)
        return f"{s} ({t.strftime('%Y-%m-%dT%H:%M:%SZ')})"
    except (OverflowError, OSError, ValueError):
        return str(s)


def dump_table(data, spec=None, title="table") -> str:
    """Readable text of a table: header fields, then every coefficient with its unit."""
    spec = _spec_of(spec)
    h, values = check_table(data, spec)
    dt = "float32" if values.dtype == np.float32 else "float64"
    lines = [f"magcal coefficient table {title}: {len(bytes(data))} bytes, "
             f"format version {h['format_version']}"]
    shown = {
        "magic": h["magic"].decode("ascii", "replace"),
        "value_bytes": f"{h['value_bytes']} ({dt})",
        "unit_id_hash": f"0x{h['unit_id_hash']:08x}",
        "unit_id": h["unit_id_text"],
        "layout_hash": f"0x{h['layout_hash']:08x}",
        "payload_bytes": f"{h['payload_bytes']} ({values.size} values)",
        "created_s": _time_text(h["created_s"]),
        "t_min_C": f"{np.float32(h['t_min_C'])} degC",
        "t_max_C": f"{np.float32(h['t_max_C'])} degC",
    }
    for f in HEADER_FIELDS:
        lines.append(f"  {f.name:<16} {shown.get(f.name, h[f.name])}")
    lines.append(f"  {'crc32':<16} 0x{h['crc32']:08x}")
    names = value_layout(spec) if spec is not None else None
    owner = None
    for i, v in enumerate(values):
        if names:
            info = names[i]
            if info.owner != owner:
                owner = info.owner
                lines.append(owner)
            name = info.block.name + "".join(f"[{j}]" for j in info.element)
            lines.append(f"  {name:<24} {_fmt(v, dt):>24}  {info.unit}".rstrip())
        else:
            lines.append(f"  value[{i}]{'':<14} {_fmt(v, dt):>24}")
    return "\n".join(lines) + "\n"


# ---- the flight C: context for templates/table.*.j2 --------------------------------------


def _byte_lines(data: bytes, per_line=12) -> list:
    return [", ".join(f"0x{b:02x}" for b in data[i:i + per_line]) + ","
            for i in range(0, len(data), per_line)]


CRC_POLY_REFLECTED = 0xEDB88320   # IEEE 802.3, as zlib.crc32


def _crc_byte_table() -> list:
    """CRC of each byte value (reflected, one byte at a time)."""
    out = []
    for i in range(256):
        c = i
        for _ in range(8):
            c = (c >> 1) ^ (CRC_POLY_REFLECTED if c & 1 else 0)
        out.append(c)
    return out


def table_context(cs: CoefficientSet) -> dict:
    """Everything table.h.j2 / table.c.j2 need beyond codegen.template_context(cs)."""

    spec = cs.spec
    ft = spec.unit.float_type
    dt = value_dtype(spec)
    nv = n_values(spec)
    tb = table_bytes(spec)
    if tb > MAX_U16:
        raise InputError(None, f"a table of {tb} bytes is too long for 16-bit part numbering")

    def fields(fs, offsets):
        return [{"name": f.name, "NAME": f.name.upper(), "offset": offsets[f.name],
                 "size": f.size, "type": f.type_name, "doc": f.doc} for f in fs]

    t_lo, t_hi = PLAUSIBLE_RANGES["temp"].bounds()
    default = encode_table(cs, serial=0, created_s=0, check=False)
    return {
        "magic": list(MAGIC), "magic_text": MAGIC.decode(),
        "part_magic": list(PART_MAGIC), "part_magic_text": PART_MAGIC.decode(),
        "format_version": FORMAT_VERSION,
        "header_bytes": HEADER_BYTES, "header_fields": fields(HEADER_FIELDS, HEADER_OFFSETS),
        "part_header_bytes": PART_HEADER_BYTES,
        "part_fields": fields(PART_FIELDS, PART_OFFSETS),
        "crc_bytes": CRC_BYTES,
        "value_bytes": dt.itemsize, "n_values": nv, "payload_bytes": nv * dt.itemsize,
        "table_bytes": tb,
        "unit_id_hash": f"0x{unit_id_hash(spec.unit.id):08x}",
        "unit_id_field": list(unit_id_field(spec.unit.id)),
        "errors": [{"name": n, "value": i, "reason": r} for i, (n, r) in enumerate(ERRORS)],
        "init_mark": f"0x{MANAGER_INIT_MARK:08x}",
        # the all-NaN <unit>_coeffs_t and <unit>_table_prepared_t of a manager not
        # initialised (and of init's fallback): their constant memory
        "nan_bytes": (nv + n_prepared_values(spec)) * dt.itemsize,
        "segments": [{"first": s.first, "count": s.count, "lo": c_literal(s.lo, ft),
                      "hi": c_literal(s.hi, ft),
                      "what": f"{s.owner} {s.block.name}"
                              + (f"[{s.order}]" if s.order is not None else "")}
                     for s in segments(spec)],
        "temp_index": [{"sensor": s.name, "t_min": i, "t_max": j}
                       for s, (i, j) in zip(_temp_sensors(spec), _temp_indices(spec))],
        "no_temp_sensors": [s.name for s in spec.unit.sensors if s not in _temp_sensors(spec)],
        "ordered_pairs": [{"lo": i, "hi": j, "what": f"{value_layout(spec)[i].label} < "
                                                       f"{value_layout(spec)[j].label}"}
                          for i, j in _ordered_pairs(spec)],
        "matrices": [{"sensor": m.sensor, "m_poly": m.m_poly, "orders": m.orders,
                      "points": m.points, "t_ref": m.t_ref or 0, "t_min": m.t_min or 0,
                      "t_max": m.t_max or 0}
                     for m in _matrix_indices(spec)],
        "rotation_index": _rotation_index(spec),
        "det_lo": c_literal(PHYSICAL_LIMITS.det_M_lo, ft),
        "det_hi": c_literal(PHYSICAL_LIMITS.det_M_hi, ft),
        "rotation_tol": c_literal(PHYSICAL_LIMITS.rotation_tol, ft),
        "no_temp_range": [c_literal(v, ft) for v in NO_TEMP_RANGE_C],
        "header_temp_lo": c_literal(t_lo, "float32"),
        "header_temp_hi": c_literal(t_hi, "float32"),
        "crc_lines": [", ".join(f"0x{c:08x}u" for c in _crc_byte_table()[i:i + 6]) + ","
                      for i in range(0, 256, 6)],
        "default_lines": _byte_lines(default),
        "default_crc": f"0x{struct.unpack_from('<I', default, len(default) - 4)[0]:08x}",
    }
