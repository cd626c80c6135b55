"""`magcal`: the one console command (ICD section 3).

Exit status 0 on success, 2 on bad input (one line on stderr), 1 otherwise.
Every verb takes -q/--quiet (no progress lines) and --json (a JSON result on stdout, for
scripts; progress and human output go to stderr). A verb returns its exit status, or
(status, JSON-able result).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
import threading
import warnings
from pathlib import Path

from generator import __version__
from generator.errors import InputError, OutputError

VERBS = {}


def verb(name, help_text):
    def deco(fn):
        VERBS[name] = (fn, help_text)
        return fn
    return deco


def _progress(args):
    """The verb's progress lines (one object per run, see _HeldProgress)."""
    held = getattr(args, "progress", None)
    if held is None:
        held = args.progress = _HeldProgress(quiet=getattr(args, "quiet", False))
    return held


class _HeldProgress:
    """Progress lines (generator.progress.Progress) of which those of the first HOLD_S
    seconds are held back: a verb that fails on its input in that time prints only its
    one error line; once the time has passed, or when the verb succeeds, they are shown."""

    HOLD_S = 1.0

    def __init__(self, quiet=False):
        from generator.progress import Progress

        self.inner = Progress(quiet=quiet)
        self.held = []

    def __call__(self, message: str):
        if self.inner.quiet:
            return
        import time

        t = time.perf_counter() - self.inner.t0
        line = f"[{t:6.1f} s] {message}"
        if self.held is not None and t < self.HOLD_S:
            self.held.append(line)
            return
        self.release()
        print(line, file=self.inner.stream, flush=True)

    @property
    def quiet(self) -> bool:
        return self.inner.quiet

    def release(self):
        for line in self.held or ():
            print(line, file=self.inner.stream, flush=True)
        self.held = None

    def discard(self):
        self.held = None


# ---- verbs --------------------------------------------------------------------------------


@verb("fit", "fit the unit's calibration from telemetry files jointly")
def cmd_fit(args):
    from generator.pipeline import fit
    from generator.report.report import write_fit_report

    from generator.io.outputs import check_output_folder, output_folder

    progress = _progress(args)
    check_output_folder(args.output)
    cs = fit(args.unit, args.data, progress=progress, method=args.method, prior=args.prior,
             accept_misfit=args.accept_misfit, max_samples=args.max_samples)
    cs.check_plausible(args.data[0] if len(args.data) == 1 else
                       f"{args.data[0]} (and {len(args.data) - 1} more)")
    extra = []
    if args.compare_methods:
        from generator.report import compare as fit_compare
        from generator.io.telemetry_csv import read_telemetry
        from generator.io.unitfile import load_unit

        unit = load_unit(args.unit)
        tels = [read_telemetry(p, unit) for p in args.data]
        progress("comparing the fit methods on the same data (ellipsoid, analytic, auto)")
        extra = fit_compare.sections(fit_compare.compare_methods(
            unit, [t for t in tels if t.has("ref_x_nT", "ref_y_nT", "ref_z_nT")] or tels,
            truth=args.truth, evaluate=[t for t in tels if not t.has("ref_x_nT")],
            progress=progress))
    with output_folder(args.output) as folder:
        cs.save(folder.tmp / "coefficients.json")
        report = None if args.no_report else write_fit_report(
            cs, folder.tmp, data_paths=args.data, progress=progress, extra_sections=extra)
    out = folder.target
    if folder.stale_note():
        progress(folder.stale_note())
    from generator.report.report import fit_summary
    if report is None:
        progress(f"wrote {out / 'coefficients.json'} (no report: --no-report)")
        summary = fit_summary(cs, out / "coefficients.json", None)
        summary["report"] = None
        return 0, summary
    report = folder.final(report)
    progress(f"wrote {out / 'coefficients.json'} and {report}")
    return 0, fit_summary(cs, out / "coefficients.json", report)


