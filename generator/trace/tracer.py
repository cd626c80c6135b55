"""`magcal trace` (issue 6): find the structure left in the residual, trace it to the
effect the model lacks, add it, refit everything jointly, report the error before and
after (ICD section 3).

Residuals (ICD section 2: what is known about the true field decides their type), per
sensor and sample:

* `ref_x/y/z_nT` present: vector rows B_cal - B_ref (3 per sample);
* else `ref_norm_nT` (or the unit's `lab_field_nT`): magnitude rows |B_cal| - |B|;
* else a static position (`position` > 0): B_cal - B_p, B_p an unknown constant per
  (file, position), fitted with the rest.

Model. The float64 model of the extended flight chain (`SensorModel`, the order of
generator.flight.chain.sensor_kernel, see generator.trace.effects) with the baseline's structure
(polynomial degree of b(T), M(T), coil coupling K) plus the effects found so far. Its
parameters are deviations from the baseline (the core fit, generator.fit.thermal.fit_unit with
the coil and boom fits of `magcal fit`, or a supplied coefficients.json), in scaled
internal units: b and M in all rows of the baseline degree (M symmetric where only
magnitudes are known; M fixed and b0 absorbed by B_p where only positions are), K where
the data drive the coils, B_p per static position, and each effect's own parameters. It
is fitted by Levenberg-Marquardt on a finite-difference Jacobian (every parameter block
is linear or nearly so).

Evaluation. With `--holdout` files: fitted on the data files, evaluated on the holdout
files ("holdout"). Without: the data are cut into contiguous time blocks and every
fifth block is held out ("split"); the models are fitted on the rest, the figures are
the held-out RMS, and the final coefficients are refitted on all the data.

Tracing, per sensor, in rounds. Each candidate of the catalogue (generator.trace.effects) is
scored by blocked cross-validation in time on the fit data (contiguous blocks, five
folds, blocks dealt to the folds in turn), linearised about the current fit: the current
model's Jacobian plus the candidate's columns (or, for a scanned effect, its residual
change at each grid value, the value chosen inside each training fold). The candidate
with the largest held-out error reduction that passes the significance rule is added, all
parameters are refitted jointly, and the next round starts; it stops when no candidate
passes. The runner-up of a round is reported with its score after the winner is in.
Details that keep the comparison fair: a thermal lag (whose linearisation is poor when
it moves the temperature by degrees) is scored again from a nonlinear fit; baseline
parameters that one fold alone determines (a coil stepped only inside one block) keep
their full-data fit in every fold instead of being refitted to noise; a channel that only
some files carry is 0 in the others and gets an offset of its own for the files that
carry it; where two candidates are statistically equivalent, Effect.prior decides.
The thresholds were set on simulated draws (host_tests/test_trace.py seeds) and checked
on draws not used to set them.

The significance rule: generator.trace.scoring. The pieces: samples (the data),
model (the float64 chain), crossval (the linearised cross-validation), scoring
(candidates and significance), coefficients (baseline and extended sets).

Public API: trace(unit, data, holdout=(), coeffs=None) -> TraceResult (.to_json(),
.coefficients, .write(dir)); to_coefficient_set(base, traces); SensorModel;
model_from_coefficients(cs, name, S); gather_samples(...); calibrated_field64(cs, tel,
sensor);
add_trace_args(parser), cmd_trace(args); px4_log_telemetry(folder) (adapter for PX4
ulog CSV exports).
"""


from __future__ import annotations

import copy
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from generator.errors import InputError
from generator.flight.coeffs import CoefficientSet
from generator.io.recordings import refuse_repeated_recordings
from generator.io.formula import add_regressors
from generator.fit.calibration import SensorCalibration  # noqa: F401 (tests use tr.SensorCalibration)
from generator.trace import effects as fx  # noqa: F401
from generator.trace.coefficients import (  # noqa: F401 (the public API lives here too)
    _fixed_model, _json_default, _recentre, _with_any_reference, baseline_coefficients,
    calibrated_field64, initial_effects, model_from_coefficients, to_coefficient_set)
from generator.trace import residual as rv
from generator.trace.crossval import CVEngine, LinearSolver, _lag1, _pinv_gram  # noqa: F401
from generator.trace.model import (  # noqa: F401
    BATCH_ELEMENTS, FD_STEP, M_UNIT, BaseFit, SensorModel, base_from_coefficients,
    declared_degree)
from generator.trace.samples import (  # noqa: F401
    KIND_NAMES, N_BLOCKS, NORM, POS, VEC, FileSeries, SensorSamples, assign_blocks,
    candidate_channels, gather_samples)
from generator.fit.samples import check_max_samples
from generator.trace.subsample import (CONFIRM_PREFIX, MAX_TRACE_SAMPLES,
                                       all_rows_confirmation, all_rows_rms, all_rows_warnings,
                                       subsample_files)
from generator.trace.scoring import (  # noqa: F401
    ACT_SHARE, ALPHA, EQUIVALENT_CORR, MIN_REL_GAIN, N_FOLDS, Score, _corr, _f,
    _make_score, candidate_columns, candidate_list, choose, equivalent, heldout_z,
    RoundProgress, score_candidate, score_round)

SPLIT_EVERY = 5           # split mode: every 5th block held out for the figures
MAX_EFFECTS = 6           # per sensor
MIN_SAMPLES = 40          # per sensor, to trace at all


# =======================================================================================
# Tracing one sensor
# =======================================================================================
@dataclass
class Step:
    effect: object
    params: np.ndarray
    score: Score
    rms_before_nT: float
    rms_after_nT: float
    model_before: SensorModel
    model_after: SensorModel
    runner_up: Score | None = None
    runner_up_after: Score | None = None        # its score in the next round
    scores: list = field(default_factory=list)  # every candidate of this round
    scores_after: list = field(default_factory=list)
    corr_runner_up: float | None = None


@dataclass
class SensorTrace:
    name: str
    S_fit: SensorSamples
    S_eval: SensorSamples
    core_rms_nT: float
    baseline_rms_nT: float
    base_model: SensorModel
    steps: list
    final_model: SensorModel          # fitted on the data used for the coefficients
    last_scores: list
    not_applicable: dict
    stop: str
    initial_effects: list = field(default_factory=list)
    noise: dict = field(default_factory=dict)         # residual.noise_floor of what is left
    unexplained: dict | None = None                   # the residual above the noise, if any
    rejected: list = field(default_factory=list)      # (label, why) refused after the refit

    @property
    def final_rms_nT(self) -> float:
        return self.steps[-1].rms_after_nT if self.steps else self.baseline_rms_nT

    @property
    def metric(self) -> str:
        return "; ".join(KIND_NAMES[k] for k in self.S_eval.kinds_present())


