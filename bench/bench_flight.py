#!/usr/bin/env python3
"""Benchmark of the flight code on the flight processor: instructions per call of each
entry point on the emulated Cortex-M4F divided by the minimum floating-point operations
of its chain, with code size and worst-case stack (generator/flight/target.py measures; the
method and its calibration are in docs/flight_target.md).

Targets (issue 7): instructions <= 2 x min flops per sensor call, < 16 KiB code for a
whole unit, < 512 B stack per call.

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
    print(f"{'entry point':28s} {'insn/call':>9s} {'worst':>6s} {'min flops':>9s} "
          f"{'ratio':>6s} {'code B':>7s} {'stack B':>7s}")
    ratios = []
    for e in m["entries"]:
        print(f"{e.entry.fn:28s} {e.nominal:9d} {e.worst:6d} {e.flops['flops']:9d} "
              f"{e.ratio:6.2f} {e.code_bytes:7d} {e.stack_static:7d}")
        if e.entry.kind != "select":
            ratios.append(e.ratio)
    u = m["unit"]
    stack = max(e.stack_static for e in m["entries"])
    print(f"whole unit: code {u['compiled']['code']} B as compiled, {u['linked_code']} B "
          f"reached from the API; constants {u['compiled']['const']} B")
    cal = m["calibration"]
    print(f"counter: trace exact on {len(cal['trace'])} calibration loops "
          f"({all(t['counted'] == t['expected'] for t in cal['trace'])}); -icount "
          f"{cal['icount_insn_per_tick']:.3f} instructions/tick")
    ok = {"ratio": max(ratios) <= ta.TARGET_RATIO,
          "code": u["compiled"]["code"] < ta.TARGET_UNIT_CODE,
          "stack": stack < ta.TARGET_STACK}
    print(f"targets: ratio <= {ta.TARGET_RATIO} (max {max(ratios):.2f}): "
          f"{'met' if ok['ratio'] else 'NOT MET'}; unit code < {ta.TARGET_UNIT_CODE} B: "
          f"{'met' if ok['code'] else 'NOT MET'}; stack < {ta.TARGET_STACK} B (max {stack}): "
          f"{'met' if ok['stack'] else 'NOT MET'}")
    return 1 if args.check and not all(ok.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
