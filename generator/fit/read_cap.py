"""What `magcal fit` reads of long telemetry: above READ_CAP_ROWS rows, contiguous blocks of
consecutive rows drawn at random over the files (systematic cluster sampling, seed fixed;
fit.blocks), read STREAMING (io.telemetry_csv.iter_telemetry: every row parsed and checked,
only the drawn blocks' rows kept), and after the fit one more streaming pass over every
row of every file: the residual of each sensor's calibration over all its usable samples
(fit.samples.residual_sums). Memory is then bounded whatever the files' length: the rows
read are at most the cap, and the passes hold one chunk or piece at a time.

Each file's kept rows are ONE Telemetry (its rows in time order, gaps where blocks were
left out, its own line numbers), so the screens, segments, hold-out groups, the fit's own
subsample (fit.samples._gather), the coil and boom fits and the checks run on them
unchanged. Under the cap (and with max_samples 0) every row is read as before and nothing
changes. docs/fit_samples.md, "What the fit reads".
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from generator.errors import InputError
from generator.fit.blocks import (MIN_BLOCK_ROWS, MIN_BLOCKS, block_rows_of_period, block_runs,
                                  draw_blocks, median_period_s)
from generator.fit.samples import MAX_FIT_SAMPLES
from generator.io.telemetry import Telemetry

# The rows the fit reads at most, per READ_ROWS_PER_SAMPLE of its sample cap: the fit keeps
# at most max_samples usable samples per sensor (fit.samples.MAX_FIT_SAMPLES, 200,000, and
# why), so reading more rows than that only serves the rows it cannot use (magnetorquer
# current on, no reference, temperatures rejected) and the spread of its own subsample.
# With READ_ROWS_PER_SAMPLE = 2 the fit still keeps its full cap of usable samples where
# at least half the rows read are usable (the per-file counts say when not), and its
# subsample is one sample in two of the rows read. The blocks spread the rows over the
# files' time: at 1 Hz, 400,000 rows are ~66 blocks of 100 min (fit.blocks: long enough for
# a board's approach and a settled 10-min hold), one per ~1.5 % of a year's telemetry; what
# the blocks leave out is checked after the fit on every row (every_row_residual). A
# --max-samples above the default raises the rows read with it (READ_ROWS_PER_SAMPLE x
# max_samples); one below thins the fit's subsample only (the rows read stay at the
# default's). The number comes from this argument, not from a timing; the memory it costs:
# bench/bench_io.py.
READ_ROWS_PER_SAMPLE = 2
READ_CAP_ROWS = READ_ROWS_PER_SAMPLE * MAX_FIT_SAMPLES
# fixed seed of the blocks (with nothing else: the same files give the same blocks)
READ_SEED = 20
# rows per piece of the every-row pass: the temperature screen runs over a piece as the fit
# runs it over a file (a running median of 5 samples and statistics of the piece's
# deviations: the same rule, applied to 131,072 rows at a time); a piece holds every
# column (~32 x 8 B a row) and the sensor's per-row arrays, ~100 MB at most
EVERY_ROW_PIECE = 1 << 17


def read_cap_rows(max_samples: int, max_rows=None) -> int:
    """The rows the fit reads at most (0: every row): max_rows when given (whole number >=
    0), else READ_CAP_ROWS or READ_ROWS_PER_SAMPLE x max_samples, the larger; 0 when
    max_samples is 0 (every sample, so every row)."""
    if max_rows is not None:
        if isinstance(max_rows, bool) or not isinstance(max_rows, (int, np.integer)) \
                or max_rows < 0:
            raise InputError("max_rows", f"fit: max_rows must be a whole number >= 0 (0: "
                                         f"every row), got {max_rows!r}")
        return int(max_rows)
    if not max_samples:
        return 0
    return max(READ_CAP_ROWS, READ_ROWS_PER_SAMPLE * int(max_samples))


@dataclass
class FileRead:
    """What the fit read of one file above the cap."""
    path: str
    rows: int                 # data rows of the file (every row parsed and checked)
    rows_read: int            # rows of its drawn blocks (kept)
    blocks: int               # blocks drawn in it
    span_s: tuple | None = None    # (first, last) time_s of its rows (None: no row)
    columns: tuple = ()            # its column names (io.recordings.StreamedRepeats)


@dataclass
class ReadCap:
    """The read cap's figures (None under the cap): the files in order, the note."""
    cap_rows: int
    block_rows: int
    seed: int
    files: list = field(default_factory=list)      # FileRead, one per data file
    note: str = ""


