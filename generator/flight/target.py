"""The generated flight C on the flight processor (Cortex-M4F), emulated by QEMU.

Builds a unit's generated sources (codegen.render) with arm-none-eabi-gcc exactly as the
flight build compiles them, links them with a small test runner of our own (start-up code,
linker script for QEMU's `mps2-an386`, a semihosting job interpreter; templates/arm/), runs
it under `qemu-system-arm -M mps2-an386 -semihosting` and reads back the outputs' bit
patterns, so that the tests compare the target's results with chain.reference_sensor bit
for bit. No vendor HAL and no C library are linked (only libgcc, which float32 code does
not use).

It also measures what the flight code costs on the target (`flight_report`):

* code size of each entry point (`<unit>_<sensor>_correct` and every function it calls,
  symbol sizes from the linked ELF) and of the whole unit;
* worst-case stack per call: the -fstack-usage frame sizes summed along the call graph
  (read from the disassembly), checked against the high-water mark of a painted stack;
* instructions executed per call, counted exactly from QEMU's execution trace with one
  instruction per translation block (`-singlestep`/`one-insn-per-tb` + `-d exec,nochain`),
  cross-checked against `-icount shift=0` virtual time read from SysTick, both calibrated
  with a function of known length (see docs/flight_target.md);
* the minimum number of floating-point operations of the chain (the arithmetic
  instructions of the CasADi Function's algorithm), and the ratio.

    python -m generator.flight.target report COEFFS.json -o docs/flight_target.md

This module gathers the three parts, one idea each, under the name the tests, the bench
and the command line use: arm_build (toolchain, flags, runner sources, the cached build),
arm_runner (QEMU, runner jobs, ArmUnit, the shared test vectors) and arm_measure (ELF
analysis, instruction counts, stack, flops, static checks, the report).
"""

from __future__ import annotations

import sys

from generator.flight.arm_build import *  # noqa: F401,F403
from generator.flight.arm_runner import *  # noqa: F401,F403
from generator.flight.arm_measure import *  # noqa: F401,F403
from generator.flight.arm_measure import main
from generator.flight.codegen import render  # noqa: F401  (ta.render in the tests)

if __name__ == "__main__":
    sys.exit(main())
