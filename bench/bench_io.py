#!/usr/bin/env python3
"""Benchmark of telemetry I/O (issue 20): `magcal apply` and `magcal fit --no-report` on
long telemetry, each against baselines measured in the same run.

    python3 bench/bench_io.py [--rows 1000000] [--fit-rows 1000000] [--read-rows 360000]
                              [--fit-cap-rows 200000 --fit-cap 50000]   (0 rows: skip)

The input is the shared thermal campaign repeated (time shifted) to the wanted length.
Every measurement runs in a fresh subprocess: wall time and peak RSS from wait4 (through
a small launcher, so the peak is the command's own: see measured()), so
imports and I/O count as a user sees them. Ratios, not seconds, are the result:

* apply vs pyarrow: `magcal apply` end to end (read, flight C, write) against
  pyarrow.csv reading the same input and writing a float64 table of the output's shape
  (rows x columns) -- a C-speed CSV library doing the I/O alone. Goal: <= 2x.
* apply start-up: `magcal apply` on 10 rows against importing the modules it needs
  (generator and the command line's parser, pyarrow.csv, pyarrow.compute; the build
  cache is keyed by hashes, so a warm start renders nothing).
* apply memory: peak RSS on the full file against a tenth of it (streaming: ~1x).
* read memory: io.telemetry_csv.read_telemetry against numpy.loadtxt of the same file
  (--read-rows rows; the issue measured 606 MB against 129 MB at 360,000 rows).
* fit: `magcal fit --no-report` time and peak RSS on --fit-rows rows, against
  numpy.loadtxt of the same file (reading the numbers at all); peak RSS per sample.
* fit cap (--fit-cap-rows R --fit-cap C): `magcal fit --no-report --max-samples C` on R
  rows against --max-samples 0 (every sample): time and peak ratios, and per sensor the
  capped fit's residual over all samples against the full fit's own (the accuracy the
  subsample gives up; generator/fit/samples.py MAX_FIT_SAMPLES). The fit on --fit-rows
  above runs with the default cap.
* the report's share: `magcal fit` of the shared thermal campaign with the report against
  --no-report (and the imports alone).
* --before CHECKOUT: apply (CSV and Parquet), read and fit of an earlier magcal measured in
  the same run; after/before ratios.

Recorded (stream4, 2026-11-24, 2 shared cores at load ~3.8 from other jobs: the times are
noisy, every "after" ran before its "before"; the memory figures are not):
    python3 bench/bench_io.py --rows 1000000 --fit-rows 1000000 --read-rows 360000 \
        --no-thermal --before <export of ceb8243>
  apply CSV 10^6 rows: 152 MiB peak (before 154), 0.98x the peak on 10^5 rows;
    1.70x pyarrow read+write time
  apply Parquet 10^6 rows (row groups of 64 Ki rows): 175 MiB peak (before 177), 1.03x the
    peak on 10^5 rows. On longer files the old reader grew: pyarrow's pre-buffering and
    reader threads kept what they read ahead (+33 MiB from 4x10^5 to 1.6x10^6 rows,
    host_tests/test_stream_memory.py; 184 -> 294 MiB from 3x10^5 to 4.8x10^6 rows in
    row groups of 3x10^5); now flat (174 MiB at 4.8x10^6 rows in 16 row groups, 179 in one).
    Time after/before 1.27x in this run, but interleaved runs on 4x10^5 rows (best of 3)
    gave 2.61 s after, 3.07 s before: load noise, not the reader.
  read 360,000 rows: 190 MiB peak, before 218 (0.87x); numpy.loadtxt 129 MiB: 1.47x, and
    1.08x counting only the memory above a 10-row read of each (the rest is pyarrow's
    import and code pages, fixed); time 0.52x loadtxt's.
  fit --no-report 10^6 rows: 1444 MiB peak, before 1451 (0.99x), 1.39 KiB per sample
    above the imports; 385 s (before 294 s in this run: load noise; no fit code changed).
    The input layer holds 8 bytes a cell of the file (32 columns: 256 B a sample) and,
    per sensor, the (N, 3) field and chip offset (48 B); the rest of the peak is made in
    the fit's own design matrices (generator/fit/reference.py: lstsq, Gauss-Newton).
  trace 10^5 rows (measured alone, `magcal trace unit.toml <10^5 rows> -o ...` through
    measured()): 129 s, 1389 MiB peak, about 13 KiB a sample: 10^6 rows would need
    ~13 GiB. The trace keeps per-sample design columns (generator/trace/*); its input is
    the reader above.

Recorded (sub6, 2026-11-24, 2 shared cores at load ~4; times noisy, memory not):
    python3 bench/bench_io.py --rows 0 --read-rows 0 --fit-rows 0 --no-thermal \
        --fit-cap-rows 200000 --fit-cap 50000
  fit --no-report 2x10^5 rows: --max-samples 50000 14.96 s, 321 MiB peak; --max-samples 0
    (every sample) 21.95 s, 380 MiB: 0.68x the time, 0.84x the peak. What is left is not
    the fit: reading every row, the screens and segments on every sample (on purpose) and
    the imports. The capped fit's residual over all 2x10^5 samples was 1.0001 to 1.0002
    times the full fit's (per sensor), as the cap's argument predicts: 1 + p / (2 n_eq) =
    1.00016 for p = 48 and n_eq = 3 x 50,000 equations.
    python3 bench/bench_io.py --rows 0 --read-rows 0 --fit-rows 0 --no-thermal \
        --fit-cap-rows 1000000 --fit-cap 200000          (the default cap)
  fit --no-report 10^6 rows: default cap (200,000 per sensor, one sample in 5) 45.93 s,
    775 MiB peak; every sample 113.47 s, 1182 MiB: 0.40x the time, 0.66x the peak. The
    residual over all 10^6 samples: 1.0000 to 1.0001 times the full fit's. (A separate run,
    --fit-rows 1000000 with the default cap: 40.74 s, 774 MiB, 0.70 KiB per sample above
    the imports.)

Recorded (fitmem14, 2026-11-25, 2 shared cores at load ~4.2-5.1 from other jobs: times
noisy, memory not; --before an export of main c6ef128, measured in the same run):
    python3 bench/bench_io.py --rows 0 --read-rows 0 --no-thermal \
        --fit-rows 1000000 3000000 --before <export of c6ef128> --before-fit-rows 1000000
  fit --no-report 10^6 rows, the read cap (fit/read_cap.py: 399,600 of the 10^6 rows read
    in 333 blocks of 1,200 rows; every row checked after the fit): 35.87 s, 579 MiB peak;
    c6ef128 (every row read, its sample cap) 47.27 s, 1324 MiB: after/before 0.76x time,
    0.44x memory.
  fit --no-report 3x10^6 rows: 55.85 s, 579 MiB peak (c6ef128 not run: ~1.3 KiB a row, ~4
    GiB). The peak does not grow with the file: 579 MiB at 10^6 and at 3x10^6 rows (1.00x,
    -0.2 B a row); the time grows by the two streaming passes over every row (~10 s per
    10^6 rows here; numpy.loadtxt alone reads 3x10^6 rows in 24.20 s).
  The residual over every usable row against the fit's own (199,800 samples per sensor):
    27.807 / 27.789 nT (mmc1), 249.223 / 249.145 (mpu1), 250.810 / 250.822 (mpu2),
    28.651 / 28.687 (mmc2), 260.059 / 260.160 nT (mpu3) at 10^6 rows; the same to 0.2 %
    at 3x10^6.
  Before this run, measured() ran its commands in the caller's working directory, where
  `python -m generator.cli` imports the checkout in that directory ahead of PYTHONPATH: a
  --before run launched from a checkout measured that checkout, not --before (a first run
  of the above from the worktree gave "before" 48.87 s, 579 MiB: today's code). Earlier
  records' after/before figures may share that fault; they now run from the temporary
  directory.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
FM1 = Path(os.environ.get("MAGCAL_SHARED") or REPO.parent / "shared") / "data" / "samsat_fm1"
COEFFS = REPO / "generated" / "samsat_fm1" / "coefficients.json"
ENV = dict(os.environ, PYTHONPATH=str(REPO))
PY = sys.executable


def write_long_file(src: Path, path: Path, rows: int) -> int:
    """src's comment and header lines, then its data rows repeated until `rows`, each
    repetition shifted in time after the last; returns the file size in bytes."""
    lines = src.read_text().split("\n")
    head = [ln for ln in lines[:10] if ln.startswith("#")]
    header = lines[len(head)]
    data = [ln for ln in lines[len(head) + 1:] if ln and not ln.startswith("#")]
    t_end = float(data[-1].split(",", 1)[0]) + 1.0
    with open(path, "w") as f:
        f.write("\n".join(head + [header]) + "\n")
        k = 0
        while k * len(data) < rows:
            take = data[:rows - k * len(data)]
            f.write("".join(f"{float(t) + k * t_end!r},{rest}\n"
                            for t, rest in (ln.split(",", 1) for ln in take)))
            k += 1
    return path.stat().st_size



def write_long_parquet(src: Path, path: Path, rows: int, row_group_rows: int = 65536) -> int:
    """src's columns (as pyarrow.csv reads them: counts int64, the others float64, empty
    cells null) repeated until `rows`, time shifted after the last as in write_long_file,
    in a Parquet file of row groups of row_group_rows; src's '# key: value' lines are the
    file's metadata. Returns the file size in bytes."""
    import pyarrow as pa
    import pyarrow.csv as pcsv
    import pyarrow.parquet as pq

    skip = _comment_lines(src)
    meta = {}
    with open(src) as f:
        for line in (next(f) for _ in range(skip)):
            key, sep, value = line[1:].partition(":")
            if sep and key.strip().isidentifier():
                meta[key.strip()] = value.strip()
    table = pcsv.read_csv(src, read_options=pcsv.ReadOptions(skip_rows=skip))
    table = table.replace_schema_metadata(meta)
    t = table.column("time_s").cast(pa.float64())
    t_end = pa.compute.max(t).as_py() + 1.0
    with pq.ParquetWriter(path, table.schema.set(0, pa.field("time_s", pa.float64()))
                          .with_metadata(meta)) as w:
        k = 0
        while k * table.num_rows < rows:
            part = table.slice(0, rows - k * table.num_rows)
            shifted = pa.compute.add(t.slice(0, part.num_rows), k * t_end)
            w.write_table(part.set_column(0, "time_s", shifted).replace_schema_metadata(meta),
                          row_group_size=row_group_rows)
            k += 1
    return path.stat().st_size