def _refine_and_fit(model, S_fit, e, sc: Score):
    """Add effect e at the chosen hyper-parameter (refined on all fit data) and refit
    everything jointly."""
    e.set_hyper(sc.hyper)
    fine = e.refine_grid(S_fit, sc.hyper)
    if fine:
        r0, J = model.jacobian(S_fit)
        solver = LinearSolver(J)
        best, best_sse = sc.hyper, math.inf
        for h in fine + [sc.hyper]:
            e.set_hyper(h)
            d0, G = candidate_columns(model, S_fit, e, r0)
            y = r0 if d0 is None else r0 + d0
            res, _, _ = solver.fit(y, G)
            if res @ res < best_sse:
                best, best_sse = h, float(res @ res)
        e.set_hyper(best)
    if hasattr(e, "settle"):
        e.settle(S_fit)
    m1 = model.with_effect(e, e.init_params())
    m1.fit(S_fit)
    if hasattr(e, "locate"):
        e.locate(S_fit)
    return m1


def _relocate(m: SensorModel, S):
    """Change points again, on all the data (the samples held out from the fit may lie
    between the last sample before and the first after)."""
    for e in m.effects:
        if not hasattr(e, "settle"):
            continue
        r0, J = m.jacobian(S)
        solver = LinearSolver(J)
        best, best_sse = e.hyper, math.inf
        for h in e.refine_grid(S, e.hyper) + [e.hyper]:
            e.set_hyper(h)
            res, _, _ = solver.fit(m.residual(m.theta[None], S)[0])
            if res @ res < best_sse:
                best, best_sse = h, float(res @ res)
        e.set_hyper(best)
        e.locate(S)


def trace_sensor(name, base: BaseFit, S_fit, S_eval, *, initial=(), alpha=ALPHA,
                 min_gain=MIN_REL_GAIN, max_effects=MAX_EFFECTS, S_final=None,
                 progress=None, confirm=None) -> SensorTrace:
    """confirm(model, m1) -> "" or why: a further check an accepted effect must pass
    (above the trace's cap: subsample.all_rows_confirmation, the error over every row)."""
    say = progress or (lambda m: None)
    blocks = np.unique(S_fit.block)
    S_fit.block = np.searchsorted(blocks, S_fit.block)       # 0 .. n_blocks - 1
    n_blocks = len(blocks)
    fold_of_block = np.arange(n_blocks) % N_FOLDS
    init_e = [e for e, _ in initial]
    init_p = [p for _, p in initial]
    model0 = SensorModel.for_samples(base, S_fit, init_e, init_p)
    core = model0.rms(S_eval)
    ref_var, ref_what = rv.reference_variation_nT(S_fit, model0.field(S_fit))
    rejected = []
    model = model0.copy().fit(S_fit)
    why_bad = (_shrink_text(model, S_fit, ref_var, ref_what)
               if rv.shrinks(model.field(S_fit), S_fit, ref_var) else
               _bad_gain(model) or _overfit_text(model0, model, S_fit, S_eval))
    if why_bad:
        rejected.append(("refit of the baseline", why_bad))
        say(f"{name}: the refit of the baseline was rejected: {rejected[-1][1]}")
        model = model0.copy()
    base_rms = model.rms(S_eval)
    say(f"{name}: baseline held-out RMS {base_rms:.2f} nT (core fit as given {core:.2f} nT)")
    steps, stop = [], ""
    t0 = time.perf_counter()
    scores, why = score_round(model, S_fit, fold_of_block, n_blocks, alpha, min_gain,
                              RoundProgress(progress, f"{name}: round 1: "))
    say(f"{name}: round 1: {len(scores)} candidates scored in {time.perf_counter() - t0:.1f} s")
    while True:
        if steps:
            st = steps[-1]
            st.scores_after = scores
            if st.runner_up is not None:
                st.runner_up_after = next((s for s in scores
                                           if s.effect.key() == st.runner_up.effect.key()),
                                          None)
        sig = [s for s in scores if s.significant]
        if not sig:
            stop = ("no candidate applies" if not scores else
                    f"no candidate passes (best: {scores[0].effect.label()}, "
                    f"{'; '.join(scores[0].reasons) or 'refused after the refit'})")
            break
        if len(steps) >= max_effects:
            stop = f"stopped at {max_effects} effects"
            break
        win = choose(sig)
        others = [s for s in scores if s is not win]
        runner = others[0] if others else None
        e = win.effect
        m1 = _refine_and_fit(model, S_fit, e, win)
        before, after = model.rms(S_eval), m1.rms(S_eval)
        refusal = _refusal(model, m1, S_fit, S_eval, ref_var, ref_what)
        if not refusal and not after < before:
            # one statistic: an effect is kept only if the held-out error the user is
            # shown (these very figures: Step.rms_before_nT -> rms_after_nT) falls; a
            # cross-validation gain the evaluation rows do not show is no gain (_refusal
            # lets a rise within chance pass: it guards against harm, this against none)
            refusal = (f"the evaluation rows show no gain: RMS {before:.2f} -> {after:.2f} nT "
                       "(an effect is kept only if the held-out error shown falls)")
        if not refusal and not _files_showing(S_fit, model, m1, win)["shown_in"]:
            refusal = ("no data file shows it on its own (its term is not detectable with a "
                       "held-out gain beyond chance in any one file)")
        if not refusal and confirm is not None:
            refusal = confirm(model, m1)
        if refusal:             # honesty: never keep an effect the evaluation refutes
            win.significant = False
            win.reasons.append(refusal)
            rejected.append((e.label(), refusal))
            say(f"{name}: {e.label()} refused: {refusal}")
            continue
        step = Step(e, m1.effect_params(len(m1.effects) - 1), win, before, after, model, m1,
                    runner_up=runner, scores=scores,
                    corr_runner_up=_corr(win.explained, runner.explained if runner else None))
        steps.append(step)
        say(f"{name}: + {e.label()}: held-out RMS {before:.2f} -> {after:.2f} nT "
            f"(CV gain {100 * win.rel_rms_gain:.1f} %, z = {win.z:.1f})")
        model = m1
        t0 = time.perf_counter()
        scores, why = score_round(model, S_fit, fold_of_block, n_blocks, alpha, min_gain,
                                  RoundProgress(progress, f"{name}: round {len(steps) + 1}: "))
        say(f"{name}: round {len(steps) + 1}: {len(scores)} candidates scored in "
            f"{time.perf_counter() - t0:.1f} s")
    r_eval = model.residual(model.theta[None], S_eval)[0]
    noise = rv.noise_floor(S_eval, r_eval)
    unexplained = None
    if stop.startswith("no candidate"):
        if noise["at_noise"]:
            stop = "nothing significant left: " + stop + _noise_text(noise)
        else:
            stop = ("no catalogue effect explains what is left: " + stop + _noise_text(noise))
    if noise["floor_nT"] and not noise["at_noise"]:
        unexplained = {"sensor": name,
                       "rms_above_noise_nT": noise["rms_above_noise_nT"],
                       "residual_rms_nT": noise["residual_rms_nT"],
                       "noise_floor_nT": noise["floor_nT"],
                       "correlates": rv.correlates(S_eval, r_eval, model.field(S_eval))}
        say(f"{name}: unexplained: {noise['residual_rms_nT']:.2f} nT left, "
            f"{noise['ratio']:.1f} x the noise floor; follows "
            + ", ".join(f"{c['quantity']} ({c['eta2']:.2f})"
                        for c in unexplained["correlates"][:3]))
    final = model
    if S_final is not None and steps:      # split mode: refit on all the data
        effs = [copy.copy(e) for e in model.effects]
        final = SensorModel.for_samples(base, S_final, effs,
                                        [model.effect_params(i) for i in range(len(effs))])
        for blk in ("b", "M", "K"):
            final.theta[final.sl[blk]] = model.theta[model.sl[blk]]
        _relocate(final, S_final)
        final.fit(S_final)
    return SensorTrace(name, S_fit, S_eval, core, base_rms, model0, steps, final, scores,
                       why, stop, initial_effects=list(initial), noise=noise,
                       unexplained=unexplained, rejected=rejected)


