"""Issue 20 (F4): above the cap, a trace of files on disk holds them by what it needs of
every row (trace.filerows.FileRows), not whole; the trace is the same as with the whole
files held (the same drawn blocks, samples, series, all-rows pieces, coefficients).

Memory: host_tests/test_trace_memory.py (slow)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO
from generator.io.telemetry_csv import read_telemetry
from generator.io.unitfile import load_unit
from generator.trace import subsample as sub
from generator.trace import tracer as tr
from generator.trace.filerows import BlockedRows, FileRows, pack
from generator.trace.samples import PackedSeries, candidate_channels, gather_samples

sys.path.insert(0, str(REPO / "bench"))
from bench_io import write_long_file  # noqa: E402


def _with_blank_cells(path: Path, every: int) -> None:
    """Every `every`-th data row's last cell (a channel) left empty: a dropout the held
    channel must carry through the rows left out the same way in both paths."""
    lines = path.read_text().split("\n")
    first = next(i for i, ln in enumerate(lines) if ln.startswith("time_s"))
    for i in range(first + 1 + every // 2, len(lines) - 1, every):
        lines[i] = lines[i].rsplit(",", 1)[0] + ","
    path.write_text("\n".join(lines))


def _moving(src: Path, dst: Path) -> Path:
    """src with every position 0 and a varying reference (moving): its reference vectors
    get slopes (samples._ref_rate), which run to the neighbouring rows, outside a block
    at its ends."""
    lines = src.read_text().split("\n")
    first = next(i for i, ln in enumerate(lines) if ln.startswith("time_s"))
    head = lines[first].split(",")
    j, k = head.index("position"), head.index("ref_x_nT")
    for i in range(first + 1, len(lines)):
        if lines[i] and not lines[i].startswith("#"):
            cells = lines[i].split(",")
            cells[j] = "0"
            cells[k] = repr(float(cells[k]) + 20.0 * float(np.sin(i / 40.0)))    # a moving field
            lines[i] = ",".join(cells)
    dst.write_text("\n".join(lines))
    return dst


@pytest.fixture(scope="module")
def fm1(fm1_dir):
    return load_unit(fm1_dir / "unit.toml")


@pytest.fixture(scope="module")
def flight_60k(fm1_dir, tmp_path_factory):
    """60,000 rows of flight_6h (5.6 repetitions), a blank channel cell every 997 rows."""
    p = tmp_path_factory.mktemp("fr") / "flight_60k.csv"
    write_long_file(fm1_dir / "flight_6h.csv", p, 60_000)
    _with_blank_cells(p, 997)
    return p


def _same(a, b, what):
    if isinstance(a, dict):
        assert a.keys() == b.keys(), what
        for k in a:
            _same(a[k], b[k], f"{what}.{k}")
    elif isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape and a.dtype == b.dtype, what
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), what
    else:
        assert a == b, what


def _gathered(unit, kept, coils=()):
    channels, _ = candidate_channels(unit, kept, coils)
    notes = []
    S = gather_samples(unit, kept, [0] * len(kept), coils=coils, channels=channels,
                       notes=notes)
    return S, notes, channels


@pytest.mark.parametrize("name,cap", [("flight_60k", 20_000), ("thermal_12pos.csv", 10_000)])
def test_held_file_gives_the_samples_and_series_of_the_whole_file(name, cap, fm1, fm1_dir,
                                                                   flight_60k, tmp_path):
    """The same blocks drawn, and gather_samples gives the same samples (every field) and
    the same per-file series from a FileRows as from the whole file in memory; on the
    orbit file (magnitude rows, blank channel cells held) and on the thermal campaign
    (reference vectors: their slopes run to rows outside the blocks; moving)."""
    path = (flight_60k if name == "flight_60k" else
            _moving(fm1_dir / name, tmp_path / name))
    whole = read_telemetry(path, fm1)
    held = FileRows(path, fm1)
    assert held.n == whole.n and np.array_equal(held.time_s, whole.time_s)
    if name == "flight_60k":
        # what it holds of a row: the time as int32 (whole seconds past 2^15), the
        # temperatures and channels (1-4 decimals, under 2^15 as integers) as int16, one
        # bit a sensor, and the row's fingerprint (uint64) and line (uint32) for
        # io.recordings.repeated_rows; not 8 B a column
        per_row = 4 + 2 * (len(held._full) - 1) + len(fm1.sensors) / 8 + 8 + 4
        assert held.nbytes <= per_row * held.n + 1024
    kw, _, iw = sub.subsample_files([whole], [], cap)
    kh, _, ih = sub.subsample_files([held], [], cap, keep=lambda f, m: f.blocked(m))
    assert iw is not None and iw == ih                     # the same draw, said the same
    assert isinstance(kh[0], BlockedRows) and np.array_equal(kh[0].sample_rows,
                                                             kw[0].sample_rows)
    Sw, nw, cw = _gathered(fm1, kw)
    Sh, nh, ch = _gathered(fm1, kh)
    assert cw == ch and nw == nh
    if name == "flight_60k":
        assert any("empty cells, held" in n for n in nw), "the blank cells must be seen"
    for s in fm1.sensors:
        a, b = Sw[s.name], Sh[s.name]
        assert a.n > 0 and a.n == b.n, s.name
        for f in ("time_s", "file_index", "file_row", "order", "x", "temp_C", "kind", "ref",
                  "norm", "group", "ref_rate", "coil", "rate_frame_dps", "channels", "role",
                  "channel_present"):
            _same(getattr(a, f), getattr(b, f), f"{s.name}.{f}")
        (fa,), (fb,) = a.files, b.files
        assert isinstance(fb, PackedSeries) and not isinstance(fa, PackedSeries)
        assert fa.name == fb.name
        _same(fa.time_s, fb.time_s, "series time")
        _same(fa.temp_C, fb.temp_C, "series temperature")
        _same(fa.channels, fb.channels, "series channels")
    if name == "thermal_12pos.csv":
        assert any(np.any(Sw[s.name].ref_rate) for s in fm1.sensors), "slopes must be seen"


@pytest.mark.parametrize("values,narrow", [
    ([26.5, 26.6, np.nan, -3.25], True),          # decimals of a few places, a blank cell
    ([0.0, -0.0, 1.5], True),                     # -0.0 ("-0" cells): its own marker
    ([0.1 + 0.2, 1.0], False),                    # not the double of a short decimal
    ([3e7 - 2, 3e7], True),                       # a year of seconds: int32
    ([0.0248, -0.0094, 8.017, 23297.8], True),
    ([np.nan, np.nan], True)])
def test_packed_columns_give_the_values_back_bit_for_bit(values, narrow):
    v = np.array(values * 70_001)                 # more than one part of PACK_ROWS rows
    c = pack(v)
    w = c.values()
    assert np.array_equal(w.view(np.int64), v.view(np.int64))
    assert (c.nbytes <= v.nbytes // 2) == narrow


def test_held_file_pieces_are_the_whole_file_pieces(fm1, flight_60k, monkeypatch):
    """The all-rows figures read the file again in the pieces the whole file gives."""
    monkeypatch.setattr(sub, "ALL_ROWS_CHUNK", 17_000)       # 4 pieces, the last shorter
    whole = read_telemetry(flight_60k, fm1)
    pw = list(sub._pieces([whole]))
    ph = list(sub._pieces([FileRows(flight_60k, fm1)]))
    assert [p.n for p in pw] == [p.n for p in ph] == [17_000] * 3 + [60_000 - 51_000]
    for a, b in zip(pw, ph):
        assert a.path == b.path
        _same(a.columns, b.columns, "piece")


def _result(res) -> tuple:
    d = res.to_json()
    d.pop("elapsed_s", None)
    return json.dumps(d, sort_keys=True, default=str), res.coefficients


def test_capped_trace_of_files_on_disk_is_the_trace_of_the_whole_files(fm1, flight_60k,
                                                                       monkeypatch):
    """The trace of the file given by its path (held: FileRows, the whole file read only
    for the baseline fit) is the trace of the same file given whole (Telemetry): the
    same note of the draw, figures and coefficients."""
    kinds = []
    real = tr.subsample_files

    def spy(tels, hold, *a, **k):
        kinds.append(type(tels[0]).__name__)
        return real(tels, hold, *a, **k)
    monkeypatch.setattr(tr, "subsample_files", spy)
    kw = dict(max_samples=20_000, sensors=["mmc1"])
    base = tr.trace(fm1, [read_telemetry(flight_60k, fm1)], **kw)
    assert base.subsample is not None
    held = tr.trace(fm1, [str(flight_60k)], **kw)
    assert kinds == ["Telemetry", "FileRows"]
    a, b = _result(base), _result(held)
    assert a[0] == b[0]
    assert a[1].to_json_dict() == b[1].to_json_dict()


def test_capped_trace_with_a_supplied_baseline_never_reads_a_file_whole(fm1, flight_60k,
                                                                        monkeypatch):
    """With a supplied baseline (no fit) the file on disk is never read whole, and the
    trace is the trace of the whole file given in memory."""
    read = []
    real_read = tr._read
    monkeypatch.setattr(tr, "_read", lambda unit, items: read.append(list(items))
                        or real_read(unit, items))
    kw = dict(max_samples=20_000, sensors=["mmc1"])
    coeffs = REPO / "generated" / "samsat_fm1" / "coefficients.json"
    c_whole = tr.trace(fm1, [read_telemetry(flight_60k, fm1)], coeffs=str(coeffs), **kw)
    c_held = tr.trace(fm1, [str(flight_60k)], coeffs=str(coeffs), **kw)
    assert not any(isinstance(x, str) for r in read for x in r), "read whole: " + str(read)
    a, b = _result(c_whole), _result(c_held)
    assert a[0] == b[0]
    assert a[1].to_json_dict() == b[1].to_json_dict()


# --- N5: --holdout counts toward the cap ----------------------------------------------

def _rows(path, n, t0=0.0):
    from generator.io.telemetry import Telemetry
    return Telemetry(path, {"time_s": t0 + np.arange(n, dtype=float)},
                     np.arange(2, n + 2))


def test_a_cap_too_small_for_a_block_per_role_is_refused():
    """With --holdout files the data's and the holdout's blocks are drawn apart, one at
    least each: a cap below two blocks cannot hold them and exits 2 naming
    --max-samples (before: one block each, over the cap, and a warning)."""
    from generator.errors import InputError
    data, hold = [_rows("d.csv", 50_000)], [_rows("h.csv", 50_000, 1e6)]
    L = sub.block_rows(data + hold, 1_500)
    assert L == 1_000
    with pytest.raises(InputError, match="--max-samples") as e:
        sub.subsample_files(data, hold, 1_500)
    assert f"at least {2 * L:,}" in str(e.value) and "--holdout" in str(e.value)
    kd, kh, info = sub.subsample_files(data, hold, 2 * L)
    assert info["traced"] <= 2 * L and len(kd) == len(kh) == 1


def test_holdout_heavy_files_keep_the_cap():
    """Holdout files with most of the blocks: the data keep one block at least and data
    and holdout together stay within the cap."""
    data, hold = [_rows("d.csv", 1_000)], [_rows("h.csv", 30_000, 1e6)]
    kd, kh, info = sub.subsample_files(data, hold, 3_000)
    assert info["traced"] <= 3_000 and len(kd) == 1 and len(kh) == 1


def test_a_bad_cell_in_a_held_file_exits_2_one_line(fm1_dir, flight_60k, tmp_path, capsys):
    """The held file is checked as read_telemetry checks it (every pass reads through
    io.telemetry_csv.iter_telemetry): a bad cell far into a long file above the cap is
    one line naming the file, line and column, exit 2, no output folder."""
    from generator.cli import main
    lines = flight_60k.read_text().split("\n")
    first = next(i for i, ln in enumerate(lines) if ln.startswith("time_s"))
    k = first + 1 + 50_000
    cells = lines[k].split(",")
    cells[-1] = "8.0x"
    lines[k] = ",".join(cells)
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(lines))
    coeffs = REPO / "generated" / "samsat_fm1" / "coefficients.json"
    rc = main(["trace", str(fm1_dir / "unit.toml"), str(bad), "-o", str(tmp_path / "out"),
               "--coeffs", str(coeffs), "--max-samples", "20000"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err, err
    assert f"bad.csv:{k + 1}" in err and "bus_voltage_V" in err, err
    assert not (tmp_path / "out").exists()
