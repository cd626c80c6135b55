"""`magcal simulate UNIT.toml [--plan PLAN.json] [--seed N] [--truth TRUTH] -o DIR`:
campaigns of a user's own unit from the project's simulator (docs/simulate.md).

Writes DIR/unit.toml (the unit file as given), DIR/truth.json (the simulated unit's
parameters: what a fit should recover, and under "simulation" the seed, the magcal version
and the options of the run), DIR/plan.json (the program the thermal campaign followed)
and per campaign DIR/<campaign>.csv (ICD telemetry) with <campaign>.truth.npz.

DIR must be new or empty: one run's files belong together (its truth is what its campaigns
were drawn from), and campaigns of two runs in one folder would be fitted against the
wrong truth. --force writes into a folder that is not empty: each file of this run
replaces its namesake atomically (written beside it, then renamed); files of this run's
names only are replaced, others are kept and listed in a note.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

from generator.errors import InputError
from generator.io.outputs import check_output_folder, output_folder
from generator.io.unitfile import load_unit

CAMPAIGNS = ("thermal_12pos", "rotation", "coils", "coil_study")
DEFAULT_SAMPLE_PERIOD_S = 60.0        # thermal campaign without --plan: one sample a minute,
DEFAULT_SAMPLES_PER_SEGMENT = 10      # 10 per segment (the segment finder's 10 min)


def add_simulate_args(p):
    p.add_argument("unit", help="unit file (TOML, ICD sections 1 and 4)")
    p.add_argument("-o", "--output", required=True, help="output folder")
    p.add_argument("--plan", default=None, metavar="PLAN.json",
                   help="the test program to follow (magcal plan's plan.json); default: the "
                        "program magcal plan writes for the unit, with the holds from the "
                        "simulated boards' time constants")
    p.add_argument("--truth", default=None, metavar="TRUTH.json|.toml",
                   help="set parameters of the simulated unit (keys of truth.json; the rest "
                        "is drawn with the seed); see docs/simulate.md")
    p.add_argument("--campaigns", nargs="+", default=list(CAMPAIGNS), choices=CAMPAIGNS,
                   help="which campaigns (default: all)")
    p.add_argument("--sample-period-s", type=float, default=None,
                   help=f"thermal campaign without --plan: sample period (default "
                        f"{DEFAULT_SAMPLE_PERIOD_S:g} s)")
    p.add_argument("--samples-per-segment", type=int, default=None,
                   help=f"thermal campaign without --plan: samples recorded per hold "
                        f"(default {DEFAULT_SAMPLES_PER_SEGMENT})")
    p.add_argument("--force", action="store_true",
                   help="write into an output folder that is not empty: the files of this "
                        "run replace their namesakes (atomically), other files are kept")


def check_empty_folder(path, force: bool) -> list:
    """The entries of an existing output folder (sorted names); InputError when it has any
    and force is not given: a run's files belong together."""
    p = Path(path)
    if not p.is_dir():
        return []
    try:
        names = sorted(e.name for e in p.iterdir())
    except OSError as e:
        raise InputError(path, f"output folder: cannot list it: {e.strerror or e}") from None
    if names and not force:
        shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
        raise InputError(path, f"output folder: not empty ({shown}); the campaigns of two "
                               "runs would mix, each fitted against the other's truth. Give a "
                               "new or empty folder, or --force to replace the files this run "
                               "writes")
    return names