def rows_of(tel: Telemetry, rows) -> Telemetry:
    """The file restricted to these rows (in order): the same path, meta and line
    numbers."""
    return Telemetry(tel.path, {c: v[rows] for c, v in tel.columns.items()},
                     tel.line_numbers[rows], dict(tel.meta), list(tel.comments))


def pieces_of(chunks, rows: int):
    """Validated telemetry chunks (iter_telemetry's, in file order) regrouped into
    consecutive pieces of `rows` rows (the last shorter), one piece held at a time."""
    from generator.io.telemetry_csv import concat_chunks
    buf, have = [], 0
    for c in chunks:
        buf.append(c)
        have += c.n
        while have >= rows:
            whole = concat_chunks(buf, rows=have)
            buf = [rows_of(whole, np.arange(rows, have))] if have > rows else []
            have -= rows
            yield rows_of(whole, np.arange(rows))
            del whole
    if have:
        yield concat_chunks(buf, rows=have)


def _chunks(path, unit):
    """The file's validated chunks (io.telemetry_csv.iter_telemetry); the field reference
    (io.orbit.attach_field_reference: row by row, the field model along a track, Kp) is
    attached to what is kept of them, as read_telemetry attaches it to the whole file."""
    from generator.io.telemetry_csv import iter_telemetry
    yield from iter_telemetry(path, unit)


def _first_chunk(path, unit) -> Telemetry:
    from generator.io.telemetry_csv import iter_telemetry
    it = iter_telemetry(path, unit)
    try:
        return next(it)
    finally:
        it.close()


def _rows_bound(path, first: Telemetry) -> int | None:
    """An upper bound on the data rows of a file, exact for a Parquet file and for a CSV
    with no comment or blank line after its header: io.telemetry_csv._rows_at_most less
    the lines before the first data row (first: the file's first chunk) and the line break
    that ends the file."""
    from generator.io.telemetry_csv import _rows_at_most
    from generator.io.telemetry_parquet import is_parquet
    b = _rows_at_most(path)
    if b is None or is_parquet(path) or not first.n:
        return b
    b -= int(first.line_numbers[0]) - 1
    try:
        with open(path, "rb") as f:
            f.seek(-1, 2)
            b -= f.read(1) in (b"\n", b"\r")    # LF, CR LF or an old Mac's CR
    except OSError:
        pass
    return max(b, first.n)


def _read_whole(path, unit, progress) -> Telemetry:
    """read_telemetry with the checks and lines the fit gives every file."""
    from generator.io.orbit import describe, require_field_reference
    from generator.io.telemetry_csv import read_telemetry
    tel = read_telemetry(path, unit)
    progress(f"read {path}: {tel.n} samples, {len(tel.columns)} columns")
    require_field_reference(tel)          # ICD section 4: orbit data need the model
    if "field_reference" in tel.meta:     # ICD section 4: |B| from the field model
        progress(f"{path}: {describe(tel.meta['field_reference'])}")
    return tel


