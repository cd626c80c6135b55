#!/usr/bin/env python3
"""Benchmark of `magcal trace` against `magcal fit` on the same files, in the same run
(issue 17: trace within 3 x fit).

Files: the shared SamSat FM1 ground campaigns (thermal_12pos, rotation, coils) plus
flight_6h.csv. Each command runs in a fresh subprocess (wall time and peak RSS from
wait4), with this checkout on PYTHONPATH, so imports and I/O count as a user sees them.

    python3 bench/bench_trace.py [--data DIR] [--repeat 1] [--files a.csv b.csv ...]

Prints the walls and CPU times (user + system, from wait4), the ratio trace / fit of
each run and of the best of the runs, and the trace's own progress lines (per sensor
and round, with the time each round took). On a shared machine the CPU ratio is the
steadier figure: the walls include waiting for a core, which differs between the runs.

    python3 bench/bench_trace.py --memory 220000 880000 1500000 --baseline DIR [--coeffs C]

Peak RSS and wall of a capped trace (API, one sensor, cap 20,000) of flight_6h repeated to
each length, this checkout against a baseline checkout DIR (`git archive <commit> | tar -x
-C DIR`) in the same run, each in a fresh process importing its own tree; the ratios this /
baseline and how the peak grows a row. Issue 20 F4, tmem12 against main 8248fa4, with
`--coeffs generated/samsat_fm1/coefficients.json` (no baseline fit: the trace's own
memory), on the shared 2-core machine under load (the walls vary by tens of %):

        rows   this            8248fa4          this / 8248fa4
     220,000    28.3 s  501 MiB    21.1 s 1047 MiB   time 1.34x, peak 0.48x
     880,000    44.8 s  512 MiB    44.9 s 1805 MiB   time 1.00x, peak 0.28x
   1,500,000    94.6 s  573 MiB   123.2 s 2145 MiB   time 0.77x, peak 0.27x
   peak grows a row: this 60 B, 8248fa4 899 B (220,000 -> 1,500,000 rows)

Without --coeffs (the baseline fitted, as `magcal trace` does by default: the files are
read whole for the fit and let go after it), same run conditions, 8248fa4 again:

     220,000    80.3 s  694 MiB   124.3 s 1249 MiB   time 0.65x, peak 0.56x
     880,000   310.9 s  846 MiB   197.0 s 2000 MiB   time 1.58x, peak 0.42x
   peak grows a row: this 241 B, 8248fa4 1193 B (220,000 -> 880,000 rows)

(the 880,000-row walls are not comparable: other test runs shared the 2 cores during
this tree's run). What still grows there is the whole read and the fit (generator.fit).

    python3 bench/bench_trace.py --long FILE... --unit-file U --coeffs C [--baseline DIR]

`magcal trace U FILE --coeffs C` on long files, this checkout and a baseline checkout in
the same run: wall, CPU, peak RSS, the longest silence between progress lines. Issue 20
F5 (review 20e), tlag14 against d1d6bb7, the reviewer's 3-sensor unit
(/tmp/review_20e/u1: IST8310 uT, a 24-bit generic with temperature, LIS3MDL G; the
simulated thermal campaign repeated to length, Parquet), the same command run by hand
with /usr/bin/time -v on the shared 2-core machine at a load average of 3-5, the runs one
after another, not interleaved (the walls include waiting for a core, and the load
differed between the runs; the CPU time, user + system, is the steadier figure):

        rows   d1d6bb7 (before)                    this
   1,000,000   311.8 s wall  84.9 s CPU 1424 MiB   100.9 s wall 32.1 s CPU 1419 MiB
   3,000,000   490.0 s wall 326.4 s CPU 1535 MiB    96.3 s wall 62.3 s CPU 1460 MiB
   peak grows a row (10^6 -> 3 x 10^6): before 58 B, this 21 B
   (the thermal-lag sensor's round 1: 238.3 s before, 36.9 s after at 10^6 rows, 416.8 s
   and 26.0 s at 3 x 10^6; at both lengths the same trace.json but elapsed_s and the
   same coefficients.json bytes)

What it was: effects.first_order's search for each chunk's end over the rest of the
stretch (quadratic in the rows with many chunks) and its short-memory loop in Python
(over Python float lists, 64 B a row besides its arrays); now doubling windows and the
loop compiled (trace.recursion), bit for bit. The peak is mostly the drawn rows' design
at the default cap (~1.3 GiB already at 250,000 rows); what grows a row is the held file
(FileRows, 31 B a row on this unit), the two lag caches' floor past ~2 million rows (up
to 40 B a row each) and one recursion's temporaries (~50 B a row with the unpacked
inputs; 57-121 B besides them before).

The 60 B a row: the packed series (~30 B, trace.filerows) and the recursions' caches
(trace.effects, at least 4 series-long arrays a cache); the rest of the peak is the
samples and the all-rows pieces, which do not grow with the length. The time: the file is
read again for the drawn rows and for every all-rows figure (reading whole once cost more
at the longer files: the whole-file preprocess and series copies).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
CANDIDATES = [REPO.parent / "shared" / "data" / "samsat_fm1",
              Path("/work/shared/data/samsat_fm1")]
FILES = ["thermal_12pos.csv", "rotation.csv", "coils.csv", "flight_6h.csv"]


def run(cmd, tree=REPO) -> tuple[float, float, str, float]:
    """(wall seconds, peak RSS MiB, stderr, CPU seconds user + system) of one
    subprocess, with `tree` (a checkout) on PYTHONPATH. The CPU time is the steadier
    figure on a shared machine (the wall time includes waiting for a core)."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env,
                         text=True)
    out = p.stdout.read()
    _, status, rusage = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"failed: {' '.join(map(str, cmd))}\n{out[-3000:]}")
    return wall, rusage.ru_maxrss / 1024.0, out, rusage.ru_utime + rusage.ru_stime


