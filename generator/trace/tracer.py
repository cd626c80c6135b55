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
parameters are deviations from the baseline (the core fit, fit_thermal.fit_unit with
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

Significance rule (all three; m = candidates in the round, Bonferroni; ALPHA = 1e-3):
  1. beyond chance, with the parameter count: the held-out likelihood ratio
     n_eff ln(SSE0_cv / SSE1_cv) (SSE of the blocks' held-out residuals without and with
     the candidate) against chi^2 with the effect's parameter count (scanned parameters
     counted), p * m < ALPHA; n_eff = rows (1 - rho) / (1 + rho), rho the lag-1
     autocorrelation of the candidate's residual (correlated noise counts less). A
     useless parameter raises the held-out error on average, so chance alone rarely
     gives a large positive ratio;
  2. consistent over time: the per-block held-out SSE reductions have a positive mean,
     one-sided t-test over the blocks, p < BLOCK_LEVEL (0.01): not one lucky block;
  3. large enough to matter: the held-out RMS falls by at least MIN_REL_GAIN (1 %).

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
from types import SimpleNamespace

import numpy as np

from generator.trace import effects as fx
from generator.fit.calibration import SensorCalibration
from generator.flight.chain import MAX_POLY_DEGREE, ChainSpec, SensorOptions
from generator.flight.coeffs import CoefficientSet, json_default
from generator.errors import InputError
from generator.fit.ellipsoid import sym_from6
from generator.fit.reference import T_REF_C

VEC, NORM, POS = 0, 1, 2
KIND_NAMES = {VEC: "vector rows B_cal - B_ref (per axis)",
              NORM: "magnitude rows |B_cal| - |B|",
              POS: "deviation from a constant per static position (per axis)"}

ALPHA = 1e-3              # family-wise level per sensor and round (Bonferroni over candidates)
BLOCK_LEVEL = 0.01        # consistency over the held-out blocks (one-sided t-test)
MIN_REL_GAIN = 0.01       # least held-out RMS reduction of an accepted effect
N_BLOCKS = 50             # contiguous time blocks over a sensor's data
N_FOLDS = 5               # cross-validation folds (blocks dealt in turn)
SPLIT_EVERY = 5           # split mode: every 5th block held out for the figures
MAX_EFFECTS = 6           # per sensor
MIN_SAMPLES = 40          # per sensor, to trace at all
M_UNIT = 1e-4             # internal unit of M deviations (~5 nT at 50 uT)
FD_STEP = 1e-3            # finite-difference step, internal units (~1e-3 nT)
BATCH_ELEMENTS = 400_000  # batch x samples per model evaluation (memory)


# =======================================================================================
# Samples
# =======================================================================================
@dataclass
class FileSeries:
    """One file's temperature series of one sensor (all its readings, in time order):
    what the thermal-lag recursion runs over."""
    name: str
    time_s: np.ndarray
    temp_C: np.ndarray


@dataclass
class SensorSamples:
    """The usable samples of one sensor with a field reference of some kind."""
    spec: object
    time_s: np.ndarray
    file_index: np.ndarray
    file_row: np.ndarray          # index into files[file_index].time_s
    order: np.ndarray             # global time order (files in the order given)
    x: np.ndarray                 # (n, 3) raw field, frame axes, nT
    temp_C: np.ndarray            # reported temperature
    kind: np.ndarray              # VEC / NORM / POS
    ref: np.ndarray               # (n, 3) reference vector (body frame), NaN where none
    norm: np.ndarray              # (n,) reference magnitude, NaN where none
    group: np.ndarray             # (n,) static-position id (file * 1e6 + position), -1
    ref_rate: np.ndarray          # (n, 2, 3) forward / backward slope of the reference, nT/s
    coil: np.ndarray | None       # (n, ncoil) modelled coil currents
    rate_frame_dps: np.ndarray | None   # (n, 3) body rate in the sensor's frame
    channels: dict                # candidate channel -> (n,), 0 where the file lacks it
    files: list                   # FileSeries per file index
    file_names: list
    role: np.ndarray              # 0 data file, 1 holdout file
    channel_present: dict = field(default_factory=dict)   # channel -> (n,) file has it
    block: np.ndarray | None = None
    _rows: tuple | None = None

    @property
    def n(self) -> int:
        return len(self.time_s)

    def subset(self, mask) -> "SensorSamples":
        m = np.asarray(mask)
        return SensorSamples(
            self.spec, self.time_s[m], self.file_index[m], self.file_row[m], self.order[m],
            self.x[m], self.temp_C[m], self.kind[m], self.ref[m], self.norm[m], self.group[m],
            self.ref_rate[m], None if self.coil is None else self.coil[m],
            None if self.rate_frame_dps is None else self.rate_frame_dps[m],
            {k: v[m] for k, v in self.channels.items()}, self.files, self.file_names,
            self.role[m], {k: v[m] for k, v in self.channel_present.items()},
            None if self.block is None else self.block[m])

    @property
    def idx(self):
        """(vector, magnitude, position) sample indices."""
        if self._rows is None:
            iv = np.nonzero(self.kind == VEC)[0]
            im = np.nonzero(self.kind == NORM)[0]
            ip = np.nonzero(self.kind == POS)[0]
            row_sample = np.concatenate([np.repeat(iv, 3), im, np.repeat(ip, 3)])
            row_axis = np.concatenate([np.tile([0, 1, 2], len(iv)), np.full(len(im), 3),
                                       np.tile([0, 1, 2], len(ip))])
            self._rows = (iv, im, ip, row_sample, row_axis)
        return self._rows[:3]

    @property
    def row_sample(self):
        self.idx
        return self._rows[3]

    @property
    def row_axis(self):
        """0, 1, 2 for the axis rows, 3 for magnitude rows."""
        self.idx
        return self._rows[4]

    @property
    def n_rows(self) -> int:
        return len(self.row_sample)

    def kinds_present(self) -> list:
        return [k for k in (VEC, NORM, POS) if np.any(self.kind == k)]


def candidate_channels(unit, tels, coils=()) -> tuple:
    """Columns that may explain a residual: numeric columns of the data files that are
    not time, position, sensor (<s>_...), reference (ref_...) or modelled coil columns.
    Returns (all names in first-seen order, the names only some files carry)."""
    prefixes = tuple(f"{s.name}_" for s in unit.sensors) + ("ref_",)
    skip = {"time_s", "position", *coils}
    per = [[c for c in t.columns if c not in skip and not c.startswith(prefixes)]
           for t in tels]
    if not per:
        return [], []
    names = list(dict.fromkeys(c for cols in per for c in cols))
    partial = [c for c in names if not all(c in cols for cols in per)]
    return names, partial


def _ref_rate(time_s, ref, position):
    """Slopes of the reference vectors to the next and from the previous reference
    sample, (n, 2, 3) nT/s, within runs of moving samples (position 0 or absent): the
    reference linearly interpolated a time dt later is ref + dt * slope (forward slope
    for dt > 0, backward for dt < 0). Zero in static positions and at the ends of runs."""
    out = np.zeros((len(ref), 2, 3))
    fin = np.isfinite(ref).all(axis=1)
    idx = np.nonzero(fin)[0]
    if len(idx) < 3:
        return out
    t = time_s[idx]
    pos = position[idx]
    dt = np.diff(t)
    med = np.median(dt[dt > 0]) if np.any(dt > 0) else 1.0
    brk = np.concatenate([[True], (pos[1:] != pos[:-1]) | (dt > 10 * med) | (dt <= 0)])
    run = np.cumsum(brk)
    for r in np.unique(run):
        sel = idx[run == r]
        if len(sel) < 3 or position[sel[0]] > 0:
            continue
        slope = np.diff(ref[sel], axis=0) / np.diff(time_s[sel])[:, None]
        out[sel[:-1], 0] = slope
        out[sel[1:], 1] = slope
    return out