def check_plan_unit(plan, unit, plan_path, unit_path) -> float:
    """The lab field of a run that follows `plan` (a plan.json read back): a plan is the
    program of one unit in one lab, so
    * a plan recording another unit (its "unit" key, the unit file's [unit] id) is
      InputError naming the plan file and both ids;
    * a plan whose lab_field_nT differs (beyond 1e-6 relative, the JSON round trip) from
      the unit file's lab_field_nT is InputError: the unit file is the authority on its own
      lab, and a run with two lab fields (the plan's in the thermal campaign, the unit's in
      the others) simulates no lab; the plan is made again from the unit file;
    * a unit file without lab_field_nT takes the plan's field (`magcal plan
      --lab-field-nT`), for every campaign.
    A plan without a "unit" key (written by hand) is not checked for its unit."""
    if plan.unit_id and plan.unit_id != unit.id:
        raise InputError(plan_path, f"key unit: the plan is the program of unit "
                                    f"{plan.unit_id!r}, {unit_path} is unit {unit.id!r}; "
                                    f"make its own: magcal plan {unit_path}")
    if unit.lab_field_nT:
        field = float(unit.lab_field_nT)
        if abs(plan.lab_field_nT - field) > 1e-6 * field:
            raise InputError(plan_path, f"key lab_field_nT: the plan's lab field "
                                        f"{plan.lab_field_nT:g} nT differs from the unit's "
                                        f"{field:g} nT (lab_field_nT of {unit_path}), the "
                                        f"authority on its lab; make the plan again: magcal "
                                        f"plan {unit_path}")
        return field
    return float(plan.lab_field_nT)


def load_truth_override(path) -> dict:
    """A truth override file: JSON or TOML (by its suffix), InputError on anything else."""
    path = Path(path)
    if path.suffix.lower() == ".toml":
        try:
            import tomllib
        except ImportError:                       # Python 3.10
            import tomli as tomllib
        try:
            return tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError(path, "file not found") from None
        except (OSError, UnicodeDecodeError) as e:
            raise InputError(path, f"cannot read: {e}") from None
        except tomllib.TOMLDecodeError as e:
            raise InputError(path, f"not a TOML truth override: {e}") from None
    from generator.io.json_input import load_json
    return load_json(path, "truth override")


