"""Issue 20 (F4): a capped trace's peak memory grows with the file's length only by what it
keeps of every row (trace.filerows.FileRows), not by the whole file.

`trace` (API, supplied baseline, one sensor, cap 20,000) runs in a fresh subprocess on
R = 220,000 rows of flight_6h and on 4 R (both above ALL_ROWS_CHUNK, so the all-rows
pieces are the same size); the peak RSS (bench_io.measured) may grow per extra row by at
most:

* what FileRows keeps of a row (FileRows.nbytes / n, measured on the short file): the
  time and the held columns (every column but the count columns and the references: the
  temperatures and the channels) packed, ~2 B a cell, and one bit a sensor;
* the lag recursions' caches (trace.effects), bounded in bytes for long files
  (SERIES_CACHE_BYTES; set to 0 here so that both lengths hold the minimum of 4 entries
  of 8 B a row, in each of the two caches: temperature lags and channel lags);
* one recursion's temporaries, 6 arrays of 8 B a row (the unpacked time and input, time
  steps, factors, forcing, output).

Holding the whole file cost 0.7-0.8 kB a row on this unit (8 B a cell of its 36 columns,
the per-sensor series copies and the whole-file preprocess): 5x the bound; its 36 cells
alone (288 B) are 2x. On top, allocator granularity that does not scale with the rows is
allowed 16 MiB.
"""

from __future__ import annotations

import os
import sys
import textwrap

import pytest

from conftest import REPO
from generator.io.unitfile import load_unit
from generator.trace.filerows import FileRows

sys.path.insert(0, str(REPO / "bench"))
from bench_io import measured, write_long_file  # noqa: E402

ROWS = 220_000
SLACK_MiB = 16


def _peak_MiB(unit_path, data) -> float:
    code = textwrap.dedent(f"""
        import generator.trace.effects as fx
        fx.SERIES_CACHE_BYTES = 0       # the caches at their minimum at both lengths
        from generator.trace.tracer import trace
        res = trace({str(unit_path)!r}, [{str(data)!r}], max_samples=20_000,
                    coeffs={str(REPO / 'generated/samsat_fm1/coefficients.json')!r},
                    sensors=["mmc1"])
        print(res.subsample["samples"])
    """)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    _, peak_MiB, rc, out, err = measured([sys.executable, "-c", code], env=env)
    assert rc == 0, err[-2000:]
    return int(out.strip()), peak_MiB


@pytest.mark.slow            # 30 s alone, 1-3 min on the loaded 2-core machine: two traces
def test_capped_trace_memory_grows_only_by_what_it_keeps_of_a_row(tmp_path, fm1_dir):
    unit_path = fm1_dir / "unit.toml"
    small = tmp_path / "small.csv"
    large = tmp_path / "large.csv"
    write_long_file(fm1_dir / "flight_6h.csv", small, ROWS)
    write_long_file(fm1_dir / "flight_6h.csv", large, 4 * ROWS)
    unit = load_unit(unit_path)
    held = FileRows(small, unit)
    per_row = held.nbytes / held.n + 2 * 4 * 8 + 6 * 8
    whole_per_row = 8 * 36                            # the file's 36 columns alone
    assert whole_per_row > 1.5 * per_row, "the bound must tell holding the whole file"
    n_s, rss_s = _peak_MiB(unit_path, small)
    n_l, rss_l = _peak_MiB(unit_path, large)
    assert (n_s, n_l) == (ROWS, 4 * ROWS)
    bound_MiB = 3 * ROWS * per_row / 2**20 + SLACK_MiB
    growth = rss_l - rss_s
    assert growth < bound_MiB, (f"peak {rss_s:.0f} MiB at {ROWS:,} rows, {rss_l:.0f} MiB at "
                                f"{4 * ROWS:,}: +{growth:.0f} MiB > {bound_MiB:.0f} MiB "
                                f"({per_row:.0f} B a row kept)")
