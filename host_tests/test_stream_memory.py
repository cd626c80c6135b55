"""Issue 20: `apply` streams, so its memory does not grow with the file's length.

apply runs in a fresh subprocess on a file of R rows and on one of 10 R rows, with a small
chunk; the peak RSS (wait4, through bench_io.measured) of the two must differ by less
than what one chunk's working set can explain. Not a timing test.

The bound: one chunk holds its text a few times (bytes read, decoded str, the body handed
to the parser), its values (8 bytes a cell, about 1.5 x the text of a 5-6 character cell)
and its output cells and rows (about 3 x): under 10 x chunk_bytes, whatever the file's
length. On top, allocator granularity that does not scale with the rows (glibc arenas,
pyarrow's pool) is allowed 16 MiB. A reader that held the file would grow by at least the
text of the 9 R extra rows, which the test checks is well above the bound.

Parquet: the same on a file of N rows against one of 4 N (row groups of a fixed size, as
writers make them): the reader holds one block of values (chunk_bytes of float64) and
pyarrow's buffered column streams (io.telemetry_parquet.STREAM_BUFFER a column), not the
row groups ahead (pyarrow's pre-buffering and reader threads kept the file's bytes: peak
RSS grew by about the file's size).
"""

from __future__ import annotations

import os
import sys
import textwrap

import pytest

from conftest import REPO

sys.path.insert(0, str(REPO / "bench"))
from bench_io import measured, write_long_file, write_long_parquet  # noqa: E402

CHUNK_BYTES = 256 * 1024
SLACK_MiB = 16


def _peak_rss_MiB(data, out) -> float:
    code = textwrap.dedent(f"""
        from generator import pipeline
        from generator.flight.coeffs import CoefficientSet
        from generator.flight.host import HostUnit
        cs = CoefficientSet.load({str(REPO / 'generated/samsat_fm1/coefficients.json')!r})
        cs = cs.with_boom_stowed()
        r = pipeline.apply(cs, {str(data)!r}, {str(out)!r}, host=HostUnit(cs),
                           coils_off=True, at_rest=True, collect=False,
                           chunk_bytes={CHUNK_BYTES})
        print(r["n"])
    """)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    # bench_io.measured, not a bare wait4: a fork of this test process (which has just
    # written the long inputs) would count in the child's peak, the same for both runs
    _, peak_MiB, code, out_text, err = measured([sys.executable, "-c", code], env=env)
    assert code == 0, err
    return int(out_text.strip()), peak_MiB


def test_apply_memory_does_not_grow_with_the_file(tmp_path, fm1_dir):
    rows = 20_000
    src = fm1_dir / "thermal_12pos.csv"
    small = write_long_file(src, tmp_path / "small.csv", rows)
    large = write_long_file(src, tmp_path / "large.csv", 10 * rows)
    bound_MiB = 10 * CHUNK_BYTES / 2**20 + SLACK_MiB
    extra_text_MiB = (large - small) / 2**20
    assert extra_text_MiB > 1.5 * bound_MiB, "the long file must be long enough to show it"
    n_small, rss_small = _peak_rss_MiB(tmp_path / "small.csv", tmp_path / "o1.csv")
    n_large, rss_large = _peak_rss_MiB(tmp_path / "large.csv", tmp_path / "o2.csv")
    assert (n_small, n_large) == (rows, 10 * rows)
    growth = rss_large - rss_small
    assert growth < bound_MiB, (f"peak RSS {rss_small:.1f} MiB for {rows} rows, "
                                f"{rss_large:.1f} MiB for {10 * rows}: grows by {growth:.1f} "
                                f"MiB > {bound_MiB:.1f} MiB")


PQ_ROWS = 400_000
PQ_ROW_GROUP = 50_000


