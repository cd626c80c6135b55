"""Telemetry in Parquet (pyarrow): the ICD section 2 columns in a columnar file, for long
recordings.

The same columns as the ICD CSV (time_s, the sensors' count and temperature columns,
channels), one numeric column each (integers or floats); a null is a missing value, as an
empty CSV cell is. The file's key-value metadata plays the part of the CSV's '# key: value'
lines (e.g. unit). A column of any type but integers and floats (string, binary, bool,
timestamp, ...) that the chain does not name (is_named) is
text: left out, listed in `text` (its type says it is no number, as a CSV column of text
cells is left out). This module only turns the file into blocks of float64 values: the
validation (header, time order, counts, physical ranges) is the CSV reader's, fed with
these blocks (io.telemetry_csv.iter_telemetry), so both formats pass the same checks and
give the same messages; a fault is named by its data row (1-based) where the CSV names
the line.
"""

from __future__ import annotations

import numpy as np

from generator.errors import InputError
from generator.io.arrow_np import integers, nulls, to_float64

MAGIC = b"PAR1"
# integers a float64 holds exactly: |i| <= 2^53 (53-bit significand); the telemetry
# checks then judge the value (io.telemetry_csv: counts in the part's range, any cell
# within 1e15)
EXACT_INT = 2**53
# bytes a column's buffered input stream reads at a time (one page is typically ~1 MiB;
# 64 KiB reads keep 32 columns' buffers at 2 MiB whatever the row group's size)
STREAM_BUFFER = 1 << 16


def is_parquet(path) -> bool:
    """True when the file starts with Parquet's magic bytes (a CSV never does: its first
    line is a comment or a header naming time_s)."""
    try:
        with open(path, "rb") as f:
            return f.read(4) == MAGIC
    except OSError:
        return False           # the CSV reader reports the unreadable file


class ParquetTelemetry:
    """An open Parquet telemetry file: names (of the numeric columns, order kept), text
    ({name: type} of the text columns left out), meta, and blocks().

    is_named(name): True for a column the chain reads (io.telemetry_csv.named_columns);
    a string or binary column is text where it is False, bad input where it is True.
    Without it every column must be numeric."""

    def __init__(self, path, is_named=None):
        import pyarrow as pa
        import pyarrow.parquet as pq

        self.path = path
        try:
            # streaming, not prefetching: pre_buffer (the default) reads whole row groups
            # ahead and keeps them, and so does iter_batches' thread pool; a buffered stream
            # reads the column chunks page by page (measured: peak RSS flat from 3x10^5 to
            # 4.8x10^6 rows, host_tests/test_stream_memory.py; prefetching grew 94 -> 220 MiB)
            self._file = pq.ParquetFile(path, pre_buffer=False, buffer_size=STREAM_BUFFER)
        except (OSError, pa.ArrowException, ValueError) as e:
            raise InputError(path, f"not a readable Parquet file: {e}") from None
        schema = self._file.schema_arrow
        self.num_rows = self._file.metadata.num_rows
        self.names, self.text = [], {}
        for field in schema:
            t = field.type
            numeric = pa.types.is_integer(t) or pa.types.is_floating(t)
            if is_named is not None and not numeric and not is_named(field.name):
                # not numbers (text, bool, timestamps, ...) in a column the chain does not
                # read: left out with a note, as a CSV's text column (review 20f N5)
                self.text[field.name] = str(t)
                continue
            self.names.append(field.name)
            if not (pa.types.is_integer(t) or pa.types.is_floating(t)):
                raise InputError(path, f"Parquet column of type {t}: telemetry columns hold "
                                       "numbers (integers or floats)", column=field.name)
        raw = schema.metadata or {}
        self.meta = {}
        for k, v in raw.items():
            try:
                key, value = k.decode("utf-8"), v.decode("utf-8").strip()
            except UnicodeDecodeError:
                continue
            if not key.startswith(("pandas", "ARROW:")):      # writers' own bookkeeping
                self.meta[key] = value

    def blocks(self, rows_per_block: int):
        """(first row number (1-based), (n, ncol) float64 values) per block; a null is NaN.
        A NaN or infinite value stored in the file is bad input (InputError naming its row
        and column), as a literal nan/inf cell is in a CSV."""
        import pyarrow as pa

        first = 1
        try:
            batches = self._file.iter_batches(batch_size=max(1, int(rows_per_block)),
                                             columns=self.names if self.text else None,
                                             use_threads=False)
            for batch in batches:
                n = batch.num_rows
                values = np.empty((n, len(self.names)))
                for j, name in enumerate(self.names):
                    col = batch.column(j)
                    if pa.types.is_integer(col.type):
                        v = self._exact(col, name, first)
                    else:
                        v = to_float64(col, copy=False)    # nulls come out as NaN
                    stored = ~np.isfinite(v)
                    if col.null_count:
                        stored &= ~nulls(col)
                    if stored.any():
                        i = int(np.flatnonzero(stored)[0])
                        what = "NaN" if np.isnan(v[i]) else "infinity"
                        raise InputError(self.path, f"{what} is not allowed; store a null "
                                                    "for a missing value",
                                         line=first + i, column=name)
                    values[:, j] = v             # nulls came out as NaN: missing values
                yield first, values
                first += n
        except (OSError, pa.ArrowException) as e:
            raise InputError(self.path, f"Parquet file unreadable after row {first - 1}: "
                                        f"{e}") from None

    def _exact(self, col, name, first) -> np.ndarray:
        """float64 of an integer column (nulls NaN); an integer beyond 2^53, which a float64
        would round (a uint64 above int64's maximum among them), is bad input naming its
        row (1-based data row) and column."""
        ints = integers(col)
        null = nulls(col) if col.null_count else None
        big = ints > EXACT_INT
        if ints.dtype.kind == "i":
            big |= ints < -EXACT_INT
        if null is not None:
            big &= ~null
        if big.any():
            i = int(np.flatnonzero(big)[0])
            raise InputError(self.path, f"integer {int(ints[i])} is beyond 2^53 in magnitude: "
                                        "not a telemetry value (a 64-bit float cannot hold "
                                        "it exactly)", line=first + i, column=name)
        v = ints.astype(np.float64)
        if null is not None:
            v[null] = np.nan
        return v