def read_for_fit(unit, paths, max_samples: int, progress, max_rows=None):
    """(telemetries, ReadCap or None): the data files as the fit takes them. At or under
    the read cap (read_cap_rows; the files' rows bounded by io.telemetry_csv._rows_at_most,
    summed), or when a coil study is among the files (its whole-file rules), every file is
    read whole, as before (None). Above it: blocks of L rows (fit.blocks.block_rows_of_period
    at the files' shortest median sample period, from their first chunks) drawn over all
    the files' blocks in order (fit.blocks.draw_blocks, seed READ_SEED), each file read
    streaming and only its drawn rows kept, as one Telemetry; a file with no block drawn is
    left out of the fit (the every-row pass still covers it). A cap below one block is
    InputError naming --max-samples."""
    from generator.io.coil_study import is_coil_study
    from generator.io.orbit import attach_field_reference, describe, require_field_reference
    from generator.io.telemetry_csv import _rows_at_most, concat_chunks
    R = read_cap_rows(max_samples, max_rows)
    bounds = [_rows_at_most(p) for p in paths]
    if not R or any(b is None for b in bounds) or sum(bounds) <= R:
        return [_read_whole(p, unit, progress) for p in paths], None
    bounds, dts = [], []
    for p in paths:           # one first chunk at a time (hundreds of files: not all held)
        c = _first_chunk(p, unit)
        if is_coil_study(c):         # its whole-file rules (io.coil_study.check_file)
            return [_read_whole(p, unit, progress) for p in paths], None
        bounds.append(_rows_bound(p, c))
        dts.append(median_period_s(c.time_s))
        del c
    if sum(bounds) <= R:
        return [_read_whole(p, unit, progress) for p in paths], None
    dts = [d for d in dts if d is not None]
    L = block_rows_of_period(min(dts) if dts else 1.0, R)
    if R < L:
        what = "--max-samples" if max_rows is None else "max_rows"
        raise InputError(paths[0] if len(paths) == 1 else what,
                         f"{what}: the fit reads at most {R:,} rows, below one block of "
                         f"{L:,} consecutive rows: give a cap that reads at least {L:,} "
                         "rows, or --max-samples 0 for every row")
    m, _, (draws, _), _ = draw_blocks(bounds, [], R, L, READ_SEED)
    tels, reads = [], []
    for (f, picks), path, bound in zip(draws, paths, bounds):
        runs = block_runs(bound, picks, L)
        want = np.concatenate(runs) if runs else np.zeros(0, int)
        a, span, names = 0, [None, None], ()

        def picked():
            """Every chunk of the file (every row parsed and checked), each cut to its
            drawn rows (maybe none): concat_chunks fills the file's columns once."""
            nonlocal a, names
            for c in _chunks(path, unit):
                if c.n:
                    span[0] = float(c.time_s[0]) if span[0] is None else span[0]
                    span[1] = float(c.time_s[-1])
                names = names or tuple(c.columns)
                lo, hi = np.searchsorted(want, [a, a + c.n])
                yield rows_of(c, want[lo:hi] - a)
                a += c.n
        tel = attach_field_reference(concat_chunks(picked(), rows=len(want)), unit)
        n_blocks = sum(1 for r in runs if len(r) and r[0] < a)    # blocks with rows
        reads.append(FileRead(str(path), int(a), int(tel.n), int(n_blocks),
                              tuple(span) if span[0] is not None else None, names))
        progress(f"read {path}: {a:,} rows, kept {tel.n:,} in {n_blocks} blocks of "
                 f"{L:,} consecutive rows (the fit's read cap {R:,})")
        if tel.n:
            require_field_reference(tel)      # ICD section 4: orbit data need the model
            if "field_reference" in tel.meta:
                progress(f"{path}: {describe(tel.meta['field_reference'])}")
            tels.append(tel)
        del tel
    n_all = sum(r.rows for r in reads)
    n_read = sum(r.rows_read for r in reads)
    m = sum(r.blocks for r in reads)
    left = [r.path for r in reads if not r.rows_read]
    few = (f"; only {m} blocks, fewer than the {MIN_BLOCKS} the cap is designed for (a cap "
           f"of at least {MIN_BLOCKS * MIN_BLOCK_ROWS:,} rows keeps them)"
           if m < MIN_BLOCKS else "")
    note = (f"read cap: {n_all:,} rows in {len(reads)} file(s); the fit read {n_read:,} in "
            f"{m} blocks of {L:,} consecutive rows"
            f"{' (fewer at the end of a file)' if n_read < m * L else ''} drawn at "
            f"random over all the files' blocks in order (seed fixed; cap {R:,} rows, "
            f"--max-samples 0 reads every row){few}"
            + (f"; {len(left)} file(s) had no block drawn and are left out of the fit "
               f"(not of the residual over every row): {', '.join(left)}" if left else "")
            + "; the screens, segments and the fit's own subsample run on the rows read; "
              "the residual over all usable samples (stats all_samples_residual_nT) is "
              "computed on every row of every file")
    progress(note)
    if not tels:
        raise InputError(paths[0], "the read cap drew no rows (every file empty?)")
    return tels, ReadCap(R, L, READ_SEED, reads, note)


