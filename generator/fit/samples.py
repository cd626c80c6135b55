"""What the fits see of one sensor: per-file FitData, gathered into _Samples (usable
samples of all files, cross-validation groups, constant-temperature segments), with the
temperature screen (impossible and outlying temperatures rejected and counted).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from generator.errors import InputError
from generator.fit.reference import NOISE_CATALOGUE, NOISE_STATED, T_REF_C
from generator.fit.segments import find_segments
from generator.io import parts as _parts

CV_FOLDS = 4

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


def screen_temperatures(temp_C, usable=None) -> tuple[np.ndarray, dict]:
    """Which reported temperatures to trust: (ok (N,) bool, counts {"impossible",
    "outlying"}). Non-finite values are left to the usable mask (not counted here)."""
    from scipy.ndimage import median_filter    # here: scipy.ndimage costs 0.2 s to import

    from generator.fit.segments import temperature_quantum

    T = np.asarray(temp_C, float)
    fin = np.isfinite(T) if usable is None else np.isfinite(T) & np.asarray(usable, bool)
    possible = fin & (T >= TEMP_POSSIBLE_C[0]) & (T <= TEMP_POSSIBLE_C[1])
    ok = possible.copy()
    idx = np.nonzero(possible)[0]
    n_out = 0
    if len(idx) >= 3:
        t = T[idx]
        med = median_filter(t, size=min(SPIKE_WINDOW, len(t) | 1), mode="nearest")
        dev = t - med
        s = 1.4826 * float(np.median(np.abs(dev - np.median(dev))))
        # the reporting step from the filtered series (a spike would pass for a step)
        step = float(np.percentile(np.abs(np.diff(med)), 99)) if len(med) > 1 else 0.0
        lim = max(SPIKE_SIGMAS * s, SPIKE_QUANTA * temperature_quantum(med), SPIKE_MIN_C,
                  SPIKE_STEPS * step)
        out = np.abs(dev) > lim
        ok[idx[out]] = False
        n_out = int(out.sum())
    return ok, {"impossible": int((fin & ~possible).sum()), "outlying": n_out}


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
    carry the field's own change under fast motion). A sensor reading physical units
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

    def subset(self, mask):
        return _Samples(self.x[mask], self.T[mask], self.ref[mask], self.norm[mask],
                        self.is_vec[mask], self.group[mask],
                        time_s=None if self.time_s is None else self.time_s[mask],
                        file_id=None if self.file_id is None else self.file_id[mask],
                        noise_nT=self.noise_nT, prior=self.prior)

    @property
    def n(self):
        return len(self.T)


def _gather(name, datas, notes, per_file):
    xs, Ts, refs, norms, vecs, groups, segs, times, files = [], [], [], [], [], [], [], [], []
    offset = 0
    gbase = 0
    for d in datas:
        n = len(d.time_s)
        if not d.has_temperature and not any("no temperature sensor" in m for m in notes):
            notes.append("no temperature sensor (temperature = false): a constant, "
                         "temperature-independent calibration")
        use = d.usable & np.isfinite(d.temp_C) & np.isfinite(d.field_frame_nT).all(axis=1)
        n_unusable = int((~use).sum())
        t_ok, t_rej = screen_temperatures(d.temp_C, use)
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
        per_file.append({"source": d.source, "samples": int(n), "used": int(use.sum()),
                         "reference": d.reference_kind, "unusable": n_unusable,
                         "coil_current_excluded": n_coil, "no_reference": n_noref,
                         "temperature_rejected": t_rej})
        if t_rej["impossible"] or t_rej["outlying"]:
            notes.append(f"{d.source}: temperatures rejected: {t_rej['impossible']} impossible "
                         f"(outside {TEMP_POSSIBLE_C[0]:g}..{TEMP_POSSIBLE_C[1]:g} degC), "
                         f"{t_rej['outlying']} outlying (spikes off the running median)")
        if n_coil:
            notes.append(f"{d.source}: {n_coil} samples with non-zero coil current left out "
                         "from the temperature fit (the coil coupling K is fitted from them separately)")
        if n_noref:
            notes.append(f"{d.source}: {n_noref} samples without any field reference unused")
        keep = np.nonzero(use)[0]
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
        remap = -np.ones(n, int)
        remap[keep] = offset + np.arange(len(keep))
        for s in fsegs:
            s.index = remap[s.index]
            segs.append(s)
        xs.append(d.field_frame_nT[keep])
        Ts.append(d.temp_C[keep])
        times.append(np.asarray(d.time_s, float)[keep])
        refs.append(ref[keep])
        norms.append(norm[keep])
        vecs.append(has_vec[keep])
        groups.append(gbase + g[keep])
        files.append(np.full(len(keep), len(files)))
        gbase += int(g.max()) + 1 if n else 0
        offset += len(keep)
    if offset == 0:
        raise InputError(datas[0].source if datas else None,
                         f"sensor '{name}': no usable sample with a field reference "
                         "(reference vectors, ref_norm_nT or the unit's lab_field_nT)")
    return _Samples(np.concatenate(xs), np.concatenate(Ts), np.concatenate(refs),
                    np.concatenate(norms), np.concatenate(vecs), np.concatenate(groups), segs,
                    time_s=np.concatenate(times), file_id=np.concatenate(files),
                    noise_nT=next((d.noise_nT for d in datas if d.noise_nT), None))