def gather_samples(unit, tels, roles, *, coils=(), H=None, channels=(), notes=None) -> dict:
    """{sensor: SensorSamples} over all files (data files then holdout files: the time
    order). roles: 0 data / 1 holdout per file. coils: the modelled coil columns; H: the
    boom -> body rotation (the rate in a boom sensor's frame is H^T w)."""
    from generator.io.telemetry_csv import preprocess
    notes = notes if notes is not None else []
    H = np.eye(3) if H is None else np.asarray(H, float)
    acc = {s.name: [] for s in unit.sensors}
    files = {s.name: [] for s in unit.sensors}
    names = [str(t.path) for t in tels]
    has_rate = any(all(f"rate_{a}_dps" in t.columns for a in "xyz") for t in tels)
    order0 = 0
    for fi, (tel, role) in enumerate(zip(tels, roles)):
        pre = preprocess(tel, unit)
        n = tel.n
        t = np.asarray(tel.time_s, float)
        pos = tel.get("position")
        pos = np.zeros(n) if pos is None else np.nan_to_num(np.asarray(pos, float))
        ref = (np.stack([tel.columns[f"ref_{a}_nT"] for a in "xyz"], axis=1).astype(float)
               if tel.has("ref_x_nT", "ref_y_nT", "ref_z_nT") else np.full((n, 3), np.nan))
        has_vec = np.isfinite(ref).all(axis=1)
        ref_rate = _ref_rate(t, ref, pos) if has_vec.any() else np.zeros((n, 2, 3))
        norm = tel.get("ref_norm_nT")
        norm = np.full(n, np.nan) if norm is None else np.asarray(norm, float)
        if unit.lab_field_nT is not None and "ref_norm_nT" not in tel.columns:
            norm = np.full(n, float(unit.lab_field_nT))
        has_norm = np.isfinite(norm) & (norm > 0)
        kind = np.where(has_vec, VEC, np.where(has_norm, NORM, np.where(pos > 0, POS, -1)))
        coil = None
        if coils:
            cols = [np.asarray(tel.columns[c], float) if c in tel.columns else np.zeros(n)
                    for c in coils]
            coil = np.stack(cols, axis=1)
        rate = None
        if has_rate:
            if all(f"rate_{a}_dps" in tel.columns for a in "xyz"):
                rate = np.nan_to_num(np.stack([tel.columns[f"rate_{a}_dps"] for a in "xyz"],
                                              axis=1).astype(float))
            else:
                rate = np.zeros((n, 3))
        ch, present = {}, {}
        for c in channels:
            v = tel.get(c)
            present[c] = v is not None
            if v is None:
                v = np.zeros(n)
            v = np.asarray(v, float)
            if not np.isfinite(v).all():
                notes.append(f"{tel.path}: channel {c} has {int((~np.isfinite(v)).sum())} "
                             "empty cells, taken as 0")
                v = np.nan_to_num(v)
            ch[c] = v
        for s in unit.sensors:
            sd = pre[s.name]
            # a sensor without temperature (temperature = false): the constant stand-in
            # (its baseline clamps every temperature to dT = 0, so the value is immaterial)
            temp_C = np.asarray(sd.temp_or(T_REF_C), float)
            series = sd.usable & np.isfinite(temp_C)
            ok = series & np.isfinite(sd.field_frame_nT).all(axis=1) & (kind >= 0)
            if coil is not None:
                ok &= np.isfinite(coil).all(axis=1)
            srow = np.cumsum(series) - 1
            files[s.name].append(FileSeries(names[fi], t[series], temp_C[series]))
            i = np.nonzero(ok)[0]
            w = None
            if rate is not None:
                w = rate[i] @ H if s.frame == "boom" else rate[i]
            acc[s.name].append(dict(
                time_s=t[i], file_index=np.full(len(i), fi), file_row=srow[i],
                order=order0 + i, x=sd.field_frame_nT[i], temp_C=temp_C[i],
                kind=kind[i], ref=ref[i], norm=np.where(has_vec[i], np.linalg.norm(
                    np.nan_to_num(ref[i]), axis=1), norm[i]),
                group=np.where(kind[i] == POS, fi * 1_000_000 + pos[i], -1).astype(np.int64),
                ref_rate=ref_rate[i], coil=None if coil is None else coil[i], rate=w,
                channels={c: v[i] for c, v in ch.items()}, role=np.full(len(i), role),
                present={c: np.full(len(i), present[c]) for c in ch}))
        order0 += n
    out = {}
    for s in unit.sensors:
        parts = acc[s.name]

        def cat(key, parts=parts):
            vals = [p[key] for p in parts]
            return None if vals[0] is None else np.concatenate(vals)
        out[s.name] = SensorSamples(
            s, cat("time_s"), cat("file_index"), cat("file_row"), cat("order"), cat("x"),
            cat("temp_C"), cat("kind"), cat("ref"), cat("norm"), cat("group"),
            cat("ref_rate"), cat("coil"), cat("rate"),
            {c: np.concatenate([p["channels"][c] for p in parts]) for c in channels},
            files[s.name], names, cat("role"),
            {c: np.concatenate([p["present"][c] for p in parts]) for c in channels})
    return out


def assign_blocks(S: SensorSamples, n_blocks=N_BLOCKS) -> np.ndarray:
    """Contiguous time blocks (sample order), cut at file changes and, for position
    rows, at position changes; a static position gets at least two blocks so that its
    constant is fitted from another block than the one held out."""
    n = S.n
    o = np.argsort(S.order, kind="stable")
    key = S.file_index[o] * 10_000_000 + np.where(S.kind[o] == POS, S.group[o] % 1_000_000, -1)
    cut = np.concatenate([[0], np.nonzero(np.diff(key))[0] + 1, [n]])
    L = max(1.0, n / n_blocks)
    block = np.empty(n, int)
    b = 0
    for a, z in zip(cut[:-1], cut[1:]):
        m = z - a
        nb = max(1, int(round(m / L)))
        if S.kind[o[a]] == POS and m >= 2:
            nb = max(nb, 2)
        for chunk in np.array_split(np.arange(a, z), nb):
            block[o[chunk]] = b
            b += 1
    return block


# =======================================================================================
# The float64 model of the extended chain
# =======================================================================================
@dataclass
class BaseFit:
    """The baseline's structure and values for one sensor (physical units)."""
    name: str
    degree: int
    t_ref_C: float
    t_min_C: float
    t_max_C: float
    b_poly: np.ndarray            # (degree+1, 3)
    M_poly: np.ndarray            # (degree+1, 3, 3)
    K: np.ndarray | None          # (3, ncoil)
    H: np.ndarray                 # (3, 3) boom -> body

    @property
    def t_scale_C(self) -> float:
        return max(abs(self.t_min_C - self.t_ref_C), abs(self.t_max_C - self.t_ref_C), 1.0)


def base_from_coefficients(cs: CoefficientSet, name: str, degree: int | None = None) -> BaseFit:
    v = cs.sensors[name]
    b = np.asarray(v["b_poly_nT"], float)
    M = np.asarray(v["M_poly"], float)
    if degree is None:
        degree = declared_degree(cs, name)
    degree = int(min(degree, b.shape[0] - 1))
    K = np.asarray(v["K_nT_per_A"], float) if "K_nT_per_A" in v else None
    H = np.asarray(cs.unit_values.get("H_boom_to_body", np.eye(3)), float)
    # a sensor with no temperature: constant, every temperature clamped to dT = 0
    t_ref, t_lo, t_hi = (float(v["t_ref_C"]), float(v["t_min_C"]), float(v["t_max_C"])) \
        if "t_ref_C" in v else (0.0, 0.0, 0.0)
    return BaseFit(name, degree, t_ref, t_lo, t_hi,
                   b[:degree + 1].copy(), M[:degree + 1].copy(), K, H)


