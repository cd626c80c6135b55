"""Long telemetry files of a capped trace, held by what the trace needs of every row.

Above the trace's cap (trace.subsample) the samples are the rows of the drawn blocks, but
three things run over every row of a file: the lag recursions (the per-file series of
trace.samples.FileSeries: time, temperatures, channels, and which rows are usable), the
draw itself (the rows and the time of every file), and the all-rows figures (the
coefficients applied to every row, in pieces). Holding the whole file for them made the
peak memory grow with the file's length (about 0.8 kB a row on the five-sensor samsat_fm1
unit: 2.9 GB at 300,000 rows). A FileRows holds instead, per row of the whole file:

* the time and the series columns (every column but the sensors' count columns and the
  references; float64, as read: the recursions run over the same values), and
* one byte per sensor: its usable rows (io.telemetry_csv.usable_rows);
* 12 bytes: the row's fingerprint and file line (io.recordings.repeated_rows: rows that
  repeat rows of another file, or of the same file, are warned as under the cap);

the vector references and the position are kept over every row only where the file
carries reference vectors (the reference's slopes run to the neighbouring rows,
samples._ref_rate). The drawn rows are read again (FileRows.blocked: the second pass,
every column of those rows only), and the all-rows figures read the file a third time,
piece by piece (FileRows.pieces: the same pieces as the in-memory file gives, so the
same figures). The file is read by io.telemetry_csv.iter_telemetry (CSV or Parquet, every
check of read_telemetry on every pass).

Files that need the whole file at once are not held this way (stream_ok): a coil study
(its whole-file rules, io.coil_study.check_file) and a file whose reference the field
model computes along its track (io.orbit); those are read whole, as before.
"""

from __future__ import annotations

import numpy as np

from generator.fit.read_cap import pieces_of, rows_of
from generator.io.recordings import row_fingerprints
from generator.io.telemetry import Telemetry

REF_VECTOR = ("ref_x_nT", "ref_y_nT", "ref_z_nT")
# decimal places tried when packing a column: telemetry cells are decimals of a few
# places (flight_6h: 0 to 4); beyond 6 a column is held as float64
MAX_PLACES = 6
PACK_ROWS = 1 << 16          # rows packed at a time by pack()


def _pack_part(v: np.ndarray, places: int):
    """(places, ints) with v == ints / 10**places bit for bit (NaN: the dtype's minimum,
    -0.0: the minimum + 1),
    ints of the narrowest integer type; or (None, a float64 copy) when no places up to
    MAX_PLACES give every value exactly. A CSV cell of d decimals is the double nearest
    k / 10^d, and so is the float64 quotient k / 10^d (IEEE division rounds correctly):
    such cells pack, and the check below makes sure of every value, -0.0 included."""
    v = np.asarray(v, np.float64)
    fin = ~np.isnan(v)
    x = v[fin]
    negz = (x == 0) & np.signbit(x)           # "-0" cells: the dtype's minimum + 1
    tries = [places] + [d for d in range(MAX_PLACES + 1) if d != places]
    for d in tries:
        scale = 10.0 ** d
        with np.errstate(invalid="ignore", over="ignore"):
            k = np.round(x * scale) + 0.0     # + 0.0: -0.0 becomes 0.0, as an integer holds it
        if x.size and not np.abs(k).max() < 2.0 ** 53:
            continue
        back = np.where(negz, -0.0, k / scale)
        if not np.array_equal(back.view(np.int64), x.view(np.int64)):
            continue
        top = float(np.abs(k).max()) if x.size else 0.0
        dtype = next(t for t in (np.int8, np.int16, np.int32, np.int64)
                     if top < np.iinfo(t).max - 1)
        ints = np.full(v.shape, np.iinfo(dtype).min, dtype)
        ints[fin] = np.where(negz, np.iinfo(dtype).min + 1, k).astype(dtype)
        return d, ints
    return None, v.copy()