Z_WORSE = 1.6449     # one-sided 5 % point of the normal: "worse beyond chance"


def _refusal(model, m1, S_fit, S_eval, ref_var, ref_what) -> str:
    """Why the refitted model m1 may not replace model ("" if it may): it shrinks the
    calibrated field below the reference's variation (a degenerate solution), or its
    error on the evaluation data rose beyond chance (held-out score test of
    generator.trace.scoring, one block per evaluation file, AR(1) inflation)."""
    if rv.shrinks(m1.field(S_fit), S_fit, ref_var):
        return _shrink_text(m1, S_fit, ref_var, ref_what)
    why = _bad_gain(m1) or _overfit_text(model, m1, S_fit, S_eval) or _unidentifiable_lag(m1, S_fit)
    if why:
        return why
    r0 = model.residual(model.theta[None], S_eval)[0]
    r1 = m1.residual(m1.theta[None], S_eval)[0]
    mag_only = rv.magnitude_only(S_eval)
    if r1 @ r1 <= r0 @ r0 and not mag_only:
        return ""
    rho = min(max(_lag1(r1, S_eval), 0.0), 0.99)
    fb = S_eval.file_index[S_eval.row_sample]
    z = heldout_z(r0, r1, np.searchsorted(np.unique(fb), fb), len(np.unique(fb)),
                  (1 + rho) / (1 - rho))
    if mag_only and z < Z_WORSE:
        # |B| alone: a term that moves the field's direction (a drift, a cubic) lowers the
        # cross-validated error of the fit rows by contracting along the unseen
        # directions; the evaluation rows must confirm the gain beyond chance
        return (f"with magnitudes only, the evaluation rows do not confirm it: RMS "
                f"{_rms(r0):.2f} -> {_rms(r1):.2f} nT (z = {z:.1f} < {Z_WORSE})")
    if z < -Z_WORSE:
        return (f"the refit raised the evaluation RMS from {_rms(r0):.2f} to {_rms(r1):.2f} nT "
                f"(z = {z:.1f}, beyond chance)")
    return ""


def _bad_gain(m) -> str:
    """A reflected or collapsed calibration (the check the coefficient set makes on
    M(t_ref), generator.flight.coeffs): a degenerate solution, never kept."""
    from generator.flight.coeffs import GAIN_LIMIT
    M0 = np.asarray(m.values()["M_poly"])[0]
    sv = np.linalg.svd(M0, compute_uv=False)
    det = float(np.linalg.det(M0))
    if det > 0 and sv[-1] >= 1.0 / GAIN_LIMIT and sv[0] <= GAIN_LIMIT:
        return ""
    return (f"a degenerate solution: M(t_ref) would have det {det:.3g} and singular values "
            f"{sv[-1]:.3g}..{sv[0]:.3g} (a reflected or collapsed calibration; allowed: det > 0, "
            f"gains {1 / GAIN_LIMIT:g}..{GAIN_LIMIT:g})")


def _overfit_text(model, m1, S_fit, S_eval) -> str:
    """Magnitude-only rows: m1's residual (held out, or on the fit data with its parameter
    count) statistically below the part's noise where model's was not (residual.
    below_part_noise): a contraction, not a better calibration."""
    for S, n_par in ((S_eval, 0), (S_fit, m1.P)):
        why = rv.below_part_noise(S, m1.residual(m1.theta[None], S)[0], n_par)
        if why and not rv.below_part_noise(S, model.residual(model.theta[None], S)[0],
                                            model.P if n_par else 0):
            return why + (" (held-out rows)" if S is S_eval else " (fit rows)")
    return ""


def _unidentifiable_lag(m1, S) -> str:
    """A time constant the data cannot resolve: below half the shortest sample period
    (the filter has settled before the next sample: it is no lag) or beyond twice the
    longest file (the filtered channel is a constant or a ramp there)."""
    dts = [float(np.median(np.diff(f.time_s))) for f in S.files if len(f.time_s) > 1]
    spans = [float(np.ptp(f.time_s)) for f in S.files if len(f.time_s) > 1]
    if not dts:
        return ""
    lo, hi = 0.5 * min(dts), 2.0 * max(spans)
    for i, e in enumerate(m1.effects):
        tau = e.time_constant_s(m1.effect_params(i))
        if tau is not None and not lo <= tau <= hi:
            return (f"{e.label()}: time constant {tau:.3g} s is not identifiable from these "
                    f"data (outside [{lo:.3g}, {hi:.3g}] s: half the shortest sample period "
                    "to twice the longest file)")
    return ""


def _rms(r) -> float:
    return float(np.sqrt(np.mean(r * r))) if r.size else float("nan")