MEMORY_CODE = """
import sys
sys.path[:] = [p for p in sys.path if p]     # not the working directory: PYTHONPATH's tree
from generator.trace.tracer import trace
res = trace(sys.argv[1], [sys.argv[2]], max_samples=int(sys.argv[3]), sensors=[sys.argv[4]],
            coeffs=sys.argv[5] or None)
import generator
print(res.subsample["samples"] if res.subsample else 0, generator.__file__)
"""


def memory(data: Path, lengths, baseline: Path | None, cap: int, sensor: str,
           coeffs: str) -> int:
    """Peak RSS and wall of a capped trace (API, one sensor) of flight_6h repeated to each
    length, this checkout against a baseline checkout (e.g. `git archive 8248fa4`) in the
    same run: the ratios this / baseline."""
    sys.path.insert(0, str(REPO / "bench"))
    from bench_io import measured, write_long_file
    trees = [("this", REPO)] + ([("baseline", baseline)] if baseline else [])
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for n in lengths:
            f = Path(tmp) / f"flight_{n}.csv"
            write_long_file(data / "flight_6h.csv", f, n)
            for name, tree in trees:
                env = dict(os.environ, PYTHONPATH=str(tree))
                wall, peak, rc, out, err = measured(
                    [sys.executable, "-c", MEMORY_CODE, str(data / "unit.toml"), str(f),
                     str(cap), sensor, coeffs], env=env)
                if rc:
                    raise SystemExit(f"failed ({name}, {n} rows):\n{err[-2000:]}")
                rows[n, name] = (wall, peak)
                assert out.split()[1].startswith(str(tree)), (name, out)   # the tree asked for
                print(f"{n:>9,} rows  {name:8s}  {wall:6.1f} s  {peak:7.0f} MiB", flush=True)
            f.unlink()
    if baseline:
        for n in lengths:
            (w, p), (wb, pb) = rows[n, "this"], rows[n, "baseline"]
            print(f"{n:>9,} rows  this / baseline: time {w / wb:.2f}x, peak {p / pb:.2f}x")
    for name, _ in trees:
        a, b = lengths[0], lengths[-1]
        slope = (rows[b, name][1] - rows[a, name][1]) * 2**20 / (b - a)
        print(f"{name}: peak grows {slope:.0f} B a row from {a:,} to {b:,} rows")
    return 0