class PackedColumn:
    """A float64 column held in parts of the narrowest exact form (_pack_part): most
    telemetry cells take 1-2 bytes instead of 8; values() gives the float64 values back
    bit for bit."""

    def __init__(self):
        self.parts, self.n, self._places = [], 0, 0

    def append(self, v) -> None:
        d, a = _pack_part(v, self._places)
        self._places = d if d is not None else self._places
        self.parts.append((d, a))
        self.n += len(a)

    def __len__(self) -> int:
        return self.n

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for _, a in self.parts)

    def values(self) -> np.ndarray:
        out = np.empty(self.n)
        i = 0
        for d, a in self.parts:
            if d is None:
                out[i:i + len(a)] = a
            else:
                part = out[i:i + len(a)]
                np.divide(a, 10.0 ** d, out=part, dtype=np.float64)
                lo = np.iinfo(a.dtype).min
                part[a == lo] = np.nan
                part[a == lo + 1] = -0.0
            i += len(a)
        return out


def pack(v) -> PackedColumn:
    """A whole float64 array as a PackedColumn (in parts of PACK_ROWS rows)."""
    c = PackedColumn()
    v = np.asarray(v, np.float64)
    for a in range(0, max(len(v), 1), PACK_ROWS):
        c.append(v[a:a + PACK_ROWS])
    return c


kept_rows = rows_of      # the file restricted to these rows: the same path, so the same file


def _chunks(path, unit, regressors):
    """The file's validated chunks as read_telemetry's rows are (the field reference of a
    file that carries its own: io.orbit.attach_field_reference, row by row; the unit
    file's regressors: io.formula.add_regressors, row by row)."""
    from generator.io.formula import add_regressors
    from generator.io.orbit import attach_field_reference
    from generator.io.telemetry_csv import iter_telemetry
    for c in iter_telemetry(path, unit):
        yield add_regressors(regressors, attach_field_reference(c, unit))


def stream_ok(path, unit) -> bool:
    """True when the file can be held as a FileRows: not a coil study, no field model
    along a track (see the module docstring); a fault in the first chunk is raised."""
    from generator.io.coil_study import is_coil_study
    from generator.io.orbit import wants_field_model
    from generator.io.telemetry_csv import iter_telemetry
    it = iter_telemetry(path, unit)
    try:
        first = next(it)
    finally:
        it.close()
    return not is_coil_study(first) and not wants_field_model(first, unit)


def _full_names(names) -> list:
    """The columns held over every row: all but the sensors' counts and the references
    (the vector references and the position where the file has reference vectors)."""
    vec = all(c in names for c in REF_VECTOR)
    return [c for c in names if c != "time_s" and not c.startswith("ref_")
            and (vec or c != "position")] + (list(REF_VECTOR) if vec else [])