def declared_degree(cs: CoefficientSet, name: str) -> int:
    """The degree a sensor's fit used (fit stats), else its highest non-zero row."""
    st = cs.fit_info.get("sensors", {}).get(name, {}).get("stats", {}) or {}
    if isinstance(st.get("degree"), int):
        return st["degree"]
    v = cs.sensors[name]
    b = np.asarray(v["b_poly_nT"])
    M = np.asarray(v["M_poly"])
    nz = [k for k in range(b.shape[0]) if np.any(b[k] != 0) or np.any(M[k] != 0)]
    return max([0] + [k for k in nz])


class SensorModel:
    """B_cal of one sensor from the extended chain, float64, batched over parameters.

    theta: internal parameters, deviations from the baseline: b rows (nT at the edge of
    the temperature range), M rows (M_UNIT), K (nT at the rms current), B_p (nT), then
    each effect's parameters (see generator.trace.effects)."""

    def __init__(self, base: BaseFit, *, free_b, free_M, free_K, groups, Bp0, i_rms=1.0,
                 effects=(), theta=None):
        self.base = base
        self.free_b = list(free_b)            # rows of b that are free
        self.free_M = free_M                  # "full" | "sym" | None
        self.free_K = bool(free_K) and base.K is not None
        self.groups = np.asarray(groups, np.int64)
        self.Bp0 = np.asarray(Bp0, float).reshape(-1, 3)
        self.i_rms = float(i_rms)
        self.effects = list(effects)
        D = base.degree
        sc = base.t_scale_C ** np.arange(D + 1)
        self.b_scaled = base.b_poly * sc[:, None]
        self.M_scaled = base.M_poly * sc[:, None, None]
        sizes = [("b", 3 * len(self.free_b)),
                 ("M", {"full": 9, "sym": 6, None: 0}[free_M] * (D + 1)),
                 ("K", base.K.size if self.free_K else 0),
                 ("Bp", 3 * len(self.groups))]
        sizes += [(f"e{i}", e.n_params) for i, e in enumerate(self.effects)]
        self.sl, k = {}, 0
        for name, size in sizes:
            self.sl[name] = slice(k, k + size)
            k += size
        self.P = k
        self.theta = np.zeros(k) if theta is None else np.asarray(theta, float).copy()
        assert self.theta.shape == (k,), (self.theta.shape, k)

    # ---- structure -------------------------------------------------------------------
    @staticmethod
    def for_samples(base: BaseFit, S: SensorSamples, effects=(), params=()):
        """The model whose free blocks the samples determine, B_p at the group means."""
        kinds = S.kinds_present()
        if VEC in kinds:
            free_b, free_M = list(range(base.degree + 1)), "full"
        elif NORM in kinds:
            free_b, free_M = list(range(base.degree + 1)), "sym"
        else:
            free_b, free_M = list(range(1, base.degree + 1)), None
        free_K = base.K is not None and S.coil is not None and np.any(S.coil != 0)
        i_rms = float(np.sqrt(np.mean(S.coil ** 2))) if free_K else 1.0
        groups = np.unique(S.group[S.kind == POS])
        m = SensorModel(base, free_b=free_b, free_M=free_M, free_K=free_K, groups=groups,
                        Bp0=np.zeros((len(groups), 3)), i_rms=max(i_rms, 1e-9))
        for e, p in zip(effects, params):
            m = m.with_effect(e, p)
        if len(groups):
            B = m.field(S)
            ip = S.kind == POS
            m.Bp0 = np.array([B[ip & (S.group == g)].mean(axis=0) for g in groups])
        return m

    def with_effect(self, effect, p0) -> "SensorModel":
        return SensorModel(self.base, free_b=self.free_b, free_M=self.free_M,
                           free_K=self.free_K, groups=self.groups, Bp0=self.Bp0,
                           i_rms=self.i_rms, effects=self.effects + [effect],
                           theta=np.concatenate([self.theta, np.asarray(p0, float)]))

    def copy(self) -> "SensorModel":
        return SensorModel(self.base, free_b=self.free_b, free_M=self.free_M,
                           free_K=self.free_K, groups=self.groups, Bp0=self.Bp0,
                           i_rms=self.i_rms, effects=list(self.effects), theta=self.theta)

    @property
    def degree(self) -> int:
        extra = [e.degree for e in self.effects if isinstance(e, fx.TemperaturePolynomial)]
        return max([self.base.degree] + extra)

    @property
    def t_scale_C(self) -> float:
        return self.base.t_scale_C

    def effect_params(self, i, theta=None):
        th = self.theta if theta is None else theta
        return th[self.sl[f"e{i}"]]

    # ---- evaluation --------------------------------------------------------------------
    def evaluate(self, th, S: SensorSamples):
        """B_cal (Bt, n, 3) and the reference shift (Bt, n, 3) or None, for parameter
        rows th (Bt, P), in the chain's order."""
        th = np.atleast_2d(th)
        Bt = th.shape[0]
        base = self.base
        D = base.degree
        T = S.temp_C[None, :]
        for i, e in enumerate(self.effects):
            if e.stage == "temperature":
                T = e.temperature(th[:, self.sl[f"e{i}"]], S, S.temp_C)
        Tc = np.clip(T, base.t_min_C, base.t_max_C)
        s = (Tc - base.t_ref_C) / base.t_scale_C
        st = SimpleNamespace(T=Tc, s=s)
        powers = [np.ones_like(s)]
        for _ in range(D):
            powers.append(powers[-1] * s)
        b_s = np.broadcast_to(self.b_scaled, (Bt, D + 1, 3)).copy()
        if self.free_b:
            b_s[:, self.free_b, :] += th[:, self.sl["b"]].reshape(Bt, len(self.free_b), 3)
        x = S.x[None, :, :] - sum(powers[k][:, :, None] * b_s[:, k, None, :]
                                  for k in range(D + 1))
        if base.K is not None and S.coil is not None:
            K = np.broadcast_to(base.K, (Bt,) + base.K.shape)
            if self.free_K:
                K = K + th[:, self.sl["K"]].reshape((Bt,) + base.K.shape) / self.i_rms
            x = x - np.matmul(S.coil, np.transpose(K, (0, 2, 1)))
        x = np.broadcast_to(x, (Bt, S.n, 3))
        for i, e in enumerate(self.effects):
            if e.stage == "offset":
                x = x - e.offset(th[:, self.sl[f"e{i}"]], S, st)
        for i, e in sorted(enumerate(self.effects), key=lambda ie: ie[1].order):
            if e.stage == "transform":
                x = e.transform(th[:, self.sl[f"e{i}"]], S, x, st)
        M_s = np.broadcast_to(self.M_scaled, (Bt, D + 1, 3, 3))
        if self.free_M == "full":
            M_s = M_s + M_UNIT * th[:, self.sl["M"]].reshape(Bt, D + 1, 3, 3)
        elif self.free_M == "sym":
            M_s = M_s + M_UNIT * sym_from6(th[:, self.sl["M"]].reshape(Bt, D + 1, 6))
        B = sum(powers[k][:, :, None] * np.matmul(x, np.transpose(M_s[:, k], (0, 2, 1)))
                for k in range(D + 1))
        for i, e in enumerate(self.effects):
            if e.stage == "calibrated":
                B = e.calibrated(th[:, self.sl[f"e{i}"]], S, B, st)
        shift = None
        for i, e in enumerate(self.effects):
            if e.stage == "reference":
                d = e.reference_shift(th[:, self.sl[f"e{i}"]], S)
                shift = d if shift is None else shift + d
        return B, shift

    def field(self, S, theta=None) -> np.ndarray:
        """B_cal (n, 3) at theta (default: the fitted parameters)."""
        th = self.theta if theta is None else theta
        return self.evaluate(th[None], S)[0][0]

    def residual(self, th, S: SensorSamples) -> np.ndarray:
        """Residual rows (Bt, R): vector rows, magnitude rows, position rows."""
        th = np.atleast_2d(th)
        Bt = th.shape[0]
        B, shift = self.evaluate(th, S)
        iv, im, ip = S.idx
        parts = []
        if len(iv):
            ref = S.ref[iv][None]
            if shift is not None:
                ref = ref + shift[:, iv]
            parts.append((B[:, iv] - ref).reshape(Bt, -1))
        if len(im):
            parts.append(np.linalg.norm(B[:, im], axis=2) - S.norm[im][None])
        if len(ip):
            g = S.group[ip]
            k = np.searchsorted(self.groups, g)
            k = np.minimum(k, max(len(self.groups) - 1, 0))
            known = (self.groups[k] == g) if len(self.groups) else np.zeros(len(g), bool)
            target = np.empty((Bt, len(ip), 3))
            if known.any():
                Bp = th[:, self.sl["Bp"]].reshape(Bt, -1, 3) + self.Bp0[None]
                target[:, known] = Bp[:, k[known]]
            for gg in np.unique(g[~known]):      # an unseen position: its own mean
                sel = g == gg
                target[:, sel] = B[:, ip[sel]].mean(axis=1, keepdims=True)
            parts.append((B[:, ip] - target).reshape(Bt, -1))
        return np.concatenate(parts, axis=1) if parts else np.zeros((Bt, 0))

    def jacobian(self, S, theta=None, cols=None):
        """(r (R,), J (R, len(cols))) by forward differences at theta."""
        th0 = self.theta if theta is None else np.asarray(theta, float)
        cols = np.arange(self.P) if cols is None else np.asarray(cols)
        r0 = self.residual(th0[None], S)[0]
        J = np.empty((len(r0), len(cols)))
        chunk = max(1, BATCH_ELEMENTS // max(S.n, 1))
        for a in range(0, len(cols), chunk):
            sub = cols[a:a + chunk]
            th = np.repeat(th0[None], len(sub), axis=0)
            th[np.arange(len(sub)), sub] += FD_STEP
            J[:, a:a + len(sub)] = (self.residual(th, S) - r0[None]).T / FD_STEP
        return r0, J

    def fit(self, S, max_nfev=60) -> "SensorModel":
        if self.P == 0:
            return self
        fun = lambda th: self.residual(th[None], S)[0]          # noqa: E731
        jac = lambda th: self.jacobian(S, th)[1]                 # noqa: E731
        method = "lm" if S.n_rows > self.P else "trf"
        from scipy.optimize import least_squares
        res = least_squares(fun, self.theta, jac=jac, method=method, xtol=1e-10, ftol=1e-12,
                            gtol=1e-12, max_nfev=max_nfev)
        self.theta = res.x
        return self

    def sse(self, S) -> float:
        r = self.residual(self.theta[None], S)[0]
        return float(r @ r)

    def rms(self, S) -> float:
        r = self.residual(self.theta[None], S)[0]
        return float(np.sqrt(np.mean(r * r))) if r.size else float("nan")

    # ---- physical values ---------------------------------------------------------------
    def values(self) -> dict:
        """b_poly_nT, M_poly (degree of the base), K_nT_per_A (or None): physical."""
        D = self.base.degree
        sc = self.base.t_scale_C ** np.arange(D + 1)
        b = self.b_scaled.copy()
        th = self.theta
        if self.free_b:
            b[self.free_b] += th[self.sl["b"]].reshape(len(self.free_b), 3)
        M = self.M_scaled.copy()
        if self.free_M == "full":
            M = M + M_UNIT * th[self.sl["M"]].reshape(D + 1, 3, 3)
        elif self.free_M == "sym":
            M = M + M_UNIT * sym_from6(th[self.sl["M"]].reshape(D + 1, 6))
        K = self.base.K
        if self.free_K:
            K = K + th[self.sl["K"]].reshape(K.shape) / self.i_rms
        return {"b_poly_nT": b / sc[:, None], "M_poly": M / sc[:, None, None],
                "K_nT_per_A": None if K is None else np.array(K)}


# =======================================================================================
# Scoring by blocked cross-validation (linearised about the current fit)
# =======================================================================================
class LinearSolver:
    """Least squares min |y + J d + G beta| over d (J: the current model's Jacobian on
    some rows) and beta (G: a candidate's columns), by normal equations with column
    scaling (only products of tall matrices and eigen-decompositions of small ones)."""

    def __init__(self, J):
        self.J = J
        P = J.shape[1]
        if P == 0:
            self.Ginv = np.zeros((0, 0))
            return
        self.Ginv = _pinv_gram(J.T @ J)

    def fit(self, y, G=None):
        """(residual, beta or None, d): the least-squares residual on these rows."""
        J = self.J
        d_y = -self.Ginv @ (J.T @ y) if J.shape[1] else np.zeros(0)
        ry = y + J @ d_y if J.shape[1] else y.copy()
        if G is None or G.shape[1] == 0:
            return ry, None, d_y
        if J.shape[1]:
            d_G = -self.Ginv @ (J.T @ G)
            rG = G + J @ d_G
        else:
            d_G = np.zeros((0, G.shape[1]))
            rG = G
        beta = -_pinv_gram(rG.T @ rG) @ (rG.T @ ry)
        return ry + rG @ beta, beta, d_y + d_G @ beta


def _pinv_gram(A, rcond=1e-13):
    """Pseudo-inverse of a symmetric positive semi-definite Gram matrix (scaled eigh)."""
    d = np.sqrt(np.maximum(np.diag(A), 0))
    d[d == 0] = 1.0
    As = A / np.outer(d, d)
    try:   # the common, well-conditioned case: Cholesky (fast), checked
        L = np.linalg.cholesky(As)
        dg = np.diag(L)
        if dg.min() > 0 and (dg.max() / dg.min()) ** 2 < 1e8:
            Li = np.linalg.inv(L)
            return (Li.T @ Li) / np.outer(d, d)
    except np.linalg.LinAlgError:
        pass
    w, V = np.linalg.eigh(As)
    keep = w > (w[-1] * rcond if len(w) and w[-1] > 0 else np.inf)
    inv = (V[:, keep] / w[keep]) @ V[:, keep].T
    return inv / np.outer(d, d)


class CVEngine:
    """The linearised fit of r0 (+ d0) + J d + G beta per training fold, and the held-out
    residual of each block. Training-fold normal equations come from the full ones minus
    the held-out rows' (no copies of the training rows), solved by block elimination with
    the pseudo-inverse of the training J^T J."""

    FREEZE_RATIO = 10.0   # a parameter whose variance grows more than this when a fold
    #                       is held out is held at its fit in every fold

    def __init__(self, r0, J, row_block, fold_of_block, n_blocks):
        self.r0 = r0
        self.row_block = row_block
        self.fold_of_block = fold_of_block
        self.n_blocks = n_blocks
        fold_of_row = fold_of_block[row_block]
        tests = [np.nonzero(fold_of_row == f)[0] for f in range(int(fold_of_block.max()) + 1)]
        tests = [te for te in tests if len(te)]
        # Parameters that one fold alone determines (the coupling of a coil whose steps
        # all lie in one block, say) would be refitted to noise when that fold is held
        # out, and their held-out error would swamp every comparison: keep them at the
        # fit of all the data in every fold (the candidate's own columns always refit).
        self.frozen = np.zeros(J.shape[1], bool)
        if J.shape[1]:
            JJ = J.T @ J
            var_full = np.diag(_pinv_gram(JJ))
            for te in tests:
                var_f = np.diag(_pinv_gram(JJ - J[te].T @ J[te]))
                with np.errstate(divide="ignore", invalid="ignore"):
                    self.frozen |= ~(var_f <= self.FREEZE_RATIO * var_full)
            self.frozen &= var_full > 0
        J = J[:, ~self.frozen]
        self.J = J
        self.JJ = J.T @ J
        self.Ainv_full = _pinv_gram(self.JJ) if J.shape[1] else np.zeros((0, 0))
        self.folds = []
        for te in tests:
            Jte = J[te]
            Ainv = _pinv_gram(self.JJ - Jte.T @ Jte) if J.shape[1] else np.zeros((0, 0))
            self.folds.append((te, Jte, row_block[te], Ainv))

    @staticmethod
    def _solve(Ainv, yy, Jy, G_parts):
        """min |y + J d + G beta|^2 from normal-equation pieces: (SSE, d, beta)."""
        d_y = -Ainv @ Jy
        if G_parts is None:
            return yy + d_y @ Jy, d_y, None
        JG, GG, Gy = G_parts
        AJG = Ainv @ JG
        S = GG - JG.T @ AJG                        # Schur complement (k x k)
        rhs = Gy - JG.T @ (Ainv @ Jy)
        beta = -_pinv_gram(S) @ rhs
        d = d_y - AJG @ beta
        sse = yy + d @ Jy + beta @ Gy
        return max(sse, 0.0), d, beta

    def evaluate(self, d0=None, G=None):
        """Train SSE per fold (K,), held-out SSE per block (B,), full-data SSE, for the
        model with offset d0 (R,) and columns G (R, k)."""
        y = self.r0 if d0 is None else self.r0 + d0
        J = self.J
        yy, Jy = float(y @ y), J.T @ y
        full_G = None
        if G is not None:
            full_G = (J.T @ G, G.T @ G, G.T @ y)
        train = np.empty(len(self.folds))
        block = np.zeros(self.n_blocks)
        for f, (te, Jte, bte, Ainv) in enumerate(self.folds):
            y_te = y[te]
            parts = None
            if G is not None:
                G_te = G[te]
                parts = (full_G[0] - Jte.T @ G_te, full_G[1] - G_te.T @ G_te,
                         full_G[2] - G_te.T @ y_te)
            sse, d, beta = self._solve(Ainv, yy - y_te @ y_te, Jy - Jte.T @ y_te, parts)
            train[f] = sse
            test = y_te + Jte @ d
            if beta is not None:
                test = test + G_te @ beta
            block += np.bincount(bte, weights=test * test, minlength=self.n_blocks)
        sse_full, _, _ = self._solve(self.Ainv_full, yy, Jy, full_G)
        return train, block, float(sse_full)

    def full_residual(self, d0=None, G=None):
        y = self.r0 if d0 is None else self.r0 + d0
        J = self.J
        Jy = J.T @ y
        parts = None if G is None else (J.T @ G, G.T @ G, G.T @ y)
        _, d, beta = self._solve(self.Ainv_full, float(y @ y), Jy, parts)
        res = y + J @ d
        if beta is not None:
            res = res + G @ beta
        return res


def _lag1(res, S: SensorSamples) -> float:
    """Pooled lag-1 autocorrelation of residual rows along time (per axis / kind)."""
    rs, ax = S.row_sample, S.row_axis
    num = den = 0.0
    for a in range(4):
        sel = np.nonzero(ax == a)[0]
        if len(sel) < 3:
            continue
        o = sel[np.argsort(S.order[rs[sel]], kind="stable")]
        v = res[o]
        num += float(v[1:] @ v[:-1])
        den += float(v @ v)
    return num / den if den > 0 else 0.0


@dataclass
class Score:
    effect: object
    hyper: object
    dof: int
    sse0_cv: float
    sse1_cv: float
    block_gain: np.ndarray
    t: float
    p_t: float
    sse0_full: float
    sse1_full: float
    n_eff: float
    lr: float                 # held-out likelihood ratio n_eff ln(SSE0_cv / SSE1_cv)
    p_lr: float
    lr_fit: float             # the same on the fit data (information)
    m: int = 1
    significant: bool = False
    reasons: list = field(default_factory=list)
    explained: np.ndarray | None = None      # r0 - full-data residual (rows of the fit set)

    @property
    def rel_rms_gain(self) -> float:
        return 1.0 - math.sqrt(self.sse1_cv / self.sse0_cv) if self.sse0_cv > 0 else 0.0

    @property
    def blocks_improved(self) -> int:
        return int(np.sum(self.block_gain > 0))

    def judge(self, m, alpha, min_gain):
        self.m = m
        self.reasons = []
        if not self.p_lr * m < alpha:
            self.reasons.append(f"held-out likelihood ratio {self.lr:.1f} for {self.dof} "
                                f"parameters is within chance (p x {m} = "
                                f"{min(self.p_lr * m, 1):.2g})")
        if not self.p_t < BLOCK_LEVEL:
            self.reasons.append(f"held-out gain not consistent over the blocks "
                                f"(t = {self.t:.2f}, p = {self.p_t:.2g})")
        if not self.rel_rms_gain >= min_gain:
            self.reasons.append(f"held-out RMS gain {100 * self.rel_rms_gain:.2f} % "
                                f"< {100 * min_gain:g} %")
        self.significant = not self.reasons
        return self.significant

    def summary(self) -> dict:
        return {"effect": self.effect.name, "explained_by": self.effect.explained_by(),
                "parameters": self.dof, "cv_rms_gain_pct": 100 * self.rel_rms_gain,
                "blocks_improved": self.blocks_improved,
                "blocks": int(len(self.block_gain)), "t": _f(self.t), "p_t": _f(self.p_t),
                "heldout_likelihood_ratio": _f(self.lr), "p_lr": _f(self.p_lr),
                "fit_likelihood_ratio": _f(self.lr_fit),
                "n_eff": _f(self.n_eff), "candidates_in_round": self.m,
                "significant": self.significant, "why_not": list(self.reasons)}


def _f(v):
    v = float(v)
    return v if math.isfinite(v) else (1e300 if v > 0 else -1e300)


def score_candidate(model: SensorModel, S: SensorSamples, cv: CVEngine, e, base_train,
                    base_block):
    """Held-out score of candidate effect e added to the model (hyper-parameters chosen
    inside each training fold on its own training error)."""
    grid = e.scan_grid(S)
    H = len(grid)
    trains = np.empty((H, len(cv.folds)))
    blocks = np.empty((H, cv.n_blocks))
    fulls = np.empty(H)
    masked = hasattr(e, "mask") and e.fd_in_scoring
    if masked:   # a linear effect switched on by a row mask: columns once, masked per value
        e.set_hyper(None)
        d0_all, G_all = candidate_columns(model, S, e, cv.r0)
    for j, h in enumerate(grid):
        e.set_hyper(h)
        if masked:
            d0, G = None, G_all * e.mask(S)[S.row_sample][:, None]
        else:
            d0, G = candidate_columns(model, S, e, cv.r0)
        trains[j], blocks[j], fulls[j] = cv.evaluate(d0, G)
    # per fold: the grid value with the least training error
    chosen = np.argmin(trains, axis=0)
    block1 = np.zeros(cv.n_blocks)
    for f, (_, _, bte, _) in enumerate(cv.folds):
        bl = np.unique(bte)
        block1[bl] = blocks[chosen[f], bl]
    jbest = int(np.argmin(fulls))
    if getattr(e, "relinearise", False) and block1.sum() < base_block.sum():
        return _rescore_refitted(model, S, cv, e, [grid[j] for j in np.argsort(fulls)[:2]],
                                 base_block)
    h = grid[jbest]
    e.set_hyper(h)
    if masked:
        d0, G = None, G_all * e.mask(S)[S.row_sample][:, None]
    else:
        d0, G = candidate_columns(model, S, e, cv.r0)
    res_full = cv.full_residual(d0, G)
    return _make_score(e, h, S, cv.r0, base_block, block1, res_full, float(fulls[jbest]))


def _make_score(e, h, S, r0, base_block, block1, res_full, sse1_full) -> Score:
    """The statistics of the significance rule from the held-out block SSEs without
    (base_block) and with (block1) the candidate, and its fit-data residual."""
    from scipy import stats as sps
    gain = base_block - block1
    B = len(gain)
    sd = float(np.std(gain, ddof=1)) if B > 1 else 0.0
    mean = float(np.mean(gain))
    t = mean / (sd / math.sqrt(B)) if sd > 0 else (math.inf if mean > 0 else 0.0)
    p_t = float(sps.t.sf(t, B - 1)) if B > 1 else 1.0
    sse0_full = float(r0 @ r0)
    rho = min(max(_lag1(res_full, S), 0.0), 0.99)
    n_eff = len(r0) * (1 - rho) / (1 + rho)
    lr_fit = n_eff * math.log(sse0_full / sse1_full) if sse1_full > 0 and sse0_full > 0 \
        else 0.0
    sse0_cv, sse1_cv = float(base_block.sum()), float(block1.sum())
    lr = n_eff * math.log(sse0_cv / sse1_cv) if sse1_cv > 0 and sse0_cv > 0 else 0.0
    dof = e.n_dof
    p_lr = float(sps.chi2.sf(max(lr, 0.0), dof))
    return Score(e, h, dof, sse0_cv, sse1_cv, gain, t, p_t, sse0_full, sse1_full, n_eff, lr,
                 p_lr, lr_fit, explained=r0 - res_full)


def _rescore_refitted(model, S, cv: CVEngine, e, starts, base_block) -> Score:
    """Second stage for an effect whose linearisation about the current model is poor
    (a thermal lag moves the temperature the polynomials see by degrees): fit the model
    with the effect from the best scanned values (nonlinear, all parameters), keep the
    best, and cross-validate linearised about that fit (the effect's own parameter in the
    Jacobian, so each training fold refits it)."""
    best = None
    for h in starts:
        e.set_hyper(h)
        m1 = model.with_effect(e, e.init_params()).fit(S, max_nfev=20)
        sse = m1.sse(S)
        if best is None or sse < best[0]:
            best = (sse, h, m1)
    _, h, m1 = best
    e.set_hyper(h)
    r1, J1 = m1.jacobian(S)
    cv1 = CVEngine(r1, J1, cv.row_block, cv.fold_of_block, cv.n_blocks)
    _, block1, _ = cv1.evaluate()
    hyper = e.hyper_after_fit(m1.effect_params(len(m1.effects) - 1))
    e.set_hyper(hyper)
    return _make_score(e, hyper, S, cv.r0, base_block, block1, r1, float(r1 @ r1))


def candidate_columns(model: SensorModel, S, e, r0):
    """(d0, G): the residual change of the model with e at its initial parameters, and
    the Jacobian columns of e's parameters there (None for scan-only effects)."""
    m1 = model.with_effect(e, e.init_params())
    cols = np.arange(model.P, m1.P) if (e.fd_in_scoring and e.n_params) else np.arange(0)
    r1, G = m1.jacobian(S, cols=cols)
    d0 = r1 - r0
    if not np.any(d0):
        d0 = None
    return d0, (G if G.shape[1] else None)


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

    @property
    def final_rms_nT(self) -> float:
        return self.steps[-1].rms_after_nT if self.steps else self.baseline_rms_nT

    @property
    def metric(self) -> str:
        return "; ".join(KIND_NAMES[k] for k in self.S_eval.kinds_present())


def _context(model: SensorModel, S: SensorSamples):
    from generator.fit.thermal import temperature_quantum
    return SimpleNamespace(samples=S, effects=model.effects, degree=model.degree,
                           temp_quantum=temperature_quantum(S.temp_C))


def candidate_list(model, S):
    ctx = _context(model, S)
    cands, why = [], {}
    for cls in fx.CATALOGUE:
        inst, reason = cls.candidates(ctx)
        if inst:
            cands.extend(inst)
        else:
            why[cls.name] = reason
    return cands, why


def score_round(model: SensorModel, S_fit, fold_of_block, n_blocks, alpha, min_gain):
    cands, why = candidate_list(model, S_fit)
    if not cands:
        return [], why
    r0, J = model.jacobian(S_fit)
    cv = CVEngine(r0, J, S_fit.block[S_fit.row_sample], fold_of_block, n_blocks)
    base_train, base_block, _ = cv.evaluate()
    scores = [score_candidate(model, S_fit, cv, e, base_train, base_block) for e in cands]
    for s in scores:
        s.judge(len(scores), alpha, min_gain)
    scores.sort(key=lambda s: s.sse1_cv)
    return scores, why


EQUIVALENT_CORR = 0.95


def equivalent(a: Score, b: Score) -> bool:
    """Two candidates explain the same thing: their fitted contributions are correlated
    above EQUIVALENT_CORR and their held-out errors differ by no more than chance
    (n_eff ln(SSE_a / SSE_b) within the 95 % point of chi^2 with 1 degree of freedom)."""
    c = _corr(a.explained, b.explained)
    if c is None or c < EQUIVALENT_CORR:
        return False
    from scipy import stats as sps
    n_eff = min(a.n_eff, b.n_eff)
    return abs(n_eff * math.log(a.sse1_cv / b.sse1_cv)) < sps.chi2.ppf(0.95, 1)


def choose(sig: list) -> Score:
    """The significant candidate with the least held-out error, unless an equivalent one
    (see `equivalent`) has a higher prior (generator.trace.effects.Effect.prior)."""
    best = sig[0]
    for s in sig[1:]:
        if s.effect.prior > best.effect.prior and equivalent(best, s):
            best = s
    return best


def _corr(a, b):
    if a is None or b is None:
        return None
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    return float(a @ b / (na * nb)) if na > 0 and nb > 0 else None


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
                 progress=None) -> SensorTrace:
    say = progress or (lambda m: None)
    blocks = np.unique(S_fit.block)
    S_fit.block = np.searchsorted(blocks, S_fit.block)       # 0 .. n_blocks - 1
    n_blocks = len(blocks)
    fold_of_block = np.arange(n_blocks) % N_FOLDS
    init_e = [e for e, _ in initial]
    init_p = [p for _, p in initial]
    model0 = SensorModel.for_samples(base, S_fit, init_e, init_p)
    core = model0.rms(S_eval)
    model = model0.copy().fit(S_fit)
    base_rms = model.rms(S_eval)
    say(f"{name}: baseline held-out RMS {base_rms:.2f} nT (core fit as given {core:.2f} nT)")
    steps, stop = [], ""
    scores, why = score_round(model, S_fit, fold_of_block, n_blocks, alpha, min_gain)
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
                    f"nothing significant left (best: {scores[0].effect.label()}, "
                    f"{'; '.join(scores[0].reasons)})")
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
        step = Step(e, m1.effect_params(len(m1.effects) - 1), win, before, after, model, m1,
                    runner_up=runner, scores=scores,
                    corr_runner_up=_corr(win.explained, runner.explained if runner else None))
        steps.append(step)
        say(f"{name}: + {e.label()}: held-out RMS {before:.2f} -> {after:.2f} nT "
            f"(CV gain {100 * win.rel_rms_gain:.1f} %, t = {win.t:.1f})")
        model = m1
        scores, why = score_round(model, S_fit, fold_of_block, n_blocks, alpha, min_gain)
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
                       why, stop, initial_effects=list(initial))


