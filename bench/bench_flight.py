#!/usr/bin/env python3
"""Benchmark of the flight code on the flight processor: instructions per call of each
entry point on the emulated Cortex-M4F against the lower bound of its floating-point
operations, with code size and worst-case stack (generator/flight/target.py measures; the
method and its calibration are in docs/flight_target.md).

The bound (issue 20): the per-call operations of the chain with every constant folded
that can be folded when a table is loaded (scale and axis signs into b and M, H M for boom
sensors, constants squared once), built from the chain definition
(chain.fold_sensor_coeffs / folded_sensor_kernel, arm_measure.flop_bound). Also shown: the
generated kernel's own operations ("kernel flops", issue 7's "min flops") and how many of
them are per call. The kernels are CasADi's code of folded_sensor_kernel on the prepared
coefficients (`<unit>_table_prepare` folds once per table), so for a sensor entry point
the kernel flops equal the bound (docs/flight_target.md: 116-176 both, the example unit);
only select's agreement kernel differs (110 kernel flops, bound 90). And floor/bound:
(bound + one load per folded coefficient and input element + one store per output
element) / bound, what a machine moving one value per instruction needs.

Targets: instructions <= 1.5 x the bound per sensor call (issue 20); <= 2 x the kernel's
flops (issue 7); < 16 KiB code for a whole unit, < 512 B stack per call.

    python3 bench/bench_flight.py [COEFFS.json] [--check]

Without COEFFS.json: the example unit generated/samsat_fm1/coefficients.json, or, when
it is absent, a random SamSat-ION unit with magnetorquer coupling. --check: exit status 1
when a target is missed. Needs gcc-arm-none-eabi, libnewlib-arm-none-eabi and
qemu-system-arm (exit status 2 without them).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "host_tests"))

from generator.flight import target as ta
from generator.flight.coeffs import CoefficientSet  # noqa: E402

EXAMPLE = REPO / "generated" / "samsat_fm1" / "coefficients.json"


def load(path: str | None):
    if path:
        return CoefficientSet.load(path), path
    if EXAMPLE.exists():
        return CoefficientSet.load(EXAMPLE), str(EXAMPLE.relative_to(REPO))
    import numpy as np
    from chain_fixtures import random_coeffs, samsat_unit
    cs = random_coeffs(np.random.default_rng(1), samsat_unit("bench"),
                       coils=("coil_x_A", "coil_y_A", "coil_z_A"))
    return cs, "random SamSat-ION unit with coils (seed 1)"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("coeffs", nargs="?", help="coefficients.json (default: the example unit)")
    ap.add_argument("--check", action="store_true", help="exit 1 when a target is missed")
    args = ap.parse_args(argv)
    miss = ta.missing_tools()
    if miss:
        print(f"missing {', '.join(miss)}; install {' '.join(ta.DEBIAN_PACKAGES)}",
              file=sys.stderr)
        return 2
    cs, label = load(args.coeffs)
    m = ta.measure(cs)
    print(f"unit {cs.unit.id} ({label}), Cortex-M4F on QEMU {ta.MACHINE}")
    print(f"{'entry point':28s} {'insn/call':>9s} {'worst':>6s} {'kernel flops':>12s} "
          f"{'per call':>8s} {'ratio':>6s} {'bound':>6s} {'insn/bound':>10s} {'floor/bound':>11s} "
          f"{'code B':>7s} {'stack B':>7s}")
    ratios, bratios = [], []
    for e in m["entries"]:
        print(f"{e.entry.fn:28s} {e.nominal:9d} {e.worst:6d} {e.flops['flops']:12d} "
              f"{e.bound['kernel_per_call']:8d} {e.ratio:6.2f} {e.bound['flops']:6d} "
              f"{e.bound_ratio:10.2f} {1 + e.bound['moves'] / e.bound['flops']:11.2f} "
              f"{e.code_bytes:7d} {e.stack_static:7d}")
        if e.entry.kind != "select":
            ratios.append(e.ratio)
            bratios.append(e.bound_ratio)
    u = m["unit"]
    stack = max(e.stack_static for e in m["entries"])
    print(f"whole unit: code {u['compiled']['code']} B as compiled, {u['linked_code']} B "
          f"reached from the API; constants {u['compiled']['const']} B")
    cal = m["calibration"]
    print(f"counter: trace exact on {len(cal['trace'])} calibration loops "
          f"({all(t['counted'] == t['expected'] for t in cal['trace'])}); -icount "
          f"{cal['icount_insn_per_tick']:.3f} instructions/tick")
    ok = {"bound": max(bratios) <= ta.TARGET_BOUND_RATIO,
          "ratio": max(ratios) <= ta.TARGET_RATIO,
          "code": u["compiled"]["code"] < ta.TARGET_UNIT_CODE,
          "stack": stack < ta.TARGET_STACK}
    print(f"targets: instructions <= {ta.TARGET_BOUND_RATIO} x bound (sensor calls "
          f"{min(bratios):.2f} .. {max(bratios):.2f}): "
          f"{'met' if ok['bound'] else 'NOT MET'}; "
          f"ratio <= {ta.TARGET_RATIO} (max {max(ratios):.2f}): "
          f"{'met' if ok['ratio'] else 'NOT MET'}; unit code < {ta.TARGET_UNIT_CODE} B: "
          f"{'met' if ok['code'] else 'NOT MET'}; stack < {ta.TARGET_STACK} B (max {stack}): "
          f"{'met' if ok['stack'] else 'NOT MET'}")
    return 1 if args.check and not all(ok.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
