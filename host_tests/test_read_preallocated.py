"""Issue 20: read_telemetry allocates its columns once, at an upper bound on the rows
(io.telemetry_csv._rows_at_most), and fills them in place; the result is that of the
growing columns, whatever the bound (exact, loose, too small, absent)."""

from __future__ import annotations

import numpy as np
import pytest

from generator.io.telemetry_csv import _rows_at_most, concat_chunks, iter_telemetry

from test_stream_io import _same, _telemetry_text, _unit


@pytest.mark.parametrize("extras", [False, True])
def test_rows_bound_gives_the_same_telemetry(tmp_path, extras):
    unit = _unit()
    p = tmp_path / "t.csv"
    p.write_text(_telemetry_text(unit, 2500, np.random.default_rng(5), extras))
    grown = concat_chunks(iter_telemetry(p, unit, chunk_bytes=4000))
    bound = _rows_at_most(p)
    # every data row is a line: the bound holds; comments and the header make it looser
    assert bound >= grown.n == 2500
    for rows in (bound, grown.n, 10 * bound, 7, 0, None):
        tel = concat_chunks(iter_telemetry(p, unit, chunk_bytes=4000), rows=rows)
        _same(tel, grown)
        assert all(v.shape == (grown.n,) for v in tel.columns.values())


def test_rows_bound_of_parquet_and_of_bad_files(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    p = tmp_path / "t.parquet"
    pq.write_table(pa.table({"time_s": pa.array(np.arange(123.0))}), p, row_group_size=50)
    assert _rows_at_most(p) == 123
    assert _rows_at_most(tmp_path / "absent.csv") is None
    bad = tmp_path / "bad.parquet"
    bad.write_bytes(b"PAR1" + b"\0" * 40)
    assert _rows_at_most(bad) is None
