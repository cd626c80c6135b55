"""`magcal trace`: trace what is left in the residual, write trace.json, coefficients and the report."""

from __future__ import annotations

from generator.errors import InputError
from generator.fit.samples import check_max_samples
from generator.io.outputs import check_output_folder, output_folder
from generator.progress import Progress
from generator.report.trace_report import write_report
from generator.trace.subsample import MAX_TRACE_SAMPLES
from generator.trace.tracer import trace


def add_trace_args(p):
    p.add_argument("unit", help="unit file (TOML, ICD section 1)")
    p.add_argument("data", nargs="+", help="telemetry files (ICD section 2: CSV or Parquet) to fit")
    p.add_argument("-o", "--output", required=True, help="output folder")
    p.add_argument("--holdout", nargs="+", default=[], metavar="DATA",
                   help="telemetry files to evaluate on (default: every 5th time block of "
                        "the data is held out)")
    p.add_argument("--coeffs", default=None,
                   help="baseline coefficients.json (default: the core fit of the data)")
    p.add_argument("--max-samples", type=_max_samples, default=MAX_TRACE_SAMPLES, metavar="N",
                   help=f"the most telemetry rows the trace works on (default "
                        f"{MAX_TRACE_SAMPLES}, trace.subsample.MAX_TRACE_SAMPLES; 0: all): "
                        "above it blocks of consecutive rows drawn at random (seed fixed) over "
                        "all the files' blocks in order, as many as the cap holds (the data "
                        "and --holdout files together: with --holdout at least two blocks); "
                        "the error over every row is checked; said in trace.json and the "
                        "notes. Memory: a capped trace keeps ~30 B per row of the whole "
                        "files, plus, for the sensor being traced, the lag recursions' two "
                        "caches (~64 MiB each, but 4-5 series-long arrays at least: up to "
                        "40 B a row each past ~2 million rows a file) and one recursion's temporaries (~50 B a row while "
                        "it runs), on top of what the drawn rows take (the larger part: "
                        "1.3-1.5 GiB peak at the default cap on a 3-sensor unit with "
                        "--coeffs, 250,000 to 3,000,000 rows); the core fit of the data "
                        "(without --coeffs) reads them whole up to 400,000 rows, above as "
                        "magcal fit does, in blocks, streaming (docs/fit_samples.md)")


def _max_samples(text):
    """--max-samples: a whole number >= 0 (fit.samples.check_max_samples; 0: all rows)."""
    import argparse
    try:
        return check_max_samples(int(text))
    except (ValueError, InputError):
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number >= 0 (0: all "
                                         "rows)") from None


def cmd_trace(args) -> int:
    progress = getattr(args, "progress", None) or Progress(quiet=getattr(args, "quiet", False))
    check_output_folder(args.output)
    res = trace(args.unit, args.data, args.holdout, args.coeffs, progress=progress,
                max_samples=getattr(args, "max_samples", MAX_TRACE_SAMPLES))
    res.coefficients.check_plausible(args.data[0] if len(args.data) == 1 else
                                     f"{args.data[0]} (and {len(args.data) - 1} more)")
    with output_folder(args.output) as folder:
        paths = res.write(folder.tmp)
        paths["report"] = write_report(res, folder.tmp)
    paths = {k: folder.final(v) for k, v in paths.items()}
    for n, tr in res.traces.items():
        found = ", ".join(st.effect.label() for st in tr.steps) or (
            "nothing added; " + tr.stop.split(":")[0])
        if tr.unexplained:
            found += (f"; unexplained: {tr.unexplained['rms_above_noise_nT']:.1f} nT above the "
                      "noise floor")
        progress(f"{n}: {tr.baseline_rms_nT:.2f} -> {tr.final_rms_nT:.2f} nT held-out RMS; "
                 f"{found}")
    for w in res.warnings:            # again last, where the user looks
        progress(w)
    if folder.stale_note():
        progress(folder.stale_note())
    progress(f"wrote {paths['trace']}, {paths['coefficients']} and {paths['report']}")
    return 0