def _shrink_text(m, S, ref_var, ref_what) -> str:
    v = rv.field_variation_nT(m.field(S)[rv._judged_rows(S)])
    return (f"a degenerate solution: the calibrated field would vary by {v:.0f} nT rms, "
            f"below the {ref_var:.0f} nT of {ref_what} (more than {100 * rv.MAX_SHRINK:g} % "
            "less): the calibration contracts toward a constant vector")


def _noise_text(noise) -> str:
    if not noise.get("floor_nT"):
        return ""
    part = (f", part noise {noise['part_noise_nT']:.2f} nT" if noise.get("part_noise_nT")
            else "")
    return (f"; the residual is {noise['residual_rms_nT']:.2f} nT, {noise['ratio']:.2f} x the "
            f"noise floor {noise['floor_nT']:.2f} nT ({noise['source']}'s sample-to-sample "
            f"noise{part}; consistent with the noise up to "
            f"{noise.get('at_noise_limit_ratio', float('nan')):.2f} x, test at "
            f"{rv.NOISE_ALPHA:g})")


# =======================================================================================
# The whole trace
# =======================================================================================
@dataclass
class TraceResult:
    unit: object
    evaluated_on: str
    traces: dict                  # sensor -> SensorTrace
    skipped: dict                 # sensor -> reason
    base: CoefficientSet
    coefficients: CoefficientSet
    notes: list
    sources: dict
    elapsed_s: float = 0.0
    subsample: dict | None = None     # trace.subsample's figures, above the cap only
    warnings: list = field(default_factory=list)   # subsample.all_rows_warnings, if any

    @property
    def effects(self) -> list:
        return [(n, st) for n, tr in self.traces.items() for st in tr.steps]

    def to_json(self) -> dict:
        out = {"format": "magcal-trace", "unit": self.unit.id,
               "evaluated_on": self.evaluated_on,
               "sources": self.sources,
               "protocol": protocol_text(self.evaluated_on),
               "baseline": {}, "effects": [], "final": {}, "rounds": {},
               "not_applicable": {}, "skipped": dict(self.skipped), "notes": list(self.notes),
               "unexplained": [{**tr.unexplained, "plot": unexplained_plot_name(n)}
                               for n, tr in self.traces.items() if tr.unexplained],
               "elapsed_s": round(self.elapsed_s, 2)}
        if self.subsample:            # above the cap only: under it the same bytes as before
            out["subsample"] = dict(self.subsample)
        if self.warnings:
            out["warnings"] = list(self.warnings)
        regs = declared_regressors(self.unit)
        for n, tr in self.traces.items():
            out["baseline"][n] = {
                "rms_nT": tr.baseline_rms_nT, "core_fit_as_given_rms_nT": tr.core_rms_nT,
                "metric": tr.metric, "samples_fit": tr.S_fit.n, "samples_evaluated": tr.S_eval.n,
                "model": _model_text(tr.base_model),
                "effects_already_in_model": [e.label() for e, _ in tr.initial_effects]}
            out["final"][n] = {"rms_nT": tr.final_rms_nT, "stop": tr.stop,
                               "noise": dict(tr.noise),
                               "refused": [{"candidate": c, "why": w} for c, w in tr.rejected],
                               "model": _model_text(tr.steps[-1].model_after if tr.steps
                                                    else tr.base_model)}
            out["not_applicable"][n] = dict(tr.not_applicable)
            rounds = []
            for k, st in enumerate(tr.steps):
                rounds.append({"round": k + 1, "chosen": st.effect.label(),
                               "candidates": [s.summary() for s in st.scores]})
            rounds.append({"round": len(tr.steps) + 1, "chosen": None,
                           "candidates": [s.summary() for s in tr.last_scores]})
            out["rounds"][n] = rounds
            for st in tr.steps:
                out["effects"].append(effect_entry(n, tr, st, regs))
        return out

    def write(self, out_dir, progress=None) -> dict:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        (out / "trace.json").write_text(json.dumps(self.to_json(), indent=1,
                                                   default=_json_default) + "\n")
        self.coefficients.save(out / "coefficients.json")
        return {"trace": out / "trace.json", "coefficients": out / "coefficients.json"}


def _why_no_samples(spec, tels) -> str:
    """Why a sensor has no usable sample in the files (an empty temperature column, ...)."""
    why = []
    for t in tels:
        col = getattr(spec, "temp_column", None)
        v = getattr(t, "full_column", t.columns.get)(col) if col else None
        if v is not None and not np.isfinite(np.asarray(v, float)).any():
            why.append(f"{t.path}: column {col} is empty")
    return "; ".join(why) if why else ("no reading with a temperature and a field reference "
                                       "or a static position in the data files")


def unexplained_plot_name(sensor) -> str:
    """The report's figure of a sensor's unexplained residual (in the output folder)."""
    return f"trace_{sensor}_unexplained.png"


def _model_text(m: SensorModel) -> str:
    parts = [f"b(T), M(T) degree {m.base.degree}"]
    if m.free_M is None:
        parts = [f"b(T) degree {m.base.degree} up to a constant per position, M as given"]
    elif m.free_M == "sym":
        parts[0] += " (M symmetric: magnitudes only)"
    if m.base.K is not None:
        parts.append("coil coupling K" + (" (refitted)" if m.free_K else ""))
    parts += [e.label() for e in m.effects]
    return " + ".join(parts)


def effect_entry(name, tr: SensorTrace, st: Step, regs=()) -> dict:
    e, sc = st.effect, st.score
    m = st.model_after
    entry = {
        "sensor": name, "effect": e.name, "explained_by": e.explained_by(),
        "rms_before_nT": st.rms_before_nT, "rms_after_nT": st.rms_after_nT,
        "evidence": evidence_sentence(name, st),
        "files": carried_by(tr, st),
        "parameters": e.describe(st.params, m),
        "in_flight_chain": e.in_chain, "flight_form": e.flight_form,
        "physics": e.physics,
        "regressors": [{"name": r["name"], "formula": r["formula"], "flight": REGRESSOR_FLIGHT}
                       for r in regs
                       if any(r["name"] == c or c.startswith(r["name"] + " ")
                              for c in e.explained_by())],
        "cross_validation": {**sc.summary(),
                             "cv_rms_before_nT": math.sqrt(sc.sse0_cv / tr.S_fit.n_rows),
                             "cv_rms_after_nT": math.sqrt(sc.sse1_cv / tr.S_fit.n_rows)},
    }
    if st.runner_up is not None:
        ru, after = st.runner_up, st.runner_up_after
        entry["runner_up"] = {
            "effect": ru.effect.name, "explained_by": ru.effect.explained_by(),
            "cv_rms_gain_pct": 100 * ru.rel_rms_gain, "significant": ru.significant,
            "cv_rms_gain_after_winner_pct": None if after is None else 100 * after.rel_rms_gain,
            "significant_after_winner": None if after is None else after.significant,
            "correlation_with_winner": st.corr_runner_up,
            "why_it_lost": runner_up_text(st),
            "equivalent": equivalent(st.score, ru),
        }
    return entry


