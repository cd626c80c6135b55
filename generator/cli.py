"""`magcal`: the one console command (ICD section 3).

Exit status 0 on success, 2 on bad input (one line on stderr), 1 otherwise.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import __version__
from .errors import InputError

VERBS = {}


def verb(name, help_text):
    def deco(fn):
        VERBS[name] = (fn, help_text)
        return fn
    return deco


def _progress(args):
    from .pipeline import Progress
    return Progress(quiet=getattr(args, "quiet", False))


# ---- verbs --------------------------------------------------------------------------------


@verb("fit", "fit the unit's calibration from telemetry files jointly")
def cmd_fit(args):
    from .pipeline import fit
    from .report import write_fit_report

    progress = _progress(args)
    cs = fit(args.unit, args.data, progress=progress, method=args.method)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    cs.save(out / "coefficients.json")
    report = write_fit_report(cs, out, data_paths=args.data, progress=progress)
    progress(f"wrote {out / 'coefficients.json'} and {report}")
    return 0


def _args_fit(p):
    p.add_argument("unit", help="unit file (TOML, ICD section 1)")
    p.add_argument("data", nargs="+", help="telemetry CSV files (ICD section 2)")
    p.add_argument("-o", "--output", required=True, help="output folder")
    p.add_argument("--method", default="auto", choices=["auto"],
                   help="fit method (auto: reference vectors where the data carry them, "
                        "else the ellipsoid fit)")


@verb("apply", "correct telemetry through the compiled flight C")
def cmd_apply(args):
    from .coeffs import CoefficientSet
    from .pipeline import apply

    cs = CoefficientSet.load(args.coeffs)
    if args.boom_stowed:
        cs = cs.with_boom_stowed()
    apply(cs, args.data, args.output, progress=_progress(args))
    return 0


def _args_apply(p):
    p.add_argument("coeffs", help="coefficients.json")
    p.add_argument("data", help="telemetry CSV")
    p.add_argument("-o", "--output", required=True, help="output CSV")
    p.add_argument("--boom-stowed", action="store_true",
                   help="the data were taken with the boom stowed (ground jig): H = identity")


@verb("generate", "write the unit's flight C sources and header")
def cmd_generate(args):
    from .codegen import generate
    from .coeffs import CoefficientSet

    cs = CoefficientSet.load(args.coeffs)
    paths = generate(cs, args.output)
    progress = _progress(args)
    for p in paths:
        progress(f"wrote {p}")
    if args.compile:
        from .host import HostUnit
        HostUnit(cs)
        progress("compiled on the host (-std=c99 -O2 -ffp-contract=off -Werror)")
    return 0


def _args_generate(p):
    p.add_argument("coeffs", help="coefficients.json")
    p.add_argument("-o", "--output", required=True, help="output folder")
    p.add_argument("--compile", action="store_true", help="also compile on the host")


@verb("demo", "run the whole chain on the bundled example unit")
def cmd_demo(args):
    from .demo import run_demo

    return run_demo(Path(args.output), seed=args.seed, progress=_progress(args))


def _args_demo(p):
    p.add_argument("-o", "--output", default="magcal_demo", help="output folder")
    p.add_argument("--seed", type=int, default=1, help="simulator seed")


ARGS = {"fit": _args_fit, "apply": _args_apply, "generate": _args_generate, "demo": _args_demo}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="magcal", description="Magnetometer calibration toolchain: fit, flight C, tables.")
    parser.add_argument("--version", action="version", version=f"magcal {__version__}")
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    for name, (fn, help_text) in VERBS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        ARGS[name](p)
        p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
        p.set_defaults(func=fn)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except InputError as e:
        print(f"magcal {args.verb}: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("magcal: interrupted", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