# wait4's ru_maxrss counts the child's memory before exec too: a fork of this process
# (tens to hundreds of MiB after writing the inputs) would set the floor of every figure.
# A small launcher (a bare interpreter, about 10 MiB) starts the command and reports its
# peak and wall time; the max with the launcher's size is then the command's own peak.
_LAUNCHER = """
import os, subprocess, sys, time
t0 = time.perf_counter()
p = subprocess.Popen(sys.argv[1:])
_, status, ru = os.wait4(p.pid, 0)
sys.stderr.write(f"\\n@@measured {time.perf_counter() - t0!r} {ru.ru_maxrss} "
                 f"{os.waitstatus_to_exitcode(status)}\\n")
"""


def measured(cmd, env=None) -> tuple[float, float, int, str, str]:
    """(wall seconds, peak RSS MiB, exit code, stdout, stderr) of one command run in a
    fresh process (through _LAUNCHER: the peak is the command's own)."""
    # cwd outside any checkout: `python -m generator.cli` puts the working directory first
    # on sys.path, so run from a checkout it would import that checkout's generator/ and
    # not PYTHONPATH's (a --before run would measure today's code)
    p = subprocess.run([PY, "-c", _LAUNCHER, *map(str, cmd)], capture_output=True,
                       env=env or ENV, cwd=tempfile.gettempdir())
    err = p.stderr.decode()
    head, _, last = err.rstrip("\n").rpartition("\n@@measured ")
    wall, kib, code = last.split()
    return float(wall), int(kib) / 1024.0, int(code), p.stdout.decode(), head