def carried_by(tr: SensorTrace, st: Step) -> dict:
    """Which data files carry the effect. Per file: `acts` - the effect's own term (the
    model with it against the same fit without it) is detectable there, sqrt(sum c^2)
    over the file's samples above the one-sided ALPHA point of the normal in units of the
    noise floor; `heldout_z` - the effect improves that file's held-out rows (score
    test of generator.trace.scoring). `shown_in`: the files where it acts and improves
    beyond the ALPHA point; `acts_not_shown_in`: where the model applies it but that file
    does not ask for it (an effect new in some files, which the model's single set of
    coefficients carries everywhere: a thermal lag, say). For a channel effect,
    `channel_in` lists the files that have the channel; the extended coefficients
    describe those (the channel's offset is theirs)."""
    S = tr.S_fit
    m1, m0 = st.model_after, st.model_before
    out = _files_showing(S, m0, m1, st.score, tr.noise.get("floor_nT"))
    chans = [ch for ch in st.effect.explained_by() if ch in S.channel_present]
    if chans:
        pres = S.channel_present[chans[0]]
        out["channel_in"] = sorted(set(S.file_names[i] for i in np.unique(S.file_index[pres])))
    return out


def _files_showing(S, m0, m1, score, floor=None) -> dict:
    """carried_by's per-file figures for the effect m1 adds to m0 (see carried_by)."""
    from scipy import stats as sps
    zc = float(sps.norm.isf(ALPHA))
    off = SensorModel(m0.base, free_b=m0.free_b, free_M=m0.free_M, free_K=m0.free_K,
                      groups=m0.groups, Bp0=m0.Bp0, i_rms=m0.i_rms, effects=m0.effects,
                      theta=m1.theta[:m0.P])
    # the effect's own term in the residual rows (a reference-stage effect, the time
    # offset, moves the reference, not the calibrated field)
    r1 = m1.residual(m1.theta[None], S)[0]
    c = r1 - off.residual(off.theta[None], S)[0]
    floor = floor or rv.data_noise_nT(S, r1) or rv.part_noise_nT(S.spec) or 1.0
    per = {}
    row_file = S.file_index[S.row_sample]
    for fi in np.unique(S.file_index):
        sel = row_file == fi
        name = S.file_names[fi]
        cz = float(np.sqrt(np.sum(c[sel] ** 2))) / floor
        per[name] = {"acts": bool(cz > zc), "contribution_z": cz,
                     "heldout_z": score.file_z.get(name)}
    shown = [f for f, v in per.items() if v["acts"] and (v["heldout_z"] or 0) > zc]
    acts = [f for f, v in per.items() if v["acts"] and f not in shown]
    return {"per_file": per, "shown_in": shown, "acts_not_shown_in": acts,
            "everywhere": len(shown) == len(per)}


def runner_up_text(st: Step) -> str:
    ru, after, win = st.runner_up, st.runner_up_after, st.score
    if ru is None:
        return ""
    less = "less" if ru.rel_rms_gain < win.rel_rms_gain else "as much"
    s = (f"{ru.effect.label()} explained {less} of the held-out residual "
         f"({100 * ru.rel_rms_gain:.1f} % against {100 * win.rel_rms_gain:.1f} %)")
    if st.corr_runner_up is not None:
        s += (f"; the two explanations are correlated (r = {st.corr_runner_up:.2f}) over the "
              "fit data")
    if equivalent(win, ru):
        s += ("; the data cannot tell the two apart (equally good held-out fits): the winner "
              "has fewer parameters" if win.dof < ru.dof else
              "; the data cannot tell the two apart (equally good held-out fits): the winner "
              "has the higher prior (a mechanism the part is known to have)" if
              ru.effect.prior < st.effect.prior else
              "; the data cannot tell the two apart (equally good held-out fits)")
    if after is None:
        s += "; after the winner it is no longer a candidate"
    elif after.significant:
        s += (f"; with the winner in, it still improves by {100 * after.rel_rms_gain:.1f} % "
              "(significant: it may come next)")
    else:
        s += (f"; with the winner in, it improves the held-out RMS by "
              f"{100 * after.rel_rms_gain:.2f} % only ({'; '.join(after.reasons)})")
    return s


def evidence_sentence(name, st: Step) -> str:
    e, sc = st.effect, st.score
    ru = st.runner_up
    s = (f"Adding {e.title} ({', '.join(e.explained_by())}) cut the held-out RMS of {name} "
         f"from {st.rms_before_nT:.1f} to {st.rms_after_nT:.1f} nT; in cross-validation it "
         f"improved {sc.blocks_improved} of {len(sc.block_gain)} held-out blocks "
         f"(z = {sc.z:.1f}; held-out likelihood ratio {sc.lr:.0f} for {sc.dof} parameters)")
    if ru is not None:
        s += (f", ahead of {ru.effect.label()} ({100 * ru.rel_rms_gain:.1f} % against "
              f"{100 * sc.rel_rms_gain:.1f} %)")
    return s + "."


