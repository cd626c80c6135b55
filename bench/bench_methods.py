"""The fit methods compared on the shared unit, and the closed form against IPOPT there.

    python bench/bench_methods.py [--data DIR] [--repeat 5] [--markdown OUT.md]

1. compare_methods on thermal_12pos.csv (fitted), scored also on rotation.csv (not
   fitted; the seed's "rotation" row is an ellipsoid fitted to it), with truth.json:
   the table of generator.report.compare with the seed's figures beside ours, and the per-
   level residuals of seed 001's model with and without the rotation R.
2. Timing on the same problems: every constant-temperature level of every sensor that
   the analytic method fitted (its windows in stats), i.e. the readings and reference
   vectors of twelve static positions at one temperature.  Timed: fit_analytic (closed
   form plus candidates and covariance), the bare closed form, IPOPT on the same
   constrained problem (bench_analytic.build_ipopt; built once, solve timed), and the
   rotated extension fit_analytic_rotated.  Prints per-problem times and the median
   ratios; no thresholds.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_analytic import best_of, build_ipopt, closed_form_core  # noqa: E402

from generator.fit.analytic import fit_analytic, fit_analytic_rotated  # noqa: E402
from generator.report.compare import compare_methods, sections  # noqa: E402
from generator.report.document import Report  # noqa: E402
from generator.io.telemetry_csv import preprocess, read_telemetry  # noqa: E402
from generator.io.unitfile import load_unit  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "samsat_fm1"


def level_problems(unit, tel, analytic_cals):
    """(sensor, level temperature, readings, reference vectors) of every fitted level."""
    data = preprocess(tel, unit)
    ref = np.stack([tel.columns[f"ref_{a}_nT"] for a in "xyz"], axis=1)
    t = tel.time_s
    out = []
    for s in unit.sensors:
        st = analytic_cals[s.name].stats
        if st.get("method") != "analytic":
            continue
        for lev in st["segments"]["level_fits"]:
            rows = np.zeros(tel.n, bool)
            for _, t0, t1 in lev["windows_s"]:
                rows |= (t >= t0) & (t <= t1)
            rows &= data[s.name].usable
            out.append((s.name, lev["temp_C"], data[s.name].field_frame_nT[rows], ref[rows]))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--markdown", type=Path, help="also write the report sections here")
    args = parser.parse_args()

    unit = load_unit(args.data / "unit.toml")
    thermal = read_telemetry(args.data / "thermal_12pos.csv", unit)
    rotation = read_telemetry(args.data / "rotation.csv", unit)
    t0 = time.perf_counter()
    result = compare_methods(unit, [thermal], args.data / "truth.json", evaluate=[rotation])
    t_compare = time.perf_counter() - t0
    rep = Report(f"magcal fit methods: unit {unit.id}")
    for sec in sections(result):
        rep.add(sec)
    md = rep.markdown()
    print(md)
    if args.markdown:
        args.markdown.write_text(md)
    fit_s = {r["key"]: r["fit_s"] for r in next(iter(result["sensors"].values()))["rows"]
             if r["fit_s"] is not None}
    print(f"compare_methods {t_compare:.2f} s; fit_unit per method (all five sensors): "
          + ", ".join(f"{k} {v:.2f} s" for k, v in fit_s.items()) + "\n")

    # ---- closed form vs IPOPT on the level problems of the analytic fit
    from generator.fit.thermal import fit_unit
    problems = level_problems(unit, thermal, fit_unit(unit, [thermal], method="analytic"))
    rows = []
    for name, temp, h, B in problems:
        t_fit, fit = best_of(args.repeat, lambda: fit_analytic(h, B))
        t_core, _ = best_of(args.repeat, lambda: closed_form_core(h, B))
        t_build, (solver, solve_args, _) = best_of(1, lambda: build_ipopt(h, B))
        t_solve, res = best_of(args.repeat, lambda: solver(**solve_args))
        status = solver.stats()["return_status"]
        t_rot, _ = best_of(max(1, args.repeat // 2),
                           lambda: fit_analytic_rotated(h, B, analytic=fit))
        x = np.array(res["x"]).ravel()
        dk = float(np.max(np.abs(1 / x[6:9] / fit.k - 1)))
        rows.append((name, temp, len(h), t_fit, t_core, t_build, t_solve, t_rot, dk, status))
    print(f"{'sensor':>6} {'level C':>8} {'N':>5} {'fit ms':>8} {'core ms':>8} {'IPOPT build':>12} "
          f"{'IPOPT solve':>12} {'rotated ms':>11} {'solve/fit':>10} {'solve/core':>11} "
          f"{'max |dk/k|':>11} status")
    for name, temp, n, tf, tc, tb, ts, tr, dk, status in rows:
        print(f"{name:>6} {temp:8.1f} {n:5d} {tf * 1e3:8.3f} {tc * 1e3:8.3f} {tb * 1e3:12.3f} "
              f"{ts * 1e3:12.3f} {tr * 1e3:11.3f} {ts / tf:10.1f} {ts / tc:11.1f} {dk:11.1e} "
              f"{status}")
    med = lambda i: statistics.median(r[i] for r in rows)  # noqa: E731
    ratio = lambda f: statistics.median(f(r) for r in rows)  # noqa: E731
    print(f"\nmedian over {len(rows)} level problems (twelve positions, one temperature): "
          f"fit_analytic {med(3) * 1e3:.3f} ms, closed-form core {med(4) * 1e3:.3f} ms, "
          f"IPOPT solve {med(6) * 1e3:.3f} ms (+ build {med(5) * 1e3:.3f} ms), rotated "
          f"extension {med(7) * 1e3:.3f} ms")
    print(f"median ratio IPOPT solve / fit_analytic {ratio(lambda r: r[6] / r[3]):.1f}, "
          f"/ core {ratio(lambda r: r[6] / r[4]):.1f}; (build + solve) / fit_analytic "
          f"{ratio(lambda r: (r[5] + r[6]) / r[3]):.1f}; rotated / fit_analytic "
          f"{ratio(lambda r: r[7] / r[3]):.1f}")


if __name__ == "__main__":
    main()
