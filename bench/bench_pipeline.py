#!/usr/bin/env python3
"""Benchmark of the core pipeline: `magcal fit` on the shared thermal campaign and
`magcal generate` + host compile, each against a baseline measured in the same run.

Targets (2-core machine): fit < 5 s and < 1 GB peak memory; generate + compile < 20 s.

    python3 bench/bench_pipeline.py [--repeat 3]

Each measurement runs `magcal` in a fresh subprocess (wall time and peak RSS of that
process, from wait4), so imports and I/O count as a user would see them. Baselines:
fit -> `numpy.loadtxt` of the same CSV (reading the numbers at all); generate+compile ->
`gcc -c` of an empty C file (the compiler's fixed start-up cost) and a bare
`python -c "import generator"` (the interpreter and import cost).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
FM1 = REPO.parent / "shared" / "data" / "samsat_fm1"


def run(cmd, env=None) -> tuple[float, float]:
    """(wall seconds, peak RSS MiB) of one subprocess."""
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    _, status, rusage = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    err = p.stderr.read().decode()
    p.stderr.close()
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"failed: {' '.join(map(str, cmd))}\n{err}")
    return wall, rusage.ru_maxrss / 1024.0


def best(cmd, repeat, env=None):
    runs = [run(cmd, env) for _ in range(repeat)]
    return min(r[0] for r in runs), max(r[1] for r in runs)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    if not FM1.is_dir():
        print(f"shared data not found at {FM1}", file=sys.stderr)
        return 2
    py = sys.executable
    work = Path(tempfile.mkdtemp(prefix="magcal-bench-"))
    env = dict(os.environ, MAGCAL_CACHE=str(work / "cache"))
    thermal = FM1 / "thermal_12pos.csv"
    rows = []

    base_t, base_m = best([py, "-c", f"import numpy; numpy.loadtxt('{thermal}', delimiter=',', "
                                      f"skiprows=3)"], args.repeat)
    rows.append(("baseline: numpy.loadtxt thermal_12pos.csv", base_t, base_m, None, None))
    fit_t, fit_m = best([py, "-m", "generator.cli", "fit", str(FM1 / "unit.toml"), str(thermal),
                         "-o", str(work / "fit"), "-q"], args.repeat, env)
    rows.append(("magcal fit thermal_12pos.csv (36,000 samples, 5 sensors)", fit_t, fit_m,
                 fit_t / base_t, "< 5 s, < 1024 MiB"))

    empty = work / "empty.c"
    empty.write_text("int magcal_bench_empty;\n")
    cc_t, cc_m = best(["gcc", "-std=c99", "-O2", "-c", str(empty), "-o", str(work / "e.o")],
                      args.repeat)
    imp_t, imp_m = best([py, "-c", "import generator.flight.codegen, generator.flight.host"], args.repeat)
    rows.append(("baseline: gcc -c empty.c", cc_t, cc_m, None, None))
    rows.append(("baseline: python import generator.flight.codegen, host", imp_t, imp_m, None, None))
    coeffs = work / "fit" / "coefficients.json"
    gen_runs = []
    for i in range(args.repeat):
        shutil.rmtree(work / "cache", ignore_errors=True)   # cold build every time
        gen_runs.append(run([py, "-m", "generator.cli", "generate", str(coeffs), "-o",
                             str(work / f"gen{i}"), "--compile", "-q"], env))
    gen_t = min(r[0] for r in gen_runs)
    gen_m = max(r[1] for r in gen_runs)
    rows.append(("magcal generate --compile (5 sensors, cold cache)", gen_t, gen_m,
                 gen_t / (cc_t + imp_t), "< 20 s"))

    print(f"{'measurement':60s} {'wall s':>8s} {'peak MiB':>9s} {'x base':>7s}  target")
    for name, t, m, ratio, target in rows:
        r = f"{ratio:7.1f}" if ratio is not None else " " * 7
        print(f"{name:60s} {t:8.2f} {m:9.0f} {r}  {target or ''}")
    ok = fit_t < 5.0 and fit_m < 1024 and gen_t < 20.0
    print("targets met" if ok else "TARGETS MISSED")
    shutil.rmtree(work, ignore_errors=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