def _args_fit(p):
    p.add_argument("unit", help="unit file (TOML, ICD section 1)")
    p.add_argument("data", nargs="+", help="telemetry files (ICD section 2): CSV or Parquet")
    p.add_argument("-o", "--output", required=True, help="output folder")
    only_one = p.add_mutually_exclusive_group()
    only_one.add_argument("--compare-methods", action="store_true",
                          help="also fit with every method (seed 000 ellipsoid, seed 001 "
                               "analytic, auto) and compare them in the report")
    only_one.add_argument("--no-report", action="store_true",
                          help="write coefficients.json only: no report and no figures "
                               "(the fit itself, e.g. for long telemetry or scripts)")
    p.add_argument("--truth", default=None,
                   help="truth.json of a simulated unit: the comparison adds errors against it")
    p.add_argument("--prior", default=None, metavar="COEFFS.json",
                   help="a ground calibration (coefficients.json with its 1-sigma): what the "
                        "data do not determine is held at it instead of the part's nominal")
    p.add_argument("--accept-misfit", action="store_true",
                   help="write the calibration even where the vector residual is far beyond "
                        "the noise and the reference's stated error (otherwise exit 2: most "
                        "often reference vectors in another frame); the report and "
                        "coefficients.json then carry a warning")
    p.add_argument("--max-samples", type=_max_samples, default=None, metavar="N",
                   help="the most usable samples of one sensor its fit takes (default "
                        "200000, fit.samples.MAX_FIT_SAMPLES; 0: all): above it one sample "
                        "drawn at random in each block of consecutive samples (seed fixed), "
                        "said in the notes, with the residual over all samples. Files of "
                        "more than 400,000 rows in all (2x the cap) are read as blocks of "
                        "consecutive rows drawn at random, streaming, and the residual "
                        "checked over every row (docs/fit_samples.md); 0 reads every row")
    p.add_argument("--method", default="auto", choices=["auto", "analytic", "ellipsoid"],
                   help="auto: reference vectors where the data carry them (joint or "
                        "per-level cubic, chosen on held-out data), else the ellipsoid fit; "
                        "analytic: seed 001 known vectors, h = Q P R B + b per temperature "
                        "level (needs ref_x/y/z_nT, else falls back to auto); ellipsoid: "
                        "seed 000, magnitudes only (M known up to a rotation)")


def _warn_refused_default(args, cs) -> None:
    """A flagged output (one line on stderr, -q or not) when the flight code's table checks
    would refuse these coefficients: `magcal table` exits 2 on them, and as a compiled-in
    default `<unit>_table_init` replaces them by NaN (review #20d F1)."""
    from generator.flight.tables import default_refusal
    why = default_refusal(cs)
    if why:
        print(f"magcal {args.verb}: warning: {args.coeffs}: the flight code's table checks "
              f"refuse these coefficients ({_one_line(why)}): `magcal table` will not "
              "write them, and as the compiled-in default `<unit>_table_init` replaces "
              "them by NaN (every correction IMPLAUSIBLE); the outputs here are not what "
              "flight would compute", file=sys.stderr)


@verb("apply", "correct telemetry through the compiled flight C")
def cmd_apply(args):
    from generator.flight.coeffs import CoefficientSet
    from generator.pipeline import apply

    from generator.io.outputs import check_output_file, refuse_inputs

    check_output_file(args.output)
    refuse_inputs(args.output, [args.coeffs, args.data])
    cs = CoefficientSet.load(args.coeffs)
    _warn_refused_default(args, cs)
    if args.boom_stowed:
        cs = cs.with_boom_stowed()
    apply(cs, args.data, args.output, progress=_progress(args), coils_off=args.coils_off,
          at_rest=args.at_rest, collect=False)     # streams: memory bounded by the chunk
    return 0


def _args_apply(p):
    p.add_argument("coeffs", help="coefficients.json")
    p.add_argument("data", help="telemetry file (ICD section 2): CSV or Parquet")
    p.add_argument("-o", "--output", required=True,
                   help="output file: Parquet when its name ends in .parquet or .pq (the "
                        "same columns; the CSV's comment lines as key-value metadata), "
                        "else CSV")
    p.add_argument("--boom-stowed", action="store_true",
                   help="the data were taken with the boom stowed (ground jig): H = identity")
    p.add_argument("--coils-off", action="store_true",
                   help="the data were recorded with the magnetorquers off: coil current "
                        "columns absent from the file are 0 A (without it, a coil column "
                        "the chain needs and the file lacks is an error)")
    p.add_argument("--at-rest", action="store_true",
                   help="the data were recorded standing still (a ground jig): body-rate and "
                        "channel columns absent from the file are 0 (without it, a column "
                        "the chain needs and the file lacks is an error)")


@verb("generate", "write the unit's flight C sources and header")
def cmd_generate(args):
    from generator.flight.codegen import generate
    from generator.flight.coeffs import CoefficientSet

    from generator.io.outputs import check_output_folder, output_folder

    check_output_folder(args.output)
    cs = CoefficientSet.load(args.coeffs)
    progress = _progress(args)
    _warn_refused_default(args, cs)
    with output_folder(args.output) as folder:
        paths = generate(cs, folder.tmp)
        if args.compile:     # before the folder is committed: no C left that fails to build
            from generator.flight.host import HostUnit
            HostUnit(cs)
            progress("compiled on the host (-std=c99 -O2 -ffp-contract=off -Werror)")
    for p in paths:
        progress(f"wrote {folder.final(p)}")
    return 0


