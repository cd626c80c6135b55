"""What `magcal trace` takes of long telemetry: above MAX_TRACE_SAMPLES rows, contiguous
blocks of L consecutive rows drawn over all the files' blocks in order (systematic
cluster sampling, seed fixed; subsample_files). The kept blocks of a file stay ONE file (its
rows in time order, with gaps where blocks were left out): a static position keeps one
constant over the whole file, "time since the start of the file" keeps one clock, and the
lag recursions run across a gap as the flight chain's own recursion runs across a gap in
its telemetry. (Traced as files of their own, the blocks gave every block its own static
constant, which absorbed any channel that is constant within a block -- the armed flag of
the real PX4 ecl_office log -- so an effect won the cross-validation, where the constant
is fitted from other blocks, and then changed nothing on the held-out rows.) Under the cap
the files are passed through unchanged (docs/fit_samples.md, "magcal trace").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from generator.errors import InputError
from generator.fit.blocks import (BLOCK_TAUS, MIN_BLOCK_ROWS, MIN_BLOCKS,  # noqa: F401
                                  TAU_MAX_S, block_rows, block_runs, draw_blocks,
                                  fractional_systematic)
from generator.fit.samples import check_max_samples
from generator.io.telemetry import Telemetry
from generator.trace.filerows import FileRows
from generator.trace.filerows import kept_rows as _kept_rows

# The most telemetry rows (data and --holdout files together) a trace works on; 0: all.
# Memory: the trace keeps per-sample design columns, about 13 KiB a sample on bench_io's
# unit (bench/bench_io.py --trace-rows: 10^5 rows, 1389 MiB peak), more with more sensors
# and channels: 3.0 GB peak at the cap on the five-sensor samsat_fm1 unit (99,000 rows
# traced, /usr/bin/time -v; ~30 KiB a row); 10^6 rows would be ~13-30 GiB. Above the cap
# files on disk are held by what the trace needs of every row (trace.filerows.FileRows:
# the series columns packed, ~30 B a row on flight_6h; the drawn rows read again); the
# rest of a row costs nothing once read (bench/bench_trace.py --memory); at the cap on
# samsat_fm1 (flight_6h to 300,000 rows, five sensors) 1976 MiB peak against 2908 MiB.
# Statistics: an effect whose term has rms a against a residual noise sigma is detected
# with z ~ (a / sigma) sqrt(n_eff); with 3 vector rows a sample, n = 10^5 samples and a
# residual lag-1 correlation as high as 0.9 (n_eff = n (1 - rho) / (1 + rho), ~16,000
# samples, ~47,000 rows), the significance rule's z of ~4 (Bonferroni over ~20
# candidates) is reached at a / sigma ~ 4 / sqrt(47,000) ~ 2 % of the noise: effects
# the cap could hide are below what a flight-chain term is worth. And the parameters:
# p <= ~120 (baseline ~60 plus 6 effects) from 3 x 10^5 rows add sqrt(p / n) ~ 2 % of the
# noise rms to the prediction, 0.02 % in quadrature.
MAX_TRACE_SAMPLES = 100_000
SUBSAMPLE_SEED = 20          # fixed: the same input gives the same trace

# The block length (TAU_MAX_S, BLOCK_TAUS, MIN_BLOCK_ROWS, MIN_BLOCKS, block_rows) and the
# draw are fit.blocks': one place for the fit's read cap and this cap. The lag recursions
# themselves are exact above the cap: a kept file stays the whole file (BlockedTelemetry),
# its rows left out feed the recursions' state (bridge rows) and never become samples, so
# the element temperature at a sample is the one the uncapped trace computes (the one step
# across a gap the first version took was wrong when the temperature moved during the gap:
# 119 nT error after a gap against 41 nT without, a 4000 s lag found at 1826 s). The scan
# grids reach tau up to half a file's span (effects.ThermalLag.scan_grid), as without the
# cap. The 50 cross-validation blocks are then not a handful of runs.
# rows per piece of the all-rows apply (all_rows_rms): its per-sample arrays (no design
# matrix) for this many rows at a time; long against the blocks (a restart per piece)
ALL_ROWS_CHUNK = 200_000


@dataclass
class BlockedTelemetry(Telemetry):
    """A whole file whose samples are only the rows of its drawn blocks (sample_rows):
    every row stays for the per-file series (trace.samples.FileSeries), so the lag
    recursions run exactly through the rows left out (bridge rows: they feed the
    recursions' state and never become samples, design rows or residual rows); the raw
    rows cost ~8 B a channel, the design columns of a sample ~13 KiB."""
    sample_rows: np.ndarray | None = None      # (N,) bool: the rows of the drawn blocks

    def sample_view(self) -> Telemetry:
        """The rows of the drawn blocks, every column (what becomes samples)."""
        return _kept_rows(self, np.flatnonzero(self.sample_rows))


def check_cap(max_samples, n_rows, L, source=None, roles=1) -> None:
    """A cap below one block cannot be met by whole blocks (the blocks would exceed it),
    nor, with --holdout files (roles 2: the data's blocks and the holdout's are drawn
    apart, one at least each), a cap below two blocks: InputError naming --max-samples and
    the smallest cap that works."""
    if max_samples and n_rows > max_samples and max_samples < roles * L:
        what = (f"one block of {L:,} consecutive rows" if roles == 1 else
                f"the {roles} blocks of {L:,} consecutive rows a trace with --holdout "
                "draws at least (one for the data files, one for the holdout files; the "
                "cap counts both)")
        raise InputError(source, f"--max-samples {max_samples:,} is below {what}: give at "
                                 f"least {roles * L:,} (at least "
                                 f"{MIN_BLOCKS * MIN_BLOCK_ROWS:,} keeps the {MIN_BLOCKS} "
                                 f"blocks the trace is designed for), or 0 for every row")


def _blocked_telemetry(t, mask):
    """The kept file of an in-memory Telemetry: the whole file, its samples the mask."""
    return BlockedTelemetry(t.path, t.columns, t.line_numbers, t.meta, t.comments,
                            sample_rows=mask)


def subsample_files(tels, hold, max_samples=MAX_TRACE_SAMPLES, seed=SUBSAMPLE_SEED,
                    keep=_blocked_telemetry):
    """(tels, hold, info): the files unchanged and info None at or under the cap (total
    rows of tels + hold <= max_samples, or max_samples 0); else every file cut into
    consecutive blocks of L rows (block_rows) and floor(cap / L) blocks drawn over all the
    blocks of all the files in order (fractional_systematic: one systematic draw over the
    concatenated block list, numpy PCG64 seeded from seed alone, not from the files'
    names), the data files' and the holdout files' blocks drawn apart in proportion to
    their blocks (at least one each), so the kept rows are at most the cap (a cap below
    one block per role is refused, check_cap). The kept blocks of a file
    are one BlockedTelemetry (the whole file, its samples the blocks' rows); a file with
    no kept block is
    left out (info counts them); info holds the figures of the note. A cap below one block
    is an InputError (check_cap). The files need only n, time_s and path to be drawn;
    keep(file, mask) makes the kept file of the drawn rows (default: BlockedTelemetry;
    FileRows.blocked reads only those rows again)."""
    max_samples = check_max_samples(max_samples)
    N = sum(t.n for t in list(tels) + list(hold))
    if not max_samples or N <= max_samples:
        return list(tels), list(hold), None
    everything = list(tels) + list(hold)
    L = block_rows(everything, max_samples)
    check_cap(max_samples, N, L, everything[0].path if len(everything) == 1 else None,
              roles=2 if hold else 1)
    m_d, m_h, draws, _ = draw_blocks([t.n for t in tels], [t.n for t in hold], max_samples,
                                     L, seed)
    n_blocks = sum(-(-t.n // L) for t in everything)
    out = []
    for role, files in enumerate((list(tels), list(hold))):
        kept = []
        for f, picks in draws[role]:
            t = files[f]
            runs = block_runs(t.n, picks, L)
            if runs:
                mask = np.zeros(t.n, bool)
                mask[np.concatenate(runs)] = True
                kept.append((keep(t, mask), runs))
        out.append(kept)
    kd, kh = out
    n_kept = sum(int(t.sample_rows.sum()) for t, _ in kd + kh)
    n_left = len(everything) - len(kd) - len(kh)
    spans = [float(np.ptp(t.time_s)) for t, _ in kd + kh if t.n > 1]
    tau_max_s = 0.5 * max(spans) if spans else 0.0      # effects.ThermalLag.scan_grid
    step = n_blocks / max(1, m_d + m_h)
    few = (f"; only {m_d + m_h} blocks, fewer than the {MIN_BLOCKS} the trace is designed "
           f"for (a cap of at least {MIN_BLOCKS * MIN_BLOCK_ROWS:,} keeps them)"
           if m_d + m_h < MIN_BLOCKS else "")
    left = (f"; {n_left} of {len(everything)} files had no block drawn and are left out of "
            "the blocks (not of the all-rows figures)" if n_left else "")
    info = {"samples": int(N), "traced": int(n_kept), "block_rows": int(L),
            "one_block_in": round(step, 3), "blocks": int(m_d + m_h),
            "files_left_out": int(n_left),
            "seed": int(seed), "cap": int(max_samples),
            "longest_scanned_tau_s": tau_max_s,
            "text": (f"{N:,} samples; traced on {n_kept:,} in {m_d + m_h} blocks of {L:,} "
                     f"consecutive rows{' (fewer at the end of a file)' if n_kept < (m_d + m_h) * L else ''} (one in {step:.3g} of all the files' blocks in order, "
                     f"drawn at random, seed fixed; cap {max_samples:,}, `--max-samples`)"
                     f"{few}{left}; the kept blocks of a file traced as that "
                     f"file (one static constant and one clock per file; the lag recursions run "
                     f"through every row of the file, the rows left out feeding only their "
                     f"state; time constants scanned up to ~{tau_max_s:.0f} s, those longer than a few "
                     f"blocks ({L:,} rows each) seen only through the blocks' slow drift, and "
                     f"missed where the blocks are too few); the "
                     f"held-out figures are those of the blocks (all_rows: the coefficients "
                     f"applied to every row, in-sample)")}
    return [t for t, _ in kd], [t for t, _ in kh], info


def _pieces(tels):
    """Every data file in pieces of at most ALL_ROWS_CHUNK consecutive rows (the file's
    path kept, so that what an effect locates in a file is found in its pieces); a
    FileRows is read again from its file, piece by piece (the same pieces)."""
    for t in tels:
        if isinstance(t, FileRows):
            yield from t.pieces(ALL_ROWS_CHUNK)
            continue
        if t.n <= ALL_ROWS_CHUNK:
            yield t
            continue
        for a in range(0, t.n, ALL_ROWS_CHUNK):
            yield _kept_rows(t, np.arange(a, min(t.n, a + ALL_ROWS_CHUNK)))


# a static position of the all-rows apply is none of the traced models' positions: its
# constant is the mean of its own rows (SensorModel._residual_rows, "an unseen position")
_UNSEEN_GROUP = 10 ** 15


def _all_rows_sse(models_of, tels, unit, *, coils, H, channels, sensors, strict=()) -> dict:
    """{sensor: {"sse": [per model...], "rows", "samples", "lag_num", "lag_den"}} over
    every usable row of tels (vector rows per axis, magnitude rows, static-position rows
    as the deviation from their own mean: the constant fitted in-sample, per piece);
    models_of(sensor, S) -> the models to apply to that piece's samples; lag_num / lag_den
    pool the lag-1 autocorrelation of the LAST model's residual (crossval.lag1_parts)."""
    from generator.trace.crossval import lag1_parts
    from generator.trace.samples import POS, gather_samples
    acc = {}
    for tel in _pieces(tels):
        S_all = gather_samples(unit, [tel], [0], coils=coils, H=H, channels=channels,
                               strict=strict, sensors=sensors)
        for n in sensors:
            S = S_all.get(n)
            if S is None or S.n == 0:
                continue
            S.group = np.where(S.kind == POS, S.group + _UNSEEN_GROUP, S.group)
            models = models_of(n, S)
            rs = [m.residual(m.theta[None], S)[0] for m in models]
            a = acc.setdefault(n, {"sse": [0.0] * len(models), "rows": 0, "samples": 0,
                                   "lag_num": 0.0, "lag_den": 0.0})
            for j, r in enumerate(rs):
                a["sse"][j] += float(r @ r)
            num, den = lag1_parts(rs[-1], S)
            a["rows"] += len(rs[0])
            a["samples"] += S.n
            a["lag_num"] += num
            a["lag_den"] += den
            del S, models, rs
        del S_all, tel           # one piece held at a time: not this one beside the next
    return acc


def n_eff(rows, lag_num, lag_den) -> float:
    """The effective number of rows of a residual with pooled lag-1 autocorrelation
    rho = lag_num / lag_den (clipped to [0, 0.99]): rows (1 - rho) / (1 + rho), as
    trace.scoring and trace.residual deflate it."""
    rho = min(max(lag_num / lag_den if lag_den > 0 else 0.0, 0.0), 0.99)
    return rows * (1 - rho) / (1 + rho)


def all_rows_rms(base, traced, tels, sensors, final_models=None, channels=(),
                 strict=()) -> dict:
    """{sensor: {"baseline_rms_nT", "traced_rms_nT", "samples", ...}}: the RMS residual over
    EVERY usable row of the data files (vector rows per axis, magnitude rows, static-
    position rows as deviations from their position's mean) of the baseline coefficient
    set and of the traced one (the apply of fixed coefficients: linear in the rows), in
    pieces of ALL_ROWS_CHUNK consecutive rows of a file (the lag recursions restart at a
    piece's first row, a static position's constant is its mean over the piece).
    In-sample: the rows the trace fitted on are among them. With final_models ({sensor:
    the trace's final model}) also "model_rms_nT", that model (effects with no flight
    stage included) over every row; "n_eff": the effective rows of the residual of that
    model (else of the traced set); channels and strict: the trace's candidate channels and regressors those models read."""
    from generator.trace.coefficients import model_from_coefficients
    unit = traced.unit
    final_models = final_models or {}
    ch = list(dict.fromkeys(c for cs in (base, traced) for s in unit.sensors
                            for c in cs.spec.opts(s).kernel_channels))

    def models_of(n, S):
        ms = [model_from_coefficients(cs, n, S) for cs in (base, traced)]
        return ms + ([final_models[n]] if n in final_models else [])
    chans = list(dict.fromkeys(ch + list(channels)))
    acc = _all_rows_sse(models_of, tels, unit, coils=traced.spec.coils,
                        H=traced.unit_values.get("H_boom_to_body"), channels=chans,
                        sensors=sensors, strict=strict)
    out = {}
    for n, a in acc.items():
        if not a["rows"]:
            continue
        v = {"baseline_rms_nT": float(np.sqrt(a["sse"][0] / a["rows"])),
             "traced_rms_nT": float(np.sqrt(a["sse"][1] / a["rows"])), "samples": a["samples"],
             "n_eff": float(n_eff(a["rows"], a["lag_num"], a["lag_den"]))}
        if n in final_models:
            v["model_rms_nT"] = float(np.sqrt(a["sse"][2] / a["rows"]))
        out[n] = v
    return out


# the warnings' threshold: the RMS of n_eff independent rows has a relative standard
# error 1 / sqrt(2 n_eff) (chi^2 with n_eff degrees of freedom: var(s^2) = 2 s^4 / n_eff,
# halved for s); two RMS of independent sets differ in ratio by sqrt(1 / (2 n_a) +
# 1 / (2 n_b)); Z_WARN = 3 (one-sided 0.13 % a sensor) is beyond chance. n_eff deflates the
# rows by the residual's lag-1 autocorrelation as trace.scoring and trace.residual do.
# Conservative for the two comparisons below: the sets overlap (the blocks are among every
# row), which makes the figures correlated and their difference smaller than this.
Z_WARN = 3.0
WARNING_PREFIX = "WARNING"


def all_rows_warnings(all_rows, blocks=None) -> dict:
    """{sensor: [warning text]}: where the figures over every row contradict what the
    trace shows. (1) the traced (flight) coefficients are worse over every row than the
    baseline's (an effect with no flight stage -- time_drift, time_offset -- moved the
    written coefficients: with the cap or without); (2) above the cap, blocks {sensor:
    (held-out RMS of the blocks' final model, its n_eff)}: the trace's final model over
    every row is above the blocks' held-out figure beyond chance (an effect in rows the
    blocks left out)."""
    out = {}
    for n, v in all_rows.items():
        ne_a = max(v["n_eff"], 1.0)
        w = []
        b_a, t_a = v["baseline_rms_nT"], v["traced_rms_nT"]
        if t_a > b_a * (1 + Z_WARN / math.sqrt(2 * ne_a)):
            w.append(f"{WARNING_PREFIX} {n}: over every row of the data files the traced "
                     f"coefficients are WORSE than the baseline's (RMS {b_a:.2f} -> "
                     f"{t_a:.2f} nT, beyond chance): the written coefficient set is not an "
                     "improvement (an effect with no flight-chain stage moved it); prefer "
                     "the baseline")
        if blocks and n in blocks and "model_rms_nT" in v:
            rms_b, ne_b = blocks[n]
            ne_b, m_a = max(ne_b, 1.0), v["model_rms_nT"]
            if m_a > rms_b * (1 + Z_WARN * math.sqrt(1 / (2 * ne_a) + 1 / (2 * ne_b))):
                w.append(f"{WARNING_PREFIX} {n}: over every row of the data files the trace's "
                         f"model leaves {m_a:.2f} nT RMS, above the blocks' held-out "
                         f"{rms_b:.2f} nT beyond chance: rows the blocks left out hold "
                         "something the blocks do not show; the blocks' verdict does not hold "
                         "for every row (trace with a higher --max-samples, or 0 for every row)")
        if w:
            out[n] = w
    return out


CONFIRM_PREFIX = "not confirmed on all rows"


def all_rows_confirmation(tels, unit, *, coils, H, channels, strict=()):
    """confirm(sensor, model, m1) -> "" or why: the check an effect the blocks accepted
    must pass above the cap. model and m1 (the trace's models before and after the
    effect, fitted on the blocks, effects with no flight stage included: not the
    baseline and traced coefficient sets of all_rows_rms) are applied to every usable
    row of the data files (in pieces, in-sample, as all_rows_rms); the effect is kept
    only if m1's all-rows error is below model's. The blocks decide; all the rows may
    only veto: an effect that lowers the blocks' held-out error and not the error over
    every row is a property of the draw."""
    def confirm(name, model, m1) -> str:
        acc = _all_rows_sse(lambda n, S: [model, m1], tels, unit, coils=coils, H=H,
                            channels=channels, sensors=[name], strict=strict).get(name)
        if not acc or not acc["rows"]:
            return ""
        e0, e1 = acc["sse"]
        r0, r1 = math.sqrt(e0 / acc["rows"]), math.sqrt(e1 / acc["rows"])
        if e1 < e0:
            return ""
        return (f"{CONFIRM_PREFIX}: over all {acc['samples']:,} usable samples of the data "
                f"files (in-sample) the trace's models before and after it do not lower "
                f"the RMS ({r0:.2f} -> {r1:.2f} nT)")
    return confirm