def run(cmd, env=None) -> tuple[float, float]:
    """(wall seconds, peak RSS MiB) of one subprocess."""
    wall, peak, code, _, err = measured(cmd, env)
    if code != 0:
        raise SystemExit(f"failed: {' '.join(map(str, cmd))}\n{err}")
    return wall, peak


def best(cmd, repeat, env=None) -> tuple[float, float]:
    runs = [run(cmd, env) for _ in range(repeat)]
    return min(r[0] for r in runs), max(r[1] for r in runs)


def _comment_lines(path) -> int:
    n = 0
    with open(path) as f:
        for line in f:
            if not line.startswith("#"):
                return n
            n += 1
    return n


# ---- workers (run in their own process) -----------------------------------------------------

def worker(kind: str, args: list) -> None:
    if kind == "arrow":            # read the input, write a float64 table of the output's shape
        import pyarrow as pa
        import pyarrow.csv as pcsv

        src, out, ncol = args[0], args[1], int(args[2])
        table = pcsv.read_csv(src, read_options=pcsv.ReadOptions(
            skip_rows=_comment_lines(src)))
        cols = [table.column(j % table.num_columns).cast(pa.float64()) for j in range(ncol)]
        pcsv.write_csv(pa.table(cols, names=[f"c{j}" for j in range(ncol)]), out)
    elif kind == "loadtxt":
        import numpy as np

        np.loadtxt(args[0], delimiter=",", comments="#", skiprows=_comment_lines(args[0]) + 1)
    elif kind == "read":
        from generator.io.telemetry_csv import read_telemetry
        from generator.io.unitfile import load_unit

        read_telemetry(args[0], load_unit(args[1]))
    elif kind == "imports":          # the modules `magcal apply` imports, nothing run
        import pyarrow.compute  # noqa: F401
        import pyarrow.csv  # noqa: F401

        import generator.cli
        import generator.flight.coeffs  # noqa: F401
        import generator.flight.host  # noqa: F401
        import generator.pipeline  # noqa: F401

        generator.cli._parser(["apply"])   # the verb's argument definitions import its modules
    else:
        raise SystemExit(f"unknown worker {kind}")