# =======================================================================================
# Baseline
# =======================================================================================
def baseline_coefficients(unit, tels, progress=None) -> tuple:
    """The core fit as `magcal fit` makes it (fit_unit; K where coil currents step; H
    from a deployed file), or the identity where no file carries any field reference
    (data calibrated upstream: only deviations from a constant can be traced).
    Returns (CoefficientSet, {sensor: degree}, notes)."""
    from generator.fit.thermal import fit_unit
    say = progress or (lambda m: None)
    notes = []
    try:
        cals = fit_unit(unit, tels, progress=None)
        degrees = {n: int(c.stats.get("degree", 3)) for n, c in cals.items()}
        core = "fit_thermal.fit_unit"
    except InputError as err:
        has_ref = any(t.has("ref_x_nT", "ref_y_nT", "ref_z_nT") or t.has("ref_norm_nT")
                      for t in tels) or unit.lab_field_nT is not None
        if has_ref:
            raise
        notes.append("no file carries a field reference (reference vectors, ref_norm_nT or "
                     "the unit's lab_field_nT): the baseline is the identity calibration "
                     "(B = B~, the data as calibrated upstream) and only deviations from a "
                     f"constant per static position are traced ({err.message})")
        lo = min(float(np.nanmin(t.columns[s.temp_column])) for t in tels for s in unit.sensors
                 if s.temp_column in t.columns)
        hi = max(float(np.nanmax(t.columns[s.temp_column])) for t in tels for s in unit.sensors
                 if s.temp_column in t.columns)
        cals = {s.name: SensorCalibration.constant(s.name, np.zeros(3), np.eye(3), 25.0,
                                                   lo, hi, method="identity (no reference)")
                for s in unit.sensors}
        degrees = {s.name: 0 for s in unit.sensors}
        core = "identity"
    K, coils, H = None, (), None
    # K from files whose coil currents step while the unit stands in static positions
    # (a moving unit's field would leak into K); elsewhere the currents stay candidates
    def steps_in_positions(t):
        pos = t.get("position")
        if pos is None:
            return False
        static = np.nan_to_num(np.asarray(pos, float)) > 0
        return any(c.startswith("coil_") and c.endswith("_A")
                   and np.nanmax(np.abs(np.where(static, t.columns[c], 0.0))) > 0
                   for c in t.columns)
    coil_tels = [t for t in tels if steps_in_positions(t)]
    if coil_tels:
        from generator.fit.coils import fit_coils
        try:
            cf = fit_coils(unit, coil_tels)
            K, coils = cf.K(), tuple(cf.coils)
            notes.append(f"coil coupling K fitted from {', '.join(str(t.path) for t in coil_tels)}")
        except InputError as err:
            notes.append(f"no coil coupling in the baseline ({err.message}); coil currents "
                         "are candidate channels")
    if any(s.frame == "boom" for s in unit.sensors) and unit.boom_reference and core != "identity":
        deployed = [t for t in tels if not t.has("ref_x_nT", "ref_y_nT", "ref_z_nT")]
        if deployed:
            from generator.fit.alignment import align_boom
            try:
                H = align_boom(unit, deployed[0], cals, coil_K_nT_per_A=K).H
            except InputError as err:
                notes.append(f"boom alignment not fitted ({err.message}); H = identity")
    cs = CoefficientSet.from_calibrations(unit, cals, H_boom_to_body=H, K_nT_per_A=K,
                                          coils=coils, fit_info={"core": core})
    say(f"baseline: {core}" + (f", coils {', '.join(coils)}" if coils else ""))
    return cs, degrees, notes


