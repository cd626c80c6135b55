"""The capped trace on mixed inputs (review #20c): short files beside a long one use the
cap (N2), and a channel's blank cells keep its last value instead of 0 (N1)."""

from __future__ import annotations

import numpy as np

from generator.io.telemetry import Telemetry
from generator.trace import subsample as sub
from generator.trace.samples import _held


def _file(name, n, t0=0.0):
    ts = t0 + np.arange(n, dtype=float)
    return Telemetry(name, {"time_s": ts, "x": 2.0 * ts}, np.arange(2, n + 2))


def test_short_files_beside_a_long_one_use_the_cap():
    """200 files of 200 rows, then one of 150,000 rows at 1 Hz (blocks of 5,000 rows):
    the short files' blocks are short, so floor(cap / L) blocks held a fifth of the cap.
    Now as many blocks are drawn as keep the drawn rows within the cap, and the long
    file's blocks reach its end."""
    short = [_file(f"s{i:03d}.csv", 200, t0=i * 300.0) for i in range(200)]
    long = _file("long.csv", 150_000, t0=200 * 300.0)
    cap = 100_000
    kept, _, info = sub.subsample_files(short + [long], [], cap)
    L = info["block_rows"]
    assert L == 5_000
    assert cap - L < info["traced"] <= cap                   # the cap used, never exceeded
    assert info["traced"] == sum(int(t.sample_rows.sum()) for t in kept)
    assert "(fewer at the end of a file)" in info["text"]
    (lk,) = [t for t in kept if t.path == "long.csv"]
    # the long file holds 150,000 of the 190,000 rows: about that share of the cap (3
    # blocks, 15,000 rows, before), spread over the file (one block in each ~2)
    assert int(lk.sample_rows.sum()) >= 0.5 * cap
    rows = np.nonzero(lk.sample_rows)[0]
    assert rows.min() < 0.1 * long.n and rows.max() > 0.9 * long.n


def test_equal_files_keep_floor_cap_over_L_blocks():
    """Whole blocks only: the count is floor(cap / L), as before (nothing to add)."""
    files = [_file(f"p{i}.csv", 1_000, t0=i * 1_100.0) for i in range(150)]
    kept, _, info = sub.subsample_files(files, [], 20_000)
    assert info["blocks"] == 20 and info["traced"] == 20_000


def test_blank_channel_cells_hold_the_last_value():
    v = np.array([np.nan, 1.0, 2.0, np.nan, np.nan, 5.0, np.inf, np.nan])
    assert _held(v).tolist() == [0.0, 1.0, 2.0, 2.0, 2.0, 5.0, 5.0, 5.0]
    assert _held(np.array([np.nan, np.nan])).tolist() == [0.0, 0.0]
    w = np.array([8.0, 8.1, 7.9])
    assert np.array_equal(_held(w), w)