def _worker_cmd(kind, *args):
    return [PY, Path(__file__).resolve(), "--worker", kind, *args]


def _apply_cmd(data, out):
    return [PY, "-m", "generator.cli", "apply", COEFFS, data, "-o", out, "--boom-stowed",
            "--coils-off", "--at-rest", "--quiet"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=1_000_000, help="apply input rows (0: skip)")
    ap.add_argument("--fit-rows", type=int, nargs="+", default=[1_000_000],
                    help="fit input rows, one or more lengths (0: skip)")
    ap.add_argument("--before-fit-rows", type=int, default=1_000_000,
                    help="the longest fit input --before runs too (an uncapped fit holds "
                         "~1.4 KiB a row: 3x10^6 rows would need ~4 GiB)")
    ap.add_argument("--read-rows", type=int, default=360_000,
                    help="read-memory rows (0: skip)")
    ap.add_argument("--fit-cap-rows", type=int, default=0,
                    help="rows of the capped-against-uncapped fit comparison (0: skip; "
                         "e.g. 200000)")
    ap.add_argument("--fit-cap", type=int, default=50_000,
                    help="--max-samples of that comparison's capped fit")
    ap.add_argument("--trace-rows", type=int, default=0,
                    help="`magcal trace` input rows (0: skip; about 13 KiB a sample)")
    ap.add_argument("--no-thermal", dest="thermal", action="store_false",
                    help="skip the fit of the shared thermal campaign with and without report")
    ap.add_argument("--before", type=Path, default=None,
                    help="a checkout of an earlier magcal: its apply, read and fit are "
                         "measured in the same run (before/after ratios)")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--worker", nargs="+", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        worker(a.worker[0], a.worker[1:])
        return 0

    from generator.flight.coeffs import CoefficientSet

    cs = CoefficientSet.load(COEFFS)
    n_out_cols = 1 + 5 * len(cs.unit.sensors) + 5
    res = {}
    env_before = dict(os.environ, PYTHONPATH=str(a.before)) if a.before else None

    def before_after(name, cmd, t, m):
        """The same command on the --before checkout: print and record the ratios."""
        if env_before is None:
            return
        t0, m0 = best(cmd, a.repeat, env_before)
        res[f"{name}_time_after_vs_before"] = t / t0
        res[f"{name}_memory_after_vs_before"] = m / m0
        print(f"  before ({a.before}): {t0:.2f} s, {m0:.0f} MiB | after/before: time "
              f"{t / t0:.2f}x, memory {m / m0:.2f}x")

    with tempfile.TemporaryDirectory(prefix="bench_io-") as tmp:
        tmp = Path(tmp)
        src = FM1 / "thermal_12pos.csv"
        unit = FM1 / "unit.toml"
        if a.rows:
            big, tenth, tiny = tmp / "big.csv", tmp / "tenth.csv", tmp / "tiny.csv"
            size = write_long_file(src, big, a.rows)
            write_long_file(src, tenth, a.rows // 10)
            write_long_file(src, tiny, 10)
            print(f"input: {a.rows} rows, {size / 2**20:.0f} MiB; output {n_out_cols} columns")
            run(_apply_cmd(tiny, tmp / "warm.csv"))        # the host build in the cache
            if env_before:
                run(_apply_cmd(tiny, tmp / "warm0.csv"), env_before)

            t_apply, m_apply = best(_apply_cmd(big, tmp / "out.csv"), a.repeat)
            t_arrow, m_arrow = best(_worker_cmd("arrow", big, tmp / "arrow.csv", n_out_cols),
                                    a.repeat)
            res["apply_vs_pyarrow_time"] = t_apply / t_arrow
            print(f"apply {a.rows} rows: {t_apply:.2f} s, {m_apply:.0f} MiB peak | pyarrow "
                  f"read+write same shape: {t_arrow:.2f} s, {m_arrow:.0f} MiB | ratio "
                  f"{t_apply / t_arrow:.2f}x (goal <= 2x)")
            before_after("apply_csv", _apply_cmd(big, tmp / "out0.csv"), t_apply, m_apply)

            t_start, _ = best(_apply_cmd(tiny, tmp / "o_tiny.csv"), max(a.repeat, 3))
            t_imp, _ = best(_worker_cmd("imports"), max(a.repeat, 3))
            res["apply_startup_vs_imports"] = t_start / t_imp
            print(f"apply start-up (10 rows): {t_start:.2f} s | imports alone: {t_imp:.2f} s | "
                  f"ratio {t_start / t_imp:.2f}x")

            _, m_tenth = best(_apply_cmd(tenth, tmp / "o_tenth.csv"), a.repeat)
            res["apply_memory_full_vs_tenth"] = m_apply / m_tenth
            print(f"apply peak RSS: {m_apply:.0f} MiB on {a.rows} rows, {m_tenth:.0f} MiB on "
                  f"{a.rows // 10}: ratio {m_apply / m_tenth:.2f}x (streaming: ~1x)")

            # Parquet: the same rows, row groups of 64 Ki rows (as a writer makes them)
            pbig, ptenth = tmp / "big.parquet", tmp / "tenth.parquet"
            psize = write_long_parquet(src, pbig, a.rows)
            write_long_parquet(src, ptenth, a.rows // 10)
            t_pq, m_pq = best(_apply_cmd(pbig, tmp / "out_pq.csv"), a.repeat)
            _, m_pq10 = best(_apply_cmd(ptenth, tmp / "out_pq10.csv"), a.repeat)
            res["apply_parquet_memory_full_vs_tenth"] = m_pq / m_pq10
            res["apply_parquet_vs_csv_time"] = t_pq / t_apply
            print(f"apply Parquet {a.rows} rows ({psize / 2**20:.0f} MiB): {t_pq:.2f} s "
                  f"({t_pq / t_apply:.2f}x the CSV's), {m_pq:.0f} MiB peak, {m_pq10:.0f} MiB on "
                  f"{a.rows // 10}: ratio {m_pq / m_pq10:.2f}x (streaming: ~1x)")
            before_after("apply_parquet", _apply_cmd(pbig, tmp / "out_pq0.csv"), t_pq, m_pq)

        if a.read_rows:
            rd, rd_tiny = tmp / "read.csv", tmp / "read_tiny.csv"
            write_long_file(src, rd, a.read_rows)
            write_long_file(src, rd_tiny, 10)
            t_read, m_read = best(_worker_cmd("read", rd, unit), a.repeat)
            t_ltx, m_ltx = best(_worker_cmd("loadtxt", rd), a.repeat)
            _, m_read0 = best(_worker_cmd("read", rd_tiny, unit), a.repeat)
            _, m_ltx0 = best(_worker_cmd("loadtxt", rd_tiny), a.repeat)
            res["read_vs_loadtxt_memory"] = m_read / m_ltx
            res["read_vs_loadtxt_memory_above_10_rows"] = (m_read - m_read0) / (m_ltx - m_ltx0)
            res["read_vs_loadtxt_time"] = t_read / t_ltx
            print(f"read {a.read_rows} rows: {t_read:.2f} s, {m_read:.0f} MiB peak | "
                  f"numpy.loadtxt: {t_ltx:.2f} s, {m_ltx:.0f} MiB | memory ratio "
                  f"{m_read / m_ltx:.2f}x, time ratio {t_read / t_ltx:.2f}x; above a 10-row "
                  f"read (imports, code pages): {m_read - m_read0:.0f} vs {m_ltx - m_ltx0:.0f} "
                  f"MiB, {(m_read - m_read0) / (m_ltx - m_ltx0):.2f}x")
            before_after("read", _worker_cmd("read", rd, unit), t_read, m_read)

        fit_peaks = {}
        for rows in [r for r in a.fit_rows if r]:
            fd = tmp / "fit.csv"
            write_long_file(src, fd, rows)
            fit_cmd = [PY, "-m", "generator.cli", "fit", unit, fd, "-o", tmp / "fit_out",
                       "--no-report", "--quiet"]
            t_fit, m_fit = best(fit_cmd, 1)
            fit_peaks[rows] = m_fit
            t_fl, m_fl = best(_worker_cmd("loadtxt", fd), 1)
            _, m_imp = best(_worker_cmd("imports"), 1)
            res[f"fit_{rows}_vs_loadtxt_time"] = t_fit / t_fl
            res[f"fit_{rows}_vs_loadtxt_memory"] = m_fit / m_fl
            cap = json.loads((tmp / "fit_out" / "coefficients.json").read_text())
            f0 = cap["fit"]["sensors"]["mmc1"]["stats"]["files"][0]
            read = (f"read {f0['rows_read']:,} of {f0['rows']:,} rows" if "rows_read" in f0
                    else "read every row")
            print(f"fit --no-report {rows} rows ({read}): {t_fit:.2f} s, {m_fit:.0f} MiB peak "
                  f"({(m_fit - m_imp) * 2**20 / rows / 1024:.2f} KiB per sample above "
                  f"the imports) | numpy.loadtxt: {t_fl:.2f} s, {m_fl:.0f} MiB | ratios "
                  f"{t_fit / t_fl:.2f}x time, {m_fit / m_fl:.2f}x memory")
            for name, v in cap["fit"]["sensors"].items():
                alls, own = v["stats"].get("all_samples_residual_nT"), v["stats"]["fit"]
                if alls:
                    key = "rms_vector_nT" if alls["rms_vector_nT"] is not None else "rms_norm_nT"
                    print(f"  {name}: {key} over all {alls['n']:,} samples {alls[key]:.3f} nT, "
                          f"on the fit's own {own.get('n', '?')}: {own[key]:.3f} nT")
            if rows <= a.before_fit_rows:
                fit_cmd[fit_cmd.index(tmp / "fit_out")] = tmp / "fit_out0"
                before_after(f"fit_{rows}", fit_cmd, t_fit, m_fit)
            fd.unlink()
        if len(fit_peaks) > 1:          # bounded memory: the peak's growth per row
            (r0, p0), (r1, p1) = min(fit_peaks.items()), max(fit_peaks.items())
            res["fit_peak_longest_vs_shortest"] = p1 / p0
            print(f"fit peak {p0:.0f} MiB at {r0} rows, {p1:.0f} MiB at {r1}: "
                  f"{p1 / p0:.2f}x, {(p1 - p0) * 2**20 / (r1 - r0):.1f} B per row")
        if a.fit_cap_rows:     # the subsample's cost and gain, both in this run
            fc = tmp / "fit_cap.csv"
            write_long_file(src, fc, a.fit_cap_rows)

            def cap_cmd(n):
                return [PY, "-m", "generator.cli", "fit", unit, fc, "-o", tmp / f"cap_{n}",
                        "--no-report", "--quiet", "--max-samples", str(n)]
            t_c, m_c = best(cap_cmd(a.fit_cap), a.repeat)
            t_0, m_0 = best(cap_cmd(0), a.repeat)
            res["fit_cap_vs_all_time"] = t_c / t_0
            res["fit_cap_vs_all_memory"] = m_c / m_0
            print(f"fit --no-report {a.fit_cap_rows} rows: --max-samples {a.fit_cap} "
                  f"{t_c:.2f} s, {m_c:.0f} MiB peak | --max-samples 0 (all) {t_0:.2f} s, "
                  f"{m_0:.0f} MiB | ratios {t_c / t_0:.2f}x time, {m_c / m_0:.2f}x memory")
            # what the subsample costs in accuracy: its residual over every usable sample
            # against the residual of the fit of all of them
            capped = json.loads((tmp / f"cap_{a.fit_cap}" / "coefficients.json").read_text())
            full = json.loads((tmp / "cap_0" / "coefficients.json").read_text())
            for name, v in capped["fit"]["sensors"].items():
                alls = v["stats"]["all_samples_residual_nT"]
                own = full["fit"]["sensors"][name]["stats"]["fit"]
                key = "rms_vector_nT" if alls["rms_vector_nT"] is not None else "rms_norm_nT"
                res[f"fit_cap_residual_{name}_vs_all"] = alls[key] / own[key]
                print(f"  {name}: {key} over all {alls['n']} samples {alls[key]:.3f} nT "
                      f"(capped fit) vs {own[key]:.3f} nT (fit of all): "
                      f"{alls[key] / own[key]:.4f}x")
        if a.trace_rows:
            td = tmp / "trace.csv"
            write_long_file(src, td, a.trace_rows)
            t_tr, m_tr = best([PY, "-m", "generator.cli", "trace", unit, td, "-o",
                               tmp / "trace_out", "--quiet"], 1)
            t_tl, m_tl = best(_worker_cmd("loadtxt", td), 1)
            _, m_imp = best(_worker_cmd("imports"), 1)
            res["trace_vs_loadtxt_memory"] = m_tr / m_tl
            print(f"trace {a.trace_rows} rows: {t_tr:.2f} s, {m_tr:.0f} MiB peak "
                  f"({(m_tr - m_imp) * 2**20 / a.trace_rows / 1024:.2f} KiB per sample above "
                  f"the imports) | numpy.loadtxt: {t_tl:.2f} s, {m_tl:.0f} MiB")
        if a.thermal:          # the report's share of a fit on the shared campaign
            th = FM1 / "thermal_12pos.csv"
            t_nr, m_nr = best([PY, "-m", "generator.cli", "fit", FM1 / "unit.toml", th, "-o",
                               tmp / "th_nr", "--no-report", "--quiet"], a.repeat)
            t_r, m_r = best([PY, "-m", "generator.cli", "fit", FM1 / "unit.toml", th, "-o",
                             tmp / "th_r", "--quiet"], a.repeat)
            t_imp, _ = best(_worker_cmd("imports"), a.repeat)
            res["thermal_fit_report_vs_no_report_time"] = t_r / t_nr
            print(f"fit thermal_12pos: {t_nr:.2f} s with --no-report ({t_nr - t_imp:.2f} s "
                  f"above the imports), {t_r:.2f} s with the report: the report adds "
                  f"{t_r - t_nr:.2f} s ({t_r / t_nr:.2f}x); peak {m_nr:.0f} / {m_r:.0f} MiB")
    print(json.dumps({k: round(v, 3) for k, v in res.items()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
