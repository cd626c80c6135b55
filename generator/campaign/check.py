"""`magcal check`: does a recorded campaign cover the test program?

Per planned position and temperature level: is there a settled constant-temperature
segment (the fit's own segment finder, generator.fit.thermal.find_segments), how many
samples, how many missing or saturated; how well the orientations cover the sphere; and
what the data would leave poorly determined, predicted from the design of the fit itself:

Prediction of the coefficient uncertainty. The calibration B = M(T)(B~ - b(T)), b and M
polynomials in dT = T - t_ref (generator.fit.calibration), is fitted by least squares on

* vector rows  r = M(T)(B~ - b(T)) - B_ref        where reference vectors are known,
* magnitude rows r = |M(T)(B~ - b(T))| - |B|      where only the magnitude is,

(generator.fit.thermal). Linearised about nominal coefficients (M = I, b = the constant
offset, or the fitted ones) the Jacobian J of these rows with respect to the polynomial
coefficients is the design matrix; with a reading noise sigma per axis the coefficients'
covariance is sigma^2 (J^T J)^-1, and the 1-sigma of b_i(T) and m_ij(T) at a temperature
is sqrt(g^T C g), g the powers of dT. `PolyCovariance` holds that covariance; the report
uses the same code (with the residual scatter instead of the a-priori noise) to draw the
confidence band of the fitted cubic. A coefficient whose predicted 1-sigma anywhere in the
target temperature range exceeds the limit (b: 50 nT, m: 1e-3 by default, with each
sensor's noise_nT from the unit file) is reported as poorly determined; one the design
does not determine at all (J^T J singular along it) as undetermined.

Size: one verb's analysis (coverage of the plan, settled segments, the predicted
coefficient covariance); the report reuses its pieces. A split of the covariance
prediction into its own module is the natural next cut.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from generator.fit.calibration import POLY_DEGREE
from generator.errors import InputError
from generator.io.parts import temperature_lsb_C
from generator.fit.ellipsoid import SYM_INDEX, _sym_grad, coverage
from generator.fit.segments import step_and_white_noise_C
from generator.fit.thermal import (DEGREE_STEP_C, T_REF_C, _powers, find_segments,
                          temperature_quantum)

AXES = "xyz"
B_NAMES = tuple(f"b_{a}" for a in AXES)
M_NAMES = tuple(f"m_{a}{c}" for a in AXES for c in AXES)

# Default limits on the predicted 1-sigma of a coefficient over the target range.
LIMIT_B_nT = 50.0
LIMIT_M = 1e-3
# Eigenvalue ratio of the column-scaled J^T J below which a direction counts as
# undetermined (J condition number 1e7: far beyond what a campaign should give).
NULL_EIG_RATIO = 1e-14
# Orientation coverage: smallest eigenvalue of mean(u u^T) (1/3 for a full sphere).
MIN_DIRECTION_EIG = 0.1
# A rotation campaign should put field directions in this fraction of the 20
# icosahedron cells (15: a hemisphere reaches 12, since u u^T cannot see it).
MIN_ICOSA_FRACTION = 0.75
# Samples per (position, level) segment when no plan says otherwise.
MIN_SEGMENT_SAMPLES = 30
# How far back before a segment the reading is looked at to tell whether the board was
# cooled or heated into it (the segment finder's 10 min window).
APPROACH_LOOKBACK_S = 600.0


# =======================================================================================
# Coefficient covariance from the design of the fit
# =======================================================================================
@dataclass
class PolyCovariance:
    """Covariance of the polynomial coefficients of one sensor's calibration.

    Parameter order: b[k, l] (k major), then M[k, a, c] (body_frame: full matrix) or
    M6[k, s] (symmetric, SYM_INDEX order); polynomials in dT = T - t_ref_C (degree K-1).
    cov holds inf where the design leaves a coefficient undetermined.
    """
    degree: int
    body_frame: bool
    t_ref_C: float
    cov: np.ndarray
    null: np.ndarray            # (p, r) basis of the undetermined directions (r may be 0)
    noise_nT: float             # per-axis noise the covariance is scaled to
    n_rows: int

    @property
    def n_b(self):
        return 3 * (self.degree + 1)

    def _g(self, temp_C):
        """(G, p, 12) maps from the parameters to b_x..b_z, m_xx..m_zz at each temperature."""
        T = np.atleast_1d(np.asarray(temp_C, float))
        K = self.degree + 1
        P = _powers(T - self.t_ref_C, self.degree)                    # (G, K)
        p = self.cov.shape[0]
        g = np.zeros((len(T), p, 12))
        for k in range(K):
            for l in range(3):
                g[:, 3 * k + l, l] = P[:, k]
        nb = self.n_b
        if self.body_frame:
            for k in range(K):
                for a in range(3):
                    for c in range(3):
                        g[:, nb + 9 * k + 3 * a + c, 3 + 3 * a + c] = P[:, k]
        else:
            for k in range(K):
                for s, (i, j) in enumerate(SYM_INDEX):
                    g[:, nb + 6 * k + s, 3 + 3 * i + j] = P[:, k]
                    g[:, nb + 6 * k + s, 3 + 3 * j + i] = P[:, k]
        return g

    def sigma_at(self, temp_C):
        """1-sigma of (b_x, b_y, b_z, m_xx, ..., m_zz) at each temperature: (G, 12); inf
        where undetermined."""
        g = self._g(temp_C)
        finite = np.where(np.isfinite(self.cov), self.cov, 0.0)
        var = np.einsum("gpi,pq,gqi->gi", g, finite, g)
        sig = np.sqrt(np.maximum(var, 0.0))
        if self.null.shape[1]:
            leak = np.einsum("gpi,pr->gir", g, self.null)
            scale = np.linalg.norm(g, axis=1)
            bad = np.linalg.norm(leak, axis=2) > 1e-6 * np.maximum(scale, 1e-300)
            sig = np.where(bad, np.inf, sig)
        return sig

    def poly_sigma(self):
        """1-sigma of the polynomial coefficients: b (K, 3) nT/degC^k, M (K, 3, 3)."""
        K = self.degree + 1
        d = np.sqrt(np.maximum(np.diag(self.cov), 0.0))
        d = np.where(np.isfinite(np.diag(self.cov)), d, np.inf)
        b = d[:self.n_b].reshape(K, 3)
        if self.body_frame:
            M = d[self.n_b:].reshape(K, 3, 3)
        else:
            m6 = d[self.n_b:].reshape(K, 6)
            M = np.zeros((K, 3, 3))
            for s, (i, j) in enumerate(SYM_INDEX):
                M[:, i, j] = M[:, j, i] = m6[:, s]
        return b, M


def poly_covariance(x_nT, temp_C, ref_nT=None, norm_nT=None, *, degree, t_range_C,
                    b_poly=None, M_poly=None, body_frame=None, noise_nT=None,
                    t_ref_C=T_REF_C, noise_free=False, max_rows=None) -> PolyCovariance:
    """Covariance of the polynomial calibration coefficients for one sensor's samples.

    x_nT (N, 3): uncalibrated readings in frame axes (usable samples only); temp_C (N,);
    ref_nT (N, 3): reference vectors, NaN rows where unknown (vector rows); norm_nT (N,):
    reference magnitude for the other rows (magnitude rows). b_poly, M_poly: coefficients to
    linearise about (None: b = 0 and M = I; for a prediction, pass the constant offset).
    t_range_C: the calibrated range (temperatures are clamped to it, as in the fit).
    noise_nT: per-axis reading noise; None: estimated from the residual scatter
    (cost / (rows - parameters)). body_frame: full M (default: where vector rows exist).
    noise_free: for vector rows, linearise with the noise-free reading M(T)^-1 B_ref in
    place of the measured one (the design of the reference-vector fit itself: a prediction
    then sees exactly which directions the campaign lacks); else the Gauss-Newton Jacobian
    at the measured readings (the covariance of a fit that was made).
    max_rows: use every k-th sample so that at most this many enter, and scale J^T J and the
    cost by k (the information of a long smooth campaign, at a fraction of the work).
    """
    x = np.asarray(x_nT, float)
    T = np.asarray(temp_C, float)
    n0 = len(x)
    stride = max(1, -(-n0 // int(max_rows))) if max_rows else 1
    sel = slice(None, None, stride)
    x, T = x[sel], T[sel]
    n = len(x)
    ref = np.full((n0, 3), np.nan) if ref_nT is None else np.asarray(ref_nT, float)
    ref = ref[sel]
    is_vec = np.isfinite(ref).all(axis=1)
    norm = np.full(n, np.nan) if norm_nT is None else np.broadcast_to(
        np.asarray(norm_nT, float), (n0,))[sel]
    is_mag = ~is_vec & np.isfinite(norm)
    if body_frame is None:
        body_frame = bool(is_vec.any())
    K = degree + 1
    t_lo, t_hi = map(float, t_range_C)
    tau = max(abs(t_lo - t_ref_C), abs(t_hi - t_ref_C), 1.0)
    P = _powers((np.clip(T, t_lo, t_hi) - t_ref_C) / tau, degree)          # scaled dT
    scale = tau ** np.arange(K)                                             # coef_s = coef * tau^k
    b_s = np.zeros((K, 3))
    M_s = np.zeros((K, 3, 3))
    M_s[0] = np.eye(3)
    if b_poly is not None:
        kb = min(K, len(b_poly))
        b_s[:kb] = np.asarray(b_poly, float)[:kb] * scale[:kb, None]
    if M_poly is not None:
        km = min(K, len(M_poly))
        M_s[:km] = np.asarray(M_poly, float)[:km] * scale[:km, None, None]
    nb = 3 * K
    nm = 9 * K if body_frame else 6 * K
    p = nb + nm
    G = np.zeros((p, p))
    cost = 0.0
    rows = 0

    # vector rows
    if is_vec.any():
        Pv = P[is_vec]
        MT = np.einsum("nk,kij->nij", Pv, M_s)
        y = x[is_vec] - Pv @ b_s
        r = np.einsum("nij,nj->ni", MT, y) - ref[is_vec]
        if noise_free:
            y = np.linalg.solve(MT, ref[is_vec][:, :, None])[:, :, 0]
        cost += float(np.sum(r * r))
        rows += 3 * int(is_vec.sum())
        nv = len(Pv)
        for a in range(3):
            J = np.zeros((nv, p))
            J[:, :nb] = -(Pv[:, :, None] * MT[:, a, None, :]).reshape(nv, nb)
            if body_frame:
                blk = (Pv[:, :, None] * y[:, None, :])                      # (n, K, 3)
                for k in range(K):
                    J[:, nb + 9 * k + 3 * a: nb + 9 * k + 3 * a + 3] = blk[:, k]
            else:   # symmetric M with vector rows: d r_a / d m_s = E_s[a, :] y
                for k in range(K):
                    for s, (i, j) in enumerate(SYM_INDEX):
                        col = np.zeros(nv)
                        if i == a:
                            col += y[:, j]
                        if j == a and i != j:
                            col += y[:, i]
                        J[:, nb + 6 * k + s] = Pv[:, k] * col
            G += J.T @ J
    # magnitude rows
    if is_mag.any():
        Pm = P[is_mag]
        MT = np.einsum("nk,kij->nij", Pm, M_s)
        y = x[is_mag] - Pm @ b_s
        z = np.einsum("nij,nj->ni", MT, y)
        nz = np.linalg.norm(z, axis=1)
        r = nz - norm[is_mag]
        cost += float(r @ r)
        rows += int(is_mag.sum())
        u = z / np.maximum(nz, 1e-300)[:, None]
        v = np.einsum("ni,nij->nj", u, MT)
        Jb = -(Pm[:, :, None] * v[:, None, :]).reshape(len(Pm), nb)
        if body_frame:
            Jm = (Pm[:, :, None, None] * u[:, None, :, None] * y[:, None, None, :]
                  ).reshape(len(Pm), -1)
        else:
            Jm = (Pm[:, :, None] * _sym_grad(u, y)[:, None, :]).reshape(len(Pm), -1)
        J = np.hstack([Jb, Jm])
        G += J.T @ J

    G *= stride
    cost *= stride
    rows *= stride
    if noise_nT is None:
        s2 = cost / max(rows - p, 1)
    else:
        s2 = float(noise_nT) ** 2
    # pseudo-inverse on the column-scaled matrix; undetermined directions kept apart
    d = np.sqrt(np.maximum(np.diag(G), 0.0))
    dz = d > 0
    dd = np.where(dz, d, 1.0)
    Gs = G / np.outer(dd, dd)
    w, V = np.linalg.eigh(Gs)
    wmax = max(float(w[-1]), 1e-300)
    keep = w > NULL_EIG_RATIO * wmax
    inv_s = (V[:, keep] / w[keep]) @ V[:, keep].T
    cov_s = inv_s / np.outer(dd, dd) * s2
    null_s = V[:, ~keep] / dd[:, None]          # directions in scaled parameters
    # zero columns (a parameter no row touches) are undetermined too
    for j in np.nonzero(~dz)[0]:
        e = np.zeros((p, 1))
        e[j] = 1.0
        null_s = np.hstack([null_s, e])
    # unscale: coef = coef_s / tau^k
    unscale = np.concatenate([np.repeat(1.0 / scale, 3), np.repeat(1.0 / scale,
                                                                   9 if body_frame else 6)])
    cov = cov_s * np.outer(unscale, unscale)
    null = null_s * unscale[:, None] if null_s.size else np.zeros((p, 0))
    if null.shape[1]:
        null, _ = np.linalg.qr(null / np.linalg.norm(null, axis=0))
        # undetermined parameters: infinite variance on the diagonal
        leak = np.linalg.norm(null, axis=1) > 1e-6
        cov = cov.copy()
        cov[leak, leak] = np.inf
    return PolyCovariance(degree=degree, body_frame=body_frame, t_ref_C=t_ref_C, cov=cov,
                          null=null, noise_nT=math.sqrt(s2), n_rows=rows)


# =======================================================================================
# Samples of a campaign, as the fit sees them
# =======================================================================================
@dataclass
class SensorSamples:
    """One sensor's fit-usable samples over all files (concatenated), with what was left
    out and the constant-temperature segments (indices into these arrays)."""
    name: str
    x: np.ndarray              # (N, 3) uncalibrated field, frame axes, nT
    T: np.ndarray              # (N,) reported temperature
    ref: np.ndarray            # (N, 3) reference vector, NaN rows where none
    norm: np.ndarray           # (N,) reference magnitude (|ref| where a vector is known)
    position: np.ndarray       # (N,) int, 0 where none / moving
    file: np.ndarray           # (N,) int, index of the file
    time_s: np.ndarray         # (N,)
    segments: list             # generator.fit.segments.Segment, index into these arrays; .file added
    excluded: dict             # reason -> count (missing, saturated, coil current, no reference)
    # per file, per sample of the file: missing / saturated flags (for per-cell counts)
    file_flags: list = field(default_factory=list)

    @property
    def n(self):
        return len(self.T)

    @property
    def is_vec(self):
        return np.isfinite(self.ref).all(axis=1)


def _coil_on(tel):
    cols = [c for c in tel.columns if c.startswith("coil_") and c.endswith("_A")]
    if not cols:
        return np.zeros(tel.n, bool)
    return np.any(np.nan_to_num(np.stack([tel.columns[c] for c in cols], 1), nan=0.0) != 0,
                  axis=1)


MIN_REF_nT = 1.0


def gather_samples(unit, tels, pres=None) -> dict:
    """{sensor: SensorSamples} from telemetry files (and their preprocess() results).

    Usable as in generator.fit.thermal: finite, not saturated, no magnetorquer current, and
    some field reference (reference vectors, ref_norm_nT or the unit's lab_field_nT)."""
    from generator.io.telemetry_csv import preprocess
    if pres is None:
        pres = [preprocess(t, unit) for t in tels]
    out = {}
    for s in unit.sensors:
        parts = {k: [] for k in ("x", "T", "ref", "norm", "pos", "file", "t")}
        segs, flags = [], []
        excluded = {"missing": 0, "saturated": 0, "coil current": 0, "no reference": 0}
        offset = 0
        for fi, (tel, pre) in enumerate(zip(tels, pres)):
            sd = pre[s.name]
            n = tel.n
            temp_C = sd.temp_or(T_REF_C)    # a sensor without temperature: the constant t_ref
            cnt = np.stack([np.asarray(sd.counts.get(c, np.full(n, np.nan)), float)
                            for c in s.count_columns], 1) if sd.counts else np.full((n, 1), np.nan)
            missing = ~np.isfinite(cnt).all(axis=1) | ~np.isfinite(temp_C)
            saturated = ~sd.usable & ~missing
            flags.append({"missing": missing, "saturated": saturated})
            use = sd.usable & np.isfinite(sd.field_frame_nT).all(axis=1)
            excluded["missing"] += int(missing.sum())
            excluded["saturated"] += int(saturated.sum())
            coil = _coil_on(tel) & use
            excluded["coil current"] += int(coil.sum())
            use &= ~coil
            if tel.has("ref_x_nT", "ref_y_nT", "ref_z_nT"):
                ref = np.stack([tel.columns[f"ref_{c}_nT"] for c in AXES], 1).astype(float)
            else:
                ref = np.full((n, 3), np.nan)
            # below 1 nT a reference vector has no direction (every part resolves coarser):
            # such rows are not reference vectors, and are counted
            with np.errstate(invalid="ignore"):
                zero = np.isfinite(ref).all(axis=1) & (np.linalg.norm(
                    np.nan_to_num(ref), axis=1) < MIN_REF_nT)
            excluded["zero reference"] = excluded.get("zero reference", 0) + int(
                (zero & use).sum())
            ref[zero] = np.nan
            has_vec = np.isfinite(ref).all(axis=1)
            norm = tel.get("ref_norm_nT")
            norm = np.asarray(norm, float) if norm is not None else np.full(
                n, float(unit.lab_field_nT) if unit.lab_field_nT else np.nan)
            norm = np.where(has_vec, np.linalg.norm(np.nan_to_num(ref), axis=1), norm)
            has_ref = has_vec | (np.isfinite(norm) & (norm > 0))
            excluded["no reference"] += int((use & ~has_ref).sum())
            use &= has_ref
            pos = tel.get("position")
            pos = np.zeros(n, int) if pos is None else np.nan_to_num(
                np.asarray(pos, float), nan=0).astype(int)
            keep = np.nonzero(use)[0]
            has_pos = tel.get("position") is not None
            fsegs = find_segments(tel.time_s, temp_C, tel.get("position"), use,
                                  temp_lsb_C=temperature_lsb_C(s.part))
            remap = -np.ones(n, int)
            remap[keep] = offset + np.arange(len(keep))
            for sg in fsegs:
                sg.index = remap[sg.index]
                sg.file = fi
                if not has_pos:
                    sg.position = 0          # a moving campaign: no static position
                segs.append(sg)
            parts["x"].append(sd.field_frame_nT[keep])
            parts["T"].append(temp_C[keep])
            parts["ref"].append(ref[keep])
            parts["norm"].append(norm[keep])
            parts["pos"].append(pos[keep])
            parts["file"].append(np.full(len(keep), fi))
            parts["t"].append(np.asarray(tel.time_s, float)[keep])
            offset += len(keep)
        cat = {k: (np.concatenate(v) if v else np.zeros(0)) for k, v in parts.items()}
        out[s.name] = SensorSamples(
            name=s.name, x=cat["x"].reshape(-1, 3), T=cat["T"], ref=cat["ref"].reshape(-1, 3),
            norm=cat["norm"], position=cat["pos"].astype(int), file=cat["file"].astype(int),
            time_s=cat["t"], segments=segs, excluded=excluded, file_flags=flags)
    return out


def settled_segments(unit, samples, nearest_level, settle_tolerance_C) -> dict:
    """Which constant-temperature segments are settled at their plan level, per sensor:
    {name: {"offset_C", "tolerance_C", "segments": [{"settled", "from_level_C"}, ...]}}
    (segments in SensorSamples.segments order; from_level_C None off the plan's levels).

    A board lags the chamber as a first-order system: until it has settled, its reading
    sits on the side it came from (above the level when cooled into it, below when heated),
    while self-heating or the sensor's own temperature offset shift every level the same
    way. So the sensor's offset is the midpoint of the median deviation (segment mean less
    level) of the segments entered cooling and of those entered heating (0 when only one
    kind exists), and a segment is settled when

    * its mean is within tol + q/2 + 3 sigma_w / sqrt(N) of level + offset: tol the plan's
      settling tolerance, q the reporting step (the mean of a reading pinned to one code is
      off by up to q/2), sigma_w the white noise of the filtered reading over N samples;
    * its drift (Segment.drift_C) is within tol + q + 3 sigma_w sqrt(12 / N) (a difference
      of quantised readings errs by up to q; generator.fit.segments).

    Whether a segment was entered cooling or heating: the sensor's mean reading over the
    APPROACH_LOOKBACK_S before it (same file) against the segment's mean."""
    tol = float(settle_tolerance_C)
    parts = {s.name: s.part for s in unit.sensors}
    out = {}
    for name, S in samples.items():
        q, sw = step_and_white_noise_C(S.T, temperature_lsb_C(parts.get(name))) \
            if S.n > 2 else (0.0, 0.0)
        spans = _sorted_file_spans(S)
        rows = []
        for sg in S.segments:
            L = nearest_level(sg.temp_C)
            if L is None or len(sg.index) == 0:
                rows.append((None, 0.0))
                continue
            Tb = _approach_temps(S, spans, sg.index[0])
            came = float(np.sign(np.mean(Tb) - sg.temp_C)) if len(Tb) else 0.0
            rows.append((sg.temp_C - L, came))
        cool = [d for d, c in rows if d is not None and c > 0]
        heat = [d for d, c in rows if d is not None and c < 0]
        offset = 0.5 * (float(np.median(cool)) + float(np.median(heat))) \
            if cool and heat else 0.0
        segs = []
        for sg, (d, _) in zip(S.segments, rows):
            if d is None:
                segs.append({"settled": False, "from_level_C": None})
                continue
            n = max(len(sg.index), 1)
            tol_mean = tol + q / 2 + 3 * sw / math.sqrt(n)
            tol_drift = tol + q + 3 * sw * math.sqrt(12.0 / n)
            dev = d - offset
            segs.append({"settled": bool(abs(dev) <= tol_mean
                                         and abs(sg.drift_C) <= tol_drift),
                         "from_level_C": float(dev)})
        out[name] = {"offset_C": float(offset), "tolerance_C": float(tol + q / 2),
                     "step_C": float(q), "segments": segs}
    return out


def _approach_temps(S: SensorSamples, spans, i0):
    """S.T of the samples of sample i0's file in the APPROACH_LOOKBACK_S before it, in
    order; spans: _sorted_file_spans(S) (a time-ordered file: a slice; else a mask)."""
    t0 = S.time_s[i0]
    span = spans.get(int(S.file[i0]))
    if span is None:
        return S.T[(S.file == S.file[i0]) & (S.time_s < t0)
                   & (S.time_s >= t0 - APPROACH_LOOKBACK_S)]
    a, b = span
    tf = S.time_s[a:b]
    lo = a + int(np.searchsorted(tf, t0 - APPROACH_LOOKBACK_S, "left"))
    hi = a + int(np.searchsorted(tf, t0, "left"))
    return S.T[lo:hi]


def _sorted_file_spans(S: SensorSamples) -> dict:
    """{file: (start, stop)} for each file whose samples are one contiguous block of S in
    non-decreasing time (gather_samples concatenates the files in order); a file that is
    not is left out (its samples are then found by a mask)."""
    out = {}
    if not S.n:
        return out
    edges = np.flatnonzero(np.diff(S.file)) + 1
    starts = np.concatenate([[0], edges])
    stops = np.concatenate([edges, [S.n]])
    for a, b in zip(starts, stops):
        f = int(S.file[a])
        if f in out:                # a file in two blocks: not contiguous
            out[f] = None
            continue
        t = S.time_s[a:b]
        out[f] = (int(a), int(b)) if bool(np.all(t[1:] >= t[:-1])) else None
    return {f: v for f, v in out.items() if v is not None}


def level_tolerance_C(temps) -> float:
    """Gap between segment temperatures that starts a new level (as generator.fit.thermal)."""
    quantum = temperature_quantum(temps) if len(temps) else 0.0
    return max(2.0, 3.0 * quantum, DEGREE_STEP_C / 2)


def degree_for_span(span_C) -> int:
    """Polynomial degree the fit uses for a temperature span (one per DEGREE_STEP_C)."""
    return int(min(POLY_DEGREE, max(0, math.floor(span_C / DEGREE_STEP_C))))


# =======================================================================================
# Orientation coverage
# =======================================================================================
def _icosa_face_centres() -> np.ndarray:
    """Unit vectors to the centres of the 20 faces of an icosahedron (= the vertices of a
    dodecahedron): a 20-cell equal-area binning of the sphere."""
    g = (1 + 5 ** 0.5) / 2
    v = [(sx, sy, sz) for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
    for a in (-1, 1):
        for b in (-1, 1):
            v += [(0, a / g, b * g), (a / g, b * g, 0), (a * g, 0, b / g)]
    v = np.array(v, float)
    return v / np.linalg.norm(v, axis=1)[:, None]


ICOSA_CELLS = _icosa_face_centres()


def direction_coverage(unit_vectors) -> dict:
    """How much of the sphere a set of field directions covers (JSON-able): fraction of
    the 20 icosahedron cells holding at least one direction, and the eigenvalues of the
    scatter matrix mean(u u^T) (1/3 each for a full sphere; the smallest ~0 when the
    directions lie in a plane)."""
    u = np.asarray(unit_vectors, float).reshape(-1, 3)
    # a direction that could not be told (zero vector, failed offset fit: NaN) covers nothing
    u = u[np.isfinite(u).all(axis=1)]
    if not len(u):
        return {"n": 0, "icosa_cells": 0, "icosa_fraction": 0.0, "eig": [0.0, 0.0, 0.0],
                "least_direction": [0.0, 0.0, 0.0], "mean_resultant": 0.0}
    cell = np.argmax(u @ ICOSA_CELLS.T, axis=1)
    occupied = len(np.unique(cell))
    cv = coverage(u)
    cv["eig"] = [max(0.0, e) for e in cv["eig"]]      # rounding can leave -1e-17
    return {"n": int(len(u)), "icosa_cells": int(occupied),
            "icosa_fraction": occupied / len(ICOSA_CELLS), **cv}


# =======================================================================================
# The check
# =======================================================================================
STATUS_ORDER = ("ok", "short", "not settled", "missing")


def _fmt_list(nums) -> str:
    """1, 2, 3, 5 -> '1-3, 5'."""
    nums = sorted(set(int(v) for v in nums))
    out, i = [], 0
    while i < len(nums):
        j = i
        while j + 1 < len(nums) and nums[j + 1] == nums[j] + 1:
            j += 1
        out.append(f"{nums[i]}" if i == j else f"{nums[i]}-{nums[j]}")
        i = j + 1
    return ", ".join(out)


def up_axis_and_heading(field_body_nT):
    """(signed body axis pointing up, heading of the horizontal field in that axis's plane,
    deg) of a static position from its reference field, or (None, None) when no body axis
    is near the vertical. Assumes the field dips downwards by more than ~45 deg (the
    vertical component dominates): a northern-hemisphere lab such as the SamSat team's
    (south of the magnetic equator the up axis would come out reversed)."""
    b = np.asarray(field_body_nT, float)
    k = int(np.argmax(np.abs(b)))
    if abs(b[k]) < 0.75 * np.linalg.norm(b):
        return None, None
    up = ("-" if b[k] > 0 else "+") + "XYZ"[k]      # the field points down
    i, j = (k + 1) % 3, (k + 2) % 3
    return up, float(np.degrees(np.arctan2(b[j], b[i])))


def _distinct_angles(angles_deg, tol_deg):
    out = []
    for a in angles_deg:
        if all(abs((a - b + 180.0) % 360.0 - 180.0) > tol_deg for b in out):
            out.append(a)
    return out


def _constant_offset(S: SensorSamples):
    """A constant offset to linearise the prediction about (and say if even that fails)."""
    from generator.fit.ellipsoid import ellipsoid_fit
    from generator.fit.thermal import reference_fit
    v = S.is_vec
    try:
        if v.sum() >= 4:
            b, M, _ = reference_fit(S.x[v], S.ref[v], None)
            return b[0], M[0], None
        b, M, _ = ellipsoid_fit(S.x, S.norm)
        return b, M, None
    except InputError as e:
        return np.median(S.x, axis=0) if S.n else np.zeros(3), np.eye(3), e.message


def predict_sensor(S: SensorSamples, spec, target_C, *, noise_nT=None,
                   limit_b_nT=LIMIT_B_nT, limit_m=LIMIT_M) -> dict:
    """Predicted 1-sigma of b_i(T), m_ij(T) over target_C = (lo, hi) from this campaign's
    design; flags coefficients above the limits (JSON-able dict)."""
    if not (noise_nT or spec.noise_nT):
        # none stated: the part catalogue's typical noise, as the fit uses it
        # (fit.samples.field_noise_nT; counts: with the LSB's quantisation). lsb_nT is no
        # noise figure: for a physical-unit input it is the unit's size (1000 nT for uT),
        # for counts one step (8 nT for a QMC5883L whose noise is 200 nT)
        from generator.fit.samples import field_noise_nT
        noise_nT = field_noise_nT(spec)
    noise = float(noise_nT or spec.noise_nT or spec.lsb_nT)
    out = {"noise_nT": noise, "limit_b_nT": limit_b_nT, "limit_m": limit_m}
    if S.n == 0:
        out.update({"degree": None, "poorly_determined": list(B_NAMES + M_NAMES),
                    "sigma_max": {}, "reason": "no usable samples"})
        return out
    t_lo, t_hi = float(S.T.min()), float(S.T.max())
    deg = degree_for_span(t_hi - t_lo)
    b0, M0, fail = _constant_offset(S)
    pc = poly_covariance(S.x, S.T, S.ref, S.norm, degree=deg, t_range_C=(t_lo, t_hi),
                         b_poly=b0[None], M_poly=np.asarray(M0)[None], noise_nT=noise,
                         noise_free=True)
    lo, hi = min(target_C[0], t_lo), max(target_C[1], t_hi)
    grid = np.linspace(lo, hi, 61)
    sig = pc.sigma_at(grid)
    names = B_NAMES + M_NAMES
    smax, poor = {}, []
    for c, nm in enumerate(names):
        k = int(np.argmax(np.where(np.isfinite(sig[:, c]), sig[:, c], np.inf)))
        s = float(sig[k, c])
        smax[nm] = {"sigma": s if np.isfinite(s) else None, "at_C": float(grid[k])}
        limit = limit_b_nT if c < 3 else limit_m
        if not np.isfinite(s) or s > limit:
            poor.append(nm)
    out.update({"degree": deg, "data_range_C": [t_lo, t_hi], "target_range_C": [lo, hi],
                "model": ("full M (reference vectors)" if pc.body_frame else
                          "symmetric M (magnitude only)"),
                "sigma_max": smax, "poorly_determined": poor,
                "undetermined": [nm for nm in poor if smax[nm]["sigma"] is None]})
    if fail:
        out["constant_fit_failed"] = fail
    return out


def _count_at(tels, S: SensorSamples, flag, position, pres=None, name=None, temp_range=None):
    """Samples flagged `flag` ("missing" / "saturated") at a static position (and, given
    pres and name, with the sensor's temperature in temp_range)."""
    n = 0
    for fi, fl in enumerate(S.file_flags):
        pos = tels[fi].get("position")
        if pos is None:
            continue
        m = fl[flag] & (np.nan_to_num(pos) == position)
        if temp_range is not None:
            T = pres[fi][name].temp_C
            m &= (T >= temp_range[0]) & (T <= temp_range[1])
        n += int(m.sum())
    return n


def _why_weak(S: SensorSamples, pred) -> str:
    """A short reason why a campaign leaves coefficients poorly determined."""
    from generator.fit.ellipsoid import distinct_rows
    why = []
    v = S.is_vec
    if v.any():
        u = S.ref[v] / np.linalg.norm(S.ref[v], axis=1)[:, None]
        nd = distinct_rows(u, 0.01, at_most=4)
        if nd < 4:
            why.append(f"only {nd} distinct reference field direction(s); a vector fit needs "
                       "at least 4 not in one plane")
        else:
            e = direction_coverage(u)["eig"][0]
            if e < MIN_DIRECTION_EIG:
                why.append(f"field directions nearly in a plane (smallest eigenvalue {e:.3f})")
    elif S.n:
        e = pred.get("coverage_eig")
        if e is not None and e < MIN_DIRECTION_EIG:
            why.append(f"orientations nearly in a plane (smallest eigenvalue {e:.3f})")
    dr, tr = pred.get("data_range_C"), pred.get("target_range_C")
    if dr and tr and (dr[0] > tr[0] + 3.0 or dr[1] < tr[1] - 3.0):
        why.append(f"data span {dr[0]:.1f}..{dr[1]:.1f} degC of the planned "
                   f"{tr[0]:.1f}..{tr[1]:.1f} degC: the cubic is extrapolated")
    if not why:
        why.append(f"{S.n} usable samples are too few for {pred['noise_nT']:g} nT noise")
    return "; ".join(why)


def _poor_message(name, pred, S, limit_b_nT, limit_m) -> str:
    sm = pred["sigma_max"]
    und = [n for n in pred["poorly_determined"] if sm.get(n, {}).get("sigma") is None]
    high = [n for n in pred["poorly_determined"] if n not in und]
    parts = []
    if und:
        parts.append(("all 12 coefficients" if len(und) == 12 else ", ".join(und))
                     + " undetermined")
    if high:
        vals = ", ".join(f"{n} {sm[n]['sigma']:.3g}{' nT' if n.startswith('b') else ''} "
                         f"at {sm[n]['at_C']:.0f} degC" for n in high)
        parts.append(f"predicted 1-sigma above the limits (b {limit_b_nT:g} nT, m {limit_m:g}): "
                     + vals)
    deg = pred.get("degree")
    return (f"{name}: coefficients poorly determined ({pred['noise_nT']:g} nT noise, degree-"
            f"{deg} model): " + "; ".join(parts) + f" -- {_why_weak(S, pred)}")


def check_campaign(unit, data_paths, profile=None, *, noise_nT=None, limit_b_nT=LIMIT_B_nT,
                   limit_m=LIMIT_M, min_samples=None, progress=None, tels=None,
                   cells_only=False) -> dict:
    """Does a recorded campaign cover the test program? Returns a JSON-able result with
    "adequate" (bool), "gaps" (list of one-line findings), "notes", and the per-position,
    per-level, per-cell, per-sensor details.

    profile: plan.PlanProfile (None: the default program of `magcal plan`, applied to
    static-position files only). min_samples: settled samples a (position, level) segment
    needs (default: the plan's samples_per_segment when a plan is given, else
    MIN_SEGMENT_SAMPLES). tels: the files already read (io.telemetry_csv.read_telemetry of
    data_paths, as `magcal fit` has them), else read here. cells_only: stop once the
    position/level cells and the settling are known (what settling_warnings needs; the
    per-sensor coverage and coefficient prediction are left out, and so are the positions'
    details, the levels' coverage, the cells' saturated counts and the gaps: "positions"
    and "levels" are empty, the cells carry no "saturated").
    """
    from generator.campaign.plan import PlanProfile, make_plan
    from generator.io.telemetry_csv import preprocess, read_telemetry

    say = progress or (lambda m: None)
    explicit = profile is not None
    if profile is None:
        profile = PlanProfile.from_plan(make_plan(unit, lab_field_nT=unit.lab_field_nT or 5e4))
    if min_samples is None:
        min_samples = profile.samples_per_segment if explicit else MIN_SEGMENT_SAMPLES
    if tels is None:
        tels = [read_telemetry(p, unit) for p in data_paths]
    pres = [preprocess(t, unit) for t in tels]
    say(f"read {len(tels)} file(s): {sum(t.n for t in tels)} samples")
    samples = gather_samples(unit, tels, pres)
    gaps, notes = [], []
    if not cells_only:      # overlapping recordings: their repeated rows count twice
        from generator.io.recordings import repeated_rows_warnings
        from generator.io.telemetry_csv import text_column_notes
        notes += repeated_rows_warnings(tels)
        notes += [n for t in tels for n in text_column_notes(t)]

    files = []
    static = False
    for t in tels:
        pos = t.get("position")
        st = pos is not None and bool(np.any(np.nan_to_num(pos) > 0))
        static |= st
        dt = np.diff(t.time_s)
        files.append({"path": str(t.path), "samples": t.n,
                      "duration_s": float(t.time_s[-1] - t.time_s[0]) if t.n else 0.0,
                      "sample_period_s": float(np.median(dt[dt > 0])) if np.any(dt > 0) else None,
                      "kind": "static positions" if st else "moving / no positions",
                      "reference": ("vectors" if t.has("ref_x_nT", "ref_y_nT", "ref_z_nT") else
                                    "ref_norm_nT" if t.has("ref_norm_nT") else
                                    "lab_field_nT" if unit.lab_field_nT else "none")})
    plan_applies = static or explicit
    levels = sorted(profile.levels_C)
    spacing = min(np.diff(levels)) if len(levels) > 1 else 30.0
    match_tol = max(3.0, spacing / 3.0)
    result = {"adequate": True, "unit": unit.id,
              "plan": {"source": profile.source if explicit else
                       "default test program (magcal plan defaults)",
                       "applied": plan_applies,
                       "positions": [p["number"] for p in profile.positions],
                       "levels_C": list(profile.levels_C), "min_samples": int(min_samples),
                       "level_match_tolerance_C": match_tol},
              "files": files, "limits": {"b_nT": limit_b_nT, "m": limit_m}}

    # ---- positions ---------------------------------------------------------------------
    pos_rows = {}
    for fi, t in enumerate(tels):
        pos = t.get("position")
        if pos is None:
            continue
        p = np.nan_to_num(np.asarray(pos, float)).astype(int)
        for q in np.unique(p[p > 0]):
            pos_rows[int(q)] = pos_rows.get(int(q), 0) + int((p == q).sum())
    planned = {p["number"]: p for p in profile.positions}
    positions_out = []
    ref_dir, renumbered, no_ref = {}, [], []
    # cells_only (settling_warnings): the positions' reference directions, counts and
    # coverage, the levels' coverage, the cells' saturated counts and the gaps are not
    # computed (nothing of the cells or the settling depends on them)
    if plan_applies and not cells_only:
        for name, S in samples.items():
            v = S.is_vec
            for q in np.unique(S.position[v & (S.position > 0)]):
                m = v & (S.position == q)
                r = S.ref[m].mean(axis=0)
                # below 1 nT no direction can be told (every part resolves coarser): a
                # zero reference is flagged, not divided by
                if not np.linalg.norm(r) >= 1.0:
                    if int(q) not in ref_dir and int(q) not in no_ref:
                        no_ref.append(int(q))
                        notes.append(f"position {int(q)}: the reference vector is zero "
                                     "(|ref| < 1 nT): no direction recorded")
                    continue
                ref_dir.setdefault(int(q), r)
        for num, p in planned.items():
            row = {"position": num, "label": p.get("label", ""), "rows": pos_rows.get(num, 0),
                   "planned_up": p.get("up"),
                   "expected_field_body_nT": p["expected_field_body_nT"]}
            if num in ref_dir:
                r = ref_dir[num]
                row["recorded_field_body_nT"] = [float(v) for v in r]
                row["recorded_up"], row["heading_deg"] = up_axis_and_heading(r)
                e = np.asarray(p["expected_field_body_nT"], float)
                c = float(np.dot(r, e) / (np.linalg.norm(r) * np.linalg.norm(e)))
                row["angle_to_plan_deg"] = float(np.degrees(np.arccos(np.clip(c, -1, 1))))
            row["usable"] = {n: int((S.position == num).sum()) for n, S in samples.items()}
            row["missing"] = {n: _count_at(tels, S, "missing", num) for n, S in samples.items()}
            row["saturated"] = {n: _count_at(tels, S, "saturated", num)
                                for n, S in samples.items()}
            positions_out.append(row)
            if row["rows"] == 0:
                label = f" ({row['label']})" if explicit and row["label"] else ""
                gaps.append(f"position {num}{label}: not recorded")
            elif explicit and row.get("recorded_up") and row.get("planned_up") and \
                    row["recorded_up"] != row["planned_up"]:
                renumbered.append(f"{num} ({row['recorded_up']} up, plan {row['planned_up']})")
        if renumbered:
            notes.append("positions numbered differently from the plan: "
                         + ", ".join(renumbered) + " (the fit uses the reference vectors, so "
                         "only the coverage below matters)")
        extra = sorted(set(pos_rows) - set(planned))
        if extra:
            notes.append(f"positions not in the plan: {_fmt_list(extra)}")
        # every signed body axis up, at two headings (the twelve-position scheme)
        if ref_dir:
            ups = {}
            for q, r in ref_dir.items():
                up, hd = up_axis_and_heading(r)
                if up is not None:
                    ups.setdefault(up, []).append((q, hd))
            want = {}
            for p in profile.positions:
                if p.get("up"):
                    want[p["up"]] = want.get(p["up"], 0) + 1
            if not want:
                want = {f"{sg}{a}": 2 for a in "XYZ" for sg in "+-"}
            for axis in sorted(want):
                got = ups.get(axis, [])
                if not got:
                    gaps.append(f"no position with body {axis} up (the plan has "
                                f"{want[axis]})")
                    continue
                nh = len(_distinct_angles([h for _, h in got], 30.0))
                if nh < min(want[axis], 2):
                    gaps.append(f"body {axis} up at one heading only (position(s) "
                                f"{_fmt_list([q for q, _ in got])}): the plan turns it to "
                                f"{want[axis]} headings")
            result["up_axes"] = {a: [{"position": q, "heading_deg": h} for q, h in v]
                                 for a, v in sorted(ups.items())}
    result["positions"] = positions_out

    # ---- temperature levels and cells ------------------------------------------------
    def nearest_level(temp):
        k = int(np.argmin([abs(temp - L) for L in levels]))
        return levels[k] if abs(temp - levels[k]) <= match_tol else None

    settle = settled_segments(unit, samples, nearest_level, profile.settle_tolerance_C)
    cells, unsettled = {}, {}
    level_seen = {L: {} for L in levels}        # level -> sensor -> list of segment temps
    unplanned = []
    for name, S in samples.items():
        for k, sg in enumerate(S.segments):
            L = nearest_level(sg.temp_C)
            if L is None:
                unplanned.append(sg.temp_C)
                continue
            level_seen[L].setdefault(name, []).append(sg.temp_C)
            if sg.position <= 0:
                continue
            off = settle[name]["segments"][k]
            if not off["settled"]:
                u = unsettled.setdefault((sg.position, L), {})
                u[name] = max(u.get(name, 0.0), abs(off["from_level_C"]))
                continue
            c = cells.setdefault((sg.position, L), {}).setdefault(
                name, {"samples": 0, "duration_s": 0.0, "temps": []})
            c["samples"] += len(sg.index)
            c["duration_s"] += sg.duration_s
            c["temps"].append(sg.temp_C)
    if unplanned:
        notes.append("constant-temperature segments at levels not in the plan: "
                     + ", ".join(f"{v:.1f}" for v in sorted(set(np.round(unplanned, 0))))
                     + " degC")
    cells_out, level_out = [], []
    if plan_applies:
        for L in ([] if cells_only else levels):
            row = {"level_C": L, "sensor_temp_C": {n: float(np.mean(v))
                                                   for n, v in level_seen[L].items()}}
            settled_pos = sorted({p for (p, LL) in cells if LL == L})
            row["positions_settled"] = settled_pos
            dirs = [ref_dir[p] / np.linalg.norm(ref_dir[p]) for p in settled_pos
                    if p in ref_dir]
            if dirs:   # what a calibration of this level alone (segments method) would see
                row["direction_coverage"] = direction_coverage(dirs)
            level_out.append(row)
        # per sensor and level, its samples within match_tol of the level (each mask once,
        # not per position)
        near_level = {name: [np.abs(S.T - L) <= match_tol for L in levels]
                      for name, S in samples.items()}
        for num in planned:
            if pos_rows.get(num, 0) == 0:
                continue
            at_pos = {name: S.position == num for name, S in samples.items()}
            for li, L in enumerate(levels):
                by = {}
                for name, S in samples.items():
                    c = cells.get((num, L), {}).get(name)
                    near = int(np.count_nonzero(at_pos[name] & near_level[name][li]))
                    far = unsettled.get((num, L), {}).get(name)
                    if c and c["samples"] >= min_samples:
                        st = "ok"
                    elif c:
                        st = "short"
                    elif near or far is not None:
                        st = "not settled"
                    else:
                        st = "missing"
                    by[name] = {"status": st, "settled_samples": c["samples"] if c else 0,
                                "settled_s": c["duration_s"] if c else 0.0,
                                "temp_C": float(np.mean(c["temps"])) if c else None,
                                "samples_near_level": near,
                                "unsettled_from_level_C": far}
                    if not cells_only:
                        by[name]["saturated"] = _count_at(tels, S, "saturated", num, pres,
                                                          name, (L - match_tol, L + match_tol))
                worst = max((b["status"] for b in by.values()), key=STATUS_ORDER.index)
                cells_out.append({"position": num, "level_C": L, "status": worst,
                                  "sensors": by})
        # gaps: whole levels first, then cells
        for L in ([] if cells_only else levels):
            lc = [c for c in cells_out if c["level_C"] == L]
            if lc and all(c["status"] in ("missing", "not settled") for c in lc):
                ns = sum(b["samples_near_level"] for c in lc for b in c["sensors"].values())
                lo = min((float(S.T.min()) for S in samples.values() if S.n), default=None)
                hi = max((float(S.T.max()) for S in samples.values() if S.n), default=None)
                reach = (f"never reached: the sensors report {lo:.1f}..{hi:.1f} degC, and a "
                         "calibration is clamped outside its data" if lo is not None
                         else "never reached")
                # per sensor, its segment closest to the level (after its offset)
                near_seg = {}
                for (p, LL), u in unsettled.items():
                    if LL == L:
                        for n, v in u.items():
                            near_seg[n] = min(near_seg.get(n, math.inf), v)
                closest = ("; closest segment " + ", ".join(
                    f"{n} {v:.1f} degC from it (settled: within "
                    f"{settle[n]['tolerance_C']:.2f})" for n, v in sorted(near_seg.items()))
                    if near_seg else "")
                gaps.append(f"level {L:g} degC: no settled segment in any position ("
                            + ("samples reach it but the temperature never settled: holds "
                               "too short?" if ns else reach) + closest + ")")
                for c in lc:
                    c["reported_with_level"] = True
        groups = {}
        for c in cells_out:
            if c["status"] == "ok" or c.get("reported_with_level"):
                continue
            bad = tuple(n for n, b in c["sensors"].items() if b["status"] != "ok")
            groups.setdefault((c["level_C"], c["status"], bad), []).append(c["position"])
        for (L, st, bad), plist in sorted(groups.items()):
            what = {"short": f"fewer than {min_samples} settled samples",
                    "not settled": "temperature not settled",
                    "missing": "no samples at this level"}[st]
            far = {n: max((unsettled.get((p, L), {}).get(n) or 0.0) for p in plist)
                   for n in bad}
            if st == "not settled" and any(far.values()):
                what += " (" + ", ".join(
                    f"{n}: a segment {v:.1f} degC from the level, settled within "
                    f"{settle[n]['tolerance_C']:.2f}" for n, v in far.items() if v) + ")"
            gaps.append(f"level {L:g} degC, position(s) {_fmt_list(plist)}: {what} "
                        f"({', '.join(bad)})")
    result["levels"] = level_out
    result["cells"] = cells_out
    result["settling"] = {n: {k: v for k, v in d.items() if k != "segments"}
                          for n, d in settle.items()}
    for n, d in settle.items():
        if plan_applies and d["offset_C"] != 0.0:
            notes.append(f"{n}: reads {abs(d['offset_C']):.2f} degC "
                         f"{'above' if d['offset_C'] > 0 else 'below'} the set-points "
                         "(self-heating or the sensor's temperature offset: the midpoint of "
                         "the holds entered cooling and those entered heating); a segment is "
                         f"settled within {d['tolerance_C']:.2f} degC of set-point + offset")
    if cells_only:
        return result

    # ---- per sensor: samples, coverage, coefficient prediction ------------------------
    plan_range = (min(levels), max(levels)) if plan_applies else None
    sensors_out = {}
    for s in unit.sensors:
        S = samples[s.name]
        so = {"usable": int(S.n), "excluded": dict(S.excluded),
              "temperature_range_C": [float(S.T.min()), float(S.T.max())] if S.n else None,
              "segments": len(S.segments)}
        total = sum(t.n for t in tels)
        if S.excluded.get("zero reference"):
            notes.append(f"{s.name}: {S.excluded['zero reference']} samples with a zero "
                         "reference vector (|ref| < 1 nT) used as magnitude-only or left out")
        if S.excluded["saturated"]:
            where = []
            for fi, fl in enumerate(S.file_flags):
                pos = tels[fi].get("position")
                if pos is not None:
                    where += list(np.unique(np.nan_to_num(pos)[fl["saturated"]]).astype(int))
            gaps.append(f"{s.name}: {S.excluded['saturated']} saturated samples"
                        + (f" (positions {_fmt_list([w for w in where if w > 0])})"
                           if any(w > 0 for w in where) else "")
                        + ": the field exceeds the part's range there (magnetic parts near "
                          "the jig?)")
        if total and S.excluded["missing"] > 0.05 * total:
            gaps.append(f"{s.name}: {S.excluded['missing']} of {total} samples missing")
        elif S.excluded["missing"]:
            notes.append(f"{s.name}: {S.excluded['missing']} samples missing (empty cells)")
        # coverage: static positions -> directions of the positions; moving -> per sample
        cov = {}
        v = S.is_vec
        static_file = np.array([f["kind"] == "static positions" for f in files])
        if static and S.n:
            dirs, b0 = [], None
            for q in np.unique(S.position[S.position > 0]):
                m = S.position == q
                if v[m].any():
                    r = S.ref[m & v].mean(axis=0)
                else:        # magnitude only: the reading less a constant offset
                    if b0 is None:
                        b0 = _constant_offset(S)[0]
                    r = np.median(S.x[m], axis=0) - b0
                dirs.append(r / np.linalg.norm(r))
            cov["static_positions"] = direction_coverage(dirs)
            if dirs and cov["static_positions"]["eig"][0] < MIN_DIRECTION_EIG:
                gaps.append(f"{s.name}: the positions' field directions do not span the sphere"
                            f" (smallest eigenvalue {cov['static_positions']['eig'][0]:.3f} of "
                            f"the direction scatter, 0.333 full sphere)")
        moving = ~static_file[S.file] if S.n else np.zeros(0, bool)   # rotation campaigns
        if moving.any():
            u = None
            if v[moving].all():
                r = S.ref[moving]
                u = r / np.linalg.norm(r, axis=1)[:, None]
            else:
                b0, M0, fail = _constant_offset(
                    SensorSamples(S.name, S.x[moving], S.T[moving], S.ref[moving],
                                  S.norm[moving], S.position[moving], S.file[moving],
                                  S.time_s[moving], [], {}))
                y = (S.x[moving] - b0) @ np.asarray(M0).T
                u = y / np.linalg.norm(y, axis=1)[:, None]
                if fail:
                    cov["moving_fit_failed"] = fail
            cm = direction_coverage(u)
            cov["moving"] = cm
            if cm["icosa_fraction"] < MIN_ICOSA_FRACTION or cm["eig"][0] < MIN_DIRECTION_EIG:
                gaps.append(f"{s.name}: rotation covers {cm['icosa_cells']} of 20 sphere cells "
                            f"(smallest direction eigenvalue {cm['eig'][0]:.3f}, 0.333 full "
                            f"sphere): turn the unit through more orientations")
        so["coverage"] = cov
        target = plan_range or ((float(S.T.min()), float(S.T.max())) if S.n else (25.0, 25.0))
        pred = predict_sensor(S, s, target, noise_nT=noise_nT, limit_b_nT=limit_b_nT,
                              limit_m=limit_m)
        so["prediction"] = pred
        poor = pred["poorly_determined"]
        if poor:
            gaps.append(_poor_message(s.name, pred, S, limit_b_nT, limit_m))
        sensors_out[s.name] = so
        # segments the grid counts: in a position, at a planned level, long enough
        n_settled = sum(1 for (pos, L), c in cells.items() if s.name in c
                        and c[s.name]["samples"] >= min_samples) if plan_applies else 0
        say(f"{s.name}: {S.n} usable samples, {len(S.segments)} constant-temperature "
            f"segment(s), {n_settled} position/level cell(s) of the grid settled, "
            f"{len(poor)} coefficient(s) poorly determined")
    result["sensors"] = sensors_out
    if plan_applies and explicit:
        for f in files:
            if f["kind"] == "static positions" and f["sample_period_s"] and \
                    f["sample_period_s"] > 1.5 * profile.sample_period_s:
                notes.append(f"{f['path']}: sampled every {f['sample_period_s']:g} s, the plan "
                             f"says {profile.sample_period_s:g} s")
    if not plan_applies:
        notes.append("no static-position file: the plan's positions and levels were not "
                     "checked (give --plan to require them)")
    result["gaps"] = gaps
    result["notes"] = notes
    result["adequate"] = not gaps
    return result


def settling_warnings(unit, data_paths, profile=None, *, tels=None) -> dict:
    """{sensor: warning} for `magcal fit` (review #19 F): the levels of the program
    (profile, else magcal plan's default, as `magcal check` without --plan) that a sensor's
    samples reach in static positions without a settled segment in any position. Taken
    from check_campaign's own cells (a level none of whose cells is 'ok' or 'short' for the
    sensor and some is 'not settled'), so fit and check say the same; {} where the program
    does not apply (no static-position file). tels: data_paths already read."""
    result = check_campaign(unit, data_paths, profile, tels=tels, cells_only=True)
    if not result["plan"]["applied"]:
        return {}
    by = {}
    for c in result["cells"]:
        for n, b in c["sensors"].items():
            by.setdefault(n, {}).setdefault(c["level_C"], []).append(b)
    out = {}
    for n, levels in by.items():
        bad, far = [], []
        for L, cells in sorted(levels.items()):
            status = {b["status"] for b in cells}
            if status & {"ok", "short"} or "not settled" not in status:
                continue
            bad.append(L)
            d = [b["unsettled_from_level_C"] for b in cells
                 if b["unsettled_from_level_C"] is not None]
            if d:
                far.append(f"{min(d):.1f} degC from {L:g}")
        if bad:
            out[n] = (f"level(s) {', '.join(f'{L:g}' for L in bad)} degC of the "
                      f"{result['plan']['source']}: no settled segment in any position, "
                      "the samples reach the level but the temperature never settled "
                      "(holds too short for the boards?"
                      + (f"; closest segment {', '.join(far)}" if far else "")
                      + "); the per-level method has no point there. magcal check "
                      "[--plan PLAN.json] lists the cells")
    return out


def summary_line(result) -> str:
    """One line for stderr."""
    if result["adequate"]:
        return "campaign covers the plan"
    g = result["gaps"]
    kinds = []
    missing_pos = [p["position"] for p in result.get("positions", []) if p["rows"] == 0]
    if missing_pos:
        kinds.append(f"positions {_fmt_list(missing_pos)} missing")
    lv = [gg for gg in g if gg.startswith("level ") and "any position" in gg]
    for what, has in (("missing", lambda gg: "never settled" not in gg),
                      ("not settled", lambda gg: "never settled" in gg)):
        sel = [gg.split(":")[0] for gg in lv if has(gg)]
        if sel:
            kinds.append(", ".join(sel) + " " + what)
    poor = [n for n, s in result.get("sensors", {}).items()
            if s.get("prediction", {}).get("poorly_determined")]
    if poor:
        kinds.append(f"coefficients poorly determined for {', '.join(poor)}")
    return (f"campaign does not cover the plan: {len(g)} gap(s)"
            + (f" ({'; '.join(kinds)})" if kinds else "") + "; the list is on stdout")


def format_text(result) -> str:
    """The full human-readable result (stdout)."""
    out = [f"magcal check: unit {result['unit']}, plan: {result['plan']['source']}"]
    for f in result["files"]:
        per = f"every {f['sample_period_s']:.3g} s" if f["sample_period_s"] else "one sample"
        out.append(f"  file {f['path']}: {f['samples']} samples, {f['kind']}, reference "
                   f"{f['reference']}, {per}")
    if result["cells"]:
        levels = result["plan"]["levels_C"]
        code = {"ok": "ok", "short": "short", "not settled": "unsettled", "missing": "-"}
        out.append("")
        out.append("settled segments per position (rows) and level degC (columns), the "
                   "worst of the sensors (each sensor's count is in the progress lines); "
                   f"'short': < {result['plan']['min_samples']} samples")
        out.append("  pos " + "".join(f"{L:>10g}" for L in levels))
        by = {(c["position"], c["level_C"]): c for c in result["cells"]}
        for p in result["positions"]:
            if p["rows"] == 0:
                out.append(f"  {p['position']:>3d} " + f"{'not recorded':>10s}")
                continue
            cells = []
            for L in levels:
                c = by.get((p["position"], L))
                if c is None:
                    cells.append(f"{'-':>10s}")
                    continue
                n = min(b["settled_samples"] for b in c["sensors"].values())
                cells.append(f"{code[c['status']] + ('' if c['status'] != 'ok' else f' {n}'):>10s}")
            out.append(f"  {p['position']:>3d} " + "".join(cells))
    out.append("")
    out.append("predicted 1-sigma, largest over the target range (b nT, m):")
    names = B_NAMES + M_NAMES
    out.append("  sensor " + "".join(f"{n:>9s}" for n in names))
    for name, s in result["sensors"].items():
        sm = s["prediction"].get("sigma_max", {})
        vals = []
        for n in names:
            v = sm.get(n, {}).get("sigma")
            vals.append(f"{'inf' if v is None else f'{v:.3g}':>9s}")
        out.append(f"  {name:6s} " + "".join(vals))
    out.append("")
    if result["gaps"]:
        out.append(f"GAPS ({len(result['gaps'])}):")
        out += [f"  - {g}" for g in result["gaps"]]
    else:
        out.append("no gaps: the campaign covers the plan")
    if result["notes"]:
        out.append("notes:")
        out += [f"  - {n}" for n in result["notes"]]
    return "\n".join(out) + "\n"


def run_check(args, progress) -> tuple:
    """`magcal check`: 0 when the campaign covers the plan, else 2 with one summary line on
    stderr and the full list on stdout (or the JSON result with --json)."""
    import sys

    from generator.campaign.plan import load_profile
    from generator.io.unitfile import load_unit

    unit = load_unit(args.unit)
    profile = load_profile(args.plan) if args.plan else None
    for name, v in (("--limit-b-nT", args.limit_b_nT), ("--limit-m", args.limit_m)):
        if not (v > 0 and math.isfinite(v)):
            raise InputError(None, f"{name} must be a positive number, got {v}")
    # beyond 1e7 nT (twice the largest full scale among the parts) a noise describes no
    # magnetometer, and its square overflows in the prediction
    if args.noise_nT is not None and not (0 < args.noise_nT <= 1e7):
        raise InputError(None, f"--noise-nT must be a positive number up to 1e7 nT, got "
                               f"{args.noise_nT}")
    if args.min_samples is not None and args.min_samples < 1:
        raise InputError(None, f"--min-samples must be at least 1, got {args.min_samples}")
    result = check_campaign(unit, args.data, profile, noise_nT=args.noise_nT,
                            limit_b_nT=args.limit_b_nT, limit_m=args.limit_m,
                            min_samples=args.min_samples, progress=progress)
    rc = 0 if result["adequate"] else 2
    if not getattr(args, "json", False):
        sys.stdout.write(format_text(result))
    print(f"magcal check: {summary_line(result)}", file=sys.stderr)
    return rc, result
