"""Issue 20: `apply` streams, so its memory does not grow with the file's length.

apply runs in a fresh subprocess on a file of R rows and on one of 10 R rows, with a small
chunk; the peak RSS (wait4) of the two must differ by less than what one chunk's working
set can explain. Not a timing test.

The bound: one chunk holds its text a few times (bytes read, decoded str, the body handed
to the parser), its values (8 bytes a cell, about 1.5 x the text of a 5-6 character cell)
and its output cells and rows (about 3 x): under 10 x chunk_bytes, whatever the file's
length. On top, allocator granularity that does not scale with the rows (glibc arenas,
pyarrow's pool) is allowed 16 MiB. A reader that held the file would grow by at least the
text of the 9 R extra rows, which the test checks is well above the bound.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

from conftest import REPO

sys.path.insert(0, str(REPO / "bench"))
from bench_io import write_long_file  # noqa: E402  (the bench's long-file maker)

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
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, env=env)
    _, status, rusage = os.wait4(p.pid, 0)
    out_text, err = p.stdout.read().decode(), p.stderr.read().decode()
    p.stdout.close(), p.stderr.close()
    assert os.waitstatus_to_exitcode(status) == 0, err
    return int(out_text.strip()), rusage.ru_maxrss / 1024.0


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