def initial_effects(cs: CoefficientSet, name: str, S: SensorSamples, model_info=None):
    """Effects a supplied coefficient set already carries (its chain options)."""
    o = cs.spec.opts(name)
    out = []
    for cls in fx.CATALOGUE:
        out.extend(cls.from_flight(cs.sensors[name], o, S, model_info))
    return out


def model_from_coefficients(cs: CoefficientSet, name: str, S: SensorSamples) -> SensorModel:
    """The float64 model of a coefficient set's chain for one sensor (all blocks as
    given, nothing free): B_cal = model.field(S)."""
    base = base_from_coefficients(cs, name, degree=cs.spec.poly_degree)
    return _fixed_model(base, initial_effects(cs, name, S))


def _fixed_model(base: BaseFit, effects) -> SensorModel:
    m = SensorModel(base, free_b=[], free_M=None, free_K=False, groups=[], Bp0=np.zeros((0, 3)))
    for e, p in effects:
        m = m.with_effect(e, p)
    return m


def calibrated_field64(cs: CoefficientSet, tel, sensor: str):
    """float64 B_cal of one sensor of a telemetry file through the extended chain model
    (boom sensors rotated by H), for every usable sample; returns (row index, (n, 3))."""
    unit = cs.unit
    ch_names = list(dict.fromkeys(c for s in unit.sensors for c in cs.spec.opts(s).channels))
    norm_tel = _with_any_reference(tel)
    S = gather_samples(unit, [norm_tel], [0], coils=cs.spec.coils,
                       H=cs.unit_values.get("H_boom_to_body"), channels=ch_names)[sensor]
    m = model_from_coefficients(cs, sensor, S)
    B = m.field(S)
    if unit.sensor(sensor).frame == "boom" and "H_boom_to_body" in cs.unit_values:
        B = B @ np.asarray(cs.unit_values["H_boom_to_body"], float).T
    return S.order.copy(), B


