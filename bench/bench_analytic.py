"""Time the seed-001 closed form against IPOPT on the same random problems.

    python bench/bench_analytic.py [--problems 50] [--repeat 5]

Both solve min Phi subject to alpha_i^2 - beta_i^2 + 1 = 0.  The closed form is timed as
`fit_analytic` (which also evaluates the paper's four candidates, the KKT residuals and the
covariance); IPOPT is timed with the NLP built once per problem (CasADi MX graph + nlpsol)
and, separately, for the solve alone.  Prints per-problem medians and the ratios; no
thresholds.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import casadi as ca
import numpy as np

from generator.fit.analytic import P_from_angles, fit_analytic
from generator.fit.analytic import _normalised, _row1, _row2, _row3, _Sums  # the bare closed form


def random_problem(seed: int):
    rng = np.random.default_rng([2024, seed])
    n = int(round(math.exp(rng.uniform(math.log(12), math.log(2000)))))
    k = rng.uniform(0.8, 1.2, 3)
    e_rad = np.radians(rng.uniform(-3.0, 3.0, 3))
    b_nT = rng.uniform(-3000.0, 3000.0, 3)
    u = rng.normal(size=(n, 3))
    B_nT = u / np.linalg.norm(u, axis=1)[:, None] * rng.uniform(45_000.0, 55_000.0, (n, 1))
    h_nT = B_nT @ (np.diag(k) @ P_from_angles(e_rad)).T + b_nT + rng.normal(size=(n, 3)) * rng.uniform(0, 200)
    return h_nT, B_nT


def build_ipopt(h_nT, B_nT):
    s = math.sqrt(float(np.mean(np.sum(B_nT * B_nT, axis=1))))
    h, B = h_nT / s, B_nT / s
    x = ca.MX.sym("x", 12)
    al, be, ga, bb = x[0:3], x[3:6], x[6:9], x[9:12]
    hc = [ca.DM(h[:, i]) for i in range(3)]
    Bc = [ca.DM(B[:, i]) for i in range(3)]
    r1 = ga[0] * (hc[0] - bb[0]) - Bc[0]
    r2 = be[0] * ga[1] * (hc[1] - bb[1]) - al[0] * Bc[0] - Bc[1]
    r3 = be[1] * be[2] * ga[2] * (hc[2] - bb[2]) - al[1] * be[2] * Bc[0] - al[2] * Bc[1] - Bc[2]
    nlp = {"x": x, "f": ca.sumsqr(r1) + ca.sumsqr(r2) + ca.sumsqr(r3), "g": al**2 - be**2 + 1}
    solver = ca.nlpsol("s", "ipopt", nlp, {"ipopt.print_level": 0, "print_time": False,
                                           "ipopt.sb": "yes", "ipopt.tol": 1e-12})
    args = dict(x0=np.r_[np.zeros(3), np.ones(6), np.zeros(3)],
                lbx=np.r_[np.full(3, -np.inf), np.zeros(3), np.full(6, -np.inf)],
                ubx=np.inf, lbg=0, ubg=0)
    return solver, args, s


def closed_form_core(h_nT, B_nT):
    """Only the closed form: normalise, form the sums, solve the three rows (all 4 roots)."""
    h, B, _, _ = _normalised(h_nT, B_nT)
    sums = _Sums.of(h, B)
    return _row1(sums), _row2(sums), _row3(sums)


def best_of(repeat: int, fn):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", type=int, default=50)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()

    rows = []
    for seed in range(args.problems):
        h, B = random_problem(seed)
        t_closed, fit = best_of(args.repeat, lambda: fit_analytic(h, B))
        t_core, _ = best_of(args.repeat, lambda: closed_form_core(h, B))
        t_build, (solver, solve_args, s) = best_of(1, lambda: build_ipopt(h, B))
        t_solve, res = best_of(args.repeat, lambda: solver(**solve_args))
        x = np.array(res["x"]).ravel()
        diff_k = float(np.max(np.abs(1 / x[6:9] / fit.k - 1)))
        rows.append((len(h), t_closed, t_build, t_solve, diff_k, t_core))

    print(f"{'N':>6} {'fit ms':>8} {'core ms':>8} {'IPOPT build ms':>15} {'IPOPT solve ms':>15} "
          f"{'solve/fit':>10} {'solve/core':>11} {'max |dk/k|':>11}")
    for n, tc, tb, ts, dk, tk in rows:
        print(f"{n:6d} {tc * 1e3:8.3f} {tk * 1e3:8.3f} {tb * 1e3:15.3f} {ts * 1e3:15.3f} "
              f"{ts / tc:10.1f} {ts / tk:11.1f} {dk:11.1e}")
    med = lambda i: statistics.median(r[i] for r in rows)  # noqa: E731
    ratio = lambda num, den: statistics.median(num(r) / den(r) for r in rows)  # noqa: E731
    print(f"\nmedian over {len(rows)} problems: fit_analytic {med(1) * 1e3:.3f} ms, closed-form core "
          f"{med(5) * 1e3:.3f} ms, IPOPT solve {med(3) * 1e3:.3f} ms (+ build {med(2) * 1e3:.3f} ms)")
    print(f"median ratio IPOPT solve / fit_analytic: {ratio(lambda r: r[3], lambda r: r[1]):.1f}, "
          f"/ core: {ratio(lambda r: r[3], lambda r: r[5]):.1f}; "
          f"(build + solve) / fit_analytic: {ratio(lambda r: r[2] + r[3], lambda r: r[1]):.1f}")


if __name__ == "__main__":
    main()
