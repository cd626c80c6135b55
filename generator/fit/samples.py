"""What the fits see of one sensor: per-file FitData, gathered into _Samples (usable
samples of all files, cross-validation groups, constant-temperature segments), with the
temperature screen (impossible and outlying temperatures rejected and counted). Above
MAX_FIT_SAMPLES usable samples a sensor's fit takes a systematic random subsample, said
in its notes, with the residual over every usable sample (all_samples_residual;
docs/fit_samples.md).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import numpy as np

from generator.errors import InputError
from generator.fit.reference import NOISE_CATALOGUE, NOISE_STATED, T_REF_C
from generator.fit.segments import find_segments
from generator.io import parts as _parts

CV_FOLDS = 4

# The most usable samples of one sensor its fit takes (fit_sensor's max_samples, the CLI's
# `magcal fit --max-samples`; 0: all). The models are nonlinear (M(T) (x - b(T)) is
# bilinear, magnitude fits are nonlinear), so there are no exact sufficient statistics:
# above the cap the fit takes a systematic random subsample (_gather). What that costs:
# with p parameters fitted from n samples of noise sigma, the estimation error adds
# sigma sqrt(p / n) rms to the prediction at the data (the mean of the hat matrix's
# diagonal is p / n). A sensor has p <= ~60 (12 coefficients of b and M per degree, cubic:
# 48, plus coil and SET/RESET terms): at n = 200,000, sqrt(60 / 200,000) = 1.7 % of sigma
# rms, and in quadrature with the noise sqrt(1 + p/n) - 1 = 0.015 % of it -- below any
# figure the fit reports to its stated precision (a vector sample gives 3 equations, so
# the bound is loose by up to 3x more). The cap follows from that, not from a timing.
MAX_FIT_SAMPLES = 200_000
# fixed seed of the subsample (with the sensor name and the file's index): the same input
# gives the same calibration
SUBSAMPLE_SEED = 20
# samples per chunk of the all-samples residual (its (chunk, 3, 3) matrices: 4.7 MB)
RESIDUAL_CHUNK = 65536

# Temperatures no part of these units can report while working (MMC5883MA and MPU-9255
# operate at -40..85 degC and are rated for storage to -40..125 degC; the limits leave a wide
# margin): a value outside is a corrupt cell, rejected and counted.
TEMP_POSSIBLE_C = (-80.0, 150.0)
# A reported temperature further from the running median of its file (SPIKE_WINDOW
# samples) than each of: SPIKE_SIGMAS robust sigmas of those deviations (1.4826 MAD),
# SPIKE_QUANTA reporting steps, SPIKE_MIN_C, and SPIKE_STEPS times the largest change the
# series itself makes from one sample to the next (99th percentile, of the median-filtered
# series, so the spikes do not count), is an outlier: a board cannot jump away from where
# its temperature was going and back. The window is short (5): a median of 5 leaves any
# monotone stretch as it is, so a chamber step (a corner, then a monotone settling) is
# kept, and the step term keeps the corners of a fast profile; a spike of up to two
# samples is caught.
SPIKE_WINDOW = 5
SPIKE_SIGMAS = 6.0
SPIKE_QUANTA = 3.0
SPIKE_MIN_C = 1.0
SPIKE_STEPS = 3.0
# How far a reported board temperature can move in a time dt: a board follows its
# surroundings as a first-order lag, so it moves at most SPAN (1 - exp(-dt / tau)) for a
# change SPAN of the surroundings. SPAN: 180 degC, the widest test there is (a thermal
# shock between -55 and +125 degC chambers); tau: 5 min, a small populated board in a
# chamber's moving air (these units' boards take 10-20 min; the planner's default board
# time constant is of that order). A change from one sample to the next beyond that (and
# beyond the spike limit) cannot be the board's. An EXCURSION -- a stretch entered and
# left by such jumps, that comes back to where the series left (within what is possible
# over the stretch), shorter than the stretches on either side -- is a corrupt block of
# readings, rejected as outlying. Where logging stopped for long enough (a gap of a few
# tau) any change is possible: a chamber recorded only at its holds keeps every level.
TEMP_SPAN_C = 180.0
BOARD_TAU_MIN_S = 300.0


def screen_temperatures(temp_C, usable=None, time_s=None,
                        temp_lsb_C=None) -> tuple[np.ndarray, dict]:
    """Which reported temperatures to trust: (ok (N,) bool, counts {"impossible",
    "outlying"}). Non-finite values are left to the usable mask (not counted here).
    time_s (the samples' times): also rejects excursions (TEMP_SPAN_C, BOARD_TAU_MIN_S);
    temp_lsb_C: the part's temperature step (parts.toml), where known."""
    from generator.fit.segments import temperature_quantum
    from generator.fit.special import running_median

    T = np.asarray(temp_C, float)
    fin = np.isfinite(T) if usable is None else np.isfinite(T) & np.asarray(usable, bool)
    possible = fin & (T >= TEMP_POSSIBLE_C[0]) & (T <= TEMP_POSSIBLE_C[1])
    ok = possible.copy()
    idx = np.nonzero(possible)[0]
    n_out = 0
    if len(idx) >= 3:
        t = T[idx]
        med = running_median(t, min(SPIKE_WINDOW, len(t) | 1))
        dev = t - med
        s = 1.4826 * float(np.median(np.abs(dev - np.median(dev))))
        # the reporting step from the filtered series (a spike would pass for a step)
        step = float(np.percentile(np.abs(np.diff(med)), 99)) if len(med) > 1 else 0.0
        # the reporting step: the spacing of the values reported, or the smallest change
        # from one sample to the next, or the part's stated step, whichever is smallest (an
        # outlying level among few distinct values would pass for a step by itself)
        moves = np.abs(np.diff(t))
        moves = moves[moves > 0]
        quantum = min([temperature_quantum(med)] + ([float(moves.min())] if len(moves) else [])
                      + ([float(temp_lsb_C)] if temp_lsb_C else []))
        lim = max(SPIKE_SIGMAS * s, SPIKE_QUANTA * quantum, SPIKE_MIN_C, SPIKE_STEPS * step)
        out = np.abs(dev) > lim
        if time_s is not None:
            out |= _excursions(t, np.asarray(time_s, float)[idx], lim)
        ok[idx[out]] = False
        n_out = int(out.sum())
    return ok, {"impossible": int((fin & ~possible).sum()), "outlying": n_out}


def _excursions(t, time_s, lim) -> np.ndarray:
    """(n,) bool: samples of t in a corrupt stretch (TEMP_SPAN_C, BOARD_TAU_MIN_S).

    The series is cut at every change beyond lim: a JUMP where the board cannot make it
    in the time step, a GAP where it can only because the time step is long (logging
    stopped). A stretch is rejected when
    * jumps enter and leave it, it comes back to within what is possible of the level
      before, and it is shorter than the stretches on either side (an excursion); or
    * a jump is on one side only, the file's start or end or a gap on the other (nothing
      to come back to), and it is shorter than the stretch across the jump (a power-on
      value in the first rows, a block right after logging resumed)."""
    out = np.zeros(len(t), bool)
    change = np.abs(np.diff(t))
    jump = change > np.maximum(lim, _possible_change_C(np.diff(time_s)))
    cut = np.nonzero(change > lim)[0]                       # cut k: between k and k + 1
    if not jump.any():
        return out
    edges = np.concatenate([[-1], cut, [len(t) - 1]])      # stretch i: edges[i]+1..edges[i+1]
    length = np.diff(edges)
    n = len(length)
    for i in range(n):
        a, b = edges[i], edges[i + 1]
        jump_in = i > 0 and bool(jump[a])                   # cut a: a -> a + 1
        jump_out = i < n - 1 and bool(jump[b])              # cut b: b -> b + 1
        if jump_in and jump_out:
            before, after = t[a], t[b + 1]
            back = abs(after - before) <= max(lim, float(_possible_change_C(
                time_s[b + 1] - time_s[a])))
            away = np.sign(t[a + 1] - before) == np.sign(t[b] - after)
            bad = back and away and length[i] < length[i - 1] and length[i] < length[i + 1]
        elif jump_in:
            bad = length[i] < length[i - 1]
        elif jump_out:
            bad = length[i] < length[i + 1]
        else:
            bad = False
        if bad:
            out[a + 1:b + 1] = True
    return out


def _possible_change_C(dt_s):
    """The most a board's temperature can move in dt_s (TEMP_SPAN_C, BOARD_TAU_MIN_S);
    a non-finite or negative time step (times out of order, missing) allows anything."""
    dt = np.asarray(dt_s, float)
    ok = np.isfinite(dt) & (dt >= 0)
    return np.where(ok, TEMP_SPAN_C * -np.expm1(-np.where(ok, dt, 0.0) / BOARD_TAU_MIN_S),
                    np.inf)


@dataclass
class FitData:
    """One file's samples of one sensor, ready to fit (arrays of the file's length)."""
    source: str
    time_s: np.ndarray
    field_frame_nT: np.ndarray
    temp_C: np.ndarray
    usable: np.ndarray
    position: np.ndarray | None = None
    ref_body_nT: np.ndarray | None = None     # (N, 3), NaN where unknown
    ref_norm_nT: np.ndarray | None = None     # (N,), NaN where unknown
    coil_A: np.ndarray | None = None          # (N, n_coils)
    reference_kind: str = ""                  # description for stats
    noise_nT: float | None = None             # stated noise of one axis of field_frame_nT
    # False: the sensor reports no temperature (temperature = false); temp_C is then the
    # constant T_REF_C (SensorData.temp_or), so the fit is the constant (degree 0) model
    has_temperature: bool = True
    temp_lsb_C: float | None = None           # the part's temperature step (parts.toml)


class NoiseFigure(float):
    """A per-axis noise figure (nT) that remembers where it came from: `source` is
    NOISE_STATED (the unit file's noise_nT) or NOISE_CATALOGUE (the part's typical figure,
    generator/io/parts.toml). It is a float everywhere (FitData.noise_nT, _Samples.noise_nT,
    reference_fit(noise_nT=...)); fit.reference.noise_source reads the label back."""

    source: str = NOISE_STATED

    def __new__(cls, value, source=NOISE_STATED):
        out = super().__new__(cls, value)
        out.source = source
        return out


def field_noise_nT(spec) -> float | None:
    """1-sigma noise of one axis of the field a sensor's fit sees: noise_nT of one
    reading with the count quantisation (lsb^2/12) added, over sqrt(2) for a SET/RESET
    pair ((SET - RESET)/2 averages two readings). A NoiseFigure: its source says whether
    the figure is the unit file's (NOISE_STATED) or the part catalogue's typical one
    (NOISE_CATALOGUE); None only for a part with no figure (generic) and none stated, whose
    fit then estimates the noise from the data (fit.reference._reading_noise_var).

    The unit's stated noise_nT, else the part's (generator/io/parts.toml), for count and
    physical-unit sensors alike: the fit's errors-in-variables correction and its goodness
    test need the reading's own noise, which sample-to-sample differences of the data
    cannot give (they carry the reference's noise too, miss it when noise < 1 LSB, and
    carry the field's own change under fast motion). They do give an UPPER bound of it,
    which the fit applies to this figure (fit.reference.data_noise_var_bound: the
    correction clipped to it, the figure's uncertainty widened up to it) and the goodness
    test compares a stated figure with (fit.goodness.figure_warning). A sensor reading physical units
    (input = nT, uT, mG, G; ICD section 4) has no count quantisation: its columns hold
    real numbers, and lsb_nT is then only the input unit's size (1000 nT for uT), not a
    step of the reading."""
    if spec is None:
        return None
    noise, source = spec.noise_nT, NOISE_STATED
    if noise is None:
        part = _parts.find(spec.part)
        noise, source = (part.noise_nT if part is not None else None), NOISE_CATALOGUE
    if noise is None:
        return None
    quant = float(spec.lsb_nT) ** 2 / 12.0 if spec.counts else 0.0
    per_reading = float(noise) ** 2 + quant
    return NoiseFigure(np.sqrt(per_reading / (2.0 if spec.set_reset else 1.0)), source)


def fit_data_from(tel, sensor_data, unit) -> FitData:
    """Collect what one telemetry file carries for one sensor (see module docstring)."""
    n = tel.n
    try:
        spec = unit.sensor(sensor_data.name)
    except (KeyError, AttributeError):
        spec = None
    ref = None
    if tel.has("ref_x_nT", "ref_y_nT", "ref_z_nT"):
        ref = np.stack([tel.columns[f"ref_{c}_nT"] for c in "xyz"], axis=1).astype(float)
    norm = tel.get("ref_norm_nT")
    kind = []
    if ref is not None:
        kind.append("ref vectors")
    if norm is not None:
        norm = np.asarray(norm, float)
        kind.append("ref_norm_nT")
    elif unit.lab_field_nT is not None:
        norm = np.full(n, float(unit.lab_field_nT))
        kind.append("lab_field_nT")
    coils = [c for c in ("coil_x_A", "coil_y_A", "coil_z_A") if c in tel.columns]
    coil = np.stack([tel.columns[c] for c in coils], axis=1).astype(float) if coils else None
    pos = tel.get("position")
    return FitData(source=tel.path, time_s=np.asarray(tel.time_s, float),
                   field_frame_nT=np.asarray(sensor_data.field_frame_nT, float),
                   temp_C=np.asarray(sensor_data.temp_or(T_REF_C), float),
                   usable=np.asarray(sensor_data.usable, bool),
                   position=None if pos is None else np.asarray(pos, float),
                   ref_body_nT=ref, ref_norm_nT=norm, coil_A=coil,
                   reference_kind=" + ".join(kind) or "none", noise_nT=field_noise_nT(spec),
                   has_temperature=bool(sensor_data.has_temperature),
                   temp_lsb_C=None if spec is None else _parts.temperature_lsb_C(spec.part))


@dataclass
class _Samples:
    """Usable samples of one sensor over all files, concatenated."""
    x: np.ndarray            # (N, 3) field
    T: np.ndarray            # (N,) reported temperature
    ref: np.ndarray          # (N, 3) reference vector (NaN where none)
    norm: np.ndarray         # (N,) reference magnitude
    is_vec: np.ndarray       # (N,) bool
    group: np.ndarray        # (N,) int: cross-validation group
    segments: list = field(default_factory=list)   # Segment with index into these arrays
    time_s: np.ndarray | None = None                 # (N,) sample time in its file
    file_id: np.ndarray | None = None                # (N,) file number (EIV weights)
    noise_nT: float | None = None                    # stated noise of one axis of x
    prior: object = None                             # reference.Prior, or None (nominal)
    # where the fit took a subsample (_gather, max_samples): every usable sample, per file
    # (FitData, indices of its usable samples, reference (n, 3), magnitude (n,)) for the
    # residual over all of them (all_samples_residual); None when the fit has them all
    all_usable: list | None = None
    # (values, at, own): the distinct reported temperatures, sorted, and each sample's
    # place among them (temperature_index); own: of these samples' T (a subset keeps its
    # parent's values, a superset of its own)
    t_index: tuple | None = None

    def temperature_index(self) -> tuple:
        """t_index, computed once (one np.unique of T); subsets taken after it share the
        values (SensorCalibration.per_value(index=): b(T), M(T) once per value)."""
        if self.t_index is None:
            values, at = np.unique(self.T, return_inverse=True)
            self.t_index = (values, np.ravel(at), True)
        return self.t_index

    def subset(self, mask):
        mask = np.asarray(mask)
        if mask.dtype == bool:      # the rows once, then each field taken by index
            mask = np.flatnonzero(mask)
        return _Samples(self.x[mask], self.T[mask], self.ref[mask], self.norm[mask],
                        self.is_vec[mask], self.group[mask],
                        time_s=None if self.time_s is None else self.time_s[mask],
                        file_id=None if self.file_id is None else self.file_id[mask],
                        noise_nT=self.noise_nT, prior=self.prior,
                        t_index=None if self.t_index is None else (
                            self.t_index[0], self.t_index[1][mask], False))

    @property
    def n(self):
        return len(self.T)


def check_max_samples(max_samples, source=None) -> int:
    """max_samples as a whole number >= 0 (0: every usable sample), else InputError."""
    if isinstance(max_samples, bool) or not isinstance(max_samples, (int, np.integer)) \
            or max_samples < 0:
        raise InputError(source, f"fit: max_samples must be a whole number >= 0 (0: all "
                                 f"samples), got {max_samples!r}")
    return int(max_samples)


def subsample_step(n_usable: int, max_samples: int) -> int:
    """k, the block length of the systematic subsample: ceil(n_usable / max_samples) above
    the cap, else 1 (every sample kept). max_samples 0: no cap."""
    if not max_samples or n_usable <= max_samples:
        return 1
    return -(-int(n_usable) // int(max_samples))


def systematic_sample(n: int, k: int, rng) -> np.ndarray:
    """Systematic random sampling of positions 0..n-1: split into consecutive blocks of k
    (the last one may be shorter) and draw one position uniformly at random in each.
    Uniform coverage in time; no aliasing with a periodic motion (the draws are
    independent); returns ceil(n / k) sorted positions."""
    starts = np.arange(0, n, k)
    return starts + rng.integers(0, np.minimum(k, n - starts))


def subsample_rng(name: str, file_index: int):
    """numpy Generator(PCG64) of sensor `name`'s subsample in file number file_index: seeded
    from SUBSAMPLE_SEED, the name (crc32, not Python's salted hash) and the index."""
    return np.random.Generator(np.random.PCG64(
        [SUBSAMPLE_SEED, zlib.crc32(name.encode("utf-8")), int(file_index)]))


def usable_samples(d: FitData):
    """The samples of one file a sensor's fit can use (the one definition: _gather and the
    residual over every row, fit.read_cap): (use (n,) bool, ref (n, 3) reference vectors
    (NaN where none), norm (n,) reference magnitude (|ref| where there is a vector),
    has_vec (n,) bool, and the counts: unusable, temperature_rejected {impossible,
    outlying}, coil_current_excluded, no_reference). Usable: a finite reading and
    temperature, a temperature the screen keeps (screen_temperatures, over d's rows), no
    magnetorquer current, a field reference."""
    n = len(d.time_s)
    use = d.usable & np.isfinite(d.temp_C) & np.isfinite(d.field_frame_nT).all(axis=1)
    n_unusable = int((~use).sum())
    t_ok, t_rej = screen_temperatures(d.temp_C, use, d.time_s, d.temp_lsb_C)
    use &= t_ok
    coil_on = np.zeros(n, bool)
    if d.coil_A is not None:
        coil_on = np.any(np.nan_to_num(d.coil_A, nan=0.0) != 0, axis=1)
    n_coil = int((use & coil_on).sum())
    use &= ~coil_on
    ref = d.ref_body_nT if d.ref_body_nT is not None else np.full((n, 3), np.nan)
    has_vec = np.isfinite(ref).all(axis=1)
    norm = d.ref_norm_nT if d.ref_norm_nT is not None else np.full(n, np.nan)
    norm = np.where(has_vec, np.linalg.norm(np.nan_to_num(ref), axis=1), norm)
    has_ref = has_vec | (np.isfinite(norm) & (norm > 0))
    n_noref = int((use & ~has_ref).sum())
    use &= has_ref
    return use, ref, norm, has_vec, n_unusable, t_rej, n_coil, n_noref


def _gather(name, datas, notes, per_file, max_samples=MAX_FIT_SAMPLES, say=None):
    """The usable samples of sensor `name` over all its files (_Samples). The screens, the
    cross-validation groups and the constant-temperature segments are found on the full
    files; then, where the usable samples exceed max_samples (0: no cap), the fit keeps a
    systematic random subsample (systematic_sample, blocks of k = ceil(usable /
    max_samples) in each file's time order): per_file entries get "fit_samples", a note
    and a progress line say it, segments keep the samples drawn in them, and
    S.all_usable keeps what all_samples_residual needs."""
    max_samples = check_max_samples(max_samples, datas[0].source if datas else None)
    files = []
    for d in datas:
        n = len(d.time_s)
        if not d.has_temperature and not any("no temperature sensor" in m for m in notes):
            notes.append("no temperature sensor (temperature = false): a constant, "
                         "temperature-independent calibration")
        use, ref, norm, has_vec, n_unusable, t_rej, n_coil, n_noref = usable_samples(d)
        per_file.append({"source": d.source, "samples": int(n), "used": int(use.sum()),
                         "reference": d.reference_kind, "unusable": n_unusable,
                         "coil_current_excluded": n_coil, "no_reference": n_noref,
                         "temperature_rejected": t_rej})
        if t_rej["impossible"] or t_rej["outlying"]:
            notes.append(f"{d.source}: temperatures rejected: {t_rej['impossible']} impossible "
                         f"(outside {TEMP_POSSIBLE_C[0]:g}..{TEMP_POSSIBLE_C[1]:g} degC), "
                         f"{t_rej['outlying']} outlying (spikes off the running median, blocks a "
                         "board cannot reach and leave: docs/temperature_screen.md)")
        if n_coil:
            notes.append(f"{d.source}: {n_coil} samples with non-zero coil current left out "
                         "from the temperature fit (the coil coupling K is fitted from them separately)")
        if n_noref:
            notes.append(f"{d.source}: {n_noref} samples without any field reference unused")
        # cross-validation groups: static positions, else four contiguous time blocks
        pos = d.position
        g = np.zeros(n, int)
        by_position = (pos is not None
                       and len(np.unique(pos[use & (np.nan_to_num(pos) > 0)])) > 1)
        per_file[-1]["holdout_groups"] = "static positions" if by_position else "time blocks"
        if by_position:
            p = np.nan_to_num(pos).astype(int)
            g = p.copy()
            moving = p <= 0
            if moving.any():  # moving samples: attach to the previous static position
                last = np.maximum.accumulate(np.where(moving, 0, np.arange(n)))
                g[moving] = p[last[moving]]
        else:
            rank = np.cumsum(use) - 1
            g = np.minimum(rank * CV_FOLDS // max(int(use.sum()), 1), CV_FOLDS - 1)
        # segments in this file's reported temperature
        fsegs = find_segments(d.time_s, d.temp_C, d.position, use, temp_lsb_C=d.temp_lsb_C)
        files.append((d, n, np.nonzero(use)[0], ref, norm, has_vec, g, fsegs))

    n_usable = sum(len(f[2]) for f in files)
    k = subsample_step(n_usable, max_samples)
    xs, Ts, refs, norms, vecs, groups, segs, times, fids = [], [], [], [], [], [], [], [], []
    offset = 0
    gbase = 0
    for i, (d, n, keep, ref, norm, has_vec, g, fsegs) in enumerate(files):
        if k > 1:
            keep = keep[systematic_sample(len(keep), k, subsample_rng(name, i))]
            per_file[i]["fit_samples"] = int(len(keep))
        remap = -np.ones(n, int)
        remap[keep] = offset + np.arange(len(keep))
        for s in fsegs:
            s.index = remap[s.index]
            if k > 1:       # the samples drawn in it (found on the full file)
                s.index = s.index[s.index >= 0]
                if not len(s.index):
                    continue
            segs.append(s)
        xs.append(d.field_frame_nT[keep])
        Ts.append(d.temp_C[keep])
        times.append(np.asarray(d.time_s, float)[keep])
        refs.append(ref[keep])
        norms.append(norm[keep])
        vecs.append(has_vec[keep])
        groups.append(gbase + g[keep])
        fids.append(np.full(len(keep), len(fids)))
        gbase += int(g.max()) + 1 if n else 0
        offset += len(keep)
    if offset == 0:
        raise InputError(datas[0].source if datas else None,
                         f"sensor '{name}': no usable sample with a field reference "
                         "(reference vectors, ref_norm_nT or the unit's lab_field_nT)")
    S = _Samples(np.concatenate(xs), np.concatenate(Ts), np.concatenate(refs),
                 np.concatenate(norms), np.concatenate(vecs), np.concatenate(groups), segs,
                 time_s=np.concatenate(times), file_id=np.concatenate(fids),
                 noise_nT=next((d.noise_nT for d in datas if d.noise_nT), None))
    if k > 1:
        S.all_usable = [(f[0], f[2], f[3], f[4]) for f in files]
        note = (f"sensor '{name}': {n_usable:,} usable samples; the fit used {offset:,} (one "
                f"drawn at random in each block of {k} consecutive samples of a file, seed "
                f"fixed; cap {max_samples:,}, --max-samples 0 for all): its sigmas are those "
                f"of {offset:,} samples; the screens, hold-out groups and temperature "
                "segments were found on all samples")
        notes.append(note)
        if say:
            say(note)
    return S


def residual_sums(cal, d: FitData, idx, ref, norm, sums=None) -> list:
    """The sums of the residual of cal over the samples idx of one file d (ref, norm:
    usable_samples' reference vectors and magnitudes of d's rows), added to sums
    ([vector sum of squares, vector equations, |B| sum of squares, samples]; None: zeros):
    calibrated minus reference vector where there is one (per axis), |calibrated| minus
    the reference magnitude for every sample; in chunks of RESIDUAL_CHUNK samples (no
    per-sample matrices kept). The one computation of all_samples_residual, in memory
    (over S.all_usable) and streamed over every row of the files (fit.read_cap)."""
    sums = [0.0, 0, 0.0, 0] if sums is None else sums
    for a in range(0, len(idx), RESIDUAL_CHUNK):
        i = idx[a:a + RESIDUAL_CHUNK]
        z = cal.apply64(d.field_frame_nT[i], d.temp_C[i])
        r = ref[i]
        vec = np.isfinite(r).all(axis=1)
        sums[0] += float(np.sum((z[vec] - r[vec]) ** 2))
        sums[1] += 3 * int(vec.sum())
        sums[2] += float(np.sum((np.linalg.norm(z, axis=1) - norm[i]) ** 2))
        sums[3] += len(i)
    return sums


def residual_figures(sums, n_in_fit: int) -> dict:
    """stats all_samples_residual_nT from residual_sums: rms_vector_nT (per axis, None
    without vector samples), rms_norm_nT, n (usable samples), n_not_in_fit."""
    sv, nv, sn, nn = sums
    return {"rms_vector_nT": float(np.sqrt(sv / nv)) if nv else None,
            "rms_norm_nT": float(np.sqrt(sn / nn)) if nn else None,
            "n": int(nn), "n_not_in_fit": int(nn - n_in_fit)}


def all_samples_residual(cal, S: _Samples):
    """Where the fit took a subsample (S.all_usable): the RMS residual of cal over EVERY
    usable sample, those left out of the fit included -- a held-out check that the
    subsample's calibration holds on the rest. Vector samples: calibrated minus
    reference (per axis, as the fit's own stats["fit"]["rms_vector_nT"]); every sample:
    |calibrated| minus the reference magnitude (rms_norm_nT). Accumulated as sums in
    chunks of RESIDUAL_CHUNK samples (residual_sums). None when the fit had every
    sample."""
    if S.all_usable is None:
        return None
    sums = None
    for d, idx, ref, norm in S.all_usable:
        sums = residual_sums(cal, d, idx, ref, norm, sums)
    return residual_figures(sums or [0.0, 0, 0.0, 0], S.n)


RESIDUAL_NOTE_TAIL = " (stats all_samples_residual_nT)"


def record_all_samples_residual(cal, S: _Samples | None, say=None, res=None,
                                where="") -> None:
    """all_samples_residual into cal.stats["all_samples_residual_nT"] (beside the fit's
    own residual stats["fit"]) and a note; nothing when the fit had every sample. res:
    the figures computed elsewhere (fit.read_cap's pass over every row of the files; they
    replace the figures and note of an earlier call); where: what "all" covers, in the
    note."""
    res = all_samples_residual(cal, S) if res is None else res
    if res is None:
        return
    cal.stats["all_samples_residual_nT"] = res
    notes = cal.stats.setdefault("notes", [])
    notes[:] = [m for m in notes if not (m.startswith(f"{cal.name}: ")
                                         and m.endswith(RESIDUAL_NOTE_TAIL))]
    fit = cal.stats.get("fit") or {}
    key = "rms_vector_nT" if res["rms_vector_nT"] is not None else "rms_norm_nT"
    what = "vector RMS per axis" if key == "rms_vector_nT" else "|B| RMS"
    own = fit.get(key)
    n_fit = res["n"] - res["n_not_in_fit"]
    note = (f"{cal.name}: {what} over all {res['n']:,} usable samples{where} "
            f"({res['n_not_in_fit']:,} not in the fit): {res[key]:.2f} nT"
            + (f", on the fit's own {fit.get('n', n_fit):,}: {own:.2f} nT" if own is not None
               else "") + RESIDUAL_NOTE_TAIL)
    notes.append(note)
    if say:
        say(note)