def _with_any_reference(tel):
    """The same telemetry with a dummy magnitude reference where it has none (so that
    every usable sample is gathered)."""
    from generator.io.telemetry import Telemetry
    cols = dict(tel.columns)
    if "ref_norm_nT" not in cols and not tel.has("ref_x_nT", "ref_y_nT", "ref_z_nT"):
        cols["ref_norm_nT"] = np.full(tel.n, 1.0)
    return Telemetry(tel.path, cols, tel.line_numbers, dict(tel.meta))


# =======================================================================================
# The extended coefficient set
# =======================================================================================
def to_coefficient_set(base: CoefficientSet, traces: dict, info=None) -> CoefficientSet:
    """The baseline coefficient set with every traced sensor's final model written in
    the chain's layout: refitted b_poly_nT, M_poly (poly_degree raised where an effect
    needs it, unit-wide), K, and the flight forms of the effects (ChainSpec options
    channels / thermal_lag / nonlinear / sr_compensation and their blocks; a bias step
    becomes the offset after it; a time offset has no flight form). Sensors without a
    traced effect keep the baseline's values."""
    unit = base.unit
    values, options = {}, {}
    degree = base.spec.poly_degree
    for s in unit.sensors:
        v = {k: np.array(a, float) for k, a in base.sensors[s.name].items()}
        o = base.spec.opts(s.name).to_dict()
        tr = traces.get(s.name)
        if tr is not None and tr.steps:
            m = tr.final_model
            mv = m.values()
            o = {"channels": [], "thermal_lag": False, "nonlinear": False,
                 "sr_compensation": False}
            for k in ("C_nT_per_unit", "lag_tau_s", "cubic_per_nT2", "sr_comp_s_per_deg"):
                v.pop(k, None)
            D = m.base.degree
            v["b_poly_nT"] = mv["b_poly_nT"].copy()
            v["M_poly"] = mv["M_poly"].copy()
            if mv["K_nT_per_A"] is not None:
                v["K_nT_per_A"] = mv["K_nT_per_A"]
            later = []
            for i, e in enumerate(m.effects):
                if e.in_chain:
                    e.to_flight(m.effect_params(i), v, o, m)
                else:
                    later.append(i)
            if m.free_M is None:   # no absolute reference: keep the baseline's mean output
                _recentre(v, o, tr, m)
            for i in later:        # a step's new offset (the others have no flight form)
                m.effects[i].to_flight(m.effect_params(i), v, o, m)
            degree = max(degree, v["b_poly_nT"].shape[0] - 1, D)
        values[s.name] = v
        options[s.name] = o
    degree = min(degree, MAX_POLY_DEGREE)
    sensor_options = tuple((s.name, SensorOptions.from_dict(options[s.name]))
                           for s in unit.sensors
                           if SensorOptions.from_dict(options[s.name]) != SensorOptions())
    spec = ChainSpec(unit, poly_degree=degree, coils=base.spec.coils,
                     sensor_options=sensor_options)
    sensors = {}
    for s in unit.sensors:
        v = values[s.name]
        for key, shape in (("b_poly_nT", (3,)), ("M_poly", (3, 3))):
            a = v[key]
            if a.shape[0] < degree + 1:
                v[key] = np.concatenate([a, np.zeros((degree + 1 - a.shape[0],) + shape)])
            # a sensor without temperature: constant b, M (its model sits at dT = 0)
            v[key] = v[key][:spec.degree(s) + 1]
        sensors[s.name] = {b.name: np.asarray(v[b.name], float).reshape(b.shape)
                           for b in spec.sensor_blocks(s)}
    fit_info = dict(base.fit_info)
    if info:
        fit_info["trace"] = info
    unc = {n: ({} if (traces.get(n) and traces[n].steps) else u)
           for n, u in base.uncertainty.items()}
    cs = CoefficientSet(spec, sensors, dict(base.unit_values), unc, fit_info)
    CoefficientSet.from_json_dict(json.loads(json.dumps(cs.to_json_dict(),
                                                        default=_json_default)))
    return cs


