"""The fit's read cap (generator/fit/read_cap.py, docs/fit_samples.md "What the fit reads"):
above the cap the fit reads blocks of consecutive rows drawn at random over the files,
streaming, says so, and checks its calibration on every row afterwards; at or under the cap
nothing changes. A small cap through max_rows on the shared thermal campaign (36,000 rows,
a sample every 5 s: blocks of MIN_BLOCK_ROWS = 1,000 rows)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from generator.errors import InputError
from generator.fit import read_cap as rc
from generator.fit.blocks import MIN_BLOCK_ROWS
from generator.io.unitfile import load_unit
from generator.pipeline import fit

CAP = 20_000            # rows read of the thermal campaign's 36,000: 20 blocks of 1,000
REPO = Path(__file__).resolve().parent.parent


def _progress(lines):
    return lambda msg: lines.append(str(msg))


@pytest.fixture(scope="module")
def capped(fm1_dir, tmp_path_factory):
    """coefficients.json bytes of the thermal campaign read capped (twice), and the
    progress lines of the first fit."""
    tmp = tmp_path_factory.mktemp("read_cap")
    out, lines = [], []
    for k in range(2):
        cs = fit(fm1_dir / "unit.toml", [fm1_dir / "thermal_12pos.csv"], max_rows=CAP,
                 progress=_progress(lines) if k == 0 else None)
        cs.save(tmp / f"{k}.json")
        out.append((tmp / f"{k}.json").read_bytes())
    return out, lines


def test_blocks_are_drawn_streaming_and_are_whole_blocks(fm1_dir):
    unit = load_unit(fm1_dir / "unit.toml")
    lines = []
    tels, cap = rc.read_for_fit(unit, [fm1_dir / "thermal_12pos.csv"], 200_000,
                                _progress(lines), max_rows=CAP)
    (tel,), (f,) = tels, cap.files
    assert cap.block_rows == MIN_BLOCK_ROWS and cap.cap_rows == CAP
    assert f.rows == 36_000 and f.rows_read == tel.n <= CAP and f.blocks == 20
    # the kept rows: whole runs of consecutive lines of the file, one run per block, in
    # time order (a run of L rows starts at a multiple of L of the data rows)
    row = tel.line_numbers - 4                        # line 4 is the first data row
    starts = np.flatnonzero(np.diff(row, prepend=-2) != 1)
    runs = np.diff(np.append(starts, len(row)))
    assert np.all(np.diff(row) > 0)
    assert np.all(row[starts] % MIN_BLOCK_ROWS == 0)
    # adjacent drawn blocks merge into one run: the runs are whole multiples of a block
    assert np.all(runs % MIN_BLOCK_ROWS == 0) and runs.sum() == 20 * MIN_BLOCK_ROWS
    # spread over the file (systematic: one block in each interval of 36 / 20 blocks)
    blocks = np.unique(row // MIN_BLOCK_ROWS)
    assert len(blocks) == 20 and blocks[0] <= 1 and blocks[-1] >= 34
    assert any("the fit read 20,000 in 20 blocks of 1,000" in m for m in lines), lines


def test_capped_fit_is_deterministic_and_says_so(capped):
    (a, b), lines = capped
    assert a == b                              # seed fixed: the same input, the same bytes
    d = json.loads(a)
    assert any(n.startswith("read cap: 36,000 rows") and "--max-samples 0" in n
               for n in d["fit"]["notes"]), d["fit"]["notes"]
    for name, v in d["fit"]["sensors"].items():
        st = v["stats"]
        (f,) = st["files"]
        assert f["rows"] == 36_000 and f["rows_read"] == f["samples"] == CAP
        assert any(n.startswith(f"{f['source']}: 36,000 rows; the fit read 20,000 in 20 "
                                "blocks of 1,000 consecutive rows drawn at random")
                   for n in st["notes"]), st["notes"]
        res = st["all_samples_residual_nT"]
        # every usable row of the file (the campaign has no unusable row), not the rows read
        assert res["n"] == 36_000 and res["n_not_in_fit"] == 36_000 - st["samples_used"]
        notes = [n for n in st["notes"] if n.endswith("(stats all_samples_residual_nT)")]
        assert len(notes) == 1 and "(every row of every file)" in notes[0], notes
    assert any(m.startswith("every row:") for m in lines)


def test_every_row_residual_is_the_in_memory_one(fm1_dir):
    """The streaming pass's figures equal the in-memory all_samples_residual (the fit's
    own path, samples._gather with S.all_usable) on the same rows: one definition."""
    from generator.fit.samples import _gather, all_samples_residual, fit_data_from
    from generator.fit.thermal import fit_unit
    from generator.io.telemetry_csv import preprocess, read_telemetry
    unit = load_unit(fm1_dir / "unit.toml")
    path = fm1_dir / "thermal_12pos.csv"
    tels, _ = rc.read_for_fit(unit, [path], 200_000, lambda m: None, max_rows=CAP)
    cals = fit_unit(unit, tels, max_samples=200_000)
    streamed = rc.every_row_residual(unit, [path], cals)
    # pieces shorter than the file: the same rows (none is screened out in this campaign)
    pieced = rc.every_row_residual(unit, [path], cals, piece_rows=7_000)
    tel = read_telemetry(path, unit)
    pre = preprocess(tel, unit)
    assert set(streamed) == set(cals) == set(pieced)
    for name, cal in cals.items():
        d = fit_data_from(tel, pre[name], unit)
        # a cap of one sample: the fit's own path keeps every usable sample in all_usable
        S = _gather(name, [d], [], [], max_samples=1)
        mem = all_samples_residual(cal, S)
        mem["n_not_in_fit"] = mem["n"] - cal.stats["samples_used"]
        assert streamed[name] == mem, (name, streamed[name], mem)
        assert pieced[name]["n"] == mem["n"]
        # summed in another order: equal to float64 round-off over 36,000 terms
        for k in ("rms_vector_nT", "rms_norm_nT"):
            assert pieced[name][k] == pytest.approx(mem[k], rel=1e-9)


def test_at_the_cap_nothing_changes(fm1_dir, tmp_path):
    """A cap equal to the data rows (the file's line count bounds them from above: the
    exact count decides) reads every row: the same bytes as no cap."""
    out = []
    for tag, rows in (("at", 36_000), ("none", 0)):
        cs = fit(fm1_dir / "unit.toml", [fm1_dir / "thermal_12pos.csv"], max_rows=rows)
        cs.save(tmp_path / f"{tag}.json")
        out.append((tmp_path / f"{tag}.json").read_bytes())
    assert out[0] == out[1]
    assert b"read cap" not in out[0] and b'"rows_read"' not in out[0]


def test_read_cap_rows():
    assert rc.read_cap_rows(0) == 0                       # --max-samples 0: every row
    assert rc.read_cap_rows(200_000) == rc.READ_CAP_ROWS == 400_000
    assert rc.read_cap_rows(3_000) == rc.READ_CAP_ROWS    # a smaller cap thins the subsample
    assert rc.read_cap_rows(1_000_000) == 2_000_000       # a larger one reads more
    assert rc.read_cap_rows(200_000, max_rows=0) == 0


def test_blocks_over_two_files(fm1_dir):
    """Blocks drawn over every file's blocks in order; a file without a drawn block is left
    out of the fit and said."""
    unit = load_unit(fm1_dir / "unit.toml")
    paths = [fm1_dir / "thermal_12pos.csv", fm1_dir / "rotation.csv"]
    lines = []
    tels, cap = rc.read_for_fit(unit, paths, 200_000, _progress(lines), max_rows=5_000)
    assert [f.rows for f in cap.files] == [36_000, 4_000]
    assert sum(f.rows_read for f in cap.files) == sum(t.n for t in tels) <= 5_000
    assert sum(f.blocks for f in cap.files) == 5
    assert len(tels) == sum(1 for f in cap.files if f.rows_read)
    if len(tels) == 1:
        assert "left out of the fit" in cap.note
    again, cap2 = rc.read_for_fit(unit, paths, 200_000, lambda m: None, max_rows=5_000)
    assert [t.line_numbers.tolist() for t in tels] == [t.line_numbers.tolist() for t in again]


def test_a_bad_cell_in_rows_not_read_is_still_refused(fm1_dir, tmp_path):
    """Every row is parsed and checked while the blocks are read: a bad cell in a row no
    block keeps exits 2 naming its line, as without the cap."""
    unit = load_unit(fm1_dir / "unit.toml")
    src = fm1_dir / "thermal_12pos.csv"
    (tel,), _ = rc.read_for_fit(unit, [src], 200_000, lambda m: None, max_rows=CAP)
    lines = src.read_text().split("\n")
    kept = set(tel.line_numbers.tolist())
    bad = next(k for k in range(5_000, 36_000) if k not in kept)   # 1-based line number
    cells = lines[bad - 1].split(",")
    cells[2] = "12x"
    lines[bad - 1] = ",".join(cells)
    path = tmp_path / "bad.csv"
    path.write_text("\n".join(lines))
    with pytest.raises(InputError) as e:
        fit(fm1_dir / "unit.toml", [path], max_rows=CAP)
    assert f"bad.csv:{bad}: column" in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_parquet_reads_the_same_blocks(fm1_dir, tmp_path):
    """A Parquet file (its row count from the footer) gives the same blocks as the CSV
    (its row count from the line breaks less the lines before the first row)."""
    sys.path.insert(0, str(REPO / "bench"))
    from bench_io import write_long_parquet
    unit = load_unit(fm1_dir / "unit.toml")
    pq = tmp_path / "thermal.parquet"
    write_long_parquet(fm1_dir / "thermal_12pos.csv", pq, 36_000)
    (a,), ca = rc.read_for_fit(unit, [fm1_dir / "thermal_12pos.csv"], 200_000,
                               lambda m: None, max_rows=CAP)
    (b,), cb = rc.read_for_fit(unit, [pq], 200_000, lambda m: None, max_rows=CAP)
    assert ca.files[0].rows == cb.files[0].rows == 36_000
    assert np.array_equal(a.time_s, b.time_s) and a.n == b.n == CAP


def test_orbit_file_streams_with_the_field_model(tmp_path, monkeypatch):
    """A file whose reference the field model computes along its track (io.orbit, a TLE):
    the model is attached row by row to the rows kept, so they carry the reference the
    whole file's read gives them, and the every-row pass computes it piece by piece."""
    import dataclasses
    from generator.campaign import simulate_orbit as so
    from generator.campaign.simulate import make_example_unit, random_truth
    from generator.fit.thermal import fit_unit
    from generator.io.telemetry_csv import read_telemetry
    monkeypatch.setenv("MAGCAL_CACHE", str(tmp_path / "cache"))
    ex = make_example_unit()
    one = dataclasses.replace(ex, sensors=ex.sensors[:1], boom_reference=None)
    rng = np.random.default_rng(1802)
    camp = so.simulate_orbit(one, random_truth(one, rng), rng, tmp_path,
                             duration_s=12 * 3600.0)            # 4,320 rows, 10 s apart
    unit = load_unit(camp["unit"])
    whole = read_telemetry(camp["csv"], unit)
    lines = []
    (tel,), cap = rc.read_for_fit(unit, [camp["csv"]], 200_000, _progress(lines),
                                  max_rows=2_000)
    assert whole.n == 4_320 and tel.n == 2_000 and cap.files[0].blocks == 2
    assert "field_reference" in tel.meta and any("IGRF" in m for m in lines)
    at = np.searchsorted(whole.line_numbers, tel.line_numbers)
    assert np.array_equal(whole.line_numbers[at], tel.line_numbers)
    assert np.array_equal(tel.columns["ref_norm_nT"], whole.columns["ref_norm_nT"][at],
                          equal_nan=True)
    cals = fit_unit(unit, [tel])
    res = rc.every_row_residual(unit, [camp["csv"]], cals, piece_rows=1_500)
    name, = cals
    from generator.fit.samples import fit_data_from, usable_samples
    from generator.io.telemetry_csv import preprocess
    d = fit_data_from(whole, preprocess(whole, unit)[name], unit)
    # the usable samples of the whole file, found piece by piece (none screened out here)
    assert res[name]["n"] == int(usable_samples(d)[0].sum()) > 0
    assert np.isfinite(res[name]["rms_norm_nT"]) and res[name]["rms_vector_nT"] is None