def protocol_text(evaluated_on) -> dict:
    return {
        "figures": ("held-out RMS on the --holdout files of models fitted on the data files"
                    if evaluated_on == "holdout" else
                    f"held-out RMS on every {SPLIT_EVERY}th contiguous time block of the data, "
                    "models fitted on the other blocks; the final coefficients are refitted "
                    "on all the data"),
        "selection": (f"blocked cross-validation in time on the fit data: about {N_BLOCKS} "
                      f"contiguous blocks dealt to {N_FOLDS} folds; each candidate linearised "
                      "about the current joint fit; scanned parameters chosen inside each "
                      "training fold"),
        "significance": (f"accept the candidate with the largest held-out SSE reduction among "
                         f"those that pass all of: (1) held-out likelihood ratio n_eff "
                         f"ln(SSE0_cv/SSE1_cv) against chi^2 with the effect's parameter count "
                         f"(scanned ones included), p x m < {ALPHA:g}, m the candidates in the "
                         f"round (Bonferroni), n_eff the rows deflated by the residual's lag-1 "
                         f"autocorrelation; (2) held-out score test: the held-out SSE gain over its "
                         f"standard deviation for a useless candidate, from each block's own "
                         f"noise where the candidate acts, one-sided normal, p x m < {ALPHA:g}; "
                         f"(3) held-out RMS reduction >= "
                         f"{100 * MIN_REL_GAIN:g} % in the blocks where the candidate acts "
                         f"(those carrying {100 * ACT_SHARE:g} % of its held-out prediction)"),
        "refit": ("after each accepted effect all coefficients (b, M, K, position constants "
                  "and every effect) are refitted jointly by Levenberg-Marquardt"),
        "stop": "when no candidate passes, or after "
                f"{MAX_EFFECTS} effects per sensor",
    }


REGRESSOR_FLIGHT = ("in flight it is a channel computed before the chain: the flight "
                    "software computes it from its inputs with the same formula and passes it "
                    "in the aux struct under its name (docs/effects.md)")


def declared_regressors(unit) -> list:
    """The unit file's [[trace.regressor]] entries, parsed (generator.io.formula; the unit
    file reader has checked them)."""
    from generator.io.formula import parse
    return [dict(r, tree=parse(r["formula"]))
            for r in (getattr(unit, "extra", None) or {}).get("trace_regressors", [])]


def _channel_units_fit(traces, tels):
    """A channel coefficient the coefficient file cannot hold (nT per unit beyond its
    plausible magnitude) comes from a channel given in tiny units: bad input, naming the
    column and a file that carries it."""
    from generator.flight.coeffs import _BLOCK_LIMITS, GENERIC_LIMIT
    for n, t in traces.items():
        m = t.final_model
        for i, e in enumerate(m.effects):
            if not isinstance(e, fx.ChannelBias):
                continue
            C = np.abs(e.C_nT_per_unit(m.effect_params(i)))
            block = "C_lag_nT_per_unit" if isinstance(e, fx.LaggedChannelBias) else \
                "C_nT_per_unit"
            limit = _BLOCK_LIMITS.get(block, GENERIC_LIMIT)
            if C.size and float(np.max(C)) > limit:
                src = next((t_.path for t_ in tels if e.channel in t_.columns), tels[0].path)
                raise InputError(src, f"column {e.channel}: the field of sensor {n} follows "
                                      f"it at {float(np.max(C)):.3g} nT per unit, beyond the "
                                      f"{limit:g} a coefficient file holds: the channel is in "
                                      "units too small (its spread is "
                                      f"{e.scale:.3g}); give it in larger units")


def _drop_series_caches(S) -> None:
    """The recursions' caches on a traced sensor's per-file series (trace.effects: whole-
    series arrays, up to SERIES_CACHE_BYTES a cache) let go once its trace is done: the
    values are the same without them (a later use recomputes), and the next sensor's
    trace does not run beside them."""
    for f in S.files:
        for k in [k for k in vars(f) if k.endswith("_cache")]:
            del f.__dict__[k]


def _drop_unused_explained(tr: SensorTrace) -> None:
    """The candidates' explained residuals (Score.explained: a float a residual row of
    the fit set, per candidate and round) let go once the sensor's trace is done, but
    those of each step's winner and runner-up (read again for trace.json: equivalent,
    runner_up_text): the rest is never read after the rounds, and kept it held ~0.1 GB a
    sensor at the cap (28 candidates x 7 rounds x 80,000 rows)."""
    keep = {id(x) for st in tr.steps for x in (st.score, st.runner_up) if x is not None}
    for sc in [*tr.last_scores, *(x for st in tr.steps
                                   for x in (*st.scores, *st.scores_after,
                                             st.runner_up_after) if x is not None)]:
        if id(sc) not in keep:
            sc.explained = None


# The rows the baseline fit reads at most (None: `magcal fit`'s read cap,
# fit.read_cap.read_cap_rows): above it the data files are read as the fit reads them, in
# blocks, and never held whole (a test sets a small value).
BASELINE_READ_ROWS = None


def _open_files(unit, data, holdout, regs, max_samples, need_whole, notes=None):
    """(data, holdout, whole, held): the telemetry of the data and holdout items. Held
    (trace.filerows.FileRows) when every item is a file on disk that can be held so
    (filerows.stream_ok) and their rows exceed the cap; whole: then the data files read
    whole for the baseline fit (need_whole, else None), or above the fit's read cap
    (BASELINE_READ_ROWS) as `magcal fit` reads them, in blocks (a note in notes).
    Otherwise read whole, as under the cap (Telemetry; whole None)."""
    from generator.fit.read_cap import read_cap_rows, read_for_fit
    from generator.fit.samples import MAX_FIT_SAMPLES
    from generator.io.telemetry_csv import _rows_at_most
    from generator.trace.filerows import FileRows, stream_ok
    items = list(data) + list(holdout)

    def read_whole():
        return ([add_regressors(regs, t) for t in _read(unit, data)],
                [add_regressors(regs, t) for t in _read(unit, holdout)])
    if not max_samples or not all(isinstance(it, (str, Path)) for it in items) \
            or sum(_rows_at_most(it) or math.inf for it in items) <= max_samples \
            or not all(stream_ok(it, unit) for it in items):
        return (*read_whole(), None, False)
    whole = None
    cap_rows = read_cap_rows(MAX_FIT_SAMPLES, BASELINE_READ_ROWS)
    if need_whole and sum(_rows_at_most(it) for it in data) > cap_rows:
        # the baseline fit takes the data files as `magcal fit` does above its read cap
        # (fit.read_cap: blocks of rows drawn at random, read streaming), so no file is
        # held whole; the trace's files are held by rows, read streaming as well
        whole, cap = read_for_fit(unit, list(data), MAX_FIT_SAMPLES, lambda m: None,
                                  max_rows=cap_rows)
        if notes is not None and cap is not None:
            n_all = sum(f.rows for f in cap.files)
            n_read = sum(f.rows_read for f in cap.files)
            notes.append(f"baseline fit: on {n_read:,} of the data files' {n_all:,} rows, "
                         f"{sum(f.blocks for f in cap.files)} blocks of {cap.block_rows:,} "
                         "consecutive rows drawn at random (seed fixed), as `magcal fit` "
                         f"reads files above {cap.cap_rows:,} rows (docs/fit_samples.md); "
                         "the trace itself holds every row")
        files = [FileRows(it, unit, regs) for it in items]
        return files[:len(data)], files[len(data):], whole, True
    if need_whole:                   # the baseline fit reads every column of every row
        whole, wh = read_whole()
        if sum(t.n for t in whole + wh) <= max_samples:
            return whole, wh, None, False
        files = [FileRows(t.path, unit, regs, tel=t) for t in whole + wh]
        del wh
    else:
        files = [FileRows(it, unit, regs) for it in items]
        if sum(f.n for f in files) <= max_samples:
            return (*read_whole(), None, False)
    return files[:len(data)], files[len(data):], whole, True