def _recentre(v, o, tr: SensorTrace, m: SensorModel):
    """Position-only data fix b(T) up to a constant: shift b0 so that the extended flight
    chain (what the blocks in v carry) has the baseline's mean output over the data."""
    S = tr.S_fit
    b = np.asarray(v["b_poly_nT"], float)
    t_ref, t_lo, t_hi = (float(v["t_ref_C"]), float(v["t_min_C"]), float(v["t_max_C"])) \
        if "t_ref_C" in v else (0.0, 0.0, 0.0)   # no temperature: constant, dT = 0
    base = BaseFit(tr.name, b.shape[0] - 1, t_ref, t_lo,
                   t_hi, b, np.asarray(v["M_poly"], float),
                   np.asarray(v["K_nT_per_A"], float) if "K_nT_per_A" in v else None, m.base.H)
    opts = SensorOptions.from_dict(o)
    inits = [ep for cls in fx.CATALOGUE for ep in cls.from_flight(v, opts, S, None)]
    B_new = _fixed_model(base, inits).field(S)
    B_old = tr.base_model.field(S)
    Mbar = np.asarray(v["M_poly"])[0]
    v["b_poly_nT"][0] = v["b_poly_nT"][0] + np.linalg.solve(Mbar, (B_new - B_old).mean(axis=0))