def run_simulate(args, progress) -> tuple:
    """`magcal simulate`: exit status and the JSON result (paths, campaigns, plan)."""
    # the simulator's imports here, not at module level: the command line's parser imports
    # this module for its arguments, and every other verb should not pay for them
    import numpy as np

    from generator.campaign import plan as plan_mod
    from generator.campaign import simulate as sim

    check_output_folder(args.output)
    before = check_empty_folder(args.output, getattr(args, "force", False))
    unit = load_unit(args.unit)
    for name, v, lo, hi in (("--sample-period-s", args.sample_period_s, 1e-2, 3600.0),
                            ("--samples-per-segment", args.samples_per_segment, 1, 10000)):
        if v is not None and not (math.isfinite(v) and lo <= v <= hi):
            raise InputError(None, f"{name} {v!r} is outside [{lo:g}, {hi:g}]")
    truth_ss, *camp_ss = np.random.SeedSequence(args.seed).spawn(1 + len(CAMPAIGNS))
    truth = sim.random_truth(unit, np.random.default_rng(truth_ss))
    override = load_truth_override(args.truth) if args.truth else None
    if override is not None:
        truth = sim.override_truth(truth, override, unit, args.truth)
    notes = []
    lab_field_nT = None          # None: the unit's (else seed 000's), scenarios._field_nT
    if args.plan and "thermal_12pos" in args.campaigns:
        pass                     # the plan's field, when the unit states none: below
    elif not unit.lab_field_nT:
        notes.append(f"the unit file has no lab_field_nT: the lab field is seed 000's "
                     f"{sim.LAB_FIELD_nT:g} nT")
    plan = None
    if "thermal_12pos" in args.campaigns:
        if args.plan:
            plan = plan_mod.load_plan(args.plan)
            lab_field_nT = check_plan_unit(plan, unit, args.plan, args.unit)
            if not unit.lab_field_nT:
                notes.append(f"the unit file has no lab_field_nT: the plan's "
                             f"{lab_field_nT:g} nT is the lab field of every campaign")
            if args.sample_period_s is not None or args.samples_per_segment is not None:
                raise InputError(args.plan, "--plan sets the sample period and the samples "
                                            "per segment: leave out --sample-period-s and "
                                            "--samples-per-segment")
        else:
            plan = sim.plan_for(unit, truth,
                                sample_period_s=args.sample_period_s or DEFAULT_SAMPLE_PERIOD_S,
                                samples_per_segment=(args.samples_per_segment
                                                     or DEFAULT_SAMPLES_PER_SEGMENT))
        tau_true = max(truth.board_tau_s[b] for b in sim.boards_of(unit))
        # compare at the printed rounding (0.1 min), so the note never says "16.5 < 16.5"
        plan_tau_min, true_tau_min = round(plan.board_tau_s / 60, 1), round(tau_true / 60, 1)
        if plan_tau_min < true_tau_min:
            notes.append(f"the plan assumes a board time constant of {plan_tau_min:.1f} "
                         f"min, the simulated boards have {true_tau_min:.1f} min: its holds "
                         "may end before the boards settle")
        progress(f"unit {unit.id}: thermal program {len(plan.positions)} positions x "
                 f"{len(plan.levels_C)} levels, {plan.total_duration_s / 3600:.1f} h, "
                 f"{plan.sample_period_s:g} s samples")
    for n in notes:
        progress(f"note: {n}")
    written = {}
    with output_folder(args.output) as folder:
        tmp = folder.tmp
        shutil.copyfile(args.unit, tmp / "unit.toml")
        record = sim.simulation_record(
            args.seed, by="magcal simulate", campaigns=list(args.campaigns),
            plan=None if args.plan is None else str(args.plan),
            sample_period_s=args.sample_period_s,
            samples_per_segment=args.samples_per_segment, truth_override=override,
            reproduce=_reproduce_command(args),
            files=["unit.toml", "truth.json", *(["plan.json"] if plan is not None else []),
                   *(f"{k}{ext}" for k in CAMPAIGNS if k in args.campaigns
                     for ext in (".csv", ".truth.npz"))])
        (tmp / "truth.json").write_text(json.dumps(truth.to_json(record), indent=1) + "\n",
                                        encoding="utf-8")
        files = {"unit": tmp / "unit.toml", "truth": tmp / "truth.json"}
        if plan is not None:
            (tmp / "plan.json").write_text(json.dumps(plan.to_json_dict(), indent=1) + "\n",
                                           encoding="utf-8")
            files["plan"] = tmp / "plan.json"
        for kind, ss in zip(CAMPAIGNS, camp_ss):
            if kind not in args.campaigns:
                continue
            opts = {"plan": plan} if kind == "thermal_12pos" else {}
            if lab_field_nT is not None and kind != "thermal_12pos":
                opts["lab_field_nT"] = lab_field_nT       # one lab field per run
            path, arrays = sim.simulate_campaign(kind, unit, truth, np.random.default_rng(ss),
                                                 tmp, **opts)
            files[kind] = path
            written[kind] = int(len(arrays["time_s"]))
            progress(f"{kind}: {written[kind]} samples")
    files = {k: folder.final(v) for k, v in files.items()}
    progress(f"wrote {len(files)} files to {folder.final(folder.tmp)}")
    kept = sorted(set(before) - set(record["files"]))
    if kept:
        notes.append(f"--force: {len(kept)} file(s) of {args.output} not written by this run "
                     f"are kept: {', '.join(kept)}")
        progress(f"note: {notes[-1]}")
    return 0, {"unit": unit.id, "seed": args.seed,
               "files": {k: str(v) for k, v in files.items()}, "kept_files": kept,
               "samples": written, "notes": notes,
               "plan": None if plan is None else {
                   "levels_C": plan.levels_C, "hold_s": [s.hold_s for s in plan.steps],
                   "board_tau_s": plan.board_tau_s, "sample_period_s": plan.sample_period_s}}


def _reproduce_command(args) -> str:
    """The command line that draws the same unit and campaigns (same magcal version), with
    the unit file, plan and truth override as given on this run."""
    import shlex
    parts = ["magcal", "simulate", str(args.unit), "--seed", str(args.seed)]
    if args.plan:
        parts += ["--plan", str(args.plan)]
    if args.truth:
        parts += ["--truth", str(args.truth)]
    if list(args.campaigns) != list(CAMPAIGNS):
        parts += ["--campaigns", *args.campaigns]
    for opt, v in (("--sample-period-s", args.sample_period_s),
                   ("--samples-per-segment", args.samples_per_segment)):
        if v is not None:
            parts += [opt, repr(v)]
    parts += ["-o", "DIR"]
    return " ".join(shlex.quote(x) for x in parts)