@pytest.mark.parametrize("value", [-1, 1.5, True, "10"])
def test_bad_max_rows_in_the_api(fm1_dir, value):
    with pytest.raises(InputError, match="max_rows"):
        fit(fm1_dir / "unit.toml", [fm1_dir / "rotation.csv"], max_rows=value)


def test_cap_below_one_block_in_the_api(fm1_dir):
    with pytest.raises(InputError) as e:
        fit(fm1_dir / "unit.toml", [fm1_dir / "thermal_12pos.csv"], max_rows=500)
    msg = str(e.value)
    assert "\n" not in msg and "max_rows" in msg and "1,000" in msg, msg


def test_cap_below_one_block_exits_2_one_line(fm1_dir, tmp_path, capsys, monkeypatch):
    from generator.cli import main
    monkeypatch.setattr(rc, "READ_CAP_ROWS", 500)          # the default read cap, small
    code = main(["fit", str(fm1_dir / "unit.toml"), str(fm1_dir / "thermal_12pos.csv"),
                 "-o", str(tmp_path / "out"), "--no-report", "--max-samples", "100"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and "--max-samples" in err, err
    assert not (tmp_path / "out").exists()


# ---- memory on long files (slow) ---------------------------------------------------------

@pytest.mark.slow
def test_peak_memory_does_not_grow_with_the_file(tmp_path):
    """Peak RSS (wait4 of a subprocess: bench_io.measured) of `magcal fit --no-report` at
    two lengths above the default read cap. Nothing in the streaming passes is kept per row
    of the file: the read pass keeps the drawn blocks' rows (at most READ_CAP_ROWS whatever
    the length) and one chunk (CHUNK_BYTES of text); the every-row pass one piece
    (EVERY_ROW_PIECE rows) and per sensor four sums. The rows read at the two lengths differ
    by less than one block (draw_blocks keeps them within L of the cap): 1,200 rows here
    (5 s a row: 100 min), at ~1.4 KiB a row read (bench_io's docstring: the fit's memory
    per row) under 2 MiB, i.e. under 2 B a row over the 1.2x10^6 rows between the lengths. Bound: 32 B a row (16x that: the allocator's page-level noise; the
    uncapped fit grew ~1,400 B a row)."""
    sys.path.insert(0, str(REPO / "bench"))
    from bench_io import FM1, measured, write_long_file
    src, unit = FM1 / "thermal_12pos.csv", FM1 / "unit.toml"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    peaks = {}
    for rows in (600_000, 1_800_000):
        data = tmp_path / f"long_{rows}.csv"
        write_long_file(src, data, rows)
        cmd = [sys.executable, "-m", "generator.cli", "fit", str(unit), str(data), "-o",
               str(tmp_path / f"out_{rows}"), "--no-report", "--quiet"]
        secs, peak_mib, code, out, err = measured(cmd, env)
        assert code == 0, err
        d = json.loads((tmp_path / f"out_{rows}" / "coefficients.json").read_text())
        st = d["fit"]["sensors"]["mmc1"]["stats"]
        f0, res = st["files"][0], st["all_samples_residual_nT"]
        # every row's usable samples, more than the rows read (the screen drops some rows
        # where the repeated campaign's temperature jumps back at each seam)
        assert f0["rows"] == rows and f0["rows_read"] <= rc.READ_CAP_ROWS < res["n"] <= rows
        peaks[rows] = peak_mib
        data.unlink()
    growth = (peaks[1_800_000] - peaks[600_000]) * 2 ** 20 / 1_200_000
    print(f"peak RSS (MiB) by rows {peaks}: {growth:.1f} B a row")
    assert growth < 32, (peaks, growth)


def test_a_trace_above_the_read_cap_fits_its_baseline_on_blocks(tmp_path, monkeypatch):
    """magcal trace without --coeffs fits its baseline as magcal fit does: above the fit's
    read cap on blocks read streaming (its files held by rows), never the whole files;
    said in the trace's notes."""
    from generator.trace import tracer
    import generator.trace.filerows as fr
    fm1 = "/work/shared/data/samsat_fm1"
    if not os.path.exists(fm1):
        pytest.skip("no shared data")
    monkeypatch.setattr(tracer, "BASELINE_READ_ROWS", 5000)
    held_whole = []
    real = fr.FileRows.__init__

    def spy(self, path, unit, regressors=(), tel=None):
        held_whole.append(tel is not None)
        real(self, path, unit, regressors, tel=tel)
    monkeypatch.setattr(fr.FileRows, "__init__", spy)
    res = tracer.trace(f"{fm1}/unit.toml", [f"{fm1}/flight_6h.csv"], max_samples=6000,
                       sensors={"mpu1"})
    assert held_whole == [False]                  # streamed, not built from a whole read
    note = next(n for n in res.notes if n.startswith("baseline fit: on "))
    read, total = (int(x.replace(",", "")) for x in
                   note[len("baseline fit: on "):].split(" rows")[0].split(" of the data "
                                                                       "files' "))
    assert total == 10_800 and 0 < read <= 5000, note