def _file_note(r: FileRead, L: int) -> str:
    return (f"{r.path}: {r.rows:,} rows; the fit read {r.rows_read:,} in {r.blocks} blocks of "
            f"{L:,} consecutive rows drawn at random (seed fixed); --max-samples 0 reads "
            "every row")


def every_row_residual(unit, paths, cals, piece_rows: int = EVERY_ROW_PIECE,
                       repeats=None) -> dict:
    """{sensor: stats all_samples_residual_nT}: each calibration of cals applied to EVERY
    usable sample of every row of the files, one streaming pass (pieces of piece_rows
    rows, one held at a time): per piece and sensor the samples as the fit takes them
    (fit.samples.fit_data_from, the SET/RESET gyro compensation of the fit where it is
    on, fit.samples.usable_samples: the temperature screen over the piece) and the sums of
    fit.samples.residual_sums, the one definition of that residual; n_not_in_fit against
    the fit's stats samples_used. repeats: an io.recordings.StreamedRepeats fed every
    piece, in the same pass."""
    from generator.fit.samples import (fit_data_from, residual_figures, residual_sums,
                                       usable_samples)
    from generator.fit.setreset_fit import _rates_of, compensate_references
    from generator.io.telemetry_csv import preprocess
    sums = {n: [0.0, 0, 0.0, 0] for n in cals}

    def pieces(path):
        return pieces_of(_chunks(path, unit), piece_rows)

    from generator.io.orbit import attach_field_reference
    for j, path in enumerate(paths):
        for tel in pieces(path):
            if repeats is not None:
                repeats.add(j, tel)
            tel = attach_field_reference(tel, unit)    # row by row: as on the whole file
            pre = preprocess(tel, unit, sensors=list(cals))
            for name, cal in cals.items():
                if name not in pre:
                    continue
                d = fit_data_from(tel, pre[name], unit)
                sr = cal.stats.get("set_reset_compensation") or {}
                if sr.get("enabled"):
                    d, = compensate_references([d], [_rates_of(tel)],
                                               float(sr["sr_comp_s_per_deg"]))
                use, ref, norm = usable_samples(d)[:3]
                residual_sums(cal, d, np.flatnonzero(use), ref, norm, sums[name])
                del d, use, ref, norm
            del pre, tel
    return {n: residual_figures(s, int(cals[n].stats.get("samples_used", 0)))
            for n, s in sums.items() if s[3]}


def check_every_row(unit, paths, cals, cap: ReadCap | None, info: dict, progress) -> None:
    """Above the read cap (cap not None): the read cap's note in the fit's notes, per file
    "rows" and "rows_read" in every sensor's stats files entries (and the file's line in
    its notes), and every sensor's stats all_samples_residual_nT (and note) over every row
    of every file (every_row_residual; it replaces the figures over the rows read).
    Nothing under the cap."""
    if cap is None:
        return
    from generator.fit.samples import record_all_samples_residual
    info["notes"].append(cap.note)
    by_path = {r.path: r for r in cap.files}
    for cal in cals.values():
        for e in cal.stats.get("files", []):
            r = by_path.get(str(e.get("source")))
            if r is not None:
                e["rows"], e["rows_read"] = r.rows, r.rows_read
    file_notes = [_file_note(r, cap.block_rows) for r in cap.files]
    for cal in cals.values():
        cal.stats.setdefault("notes", []).extend(file_notes)
    progress("every row: the calibrations applied to every usable sample of every file")
    from generator.io.recordings import StreamedRepeats, repeated_rows_warnings
    repeats = StreamedRepeats(paths, [r.span_s for r in cap.files],
                              [r.columns for r in cap.files])
    res = every_row_residual(unit, paths, cals, repeats=repeats)
    for w in repeated_rows_warnings(None, repeats.findings()):   # over every row
        info["notes"].append(w)
        progress(w)
    for n, v in res.items():
        record_all_samples_residual(cals[n], None, say=progress, res=v,
                                    where=" (every row of every file)")