def _read(unit, items):
    from generator.io.orbit import require_field_reference
    from generator.io.telemetry import Telemetry
    from generator.io.telemetry_csv import read_telemetry
    out = []
    for it in items:
        out.append(it if isinstance(it, Telemetry) else read_telemetry(it, unit))
        require_field_reference(out[-1])   # ICD section 4: orbit data need the field model
    return out


def trace(unit, data, holdout=(), coeffs=None, progress=None, *, sensors=None,
          alpha=ALPHA, min_gain=MIN_REL_GAIN, max_effects=MAX_EFFECTS,
          max_samples=MAX_TRACE_SAMPLES) -> TraceResult:
    """Trace the residual of every sensor of the unit (see the module docstring).

    unit: Unit or unit-file path; data, holdout: telemetry paths or Telemetry objects;
    coeffs: baseline CoefficientSet or path (default: the core fit of the data files).
    max_samples: above this many rows (data and holdout files) the trace works on
    contiguous blocks drawn at random (trace.subsample; 0: every row); the baseline is
    fitted on all the rows (the fit has its own cap).
    """
    from generator.io.unit import Unit
    from generator.io.unitfile import load_unit
    t0 = time.perf_counter()
    say = progress or (lambda m: None)
    if not isinstance(unit, Unit):
        unit = load_unit(unit)
    if not data:
        raise InputError(unit.path, "trace: no telemetry files given")
    max_samples = check_max_samples(max_samples, unit.path)
    regs = declared_regressors(unit)
    # each recording once, and no held-out file that the fit also sees (io.recordings:
    # the same path, a link or the same bytes; Telemetry objects by their path)
    refuse_repeated_recordings([getattr(d, "path", d) for d in data],
                               held_out=[getattr(h, "path", h) for h in holdout])
    # above the cap, files on disk are held by what the trace needs of every row
    # (trace.filerows: the drawn rows read again, the all-rows figures read piece by piece)
    read_notes = []
    tels, hold, whole, held = _open_files(unit, data, holdout, regs, max_samples,
                                          need_whole=coeffs is None, notes=read_notes)
    # rows that repeat earlier rows (overlapping recordings): said, not dropped (files held
    # by rows above the cap carry their rows' fingerprints)
    from generator.io.recordings import repeated_rows, repeated_rows_warnings
    found = repeated_rows(tels + hold)
    held_paths = {str(t.path) for t in hold} - {str(t.path) for t in tels}
    for r in found:   # held-out rows that the fit also sees: nothing would be held out
        if str(r["path"]) in held_paths and str(r["of"]) not in held_paths:
            raise InputError(r["path"], f"held-out file: {r['rows']} row(s) from line "
                                        f"{r['first_line']} repeat rows of {r['of']}, which "
                                        "the fit uses (the same time and values): they "
                                        "would hold nothing out; hold out other rows")
    repeated = repeated_rows_warnings(tels + hold, found)
    from generator.io.telemetry_csv import text_column_notes
    for t in tels + hold:                 # columns that are not numbers: left out, said
        for n in text_column_notes(t):
            read_notes.append(n)
            say(n)
    # the blocks are drawn first (a cap below one block is refused before any fit)
    kept_tels, kept_hold, subsample = subsample_files(
        tels, hold, max_samples, **({"keep": lambda f, mask: f.blocked(mask)} if held else {}))
    notes = list(read_notes)
    for r in regs:
        have = [str(t.path) for t in tels + hold if r["name"] in t.columns]
        notes.append(f"regressor {r['name']} = {r['formula']} (unit file [[trace.regressor]]): "
                     + (f"a candidate channel in {len(have)} of {len(tels + hold)} files; "
                        if have else "no file carries all of "
                        f"{', '.join(r['inputs'])}: not a candidate; ")
                     + REGRESSOR_FLIGHT)
    if coeffs is None:
        base, degrees, bnotes = baseline_coefficients(unit, whole or tels, say)
        notes += bnotes
        whole = None                     # held files: the whole files are let go here
    else:
        base = coeffs if isinstance(coeffs, CoefficientSet) else CoefficientSet.load(coeffs)
        if set(base.unit.sensor_names) != set(unit.sensor_names):
            raise InputError(getattr(coeffs, "path", coeffs),
                             f"coefficients are for sensors {list(base.unit.sensor_names)}, "
                             f"the unit has {list(unit.sensor_names)}")
        degrees = {s.name: declared_degree(base, s.name) for s in unit.sensors}
        notes.append("baseline: the supplied coefficient set")
        for s in unit.sensors:       # the channels the supplied chain reads (as apply)
            for c in base.spec.opts(s).kernel_channels:
                for t in tels + hold:
                    if c not in t.columns:
                        raise InputError(t.path, f"column '{c}' is missing: the supplied "
                                                 f"coefficients read it (sensor {s.name})")
    coils = base.spec.coils
    tels_all, hold_all = tels, hold
    tels, hold = kept_tels, kept_hold
    if subsample:
        notes.append("subsample: " + subsample["text"])
        say(f"trace: {subsample['text']}")
    channels, partial = candidate_channels(unit, tels, coils)
    if partial:
        notes.append("channels only some data files carry (taken as 0 elsewhere, and fitted "
                     "with an offset of their own for the files that carry them, so that "
                     "only their variation counts): " + ", ".join(partial))
    allt = tels + hold
    roles = [0] * len(tels) + [1] * len(hold)
    H = base.unit_values.get("H_boom_to_body")
    samples = gather_samples(unit, allt, roles, coils=coils, H=H, channels=channels,
                             notes=notes, strict={r["name"] for r in regs})
    evaluated_on = "holdout" if hold else "split"
    checker = (all_rows_confirmation(tels_all, unit, coils=coils, H=H, channels=channels,
                                     strict={r["name"] for r in regs})
               if subsample else None)
    traces, skipped = {}, {}
    for s in unit.sensors:
        if sensors is not None and s.name not in sensors:
            continue
        S = samples[s.name]
        if S.n == 0 or not np.any(S.role == 0):
            skipped[s.name] = "no usable sample: " + _why_no_samples(s, tels_all + hold_all)
            say(f"{s.name}: skipped ({skipped[s.name]})")
            continue
        if evaluated_on == "holdout":
            S_fit, S_eval = S.subset(S.role == 0), S.subset(S.role == 1)
            S_fit.block = assign_blocks(S_fit)
            S_final = None
        else:
            S = S.subset(S.role == 0)
            S.block = assign_blocks(S)
            held = (S.block % SPLIT_EVERY) == SPLIT_EVERY // 2
            S_fit, S_eval = S.subset(~held), S.subset(held)
            S_final = S
        if S_fit.n < MIN_SAMPLES or S_eval.n < 3:
            skipped[s.name] = (f"{S_fit.n} samples to fit and {S_eval.n} to evaluate "
                               f"(at least {MIN_SAMPLES} needed)")
            continue
        bf = base_from_coefficients(base, s.name, degrees[s.name])
        init = initial_effects(base, s.name, S_fit) if coeffs is not None else []
        say(f"{s.name}: {S_fit.n} samples to fit, {S_eval.n} to evaluate "
            f"({', '.join(KIND_NAMES[k].split(' ')[0] for k in S_fit.kinds_present())} rows)")
        traces[s.name] = trace_sensor(s.name, bf, S_fit, S_eval, initial=init, alpha=alpha,
                                      min_gain=min_gain, max_effects=max_effects,
                                      S_final=S_final, progress=say,
                                      confirm=None if checker is None else
                                      (lambda m0, m1, n=s.name: checker(n, m0, m1)))
        _drop_series_caches(S)
        if s.name in traces:
            _drop_unused_explained(traces[s.name])
    if not traces:
        why = "; ".join(f"{n}: {w}" for n, w in skipped.items())
        raise InputError(tels[0].path if len(tels) == 1 else unit.path,
                         "trace: no sensor has enough usable samples with a field reference "
                         "or a static position" + (f" ({why})" if why else ""))
    info = {"effects": [{"sensor": n, "effect": st.effect.name,
                         "explained_by": st.effect.explained_by(),
                         "parameters": st.effect.describe(st.params, st.model_after),
                         "in_flight_chain": st.effect.in_chain}
                        for n, tr in traces.items() for st in tr.steps],
            "evaluated_on": evaluated_on}
    if subsample:
        info["subsample"] = subsample["text"]
        vetoed = [f"{n}: {c}" for n, t in traces.items() for c, w in t.rejected
                  if w.startswith(CONFIRM_PREFIX)]
        if vetoed:         # said where the user looks first, besides each sensor's refusals
            notes.append("subsample: accepted on the blocks but dropped because the error "
                         "over every row of the data files did not fall: " + "; ".join(vetoed))
    _channel_units_fit(traces, tels_all)
    cs = to_coefficient_set(base, traces, info)
    warnings = list(repeated)
    if subsample:        # the figures of the blocks, and the apply over every row
        subsample["all_rows"] = all_rows_rms(
            base, cs, tels_all, list(traces), {n: t.final_model for n, t in traces.items()},
            channels=channels, strict={r["name"] for r in regs})
        for n, v in subsample["all_rows"].items():
            say(f"{n}: over all {v['samples']:,} usable samples of the data files (in-sample): "
                f"RMS {v['baseline_rms_nT']:.2f} nT baseline -> {v['traced_rms_nT']:.2f} nT "
                f"traced ({v['model_rms_nT']:.2f} nT the trace's model)")
        warned = all_rows_warnings(subsample["all_rows"],
                                   {n: _blocks_figure(t) for n, t in traces.items()})
        for n, ws in warned.items():
            warnings += ws
            t = traces[n]
            if t.stop.startswith("nothing significant left"):
                t.stop = ("nothing significant left in the blocks, but NOT over every row "
                          "(see the WARNING notes): " + t.stop)
    elif any(t.steps for t in traces.values()):   # every row traced: the flight set's check
        rows = all_rows_rms(base, cs, tels_all, [n for n, t in traces.items() if t.steps])
        for ws in all_rows_warnings(rows).values():
            warnings += ws
    if warnings:          # first: the report shows the notes at its top
        notes[:0] = warnings
        if subsample:
            subsample["warnings"] = list(warnings)
        cs.fit_info["trace"]["warnings"] = list(warnings)
        for w in warnings:
            say(w)
    sources = {"data": [str(t.path) for t in tels_all],
               "holdout": [str(t.path) for t in hold_all],
               "baseline": "supplied coefficients" if coeffs is not None else
               base.fit_info.get("core", "fit")}
    return TraceResult(unit, evaluated_on, traces, skipped, base, cs, notes, sources,
                       time.perf_counter() - t0, subsample=subsample, warnings=warnings)


