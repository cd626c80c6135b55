"""What `magcal trace` takes of long telemetry: above MAX_TRACE_SAMPLES rows, contiguous
blocks of L consecutive rows of each file, one block drawn at random in each run of k
(systematic cluster sampling, seed fixed). The kept blocks of a file stay ONE file (its
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

import numpy as np

from generator.fit.samples import check_max_samples, subsample_step, systematic_sample
from generator.io.telemetry import Telemetry

# The most telemetry rows (data and --holdout files together) a trace works on; 0: all.
# Memory: the trace keeps per-sample design columns, about 13 KiB a sample
# (bench/bench_io.py --trace-rows: 10^5 rows, 1389 MiB peak), so 10^5 rows is ~1.3 GiB,
# what one run may take on a machine shared with other work; 10^6 rows would be ~13 GiB.
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

# The block length. The slowest time constant the catalogue's effects are meant to find
# is a board's thermal lag: 10-20 min for these units' boards (fit.samples
# BOARD_TAU_MIN_S documents the 5-min lower bound); TAU_MAX_S = 20 min. A block spans
# BLOCK_TAUS = 5 of it (100 min). Across the gap before a block the lag recursion takes
# one step (dt the gap: generator.flight.chain.lag_kernel's backward-Euler step, what the
# chain itself does over a gap in its telemetry), exact if the temperature held still
# over the gap; the error it leaves at the block's first row decays as exp(-t / tau),
# under 1 % after 5 tau, so all but the block's first fifth is free of it even at the
# slowest tau. The scan grids reach tau up to half a file's span, gaps included
# (effects.ThermalLag.scan_grid), as without the cap. In rows: the block's duration over
# the files' shortest median sample period, at least MIN_BLOCK_ROWS (the lag-1
# statistics -- crossval._lag1, the successive-difference noise of trace.residual --
# take one pair across each gap: under 0.1 % of the pairs), and at most the cap over
# MIN_BLOCKS (so that the data keep at least that many blocks spread over the files'
# time, and the 50 cross-validation blocks are not a handful of runs; a block is then
# shorter than 5 tau of the slowest lag, and the note says how long it is).
TAU_MAX_S = 1200.0
BLOCK_TAUS = 5.0
MIN_BLOCK_ROWS = 1000
MIN_BLOCKS = 20
# rows per piece of the all-rows apply (all_rows_rms): its per-sample arrays (no design
# matrix) for this many rows at a time; long against the blocks (a restart per piece)
ALL_ROWS_CHUNK = 200_000


def block_rows(tels, max_samples) -> int:
    """L, the rows of one block (see the constants above)."""
    dts = []
    for t in tels:
        ts = np.asarray(t.time_s, float)
        d = np.diff(ts)
        d = d[np.isfinite(d) & (d > 0)]
        if len(d):
            dts.append(float(np.median(d)))
    dt = min(dts) if dts else 1.0
    L = max(MIN_BLOCK_ROWS, math.ceil(BLOCK_TAUS * TAU_MAX_S / dt))
    return int(min(L, max(MIN_BLOCK_ROWS, max_samples // MIN_BLOCKS)))


def _kept_rows(tel: Telemetry, rows: np.ndarray) -> Telemetry:
    """The file restricted to these rows (in order): the same path, so the same file."""
    return Telemetry(tel.path, {c: v[rows] for c, v in tel.columns.items()},
                     tel.line_numbers[rows], dict(tel.meta), list(tel.comments))


def subsample_files(tels, hold, max_samples=MAX_TRACE_SAMPLES, seed=SUBSAMPLE_SEED):
    """(tels, hold, info): the files unchanged and info None at or under the cap (total
    rows of tels + hold <= max_samples, or max_samples 0); else every file cut into
    consecutive blocks of L rows (block_rows), one block drawn at random in each run of k
    consecutive blocks of a file (fit.samples.systematic_sample; numpy PCG64 seeded from
    seed and the file's index: not its name, so a renamed file gives the same draw), the
    kept blocks of a file one Telemetry (the file's path, its rows in order), and info
    the figures of the note."""
    max_samples = check_max_samples(max_samples)
    N = sum(t.n for t in list(tels) + list(hold))
    if not max_samples or N <= max_samples:
        return list(tels), list(hold), None
    L = block_rows(list(tels) + list(hold), max_samples)
    n_blocks = sum(-(-t.n // L) for t in list(tels) + list(hold))
    k = subsample_step(n_blocks, max(1, max_samples // L))
    out = []
    for fi, t in enumerate(list(tels) + list(hold)):
        nb = -(-t.n // L)
        rng = np.random.Generator(np.random.PCG64([seed, fi]))
        picks = np.sort(systematic_sample(nb, k, rng)) if nb else np.zeros(0, int)
        runs = [np.arange(int(b) * L, min(t.n, (int(b) + 1) * L)) for b in picks]
        out.append((_kept_rows(t, np.concatenate(runs) if runs else np.zeros(0, int)),
                    runs))
    n_kept = sum(t.n for t, _ in out)
    spans = [float(np.ptp(t.time_s)) for t, _ in out if t.n > 1]
    tau_max_s = 0.5 * max(spans) if spans else 0.0      # effects.ThermalLag.scan_grid
    info = {"samples": int(N), "traced": int(n_kept), "block_rows": int(L),
            "one_block_in": int(k), "blocks": int(sum(len(runs) for _, runs in out)),
            "seed": int(seed), "cap": int(max_samples),
            "longest_scanned_tau_s": tau_max_s,
            "text": (f"{N:,} samples; traced on {n_kept:,} in blocks of {L:,} consecutive rows "
                     f"(one in {k} of each file, drawn at random, seed fixed; cap "
                     f"{max_samples:,}, `--max-samples`), the kept blocks of a file traced as that "
                     f"file (one static constant and one clock per file; lag recursions run "
                     f"across the gaps; time constants scanned up to ~{tau_max_s:.0f} s); the "
                     f"held-out figures are those of the blocks (all_rows: the coefficients "
                     f"applied to every row, in-sample)")}
    return [t for t, _ in out[:len(tels)]], [t for t, _ in out[len(tels):]], info


def _pieces(tels):
    """Every data file in pieces of at most ALL_ROWS_CHUNK consecutive rows (the file's
    path kept, so that what an effect locates in a file is found in its pieces)."""
    for t in tels:
        if t.n <= ALL_ROWS_CHUNK:
            yield t
            continue
        for a in range(0, t.n, ALL_ROWS_CHUNK):
            yield _kept_rows(t, np.arange(a, min(t.n, a + ALL_ROWS_CHUNK)))


# a static position of the all-rows apply is none of the traced models' positions: its
# constant is the mean of its own rows (SensorModel._residual_rows, "an unseen position")
_UNSEEN_GROUP = 10 ** 15


def _sse(model, S) -> tuple:
    """(sum of squared residual rows, rows) of a model on samples S: vector rows per axis,
    magnitude rows, static-position rows as the deviation from their own mean (the
    constant fitted in-sample, per piece)."""
    r = model.residual(model.theta[None], S)[0]
    return float(r @ r), len(r)


def _all_rows_sse(models_of, tels, unit, *, coils, H, channels, sensors, strict=()) -> dict:
    """{sensor: [sse per model..., rows, samples]} over every usable row of tels;
    models_of(sensor, S) -> the models to apply to that piece's samples."""
    from generator.trace.samples import POS, gather_samples
    acc = {}
    for tel in _pieces(tels):
        S_all = gather_samples(unit, [tel], [0], coils=coils, H=H, channels=channels,
                               strict=strict)
        for n in sensors:
            S = S_all.get(n)
            if S is None or S.n == 0:
                continue
            S.group = np.where(S.kind == POS, S.group + _UNSEEN_GROUP, S.group)
            models = models_of(n, S)
            sse = [_sse(m, S) for m in models]
            a = acc.setdefault(n, [0.0] * len(models) + [0, 0])
            for j, (e, _) in enumerate(sse):
                a[j] += e
            a[-2] += sse[0][1]
            a[-1] += S.n
    return acc


def all_rows_rms(base, traced, tels, sensors) -> dict:
    """{sensor: {"baseline_rms_nT", "traced_rms_nT", "samples"}}: the RMS residual over
    EVERY usable row of the data files (vector rows per axis, magnitude rows, static-
    position rows as deviations from their position's mean) of the baseline coefficient
    set and of the traced one (the apply of fixed coefficients: linear in the rows), in
    pieces of ALL_ROWS_CHUNK consecutive rows of a file (the lag recursions restart at a
    piece's first row, a static position's constant is its mean over the piece).
    In-sample: the rows the trace fitted on are among them."""
    from generator.trace.coefficients import model_from_coefficients
    unit = traced.unit
    ch = list(dict.fromkeys(c for cs in (base, traced) for s in unit.sensors
                            for c in cs.spec.opts(s).kernel_channels))
    acc = _all_rows_sse(lambda n, S: [model_from_coefficients(cs, n, S) for cs in (base, traced)],
                        tels, unit, coils=traced.spec.coils,
                        H=traced.unit_values.get("H_boom_to_body"), channels=ch,
                        sensors=sensors)
    return {n: {"baseline_rms_nT": float(np.sqrt(a[0] / a[2])),
                "traced_rms_nT": float(np.sqrt(a[1] / a[2])), "samples": a[3]}
            for n, a in acc.items() if a[2]}


CONFIRM_PREFIX = "not confirmed on all rows"


def all_rows_confirmation(tels, unit, *, coils, H, channels, strict=()):
    """confirm(sensor, model, m1) -> "" or why: the check an effect the blocks accepted
    must pass above the cap. model and m1 (the traced models before and after the effect,
    fitted on the blocks) are applied to every usable row of the data files (in pieces,
    in-sample, as all_rows_rms); the effect is kept only if m1's all-rows error is below
    model's. The blocks decide; all the rows may only veto: an effect that lowers the
    blocks' held-out error and not the error over every row is a property of the draw."""
    def confirm(name, model, m1) -> str:
        acc = _all_rows_sse(lambda n, S: [model, m1], tels, unit, coils=coils, H=H,
                            channels=channels, sensors=[name], strict=strict).get(name)
        if not acc or not acc[2]:
            return ""
        r0, r1 = math.sqrt(acc[0] / acc[2]), math.sqrt(acc[1] / acc[2])
        if acc[1] < acc[0]:
            return ""
        return (f"{CONFIRM_PREFIX}: over all {acc[3]:,} usable samples of the data files "
                f"(in-sample) the RMS does not fall ({r0:.2f} -> {r1:.2f} nT)")
    return confirm
