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

from generator.io.telemetry import Telemetry

REF_VECTOR = ("ref_x_nT", "ref_y_nT", "ref_z_nT")


def kept_rows(tel: Telemetry, rows: np.ndarray) -> Telemetry:
    """The file restricted to these rows (in order): the same path, so the same file."""
    return Telemetry(tel.path, {c: v[rows] for c, v in tel.columns.items()},
                     tel.line_numbers[rows], dict(tel.meta), list(tel.comments))


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
        from generator.io.telemetry_csv import _rows_at_most, concat_chunks, usable_rows
        self.path, self.unit, self.regressors = path, unit, list(regressors)
        counts = {c for s in unit.sensors for c in s.count_columns}
        usable = {s.name: [] for s in unit.sensors}
        held = {}

        def reduced(chunks):
            for c in chunks:
                if not held:
                    held["names"] = list(c.columns)
                    held["meta"], held["comments"] = dict(c.meta), list(c.comments)
                for s in unit.sensors:
                    usable[s.name].append(usable_rows(c, s))
                keep = ["time_s"] + [k for k in _full_names(c.columns) if k not in counts]
                yield Telemetry(c.path, {k: c.columns[k] for k in keep}, c.line_numbers)
        if tel is not None:
            full = next(reduced([tel]))
        else:
            full = concat_chunks(reduced(_chunks(path, unit, self.regressors)),
                                 rows=_rows_at_most(path))
        self.names = held["names"]
        self.meta, self.comments = held["meta"], held["comments"]
        self._full = full.columns
        self.time_s = self._full["time_s"]
        self._usable = {k: np.concatenate(v) if len(v) != 1 else v[0]
                        for k, v in usable.items()}

    @property
    def n(self) -> int:
        return int(self.time_s.shape[0])

    @property
    def columns(self) -> dict:
        """Every column name of the file (in order); the values of the held ones over
        every row, None for the others (read them with pieces or blocked)."""
        return {c: self._full.get(c) for c in self.names}

    def has(self, *names) -> bool:
        return all(n in self.names for n in names)

    def full_column(self, name):
        """A held column over every row (None when not held or not in the file)."""
        return self._full.get(name)

    def usable_of(self, spec) -> np.ndarray:
        """(n,) bool: the rows preprocess marks usable for this sensor."""
        return self._usable[spec.name]

    def pieces(self, rows: int):
        """The file again, every column, in consecutive pieces of `rows` rows (the last
        shorter): read from the file chunk by chunk, one piece held at a time."""
        from generator.io.telemetry_csv import concat_chunks
        buf, have = [], 0
        for c in _chunks(self.path, self.unit, self.regressors):
            buf.append(c)
            have += c.n
            while have >= rows:
                whole = concat_chunks(buf, rows=have)
                buf = [kept_rows(whole, np.arange(rows, have))] if have > rows else []
                have -= rows
                yield kept_rows(whole, np.arange(rows))
                del whole
        if have:
            yield concat_chunks(buf, rows=have)

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

    def usable_of(self, spec) -> np.ndarray:
        return self.file.usable_of(spec)

    def sample_view(self) -> Telemetry:
        return self._sample