def _blocks_figure(t: SensorTrace) -> tuple:
    """(held-out RMS of the blocks' last model, its effective rows): the fewer of the
    rows deflated by the residual's lag-1 autocorrelation and of what the spread of the
    mean square between the evaluation's time blocks allows (a cluster sample: a
    non-stationary residual varies from block to block more than its lag-1 correlation
    says; the RMS's relative s.e. is half the mean square's, 1 / sqrt(2 n_eff) =
    sd(ms_b) / (2 mean(ms_b) sqrt(B)), so n_eff = 2 B mean^2 / sd^2)."""
    S = t.S_eval
    model = t.steps[-1].model_after if t.steps else t.base_model
    r = model.residual(model.theta[None], S)[0]
    rho = min(max(_lag1(r, S), 0.0), 0.99)
    n_eff = r.size * (1 - rho) / (1 + rho)
    blk = (S.block if S.block is not None else assign_blocks(S))[S.row_sample]
    ids = np.unique(blk)
    if len(ids) >= 3:
        ms = np.array([float(np.mean(r[blk == b] ** 2)) for b in ids])
        sd = float(np.std(ms, ddof=1))
        if sd > 0:
            n_eff = min(n_eff, 2 * len(ids) * float(np.mean(ms)) ** 2 / sd ** 2)
    return t.final_rms_nT, n_eff


__all__ = ["trace", "TraceResult", "SensorModel", "SensorSamples", "to_coefficient_set",
           "gather_samples", "model_from_coefficients", "calibrated_field64",
           "ALPHA", "MIN_REL_GAIN"]