class FileRows:
    """One telemetry file on disk, held by what a capped trace needs of every row (see the
    module docstring): path, n, time_s, columns (the names, file order; values of the
    held columns), full_column(name), usable_of(sensor), pieces(rows), blocked(mask)."""

    def __init__(self, path, unit, regressors=(), tel: Telemetry | None = None):
        """Reads the file once (or takes the in-memory tel of it, read from path, as
        read_telemetry gives it: its held columns are kept, the rest is not)."""
        self.path, self.unit, self.regressors = path, unit, list(regressors)
        from generator.io.telemetry_csv import usable_rows
        counts = {c for s in unit.sensors for c in s.count_columns}
        usable = {s.name: [] for s in unit.sensors}
        prints, lines = [], []       # io.recordings: each row's fingerprint and line
        self._full = None
        chunks = ([kept_rows(tel, np.arange(a, min(tel.n, a + PACK_ROWS)))
                   for a in range(0, max(tel.n, 1), PACK_ROWS)] if tel is not None
                  else _chunks(path, unit, self.regressors))
        for c in chunks:
            if self._full is None:
                self.names = list(c.columns)
                self.meta, self.comments = dict(c.meta), list(c.comments)
                keep = ["time_s"] + [k for k in _full_names(c.columns) if k not in counts]
                self._full = {k: PackedColumn() for k in keep}
            for k, col in self._full.items():
                col.append(c.columns[k])
            for s in unit.sensors:
                usable[s.name].append(usable_rows(c, s))
            prints.append(row_fingerprints(c))
            lines.append(np.asarray(c.line_numbers, np.uint32))
        self._n = len(self._full["time_s"])
        self.row_fingerprints = np.concatenate(prints)
        self.line_numbers = np.concatenate(lines)
        # one bit a row and sensor
        self._usable = {k: np.packbits(np.concatenate(v)) for k, v in usable.items()}

    @property
    def n(self) -> int:
        return self._n

    @property
    def time_s(self) -> np.ndarray:
        """(n,) float64, unpacked at each call (not kept)."""
        return self._full["time_s"].values()

    @property
    def columns(self) -> dict:
        """Every column name of the file (in order) -> None (the values: full_column,
        pieces or blocked)."""
        return dict.fromkeys(self.names)

    @property
    def nbytes(self) -> int:
        """The bytes held for every row (the packed columns and usable bits)."""
        return (sum(c.nbytes for c in self._full.values())
                + sum(u.nbytes for u in self._usable.values())
                + self.row_fingerprints.nbytes + self.line_numbers.nbytes)

    def has(self, *names) -> bool:
        return all(n in self.names for n in names)

    def full_column(self, name):
        """A held column over every row, unpacked (None when not held or not in the
        file)."""
        c = self._full.get(name)
        return None if c is None else c.values()

    def packed_column(self, name):
        """A held column as held (PackedColumn), None when not held."""
        return self._full.get(name)

    def usable_of(self, spec) -> np.ndarray:
        """(n,) bool: the rows preprocess marks usable for this sensor."""
        return np.unpackbits(self._usable[spec.name], count=self._n).astype(bool)

    def pieces(self, rows: int):
        """The file again, every column, in consecutive pieces of `rows` rows (the last
        shorter): read from the file chunk by chunk, one piece held at a time."""
        return pieces_of(_chunks(self.path, self.unit, self.regressors), rows)

    def blocked(self, mask: np.ndarray) -> "BlockedRows":
        """The kept file of a capped trace: these rows (the drawn blocks) read again with
        every column, the held columns over every row (trace.subsample keep=)."""
        from generator.io.telemetry_csv import concat_chunks
        rows = np.flatnonzero(mask)

        def picked():
            a = 0
            for c in _chunks(self.path, self.unit, self.regressors):
                lo, hi = np.searchsorted(rows, [a, a + c.n])
                a += c.n
                if hi > lo or a >= self.n:
                    yield kept_rows(c, rows[lo:hi] - (a - c.n))
        sample = concat_chunks(picked(), rows=len(rows))
        return BlockedRows(self, mask, sample)


class BlockedRows:
    """A kept file of a capped trace (trace.subsample): the FileRows of the whole file and
    the rows of its drawn blocks with every column (sample_view); what gather_samples
    takes of a BlockedTelemetry, without the whole file's columns."""

    def __init__(self, file: FileRows, sample_rows: np.ndarray, sample: Telemetry):
        self.file, self.sample_rows, self._sample = file, sample_rows, sample
        self.path, self.meta, self.comments = file.path, file.meta, file.comments

    n = property(lambda self: self.file.n)
    time_s = property(lambda self: self.file.time_s)
    columns = property(lambda self: self.file.columns)

    def has(self, *names) -> bool:
        return self.file.has(*names)

    def get(self, name, default=None):
        v = self.file.full_column(name)
        return default if v is None else v

    def full_column(self, name):
        return self.file.full_column(name)

    def packed_column(self, name):
        return self.file.packed_column(name)

    def usable_of(self, spec) -> np.ndarray:
        return self.file.usable_of(spec)

    def sample_view(self) -> Telemetry:
        return self._sample