@pytest.mark.slow            # about 20 s: two files and two runs of 4x10^5 and 1.6x10^6 rows
def test_apply_memory_on_parquet_does_not_grow_with_the_file(tmp_path, fm1_dir):
    """Peak RSS of apply on a Parquet file of N rows and of 4 N rows.

    The bound on the growth: one block of values (chunk_bytes of float64) and its copies
    through the chain and the output cells (under 10 x chunk_bytes, as for the CSV), the
    column streams' buffers (2 x STREAM_BUFFER a column, counted generously) and allocator
    granularity (16 MiB, as above); none of it scales with the rows. A reader that kept
    what it read ahead (the compressed file, as pyarrow's pre-buffering did) would grow by
    the 3 N extra rows' share of the file, one that kept the decoded columns by 8 bytes a
    value: the test checks both exceed the bound. The ratio of the two peaks is also held
    under 1.3: the small run's peak is the interpreter, the imports and the compiled
    flight C (over 100 MiB), so 1.3 allows 30 MiB and more, above the growth bound."""
    from generator.io.telemetry_parquet import STREAM_BUFFER

    src = fm1_dir / "thermal_12pos.csv"
    small, large = tmp_path / "small.parquet", tmp_path / "large.parquet"
    size_small = write_long_parquet(src, small, PQ_ROWS, PQ_ROW_GROUP)
    size_large = write_long_parquet(src, large, 4 * PQ_ROWS, PQ_ROW_GROUP)
    ncol = len(src.read_text().split("\n", 3)[2].split(","))
    bound_MiB = (10 * CHUNK_BYTES + 2 * ncol * STREAM_BUFFER) / 2**20 + SLACK_MiB
    kept_file_MiB = (size_large - size_small) / 2**20
    kept_values_MiB = 3 * PQ_ROWS * ncol * 8 / 2**20
    assert min(kept_file_MiB, kept_values_MiB) > 1.5 * bound_MiB, \
        "the long file must be long enough to show it"
    n_small, rss_small = _peak_rss_MiB(small, tmp_path / "o1.csv")
    n_large, rss_large = _peak_rss_MiB(large, tmp_path / "o2.csv")
    assert (n_small, n_large) == (PQ_ROWS, 4 * PQ_ROWS)
    growth = rss_large - rss_small
    assert growth < bound_MiB and rss_large / rss_small < 1.3, (
        f"peak RSS {rss_small:.1f} MiB for {PQ_ROWS} rows, {rss_large:.1f} MiB for "
        f"{4 * PQ_ROWS}: grows by {growth:.1f} MiB (bound {bound_MiB:.1f} MiB), ratio "
        f"{rss_large / rss_small:.2f}")


def test_parquet_apply_streamed_is_the_whole_file_result(tmp_path, fm1_dir):
    """The output of apply on a Parquet file read in small blocks across row groups is
    byte for byte the output of one block (and of the same rows as CSV, after the line
    naming the source)."""
    from generator import pipeline
    from generator.flight.coeffs import CoefficientSet

    src = fm1_dir / "thermal_12pos.csv"
    rows = 5000
    pqp = tmp_path / "t.parquet"
    write_long_parquet(src, pqp, rows, row_group_rows=1234)
    csv = tmp_path / "t.csv"
    write_long_file(src, csv, rows)
    cs = CoefficientSet.load(REPO / "generated/samsat_fm1/coefficients.json").with_boom_stowed()
    kw = dict(coils_off=True, at_rest=True, collect=False)
    pipeline.apply(cs, pqp, tmp_path / "one.csv", chunk_bytes=1 << 30, **kw)
    pipeline.apply(cs, pqp, tmp_path / "many.csv", chunk_bytes=7_000, **kw)   # 27 rows
    pipeline.apply(cs, csv, tmp_path / "csv.csv", **kw)
    one = (tmp_path / "one.csv").read_bytes()
    assert (tmp_path / "many.csv").read_bytes() == one
    assert one.split(b"\n", 1)[1] == (tmp_path / "csv.csv").read_bytes().split(b"\n", 1)[1]
