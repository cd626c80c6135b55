"""docs/chain.md, written from the chain definition (not by hand).

    python3 -m generator.report.chain_doc [COEFFS.json] [-o docs/chain.md]

host_tests/test_docs.py regenerates it and requires the committed page to match, so
the documentation of the layout cannot drift from the code.
"""

from __future__ import annotations

import argparse
import inspect
import sys
from pathlib import Path

from generator.flight import chain
from generator.fit.thermal import extrapolation_growth
from generator.flight.coeffs import CoefficientSet, temp_margin_C

# The defaults name the source checkout's files; an installed package has no docs/ and no
# generated/ of its own, so there both arguments must be given.
REPO = Path(__file__).resolve().parents[2]
IN_CHECKOUT = (REPO / "pyproject.toml").is_file() and (REPO / "generator").is_dir()
EXAMPLE = REPO / "generated" / "samsat_fm1" / "coefficients.json"
OUT = REPO / "docs" / "chain.md"


def _shape(b) -> str:
    return "scalar" if not b.shape else "[" + "][".join(map(str, b.shape)) + "]"


def chain_markdown(cs: CoefficientSet) -> str:
    spec = cs.spec
    unit = spec.unit
    lines = [
        "# The correction chain",
        "",
        "_Written by `python3 -m generator.report.chain_doc` from `generator/flight/chain.py`; do not edit._",
        "",
        "## Stages",
        "",
        "```",
        inspect.getdoc(chain).split("Per sensor, per sample")[1].split("The kernels use")[0]
        .strip("\n :"),
        "```",
        "",
        "Optional stages per sensor (`SensorOptions`, the flight forms of traced effects):",
        "",
        "```",
        inspect.getdoc(chain.SensorOptions),
        "```",
        "",
        "## Status bits",
        "",
        "| bit | name | meaning |",
        "|---|---|---|",
    ]
    meanings = {
        "NONFINITE": "a non-finite temperature or auxiliary input: the outputs are zeros",
        "SATURATED": "a count at a rail of the part's range",
        "TEMP_CLAMPED": "temperature further outside the calibrated range than the sensor's "
                        "temp_margin_C (the extrapolated error passes the unit's requirement): "
                        "invalid",
        "IMPLAUSIBLE": "field magnitude outside [field_min_nT, field_max_nT]",
        "DISAGREE": "disagrees with most (and at least two) other valid sensors",
        "NO_OFFSET": "SET-only reading before any SET/RESET pair stored an offset",
        "TEMP_EXTRAPOLATED": "temperature outside the calibrated range (the polynomials see "
                             "the end of the range): informational, the sample stays valid",
    }
    for name, bit in sorted(chain.STATUS_BITS.items(), key=lambda kv: kv[1]):
        lines.append(f"| 0x{bit:02x} | {name} | {meanings[name]} |")
    lines += ["", "A sample is valid (ICD valid = 1) when its status has no bit but the "
              f"informational ones (STATUS_INFO_MASK 0x{chain.STATUS_INFO_MASK:02x}: "
              "TEMP_EXTRAPOLATED).", "",
              "### Outside the calibrated temperature range", "",
              inspect.getdoc(extrapolation_growth), "",
              inspect.getdoc(temp_margin_C), "",
              "## Selection for the attitude system", "",
              inspect.getdoc(chain.ChainSpec.fallback_order), "",
              "| reason | code | meaning |", "|---|---|---|"]
    why = {"CONFIRMED": "the chosen sensor agrees with at least one other valid sensor",
           "SINGLE": "the chosen sensor is the only valid one",
           "UNCONFIRMED": "the chosen sensor disagrees with the only other valid sensor",
           "NONE": "no valid sensor: zero vector"}
    for name, code in sorted(chain.SELECT_REASONS.items(), key=lambda kv: kv[1]):
        lines.append(f"| {name} | {code} | {why[name]} |")
    lines += ["", f"## Coefficient layout of the example unit `{unit.id}`", "",
              f"Float type {unit.float_type}, polynomial degree {spec.poly_degree}, coils "
              f"{', '.join(spec.coils) or 'none'}, layout hash 0x{spec.layout_hash():08x}. "
              "Each sensor's coefficients are one flat array, blocks in this order, row-major; "
              "the unit-wide array follows the sensors. The same order is the C struct, the "
              "uplink table payload and `coefficients.json`.", ""]
    for s in unit.sensors:
        opts = spec.opts(s)
        extra = [k for k, v in opts.to_dict().items() if v]
        lines += [f"### {s.name} ({s.part}, {s.frame} frame, axes {' '.join(s.axes)}"
                  f"{', SET/RESET' if s.set_reset else ''}"
                  f"{', options: ' + ', '.join(extra) if extra else ''})", "",
                  "| offset | block | shape | unit | meaning |", "|---|---|---|---|---|"]
        for b in spec.sensor_blocks(s):
            lines.append(f"| {spec.offsets(spec.sensor_blocks(s))[b.name]} | `{b.name}` | "
                         f"{_shape(b)} | {b.unit} | {b.doc} |")
        lines += ["", f"{spec.n_sensor_coeffs(s)} coefficients.", ""]
    lines += ["### unit-wide", "", "| offset | block | shape | unit | meaning |",
              "|---|---|---|---|---|"]
    for b in spec.unit_blocks():
        lines.append(f"| {spec.offsets(spec.unit_blocks())[b.name]} | `{b.name}` | {_shape(b)} | "
                     f"{b.unit} | {b.doc} |")
    lines += ["", f"{spec.n_unit_coeffs()} coefficients.", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python3 -m generator.report.chain_doc",
                                 description="write docs/chain.md from the chain definition")
    ap.add_argument("coeffs", nargs="?", default=str(EXAMPLE) if IN_CHECKOUT else None,
                    help="coefficients.json (default in a checkout: the example unit's)")
    ap.add_argument("-o", "--output", default=str(OUT) if IN_CHECKOUT else None,
                    help="page to write (default in a checkout: docs/chain.md)")
    args = ap.parse_args(argv)
    if args.coeffs is None or args.output is None:
        ap.error("outside a source checkout give COEFFS.json and -o PAGE.md")
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    Path(args.output).write_text(chain_markdown(CoefficientSet.load(args.coeffs)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