_json_default = json_default          # (kept name: tests use it)


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
               "elapsed_s": round(self.elapsed_s, 2)}
        for n, tr in self.traces.items():
            out["baseline"][n] = {
                "rms_nT": tr.baseline_rms_nT, "core_fit_as_given_rms_nT": tr.core_rms_nT,
                "metric": tr.metric, "samples_fit": tr.S_fit.n, "samples_evaluated": tr.S_eval.n,
                "model": _model_text(tr.base_model),
                "effects_already_in_model": [e.label() for e, _ in tr.initial_effects]}
            out["final"][n] = {"rms_nT": tr.final_rms_nT, "stop": tr.stop,
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
                out["effects"].append(effect_entry(n, tr, st))
        return out

    def write(self, out_dir, progress=None) -> dict:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        (out / "trace.json").write_text(json.dumps(self.to_json(), indent=1,
                                                   default=_json_default) + "\n")
        self.coefficients.save(out / "coefficients.json")
        return {"trace": out / "trace.json", "coefficients": out / "coefficients.json"}


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


def effect_entry(name, tr: SensorTrace, st: Step) -> dict:
    e, sc = st.effect, st.score
    m = st.model_after
    entry = {
        "sensor": name, "effect": e.name, "explained_by": e.explained_by(),
        "rms_before_nT": st.rms_before_nT, "rms_after_nT": st.rms_after_nT,
        "evidence": evidence_sentence(name, st),
        "parameters": e.describe(st.params, m),
        "in_flight_chain": e.in_chain, "flight_form": e.flight_form,
        "physics": e.physics,
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
         f"(t = {sc.t:.1f}; held-out likelihood ratio {sc.lr:.0f} for {sc.dof} parameters)")
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
                         f"autocorrelation; (2) one-sided t-test over the blocks' held-out SSE "
                         f"reductions, p < {BLOCK_LEVEL:g}; (3) held-out RMS reduction >= "
                         f"{100 * MIN_REL_GAIN:g} %"),
        "refit": ("after each accepted effect all coefficients (b, M, K, position constants "
                  "and every effect) are refitted jointly by Levenberg-Marquardt"),
        "stop": "when no candidate passes, or after "
                f"{MAX_EFFECTS} effects per sensor",
    }


def _read(unit, items):
    from generator.io.telemetry import Telemetry
    from generator.io.telemetry_csv import read_telemetry
    out = []
    for it in items:
        out.append(it if isinstance(it, Telemetry) else read_telemetry(it, unit))
    return out


def trace(unit, data, holdout=(), coeffs=None, progress=None, *, sensors=None,
          alpha=ALPHA, min_gain=MIN_REL_GAIN, max_effects=MAX_EFFECTS) -> TraceResult:
    """Trace the residual of every sensor of the unit (see the module docstring).

    unit: Unit or unit-file path; data, holdout: telemetry paths or Telemetry objects;
    coeffs: baseline CoefficientSet or path (default: the core fit of the data files).
    """
    from generator.io.unit import Unit
    from generator.io.unitfile import load_unit
    t0 = time.perf_counter()
    say = progress or (lambda m: None)
    if not isinstance(unit, Unit):
        unit = load_unit(unit)
    if not data:
        raise InputError(unit.path, "trace: no telemetry files given")
    tels = _read(unit, data)
    hold = _read(unit, holdout)
    notes = []
    if coeffs is None:
        base, degrees, bnotes = baseline_coefficients(unit, tels, say)
        notes += bnotes
    else:
        base = coeffs if isinstance(coeffs, CoefficientSet) else CoefficientSet.load(coeffs)
        if set(base.unit.sensor_names) != set(unit.sensor_names):
            raise InputError(getattr(coeffs, "path", coeffs),
                             f"coefficients are for sensors {list(base.unit.sensor_names)}, "
                             f"the unit has {list(unit.sensor_names)}")
        degrees = {s.name: declared_degree(base, s.name) for s in unit.sensors}
        notes.append("baseline: the supplied coefficient set")
    coils = base.spec.coils
    channels, partial = candidate_channels(unit, tels, coils)
    if partial:
        notes.append("channels only some data files carry (taken as 0 elsewhere, and fitted "
                     "with an offset of their own for the files that carry them, so that "
                     "only their variation counts): " + ", ".join(partial))
    allt = tels + hold
    roles = [0] * len(tels) + [1] * len(hold)
    H = base.unit_values.get("H_boom_to_body")
    samples = gather_samples(unit, allt, roles, coils=coils, H=H, channels=channels,
                             notes=notes)
    evaluated_on = "holdout" if hold else "split"
    traces, skipped = {}, {}
    for s in unit.sensors:
        if sensors is not None and s.name not in sensors:
            continue
        S = samples[s.name]
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
                                      S_final=S_final, progress=say)
    if not traces:
        raise InputError(unit.path, "trace: no sensor has enough usable samples with a "
                                    "field reference or a static position")
    info = {"effects": [{"sensor": n, "effect": st.effect.name,
                         "explained_by": st.effect.explained_by(),
                         "parameters": st.effect.describe(st.params, st.model_after),
                         "in_flight_chain": st.effect.in_chain}
                        for n, tr in traces.items() for st in tr.steps],
            "evaluated_on": evaluated_on}
    cs = to_coefficient_set(base, traces, info)
    sources = {"data": [str(t.path) for t in tels], "holdout": [str(t.path) for t in hold],
               "baseline": "supplied coefficients" if coeffs is not None else
               base.fit_info.get("core", "fit")}
    return TraceResult(unit, evaluated_on, traces, skipped, base, cs, notes, sources,
                       time.perf_counter() - t0)


__all__ = ["trace", "TraceResult", "SensorModel", "SensorSamples", "to_coefficient_set",
           "gather_samples", "model_from_coefficients", "calibrated_field64",
           "ALPHA", "MIN_REL_GAIN"]
