"""`magcal apply`'s output side (review 20e: F6, F8, F9c).

F6: an output named *.parquet or *.pq is a Parquet file of the CSV's columns (names as in
the CSV header; a float64 holding exactly the value the CSV cell's text reads back as,
null where the cell is empty; integers as integers; the CSV's comment lines as key-value
metadata), in row groups of a fixed number of rows, atomically; any other name: CSV, as before.
F8: progress lines on long work, at most one every PROGRESS_EVERY_S of wall time (a fake
clock here, no sleeps). F9c: an OSError while writing any output (a full disk) is one line
naming the output and the system's reason, exit 1, nothing left behind.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import REPO
from hardening_fixtures import csv_slice, run
from test_physical_apply import _write_telemetry      # an ICD CSV with missing cells
from generator import cli, pipeline
from generator.errors import OutputError
from generator.flight.coeffs import CoefficientSet
from generator.flight.host import HostUnit
from generator.io import outputs, telemetry_csv
from generator.io.outputs import atomic_file, output_folder

COEFFS = REPO / "generated" / "samsat_fm1" / "coefficients.json"
FLAGS = ["--boom-stowed", "--coils-off", "--at-rest"]


# ---- reading the two outputs back ---------------------------------------------------------


def _read_csv(path):
    """(comment lines without '# ', header, rows of cells) of an apply CSV."""
    lines = Path(path).read_text(encoding="utf-8").split("\n")
    assert lines[-1] == ""
    lines = lines[:-1]
    hi = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    comments = [ln[2:] for ln in lines[:hi]]
    return comments, lines[hi].split(","), [ln.split(",") for ln in lines[hi + 1:]]


def assert_parquet_equals_csv(pq_path, csv_path):
    """The Parquet output holds the CSV output's values bit for bit: every float64 is the
    value its CSV cell reads back as (bit patterns compared), null exactly where the cell
    is empty; integer and text columns equal; metadata = the comment lines."""
    comments, header, rows = _read_csv(csv_path)
    f = pq.ParquetFile(pq_path)
    table = f.read()
    assert table.column_names == header
    assert table.num_rows == len(rows)
    meta = {k.decode(): v.decode() for k, v in (table.schema.metadata or {}).items()}
    assert meta == dict(c.split(": ", 1) for c in comments)
    assert len(meta) == len(comments) >= 3
    cells = list(zip(*rows)) if rows else [()] * len(header)
    for name, col_cells in zip(header, cells):
        col = table.column(name)
        t = col.type
        values = col.to_pylist()
        empty = [c == "" for c in col_cells]
        assert [v is None for v in values] == empty, name
        if pa.types.is_floating(t):
            assert t == pa.float64(), name
            x = col.to_numpy(zero_copy_only=False)
            ref = np.array([float(c) if c else np.nan for c in col_cells], dtype=np.float64)
            ok = ~np.array(empty, dtype=bool)
            assert np.array_equal(x[ok].view(np.uint64), ref[ok].view(np.uint64)), name
        elif pa.types.is_integer(t):
            assert not any(empty), name
            assert values == [int(c) for c in col_cells], name
        else:
            assert pa.types.is_string(t), (name, t)
            assert values == [c or None for c in col_cells], name
    return f


# ---- F6: Parquet output ------------------------------------------------------------------


def test_parquet_output_equals_csv_on_the_shared_campaign(tmp_path, fm1_dir, monkeypatch):
    # small chunks (~3,200 rows each) and row groups of 5,000 rows: a row group is made of
    # parts of chunks (the rest of one chunk carried to the next row group)
    monkeypatch.setattr(telemetry_csv, "CHUNK_BYTES", 1 << 20)
    monkeypatch.setattr(pipeline._ParquetOutput, "ROW_GROUP_ROWS", 5000)
    data = fm1_dir / "thermal_12pos.csv"
    rc, _, err = run(["apply", COEFFS, data, "-o", tmp_path / "out.csv", *FLAGS])
    assert rc == 0, err
    assert err[-1].endswith(f"wrote {tmp_path / 'out.csv'}: CSV, 36,000 rows"), err
    for name in ("out.parquet", "out.PQ"):
        rc, _, err = run(["apply", COEFFS, data, "-o", tmp_path / name, *FLAGS])
        assert rc == 0, err
        assert err[-1].endswith(f"wrote {tmp_path / name}: Parquet, 36,000 rows"), err
        assert (tmp_path / name).read_bytes()[:4] == b"PAR1"
        f = assert_parquet_equals_csv(tmp_path / name, tmp_path / "out.csv")
        sizes = [f.metadata.row_group(i).num_rows for i in range(f.metadata.num_row_groups)]
        assert sizes == [5000] * 7 + [1000]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.PQ", "out.csv", "out.parquet"]


def test_other_suffixes_are_csv_and_say_so(tmp_path, fm1_dir):
    src = tmp_path / "short.csv"
    src.write_text(csv_slice(fm1_dir / "thermal_12pos.csv", rows=50))
    rc, _, err = run(["apply", COEFFS, src, "-o", tmp_path / "a.csv", *FLAGS])
    assert rc == 0, err
    for name in ("a.txt", "a", "a.parquet.csv"):
        rc, _, err = run(["apply", COEFFS, src, "-o", tmp_path / name, *FLAGS])
        assert rc == 0, err
        assert err[-1].endswith(f"wrote {tmp_path / name}: CSV, 50 rows"), err
        assert (tmp_path / name).read_bytes() == (tmp_path / "a.csv").read_bytes()


def test_empty_telemetry_gives_an_empty_parquet_file_with_the_columns(tmp_path, fm1_dir):
    src = tmp_path / "empty.csv"
    src.write_text(csv_slice(fm1_dir / "thermal_12pos.csv", rows=0))
    rc, _, err = run(["apply", COEFFS, src, "-o", tmp_path / "e.csv", *FLAGS])
    assert rc == 0, err
    rc, _, err = run(["apply", COEFFS, src, "-o", tmp_path / "e.parquet", *FLAGS])
    assert rc == 0, err
    f = assert_parquet_equals_csv(tmp_path / "e.parquet", tmp_path / "e.csv")
    assert f.metadata.num_rows == 0


_HOST = {}


def _fm1():
    if "cs" not in _HOST:
        cs = CoefficientSet.load(COEFFS).with_boom_stowed()
        _HOST["cs"], _HOST["host"] = cs, HostUnit(cs)
    return _HOST["cs"], _HOST["host"]


@settings(max_examples=8, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 300),
       chunk_bytes=st.sampled_from([2_000, 20_000, 1 << 20]))
def test_parquet_equals_csv_on_random_files(tmp_path, seed, n, chunk_bytes):
    """Random counts over the parts' whole range (rails, saturation), random temperatures
    and missing cells (test_physical_apply's file writer): statuses, absent samples and
    unselected rows give nulls and flags in every column kind."""
    cs, host = _fm1()
    d = tmp_path / f"h{seed}_{n}_{chunk_bytes}"
    d.mkdir()
    _write_telemetry(d / "t.csv", cs, np.random.default_rng(seed), n=n)
    for out in ("o.csv", "o.parquet"):
        pipeline.apply(cs, d / "t.csv", d / out, host=host, coils_off=True, at_rest=True,
                       collect=False, chunk_bytes=chunk_bytes)
    assert_parquet_equals_csv(d / "o.parquet", d / "o.csv")


def test_a_fault_in_a_late_chunk_leaves_no_parquet_file(tmp_path, fm1_dir):
    text = csv_slice(fm1_dir / "thermal_12pos.csv", rows=3000)
    lines = text.splitlines(keepends=True)
    bad_line = len(lines) - 10
    cells = lines[bad_line - 1].split(",")
    cells[1] = "abc"
    lines[bad_line - 1] = ",".join(cells)
    (tmp_path / "bad.csv").write_text("".join(lines))
    cs, host = _fm1()
    from generator.errors import InputError

    with pytest.raises(InputError, match=f":{bad_line}:"):
        pipeline.apply(cs, tmp_path / "bad.csv", tmp_path / "o.parquet", host=host,
                       coils_off=True, at_rest=True, collect=False, chunk_bytes=20_000)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.csv"]


def _env():
    return dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_during_a_parquet_apply_leaves_nothing(tmp_path, fm1_dir, sig):
    sys.path.insert(0, str(REPO / "bench"))
    from bench_io import write_long_file

    write_long_file(fm1_dir / "thermal_12pos.csv", tmp_path / "long.csv", 400_000)
    out = tmp_path / "out"
    out.mkdir()
    proc = subprocess.Popen([sys.executable, "-m", "generator.cli", "apply", str(COEFFS),
                             str(tmp_path / "long.csv"), "-o", str(out / "o.parquet"), *FLAGS],
                            env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    t0 = time.monotonic()
    while not any(p.name.endswith(".tmp") for p in out.iterdir()):   # writing: mid-work
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < 120, "apply never started writing"
        time.sleep(0.05)
    # a few chunks in: the ParquetWriter is open with row groups written
    t1 = time.monotonic()
    while (out / next(p.name for p in out.iterdir())).stat().st_size == 0 \
            and time.monotonic() - t1 < 60 and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + sig, (proc.returncode, err)
    assert err.strip().splitlines()[-1] in ("magcal: interrupted", "magcal: terminated"), err
    assert "Traceback" not in err and "Exception ignored" not in err, err
    assert list(out.iterdir()) == []


@pytest.mark.slow            # about a minute: two applies of 2x10^5 and 10^6 rows
def test_parquet_output_memory_does_not_grow_with_the_file(tmp_path, fm1_dir):
    """Peak RSS (bench_io.measured: a fresh process) of apply to Parquet on R rows and on
    5 R rows with a fixed chunk: the writer holds one row group (a chunk) at a time, so the
    two differ by less than one chunk's working set (test_stream_memory.py's bound: 10 x
    chunk_bytes, plus 16 MiB of allocator granularity), while the extra output alone
    (31 columns of 8 bytes, 4 x 2x10^5 rows: ~190 MiB before compression) is far above."""
    sys.path.insert(0, str(REPO / "bench"))
    from bench_io import measured, write_long_file

    chunk = 256 * 1024
    rows = 200_000
    bound_MiB = 10 * chunk / 2**20 + 16
    assert 4 * rows * 31 * 8 / 2**20 > 3 * bound_MiB
    peaks = []
    for r in (rows, 5 * rows):
        write_long_file(fm1_dir / "thermal_12pos.csv", tmp_path / f"in{r}.csv", r)
        code = textwrap.dedent(f"""
            from generator import cli, pipeline
            from generator.flight.coeffs import CoefficientSet
            cs = CoefficientSet.load({str(COEFFS)!r}).with_boom_stowed()
            print(pipeline.apply(cs, {str(tmp_path / f'in{r}.csv')!r},
                                 {str(tmp_path / f'out{r}.parquet')!r}, coils_off=True,
                                 at_rest=True, collect=False, chunk_bytes={chunk})["n"])
        """)
        _, peak, rc, out, err = measured([sys.executable, "-c", code], env=_env())
        assert rc == 0, err
        assert int(out.strip()) == r
        assert pq.ParquetFile(tmp_path / f"out{r}.parquet").metadata.num_rows == r
        peaks.append(peak)
        (tmp_path / f"in{r}.csv").unlink()
    print(f"peak RSS {peaks[0]:.1f} MiB ({rows} rows), {peaks[1]:.1f} MiB ({5 * rows} rows)")
    assert peaks[1] - peaks[0] < bound_MiB, (peaks, bound_MiB)


# ---- F8: progress ------------------------------------------------------------------------


class _Clock:
    """A clock that advances `step` seconds each time it is read."""

    def __init__(self, step):
        self.t, self.step, self.reads = 0.0, step, 0

    def __call__(self):
        self.t += self.step
        self.reads += 1
        return self.t


class _Lines:
    quiet = False

    def __init__(self):
        self.lines = []

    def __call__(self, message):
        self.lines.append(message)


def test_progress_lines_at_most_one_per_interval(tmp_path, fm1_dir):
    src = tmp_path / "t.csv"
    src.write_text(csv_slice(fm1_dir / "thermal_12pos.csv", rows=2000))
    cs, host = _fm1()
    total = telemetry_csv._rows_at_most(src)
    assert total >= 2000
    # the clock reads once at the start (t = 1: the first line due at 3.5) and once after
    # each chunk (chunk k at t = 1 + k), one second apart: with an interval of 2.5 s a
    # line comes after chunks 3 (t = 4, next due 6.5), 6, 9, ...: one every 3 chunks
    lines, clock = _Lines(), _Clock(1.0)
    r = pipeline.apply(cs, src, tmp_path / "o.csv", host=host, progress=lines,
                       coils_off=True, at_rest=True, collect=False, chunk_bytes=8_000,
                       progress_every_s=2.5, clock=clock)
    chunks = clock.reads - 1
    assert chunks > 20                           # 2000 rows of ~325 bytes in 8 kB chunks
    rows_lines = [ln for ln in lines.lines if ln.startswith("apply: ")]
    assert len(rows_lines) == chunks // 3
    done = []
    for ln in rows_lines:
        head, _, pct = ln.partition(" rows (")
        n_done, _, of = head[len("apply: "):].partition(" of ~")
        n_done, of = int(n_done.replace(",", "")), int(of.replace(",", ""))
        assert of == total
        assert pct == f"{100.0 * n_done / total:.0f} %)"
        done.append(n_done)
    assert done == sorted(done) and 0 < done[0] and done[-1] <= r["n"] == 2000
    assert lines.lines[-1] == f"wrote {tmp_path / 'o.csv'}: CSV, 2,000 rows"


def test_no_progress_line_within_the_interval_and_none_when_quiet(tmp_path, fm1_dir,
                                                                  monkeypatch):
    src = tmp_path / "t.csv"
    src.write_text(csv_slice(fm1_dir / "thermal_12pos.csv", rows=500))
    cs, host = _fm1()
    lines = _Lines()
    pipeline.apply(cs, src, tmp_path / "o.csv", host=host, progress=lines, coils_off=True,
                   at_rest=True, collect=False, chunk_bytes=8_000, progress_every_s=1000.0,
                   clock=_Clock(1.0))
    assert not [ln for ln in lines.lines if ln.startswith("apply: ")]

    def count_not(path):
        raise AssertionError("the total is counted although nothing is shown")

    monkeypatch.setattr(telemetry_csv, "_rows_at_most", count_not)
    quiet = _Lines()
    quiet.quiet = True
    pipeline.apply(cs, src, tmp_path / "o.csv", host=host, progress=quiet, coils_off=True,
                   at_rest=True, collect=False, chunk_bytes=8_000, progress_every_s=0.5,
                   clock=_Clock(1.0))


def test_progress_through_the_command_line_and_quiet(tmp_path, fm1_dir, monkeypatch):
    src = tmp_path / "t.csv"
    src.write_text(csv_slice(fm1_dir / "thermal_12pos.csv", rows=1000))
    monkeypatch.setattr(telemetry_csv, "CHUNK_BYTES", 8_000)
    monkeypatch.setattr(pipeline, "PROGRESS_EVERY_S", 0.0)     # a line after every chunk
    monkeypatch.setattr(cli._HeldProgress, "HOLD_S", 0.0)      # none held back
    rc, _, err = run(["apply", COEFFS, src, "-o", tmp_path / "o.pq", *FLAGS])
    assert rc == 0, err
    shown = [ln for ln in err if "] apply: " in ln]
    assert shown and all(" of ~" in ln and ln.endswith(" %)") for ln in shown), err
    rc, _, err = run(["apply", COEFFS, src, "-o", tmp_path / "o.pq", *FLAGS, "-q"])
    assert rc == 0 and err == [], err


# ---- F9c: the system refusing to store an output ----------------------------------------


class _FullDisk:
    """A file object whose writes fail as on a full disk once `room` bytes are written."""

    def __init__(self, f, room):
        self.f, self.room = f, room

    def write(self, data):
        n = len(memoryview(data).cast("B")) if not isinstance(data, str) else len(data)
        if n > self.room:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.room -= n
        return self.f.write(data)

    def __getattr__(self, name):
        return getattr(self.f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return self.f.__exit__(*exc)


def _full_disk(monkeypatch, room):
    real = os.fdopen

    def fdopen(fd, *a, **kw):
        return _FullDisk(real(fd, *a, **kw), room)

    monkeypatch.setattr(outputs.os, "fdopen", fdopen)


@pytest.mark.parametrize("name", ["o.csv", "o.parquet"])
@pytest.mark.parametrize("room", [0, 200_000])
def test_full_disk_during_apply_is_one_line_exit_1(tmp_path, fm1_dir, monkeypatch, name,
                                                   room):
    src = tmp_path / "t.csv"
    src.write_text(csv_slice(fm1_dir / "thermal_12pos.csv", rows=3000))
    monkeypatch.setattr(telemetry_csv, "CHUNK_BYTES", 100_000)
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / name).write_text("an earlier output\n")
    _full_disk(monkeypatch, room)
    rc, _, err = run(["apply", COEFFS, src, "-o", tmp_path / "out" / name, *FLAGS, "-q"])
    assert rc == 1, err
    assert err == [f"magcal apply: {tmp_path / 'out' / name}: cannot write the output: "
                   f"No space left on device (ENOSPC)"], err
    # nothing half-written: the earlier output as it was, no temporary file
    assert [p.name for p in (tmp_path / "out").iterdir()] == [name]
    assert (tmp_path / "out" / name).read_text() == "an earlier output\n"


def test_full_disk_in_a_folder_verb_is_one_line_exit_1(tmp_path, monkeypatch):
    real = Path.write_text

    def write_text(self, *a, **kw):
        if ".tmp" in str(self):                   # the output folder being built
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(self, *a, **kw)

    monkeypatch.setattr(Path, "write_text", write_text)
    rc, out, err = run(["generate", COEFFS, "-o", tmp_path / "gen", "-q", "--json"])
    assert rc == 1, err
    message = (f"{tmp_path / 'gen'}: cannot write the output: No space left on device "
               "(ENOSPC)")
    assert err == [f"magcal generate: {message}"], err
    assert json.loads(out) == {"verb": "generate", "exit": 1, "error": message}
    assert list(tmp_path.iterdir()) == []


def test_full_disk_in_a_table_is_one_line_exit_1(tmp_path, monkeypatch):
    _full_disk(monkeypatch, 0)
    rc, _, err = run(["table", COEFFS, "-o", tmp_path / "t.bin", "-q"])
    assert rc == 1, err
    assert len(err) == 1 and "No space left on device (ENOSPC)" in err[0], err
    assert "internal error" not in err[0]
    assert list(tmp_path.iterdir()) == []


def test_atomic_file_errors(tmp_path, monkeypatch):
    # after the caller's writes (flush, fsync, rename): any OSError is the output's
    def eio(fd):
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(outputs.os, "fsync", eio)
    with pytest.raises(OutputError, match="Input/output error .EIO."):
        with atomic_file(tmp_path / "a.txt") as f:
            f.write("x")
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []
    # an OSError of the caller's that is not about the output passes unchanged
    with pytest.raises(FileNotFoundError):
        with atomic_file(tmp_path / "a.txt") as f:
            open(tmp_path / "no such input")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(OutputError, match="File too large"):
        with atomic_file(tmp_path / "a.txt") as f:
            raise OSError(errno.EFBIG, os.strerror(errno.EFBIG))
    assert list(tmp_path.iterdir()) == []


def test_output_folder_errors(tmp_path):
    with pytest.raises(OutputError, match=r"^.*/d: cannot write the output: Disk quota"):
        with output_folder(tmp_path / "d") as folder:
            (folder.tmp / "x").write_text("x")
            raise OSError(errno.EDQUOT, os.strerror(errno.EDQUOT))
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(OutputError, match="Permission denied"):      # a file under it
        with output_folder(tmp_path / "d") as folder:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES),
                                  str(folder.tmp / "x"))
    with pytest.raises(PermissionError):                              # not under it
        with output_folder(tmp_path / "d") as folder:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), "/etc/other")
    assert list(tmp_path.iterdir()) == []