def _args_generate(p):
    p.add_argument("coeffs", help="coefficients.json")
    p.add_argument("-o", "--output", required=True, help="output folder")
    p.add_argument("--compile", action="store_true", help="also compile on the host")


@verb("demo", "run the whole chain on the bundled example unit")
def cmd_demo(args):
    from generator.demo import run_demo_atomic
    from generator.io.outputs import check_output_folder

    check_output_folder(args.output)
    if getattr(args, "json", False):   # stdout carries the JSON only
        with contextlib.redirect_stdout(sys.stderr):
            rc = run_demo_atomic(Path(args.output), seed=args.seed, progress=_progress(args))
        return rc, {"output": str(Path(args.output)),
                    "report": str(Path(args.output) / "report.html"), "exit": rc}
    return run_demo_atomic(Path(args.output), seed=args.seed, progress=_progress(args))


def _max_samples(text):
    """--max-samples: a whole number >= 0 (0: every usable sample)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"{v} is negative (0: all samples)")
    return v


def _seed(text):
    """A simulator seed: a whole number 0 .. 2**32 - 1 (numpy's range)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if not 0 <= v < 2 ** 32:
        raise argparse.ArgumentTypeError(f"{v} is outside 0 .. 2**32-1")
    return v


def _args_demo(p):
    p.add_argument("-o", "--output", default="magcal_demo", help="output folder")
    p.add_argument("--seed", type=_seed, default=1, help="simulator seed (0 .. 2**32-1)")


@verb("plan", "write the ground-test program of a unit (positions, temperature profile)")
def cmd_plan(args):
    from generator.verbs.plan import run_plan
    return run_plan(args, _progress(args))


def _args_plan(p):
    from generator.campaign import plan as P
    p.add_argument("unit", help="unit file (TOML, ICD section 1)")
    p.add_argument("-o", "--output", required=True,
                   help="output folder: plan.md, plan.html, plan.json, figures")
    p.add_argument("--lab-field-nT", type=float, default=None,
                   help="lab field magnitude, nT (default: the unit's lab_field_nT)")
    p.add_argument("--inclination-deg", type=float, default=P.DEFAULT_INCLINATION_DEG,
                   help=f"lab field inclination, deg (default {P.DEFAULT_INCLINATION_DEG:g})")
    p.add_argument("--levels", type=float, nargs="+", default=list(P.DEFAULT_LEVELS_C),
                   metavar="DEGC", help="chamber temperature levels in order, degC (default "
                   + " ".join(f"{v:g}" for v in P.DEFAULT_LEVELS_C) + ")")
    p.add_argument("--board-tau-min", type=float, default=P.DEFAULT_BOARD_TAU_MIN,
                   help=f"thermal time constant of the slowest board (flight computer, "
                        f"boom board), min (default {P.DEFAULT_BOARD_TAU_MIN:g}: an "
                        f"assumption, see generator/campaign/plan.py; measure it on the first step)")
    p.add_argument("--settle-tol-C", type=float, default=P.DEFAULT_SETTLE_TOL_C,
                   help=f"settled: within this of the level, degC (default "
                        f"{P.DEFAULT_SETTLE_TOL_C:g})")
    p.add_argument("--ramp-C-per-min", type=float, default=P.DEFAULT_RAMP_C_PER_MIN,
                   help=f"chamber ramp rate, degC/min (default {P.DEFAULT_RAMP_C_PER_MIN:g})")
    p.add_argument("--sample-period-s", type=float, default=P.DEFAULT_SAMPLE_PERIOD_S,
                   help=f"sample period, s (default {P.DEFAULT_SAMPLE_PERIOD_S:g})")
    p.add_argument("--samples-per-segment", type=int, default=P.DEFAULT_SAMPLES_PER_SEGMENT,
                   help=f"samples recorded per position and level (default "
                        f"{P.DEFAULT_SAMPLES_PER_SEGMENT})")
    p.add_argument("--room-C", type=float, default=P.DEFAULT_ROOM_C,
                   help=f"room temperature where the jig is turned, degC (default "
                        f"{P.DEFAULT_ROOM_C:g})")
    p.add_argument("--reposition-min", type=float, default=P.DEFAULT_REPOSITION_MIN,
                   help=f"time to turn the jig, min (default {P.DEFAULT_REPOSITION_MIN:g})")


@verb("check", "does a recorded campaign cover the test program? (exit 2 with the gaps)")
def cmd_check(args):
    from generator.campaign.check import run_check
    from generator.io.recordings import refuse_repeated_recordings

    refuse_repeated_recordings(args.data)
    return run_check(args, _progress(args))


def _args_check(p):
    from generator.campaign import check as C
    p.add_argument("unit", help="unit file (TOML, ICD section 1)")
    p.add_argument("data", nargs="+", help="telemetry CSV files of the campaign")
    p.add_argument("--plan", default=None, metavar="PLAN.json",
                   help="the program to check against (magcal plan's plan.json); default: "
                        "magcal plan's default program, applied to static-position files")
    p.add_argument("--noise-nT", type=float, default=None,
                   help="reading noise per axis for the prediction, nT (default: each "
                        "sensor's noise_nT)")
    p.add_argument("--limit-b-nT", type=float, default=C.LIMIT_B_nT,
                   help=f"largest acceptable predicted 1-sigma of an offset, nT (default "
                        f"{C.LIMIT_B_nT:g})")
    p.add_argument("--limit-m", type=float, default=C.LIMIT_M,
                   help=f"largest acceptable predicted 1-sigma of a matrix entry (default "
                        f"{C.LIMIT_M:g})")
    p.add_argument("--min-samples", type=int, default=None,
                   help="settled samples a position and level need (default: the plan's "
                        f"samples per segment, or {C.MIN_SEGMENT_SAMPLES} without --plan)")


@verb("table", "write, decode, diff, split or check an uplink coefficient table")
def cmd_table(args):
    from generator.verbs.table import cmd_table as run

    return run(args)


def _args_table(p):
    from generator.verbs.table import add_table_args

    add_table_args(p)


@verb("trace", "trace structure left in the residual to an effect the model lacks, "
               "add it, report before and after")
def cmd_trace(args):
    from generator.verbs.trace import cmd_trace as run

    return run(args)


def _args_trace(p):
    from generator.verbs.trace import add_trace_args

    add_trace_args(p)


@verb("import", "recordings from elsewhere (PX4 logs, CSV/HDF5 in physical units) -> "
                "unit TOML skeleton and ICD telemetry CSV")
def cmd_import(args):
    from generator.verbs.import_ import cmd_import as run

    return run(args)


def _args_import(p):
    from generator.verbs.import_ import add_import_args

    add_import_args(p)


@verb("simulate", "simulate campaigns of your own unit (thermal following the plan, rotation, "
                  "coils, coil study) and its truth")
def cmd_simulate(args):
    from generator.verbs.simulate import run_simulate

    return run_simulate(args, _progress(args))


def _args_simulate(p):
    from generator.verbs.simulate import add_simulate_args

    add_simulate_args(p)
    p.add_argument("--seed", type=_seed, default=0,
                   help="seed of the simulated unit and its campaigns (0 .. 2**32-1)")


ARGS = {"fit": _args_fit, "apply": _args_apply, "generate": _args_generate, "demo": _args_demo,
        "plan": _args_plan, "check": _args_check, "table": _args_table,
        "trace": _args_trace, "import": _args_import, "simulate": _args_simulate}


class _UsageError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    """Bad usage is one line on stderr (exit 2), like any other bad input."""

    def error(self, message):
        raise _UsageError(f"{self.prog}: {message} (see {self.prog} --help)")


def build_parser(only=None, verbs_args=True) -> argparse.ArgumentParser:
    """The command line's parser. Every verb is listed; its arguments are defined for
    every verb (verbs_args), or for the verb `only` alone: a verb's argument definitions
    import its modules (trace, tables, campaigns: ~1 s together on a loaded 2-core
    machine), which `magcal fit` would otherwise pay before it starts."""
    parser = _Parser(
        prog="magcal", description="Magnetometer calibration toolchain: fit, flight C, tables.")
    parser.add_argument("--version", action="version", version=f"magcal {__version__}")
    parser.add_argument("--debug", action="store_true",
                        help="on an internal fault (exit 1), print the Python traceback")
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    for name, (fn, help_text) in VERBS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if verbs_args or name == only:
            ARGS[name](p)
            if name != "import":           # its sub-commands carry them
                p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
                p.add_argument("--json", action="store_true",
                               help="print a JSON result on stdout (for scripts)")
        p.set_defaults(func=fn)
    return parser


_PARSERS: dict = {}


def _parser(argv=()) -> argparse.ArgumentParser:
    """The parser for this command line, built once per process and verb (main may be
    called many times in-process): the arguments of the verb it names only (the first
    word that is a verb; none for `magcal --help` or a misspelt verb, whose messages do
    not show any verb's arguments)."""
    verb = next((a for a in argv if not a.startswith("-")), None)
    verb = verb if verb in VERBS else None
    if verb not in _PARSERS:
        _PARSERS[verb] = build_parser(only=verb, verbs_args=False)
    return _PARSERS[verb]


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = _parser(argv)
    # --debug is global; accepted anywhere on the line so `magcal fit ... --debug` works too
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]
    try:
        args = parser.parse_args(argv)
    except _UsageError as e:
        print(_one_line(str(e)), file=sys.stderr)
        return 2
    except SystemExit as e:          # argparse: --help and --version
        return int(e.code or 0) if not isinstance(e.code, str) else 2
    if not getattr(args, "func", None):
        parser.print_help()
        print("magcal: no verb given (see magcal --help)", file=sys.stderr)
        return 2
    want_json = getattr(args, "json", False)
    progress = _progress(args)
    previous_term = _raise_on_sigterm()
    try:
        with warnings.catch_warnings():
            if not debug:   # numeric warnings of bad data: the outcome says it, in one line
                warnings.simplefilter("ignore", RuntimeWarning)
            result = args.func(args)
    except InputError as e:
        progress.discard()
        print(f"magcal {args.verb}: {_one_line(str(e))}", file=sys.stderr)
        if want_json:
            _print_json({"verb": args.verb, "exit": 2, "error": str(e)})
        return 2
    except OutputError as e:
        # the system refused to store an output (a full disk, ...): not bad input (2), not
        # an internal fault; io.outputs has removed what was begun (ICD 3: 1 otherwise)
        progress.release()
        print(f"magcal {args.verb}: {_one_line(str(e))}", file=sys.stderr)
        if want_json:
            _print_json({"verb": args.verb, "exit": 1, "error": str(e)})
        return 1
    except (KeyboardInterrupt, _Terminated) as e:
        # Unwinding runs every output's cleanup: nothing half-written stays behind. The
        # exit status is the shell's convention for death by that signal (128 + number).
        progress.release()
        term = isinstance(e, _Terminated)
        print(f"magcal: {'terminated' if term else 'interrupted'}", file=sys.stderr)
        return 128 + (signal.SIGTERM if term else signal.SIGINT)
    except Exception as e:           # a genuine internal fault: one line, or the traceback
        if debug:
            progress.release()
            import traceback
            traceback.print_exc(file=sys.stderr)
        print(f"magcal {args.verb}: internal error: {type(e).__name__}: "
              f"{_one_line(str(e))} (run with --debug for the traceback)", file=sys.stderr)
        if want_json:
            _print_json({"verb": args.verb, "exit": 1, "error": f"{type(e).__name__}: {e}"})
        return 1
    finally:
        _restore_sigterm(previous_term)
    payload = None
    if isinstance(result, tuple):
        result, payload = result
    rc = int(result or 0)
    if rc == 2:            # a verb's own verdict on its input (check): its one line only
        progress.discard()
    else:
        progress.release()
    if want_json:
        _print_json(payload if payload is not None else {"verb": args.verb, "exit": rc})
    return rc


class _Terminated(BaseException):
    """SIGTERM as an exception, so `with` blocks remove their temporary outputs."""


_MAIN_PID = [None]


def _on_sigterm(signum, frame):
    if os.getpid() != _MAIN_PID[0]:
        # a forked worker (a sensor fit or a figure, generator/forked.py) inherited this
        # handler: it ends the way SIGTERM ends it by default, quietly, and its parent
        # cleans up
        os._exit(128 + signal.SIGTERM)
    raise _Terminated()


def _raise_on_sigterm():
    """Turn SIGTERM into _Terminated while a verb runs (main thread only: a library
    caller in another thread keeps its own handling)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    _MAIN_PID[0] = os.getpid()
    return signal.signal(signal.SIGTERM, _on_sigterm)


def _restore_sigterm(previous) -> None:
    if previous is not None:
        signal.signal(signal.SIGTERM, previous)


def _one_line(text: str, limit: int = 400) -> str:
    """A message as one line of bounded length (stderr carries exactly one line)."""
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[:limit] + "..."


def _print_json(obj):
    from generator.flight.coeffs import json_default
    print(json.dumps(obj, indent=1, default=json_default))


if __name__ == "__main__":
    sys.exit(main())