def long_cli(unit: str, coeffs: str, files, baseline: Path | None) -> int:
    """`magcal trace UNIT FILE --coeffs C` on each long file, this checkout and then a
    baseline checkout in the same run (fresh processes): wall, CPU, peak RSS, the ratios
    this / baseline, and the longest wait between two progress lines."""
    import re
    trees = [("this", REPO)] + ([("baseline", baseline)] if baseline else [])
    got = {}
    with tempfile.TemporaryDirectory() as tmp:
        for f in files:
            for name, tree in trees:
                w, rss, out, cpu = run([sys.executable, "-m", "generator.cli", "trace", unit,
                                        f, "--coeffs", coeffs, "-o", f"{tmp}/{name}"], tree)
                stamps = [float(m) for m in re.findall(r"^\[\s*([0-9.]+) s\]", out, re.M)]
                gap = max(np.diff([0.0] + stamps)) if stamps else w
                got[f, name] = (w, cpu, rss)
                print(f"{Path(f).name}  {name:8s} {w:7.1f} s wall {cpu:7.1f} s CPU "
                      f"{rss:6.0f} MiB; longest silence {gap:.1f} s", flush=True)
    if baseline:
        for f in files:
            (w, c, r), (wb, cb, rb) = got[f, "this"], got[f, "baseline"]
            print(f"{Path(f).name}  this / baseline: wall {w / wb:.2f}x, CPU {c / cb:.2f}x, "
                  f"peak {r / rb:.2f}x")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--memory", type=int, nargs="+", default=None, metavar="ROWS",
                    help="peak memory and time of a capped one-sensor trace at these lengths "
                         "(flight_6h repeated) instead of the fit comparison")
    ap.add_argument("--baseline", type=Path, default=None,
                    help="with --memory: a baseline checkout run in the same run")
    ap.add_argument("--cap", type=int, default=20_000)
    ap.add_argument("--sensor", default="mmc1")
    ap.add_argument("--coeffs", default="", help="with --memory: a supplied baseline")
    ap.add_argument("--long", nargs="+", default=None, metavar="FILE",
                    help="`magcal trace U FILE --coeffs C` (U: --unit-file) on these long files "
                         "(needs --unit-file and --coeffs; with --baseline: against it)")
    ap.add_argument("--unit-file", default=None, help="with --long: the unit")
    ap.add_argument("--data", default=None, help="the samsat_fm1 folder")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--files", nargs="+", default=FILES)
    a = ap.parse_args(argv)
    if a.long:
        if not (a.unit_file and a.coeffs):
            print("--long needs --unit-file and --coeffs", file=sys.stderr)
            return 2
        return long_cli(a.unit_file, a.coeffs, a.long, a.baseline)
    data = Path(a.data) if a.data else next((p for p in CANDIDATES if p.is_dir()), None)
    if data is None:
        print("shared samsat_fm1 data not found; pass --data", file=sys.stderr)
        return 2
    if a.memory:
        return memory(data, a.memory, a.baseline, a.cap, a.sensor, a.coeffs)
    files = [str(data / f) for f in a.files]
    unit = str(data / "unit.toml")
    py = [sys.executable, "-m", "generator.cli"]
    fits, traces = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(a.repeat):
            w, rss, _, cpu = run(py + ["fit", unit, *files, "-o", f"{tmp}/fit{k}"])
            fits.append((w, rss, cpu))
            w, rss, out, cpu = run(py + ["trace", unit, *files, "-o", f"{tmp}/trace{k}"])
            traces.append((w, rss, cpu))
            print(f"run {k + 1}: fit {fits[-1][0]:.1f} s wall, {fits[-1][2]:.1f} s CPU "
                  f"({fits[-1][1]:.0f} MiB); trace {traces[-1][0]:.1f} s wall, "
                  f"{traces[-1][2]:.1f} s CPU ({traces[-1][1]:.0f} MiB); ratio "
                  f"{traces[-1][0] / fits[-1][0]:.2f} wall, "
                  f"{traces[-1][2] / fits[-1][2]:.2f} CPU")
    fit = min(w for w, _, _ in fits)
    trace = min(w for w, _, _ in traces)
    fit_cpu = min(c for _, _, c in fits)
    trace_cpu = min(c for _, _, c in traces)
    print("trace progress (last run):")
    for line in out.splitlines():
        print("  " + line)
    print(f"files: {', '.join(a.files)}")
    print(f"magcal fit   {fit:7.1f} s wall {fit_cpu:7.1f} s CPU   (best of {a.repeat})")
    print(f"magcal trace {trace:7.1f} s wall {trace_cpu:7.1f} s CPU   (best of {a.repeat})")
    print(f"ratio trace / fit = {trace / fit:.2f} wall, {trace_cpu / fit_cpu:.2f} CPU   "
          "(target <= 3)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
