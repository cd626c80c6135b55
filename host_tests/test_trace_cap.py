"""Review 20b of `magcal trace` above its cap (generator.trace.subsample): the cap holds
however the telemetry is cut into files (F3), a cap just under the data keeps about the
cap (F10), a cap below one block is refused (F7). Small synthetic files, no trace run
except for the command-line refusal."""

from __future__ import annotations

import numpy as np
import pytest

from generator.errors import InputError
from generator.io.telemetry import Telemetry
from generator.trace import subsample as sub

from conftest import FM1


SAMSAT = FM1                 # rotation.csv: 4,001 rows


def _file(name, n, t0=0.0):
    ts = t0 + np.arange(n, dtype=float)
    return Telemetry(name, {"time_s": ts, "x": 2.0 * ts}, np.arange(2, n + 2))


def _passes(k, n, prefix="p"):
    """k files of n rows at 1 Hz, one after the other in time (passes of one recording)."""
    return [_file(f"{prefix}{i:03d}.csv", n, t0=i * (n + 100.0)) for i in range(k)]


def test_many_short_files_keep_the_cap():
    files = _passes(150, 1_000)
    cap = 20_000
    kept, _, info = sub.subsample_files(files, [], cap)
    L = info["block_rows"]
    assert L == 1_000 and info["samples"] == 150_000
    assert info["traced"] == sum(t.n for t in kept) <= cap
    assert info["blocks"] == cap // L                       # as close to the cap as blocks go
    assert info["files_left_out"] == 150 - len(kept) > 0    # files with no block left out
    assert f"{info['files_left_out']} of 150 files had no block drawn" in info["text"]
    assert all(t.n > 0 for t in kept)
    # one systematic draw over the blocks in order: spread over the whole recording
    starts = np.array([t.time_s[0] for t in kept])
    assert starts.min() < 0.1 * files[-1].time_s[-1] and starts.max() > 0.9 * files[-1].time_s[-1]
    # independent of the files' names
    renamed = [Telemetry(f"q/{i}.csv", t.columns, t.line_numbers) for i, t in enumerate(files)]
    again, _, _ = sub.subsample_files(renamed, [], cap)
    assert [t.time_s[0] for t in again] == list(starts)


def test_kept_blocks_of_a_file_stay_one_file():
    files = _passes(3, 40_000)
    kept, _, info = sub.subsample_files(files, [], 30_000)
    assert len(kept) == 3 and [t.path for t in kept] == [t.path for t in files]
    assert info["traced"] <= 30_000 and info["blocks"] == 30_000 // info["block_rows"]


def test_cap_just_under_the_data_keeps_about_the_cap():
    t = _file("long.csv", 150_000)
    (kept,), _, info = sub.subsample_files([t], [], 149_999)
    L = info["block_rows"]
    # floor(cap / L) whole blocks: within one block of the cap, never above it
    assert 149_999 - L < kept.n <= 149_999, (kept.n, L)


def test_holdout_blocks_are_drawn_apart_and_kept():
    data, hold = _passes(4, 30_000), _passes(1, 5_000, prefix="h")
    kd, kh, info = sub.subsample_files(data, hold, 40_000)
    assert len(kh) == 1 and kh[0].n > 0
    assert info["traced"] <= 40_000


@pytest.mark.parametrize("cap", [1, 999])
def test_cap_below_one_block_is_refused(cap):
    with pytest.raises(InputError, match="--max-samples") as e:
        sub.subsample_files([_file("a.csv", 5_000)], [], cap)
    assert "at least 1,000" in str(e.value)


def test_cap_below_min_blocks_is_said():
    (kept,), _, info = sub.subsample_files([_file("a.csv", 20_000)], [], 5_000)
    assert info["blocks"] == 5 and kept.n == 5_000
    assert f"fewer than the {sub.MIN_BLOCKS}" in info["text"]


def test_cli_cap_below_one_block_exits_2_one_line(tmp_path, capsys):
    from generator.cli import main
    rc = main(["trace", str(SAMSAT / "unit.toml"), str(SAMSAT / "rotation.csv"), "-o",
               str(tmp_path / "out"), "--max-samples", "999"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "--max-samples" in err, err
    assert not (tmp_path / "out").exists()
