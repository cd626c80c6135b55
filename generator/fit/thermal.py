"""Temperature-dependent calibration of every sensor of a unit (seed 000 eq. 5-7, seed 001).

Model (generator.fit.calibration): B_cal = M(T) (B~ - b(T)), b and M polynomials in
dT = clamp(T) - t_ref. What is known about the true field decides the fit:

* reference vectors (`ref_x/y/z_nT`, body frame): `reference_fit`. The measurement model
  B~ = W(T) B_ref + b(T) is linear in the coefficients of W and b, so it is solved by
  ordinary least squares with the noise where it is, in B~; then M(T) = W(T)^-1 is fitted
  by a polynomial of the same degree (truncation ~(|W2| dT^2)^2 + (|W1| dT)^4, about 1e-6
  or 0.05 nT for parts like the SamSat ones, far below the noise). M is then the full
  matrix to the body frame.
* only the magnitude (`ref_norm_nT` or the unit's `lab_field_nT`): ellipsoid fit
  (generator.fit.ellipsoid), M symmetric (known only up to a rotation).

Temperature dependence is fitted two ways and the better one on held-out data is kept:

* "segments" (seed 000 sec. 5): find the constant-temperature segments in the reported
  temperature itself (`find_segments`), group them across positions into temperature
  levels, calibrate each level at constant temperature, then fit a weighted polynomial to
  every b_i and m_ij over the levels;
* "joint": fit the polynomial model directly to all usable samples, ramps included
  (linear least squares for reference vectors, Levenberg-Marquardt when magnitudes enter).

Held-out comparison: leave-positions-out cross-validation when the files have static
positions, contiguous time blocks otherwise; the score is the RMS of the held-out vector
residual (per axis) where reference vectors exist, else of the magnitude residual. The
figures and the choice go into SensorCalibration.stats.

Samples with non-zero magnetorquer current are not used (coil coupling is fitted
elsewhere); they are counted in stats.

The above is method "auto". Two more methods (`fit_unit(..., method=)`, FIT_METHODS):

* "analytic" (seed 001): per constant-temperature level the known-vector model with a
  rotation, h = Q P R B + b (generator.fit.analytic.fit_analytic_rotated), M = (Q P R)^-1;
  then the weighted polynomial over the levels as in "segments". Per level, stats keep
  k, e, R, b with 1-sigma and the residual of seed 001's model without R. Without
  reference vectors the sensor falls back to "auto" (stats say so);
* "ellipsoid" (seed 000): per level an ellipsoid fit of the magnitudes only, even where
  vectors exist (M symmetric, up to a rotation); the polynomial over the levels.

Public API: fit_unit(unit, telemetries, progress, method="auto") -> {name:
SensorCalibration}; fit_sensor(name, [FitData], degree=3, method="auto"); FIT_METHODS;
reference_fit(...); rotated_fit_M(...); find_segments(...), group_levels(...),
temperature_quantum(...), temperature_noise(...).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from generator.fit.calibration import POLY_DEGREE, SensorCalibration
from generator.errors import InputError
from generator.fit.ellipsoid import (SYM_INDEX, _sym_grad, coverage, covariance, distinct_rows,
                            ellipsoid_fit, lm_solve, sym_from6, sym_to6)

#: The fit methods of fit_unit / fit_sensor (the CLI's `magcal fit --method`).
FIT_METHODS = ("auto", "analytic", "ellipsoid")

T_REF_C = 25.0
DEGREE_STEP_C = 5.0        # one polynomial degree per 5 degC of temperature span
MAX_REF_COND = 1e10        # condition number of the column-scaled reference-fit design
CV_FOLDS = 4


# =======================================================================================
# Reference-vector fit
# =======================================================================================
def _powers(dT_scaled, degree):
    """[1, d, d^2, ...] per sample, (N, degree+1)."""
    P = np.empty((len(dT_scaled), degree + 1))
    P[:, 0] = 1.0
    for k in range(1, degree + 1):
        P[:, k] = P[:, k - 1] * dT_scaled
    return P


def _fit_inverse_poly(W_poly_s, degree, lo_s, hi_s):
    """Polynomial (in scaled dT) of W(T)^-1 over [lo_s, hi_s]; also its Jacobian d/dW."""
    n_grid = max(4 * (degree + 1), 16)
    if hi_s - lo_s < 1e-12:
        g = np.array([lo_s])
    else:  # Chebyshev nodes over the calibrated range
        c = np.cos(np.pi * (np.arange(n_grid) + 0.5) / n_grid)
        g = 0.5 * (lo_s + hi_s) + 0.5 * (hi_s - lo_s) * c
    kW = W_poly_s.shape[0] - 1
    Pw = g[:, None] ** np.arange(kW + 1)
    W_g = np.einsum("gk,kij->gij", Pw, W_poly_s)
    M_g = np.linalg.inv(W_g)
    Pm = g[:, None] ** np.arange(degree + 1)
    proj = np.linalg.pinv(Pm)                          # (degree+1, G) least-squares map
    M_poly_s = np.einsum("qg,gij->qij", proj, M_g)
    # dM_poly[q][i,l] / dW_k[a,c] = -sum_g proj[q,g] Pw[g,k] M_g[i,a] M_g[c,l]
    jac = -np.einsum("qg,gk,gia,gcl->qilkac", proj, Pw, M_g, M_g)
    return M_poly_s, jac


def reference_fit(field_frame_nT, ref_body_nT, temp_C=None, degree=POLY_DEGREE, *,
                  t_ref_C=T_REF_C, t_range_C=None, source=None):
    """Calibration from known field vectors: B_ref = M(T) (B~ - b(T)).

    field_frame_nT: (N, 3) uncalibrated readings in frame axes; ref_body_nT: (N, 3) true
    field (body frame); temp_C: (N,) reported temperature, or None for a constant
    calibration (degree 0). Only finite rows may be passed.
    Returns (b_poly_nT (degree+1, 3), M_poly (degree+1, 3, 3), info), polynomials in
    dT = clamp(T, t_range) - t_ref_C (t_range defaults to the data's range). info holds
    b_poly_sigma_nT, M_poly_sigma (1-sigma, from the least-squares covariance propagated
    to M to first order), W_poly, residual_sigma_nT (per axis), cond.
    """
    x = np.asarray(field_frame_nT, float)
    B = np.asarray(ref_body_nT, float)
    if x.ndim != 2 or x.shape[1] != 3 or B.shape != x.shape:
        raise InputError(source, f"reference fit: field {x.shape} and reference {B.shape} "
                                 "must both be (N, 3)")
    if not (np.isfinite(x).all() and np.isfinite(B).all()):
        raise InputError(source, "reference fit: non-finite readings or reference vectors "
                                 "(drop unusable samples first)")
    n = len(x)
    if temp_C is None:
        degree = 0
        T = np.full(n, float(t_ref_C))
    else:
        T = np.asarray(temp_C, float)
        if T.shape != (n,) or not np.isfinite(T).all():
            raise InputError(source, "reference fit: temperature must be finite, one per sample")
    t_lo, t_hi = (float(T.min()), float(T.max())) if n else (t_ref_C, t_ref_C)
    if t_range_C is not None:
        t_lo, t_hi = map(float, t_range_C)
    p = 4 * (degree + 1)
    if n * 3 <= p:
        raise InputError(source, f"reference fit: {n} samples for {p} unknowns per axis")
    n_dir = distinct_rows(B, 1.0, at_most=4)
    if n_dir < 4:
        raise InputError(source, f"reference fit: the reference field takes only {n_dir} "
                                 "distinct values; at least 4 directions not in one plane "
                                 "are needed")
    tau = max(abs(t_lo - t_ref_C), abs(t_hi - t_ref_C), 1.0)
    dts = (np.clip(T, t_lo, t_hi) - t_ref_C) / tau
    P = _powers(dts, degree)
    Phi = np.concatenate([(P[:, :, None] * B[:, None, :]).reshape(n, 3 * (degree + 1)), P],
                         axis=1)
    # Normal equations of the column-scaled design (cheap for N >> p); their condition
    # number is squared, so fall back to the SVD when the design is not well conditioned.
    G = Phi.T @ Phi
    col = np.sqrt(np.diag(G))
    col[col == 0] = 1.0
    G = G / np.outer(col, col)
    ev, EV = np.linalg.eigh(G)
    cond = float(np.sqrt(ev[-1] / ev[0])) if ev[0] > 0 else np.inf
    if cond < 1e3:   # normal-equation error ~ eps cond^2 < 1e-9
        inv_G = (EV / ev) @ EV.T
        theta_s = inv_G @ ((Phi.T @ x) / col[:, None])
    else:
        U, sv, Vt = np.linalg.svd(Phi / col, full_matrices=False)
        cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
        if cond < MAX_REF_COND:
            inv_G = (Vt.T / sv ** 2) @ Vt
            theta_s = Vt.T @ ((U.T @ x) / sv[:, None])
    if not cond < MAX_REF_COND:
        u = B / np.linalg.norm(B, axis=1)[:, None]
        cv = coverage(u)
        raise InputError(source, "reference fit: the data do not determine the model "
                                 f"(condition {cond:.3g}): reference directions spread "
                                 f"{np.sqrt(max(cv['eig'][0], 0)):.3f} (0.577 full sphere) "
                                 f"and temperature spans {t_hi - t_lo:.1f} degC for a "
                                 f"degree-{degree} model")
    theta = theta_s / col[:, None]                                      # (p, 3)
    resid = x - Phi @ theta
    dof = max(n - p, 1)
    sig2 = np.sum(resid ** 2, axis=0) / dof                             # per output axis
    inv_ntn = inv_G / np.outer(col, col)                                # (Phi^T Phi)^-1
    nW = 3 * (degree + 1)
    W_s = theta[:nW].reshape(degree + 1, 3, 3).transpose(0, 2, 1)       # W_k[j, l]
    b_s = theta[nW:]                                                    # (degree+1, 3)
    lo_s, hi_s = (t_lo - t_ref_C) / tau, (t_hi - t_ref_C) / tau
    M_s, jac = _fit_inverse_poly(W_s, degree, lo_s, hi_s)
    # Covariances: row j of (W, b) has covariance sig2[j] * inv_ntn; rows independent.
    var_b = np.diag(inv_ntn)[nW:, None] * sig2[None, :]                 # (degree+1, 3)
    CW = inv_ntn[:nW, :nW].reshape(degree + 1, 3, degree + 1, 3)        # [k,c,k',c']
    # var(M[q][i,l]) = sum_a sig2[a] sum_{k c k' c'} J[q,i,l,k,a,c] CW[k,c,k',c'] J[q,i,l,k',a,c']
    var_M = np.einsum("qilkac,kcmd,qilmad,a->qil", jac, CW, jac, sig2, optimize=True)
    scale = tau ** -np.arange(degree + 1)
    b_poly = b_s * scale[:, None]
    M_poly = M_s * scale[:, None, None]
    W_poly = W_s * scale[:, None, None]
    info = {
        "n": int(n), "degree": int(degree), "cond": cond, "t_range_C": (t_lo, t_hi),
        "W_poly": W_poly,
        "b_poly_sigma_nT": np.sqrt(var_b) * scale[:, None],
        "M_poly_sigma": np.sqrt(np.maximum(var_M, 0)) * scale[:, None, None],
        "residual_sigma_nT": np.sqrt(sig2),   # per frame axis, of the reading model
    }
    return b_poly, M_poly, info


# =======================================================================================
# Constant-temperature segments
# =======================================================================================
@dataclass
class Segment:
    index: np.ndarray          # sample indices (into the arrays given to find_segments)
    temp_C: float              # mean reported temperature
    temp_range_C: float        # max - min of the (spike-filtered) temperature
    t_start_s: float
    t_stop_s: float
    position: int = 0          # static position (0: none given)

    @property
    def duration_s(self) -> float:
        return self.t_stop_s - self.t_start_s


def temperature_quantum(temp_C) -> float:
    """Reporting step of a temperature channel (median spacing of its distinct values)."""
    u = np.unique(np.asarray(temp_C, float)[np.isfinite(temp_C)])
    return float(np.median(np.diff(u))) if len(u) > 1 else 0.0


def temperature_noise(temp_C) -> float:
    """Robust 1-sigma noise of a temperature channel from second differences."""
    t = np.asarray(temp_C, float)
    t = t[np.isfinite(t)]
    if len(t) < 3:
        return 0.0
    d2 = t[2:] - 2 * t[1:-1] + t[:-2]
    return float(1.4826 * np.median(np.abs(d2)) / np.sqrt(6.0))


def _runs(mask):
    """(start, stop) of the runs of True in a boolean array."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(np.int8))
    return list(zip(np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]))


def find_segments(time_s, temp_C, position=None, usable=None, *, window_s=600.0,
                  min_duration_s=600.0, band_C=None, min_band_C=0.5):
    """Constant-temperature segments, found in the reported temperature itself.

    A sample is settled when some window of `window_s` that contains it keeps the
    (5-sample median filtered) temperature within `band_C`, i.e. the slope stays below
    band_C / window_s for at least that long. Settled runs of at least `min_duration_s`
    are segments; a run drifting more than 2 band_C is cut; neighbouring segments of the
    same position within band_C of each other and less than min_duration_s apart are
    merged (a glitch does not split a plateau). The boards lag the chamber, so nothing
    about the chamber profile is assumed.

    band_C defaults to max(min_band_C, 1.5 x reporting quantum, 6 x noise sigma), so a
    quantised channel (MMC5883: ~0.7 degC steps) toggling between two levels is settled.
    position: split into runs of constant position; 0 (moving) is never a segment.
    Returns a list of Segment in time order.
    """
    t = np.asarray(time_s, float)
    T = np.asarray(temp_C, float)
    n = len(t)
    ok = np.isfinite(T) & np.isfinite(t)
    if usable is not None:
        ok &= np.asarray(usable, bool)
    pos = np.zeros(n, int) if position is None else np.nan_to_num(
        np.asarray(position, float), nan=0).astype(int)
    if position is None:
        pos[:] = 1
    if band_C is None:
        band_C = max(min_band_C, 1.5 * temperature_quantum(T[ok]),
                     6.0 * temperature_noise(T[ok]))
    dt = np.diff(t[ok])
    dt_med = float(np.median(dt[dt > 0])) if np.any(dt > 0) else 1.0
    # runs of constant position, split at time gaps
    brk = np.zeros(n, bool)
    brk[1:] = (pos[1:] != pos[:-1]) | (np.diff(t) > 10 * dt_med)
    run_id = np.cumsum(brk)
    segs = []
    for rid in np.unique(run_id[ok & (pos > 0)]):
        idx = np.nonzero((run_id == rid) & ok)[0]
        segs.extend(_segments_in_run(idx, t, T, int(pos[idx[0]]), dt_med, window_s,
                                     min_duration_s, band_C))
    return segs


def _segments_in_run(idx, t, T, position, dt_med, window_s, min_duration_s, band_C):
    n_w = max(3, int(round(window_s / dt_med)))
    if len(idx) < n_w:
        return []
    from scipy.ndimage import median_filter    # here: scipy.ndimage costs 0.2 s to import

    Tf = median_filter(T[idx], size=5, mode="nearest") if len(idx) >= 5 else T[idx]
    win = np.lib.stride_tricks.sliding_window_view(Tf, n_w)
    quiet = (win.max(axis=1) - win.min(axis=1)) <= band_C
    cover = np.zeros(len(idx) + 1, int)
    starts = np.nonzero(quiet)[0]
    np.add.at(cover, starts, 1)
    np.add.at(cover, starts + n_w, -1)
    settled = np.cumsum(cover)[:-1] > 0
    out = []
    for a, b in _runs(settled):
        # cut a run that drifts by more than 2 band_C in all
        while a < b:
            seg = Tf[a:b]
            rng = np.maximum.accumulate(seg) - np.minimum.accumulate(seg)
            over = np.nonzero(rng > 2 * band_C)[0]
            c = a + (over[0] if len(over) else b - a)
            out.append((a, c))
            a = c
    segs = []
    for a, b in out:
        if t[idx[b - 1]] - t[idx[a]] + dt_med < min_duration_s:
            continue
        if segs and (abs(np.mean(Tf[a:b]) - segs[-1][2]) < band_C
                     and t[idx[a]] - t[idx[segs[-1][1] - 1]] < min_duration_s):
            a0 = segs[-1][0]
            keep = np.concatenate([np.arange(a0, segs[-1][1]), np.arange(a, b)])
            segs[-1] = (a0, b, float(np.mean(Tf[keep])), keep)
            continue
        segs.append((a, b, float(np.mean(Tf[a:b])), np.arange(a, b)))
    result = []
    for a, b, _, keep in segs:
        ii = idx[keep]
        result.append(Segment(index=ii, temp_C=float(np.mean(T[ii])),
                              temp_range_C=float(np.ptp(Tf[keep])), t_start_s=float(t[ii[0]]),
                              t_stop_s=float(t[ii[-1]]), position=position))
    return result


def group_levels(segments, tol_C):
    """Group segments (from all positions) into temperature levels: sorted by mean
    temperature, a new level starts where the gap to the previous one exceeds tol_C."""
    if not segments:
        return []
    order = sorted(segments, key=lambda s: s.temp_C)
    levels = [[order[0]]]
    for s in order[1:]:
        if s.temp_C - levels[-1][-1].temp_C > tol_C:
            levels.append([s])
        else:
            levels[-1].append(s)
    return levels


# =======================================================================================
# Data gathering
# =======================================================================================
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


def fit_data_from(tel, sensor_data, unit) -> FitData:
    """Collect what one telemetry file carries for one sensor (see module docstring)."""
    n = tel.n
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
                   temp_C=np.asarray(sensor_data.temp_C, float),
                   usable=np.asarray(sensor_data.usable, bool),
                   position=None if pos is None else np.asarray(pos, float),
                   ref_body_nT=ref, ref_norm_nT=norm, coil_A=coil,
                   reference_kind=" + ".join(kind) or "none")


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

    def subset(self, mask):
        return _Samples(self.x[mask], self.T[mask], self.ref[mask], self.norm[mask],
                        self.is_vec[mask], self.group[mask],
                        time_s=None if self.time_s is None else self.time_s[mask])

    @property
    def n(self):
        return len(self.T)


def _gather(name, datas, notes, per_file):
    xs, Ts, refs, norms, vecs, groups, segs, times = [], [], [], [], [], [], [], []
    offset = 0
    gbase = 0
    for d in datas:
        n = len(d.time_s)
        use = d.usable & np.isfinite(d.temp_C) & np.isfinite(d.field_frame_nT).all(axis=1)
        n_unusable = int((~use).sum())
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
                         "coil_current_excluded": n_coil, "no_reference": n_noref})
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
        fsegs = find_segments(d.time_s, d.temp_C, d.position, use)
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
        gbase += int(g.max()) + 1 if n else 0
        offset += len(keep)
    if offset == 0:
        raise InputError(datas[0].source if datas else None,
                         f"sensor '{name}': no usable sample with a field reference "
                         "(reference vectors, ref_norm_nT or the unit's lab_field_nT)")
    return _Samples(np.concatenate(xs), np.concatenate(Ts), np.concatenate(refs),
                    np.concatenate(norms), np.concatenate(vecs), np.concatenate(groups), segs,
                    time_s=np.concatenate(times))


# =======================================================================================
# Fitting strategies
# =======================================================================================
def _pad(b_poly, M_poly, degree=POLY_DEGREE):
    b = np.zeros((degree + 1, 3))
    M = np.zeros((degree + 1, 3, 3))
    b[: len(b_poly)] = b_poly
    M[: len(M_poly)] = M_poly
    return b, M


def _make_cal(name, b_poly, M_poly, t_lo, t_hi, body_frame, method, b_sig=None, M_sig=None):
    b, M = _pad(b_poly, M_poly)
    bs = Ms = None
    if b_sig is not None:
        bs, Ms = _pad(b_sig, M_sig)
    return SensorCalibration(name, b, M, T_REF_C, float(t_lo), float(t_hi),
                             body_frame=body_frame, method=method, b_poly_sigma_nT=bs,
                             M_poly_sigma=Ms)


def _degree_for_span(span_C, max_degree=POLY_DEGREE):
    return int(min(max_degree, np.floor(span_C / DEGREE_STEP_C)))


def _joint_nonlinear(S: _Samples, degree, t_lo, t_hi, body_frame, init, source):
    """Levenberg-Marquardt on the flight parameterisation over vector and magnitude rows."""
    tau = max(abs(t_lo - T_REF_C), abs(t_hi - T_REF_C), 1.0)
    P = _powers((np.clip(S.T, t_lo, t_hi) - T_REF_C) / tau, degree)
    scale = tau ** np.arange(degree + 1)
    b0, M0 = init
    b0s = np.zeros((degree + 1, 3))
    M0s = np.zeros((degree + 1, 3, 3))
    k0 = min(len(b0), degree + 1)
    b0s[:k0] = b0[:k0] * scale[:k0, None]
    M0s[:k0] = M0[:k0] * scale[:k0, None, None]
    nb = 3 * (degree + 1)
    vec, mag = S.is_vec, ~S.is_vec
    Bv = S.ref[vec]
    Rm = S.norm[mag]

    if body_frame:
        def unpack(q):
            return q[:nb].reshape(degree + 1, 3), q[nb:].reshape(degree + 1, 3, 3)
        q0 = np.concatenate([b0s.ravel(), M0s.ravel()])
    else:
        def unpack(q):
            return q[:nb].reshape(degree + 1, 3), sym_from6(q[nb:].reshape(degree + 1, 6))
        q0 = np.concatenate([b0s.ravel(), sym_to6(M0s).ravel()])

    K = degree + 1
    Pv, Pm = P[vec], P[mag]
    xv, xm = S.x[vec], S.x[mag]
    nv, nm = len(Pv), len(Pm)

    PPv = (Pv[:, :, None] * Pv[:, None, :]).reshape(nv, K * K)

    def vector_normal(bp, Mp, jac):
        """Vector rows r = M(T)(x - b(T)) - B_ref: cost and, in closed form, J^T J, J^T r
        (params: b[k,l], then M[k,a,c]); no (3N x p) Jacobian is formed."""
        MT = (Pv @ Mp.reshape(K, 9)).reshape(nv, 3, 3)
        y = xv - Pv @ bp
        r = np.einsum("nij,nj->ni", MT, y) - Bv
        cost = float(np.sum(r * r))
        if not jac:
            return cost, None, None
        # M-M: delta_aa' sum_n P_k y_c P_m y_d
        Py = (Pv[:, :, None] * y[:, None, :]).reshape(nv, 3 * K)
        G = (Py.T @ Py).reshape(K, 3, K, 3)
        MM = np.einsum("kcmd,ab->kacmbd", G, np.eye(3)).reshape(9 * K, 9 * K)
        # b-b: sum_n P_k P_m (M^T M)[l,p]
        Q = np.einsum("nil,nip->nlp", MT, MT).reshape(nv, 9)
        bb = (PPv.T @ Q).reshape(K, K, 3, 3).transpose(0, 2, 1, 3).reshape(nb, nb)
        # M-b: -sum_n P_k P_m y_c M[a,l]
        YM = (y[:, :, None, None] * MT[:, None, :, :]).reshape(nv, 27)       # [c,a,l]
        Mb = -(PPv.T @ YM).reshape(K, K, 3, 3, 3).transpose(0, 3, 2, 1, 4).reshape(9 * K, nb)
        JTJ = np.block([[bb, Mb.T], [Mb, MM]])
        gM = (Py.T @ r).reshape(K, 3, 3).transpose(0, 2, 1).reshape(-1)       # [k,a,c]
        gb = -(Pv.T @ np.einsum("nil,ni->nl", MT, r)).reshape(-1)              # [k,l]
        return cost, JTJ, np.concatenate([gb, gM])

    def magnitude_rows(bp, Mp, jac):
        """Magnitude rows r = |M(T)(x - b(T))| - |B| and their Jacobian."""
        MT = (Pm @ Mp.reshape(K, 9)).reshape(nm, 3, 3)
        y = xm - Pm @ bp
        z = np.einsum("nij,nj->ni", MT, y)
        nz = np.linalg.norm(z, axis=1)
        r = nz - Rm
        if not jac:
            return r, None
        u = z / nz[:, None]
        v = np.einsum("ni,nij->nj", u, MT)                       # u^T M
        Jb = -(Pm[:, :, None] * v[:, None, :]).reshape(nm, nb)
        if body_frame:
            Jm = (Pm[:, :, None, None] * u[:, None, :, None]
                  * y[:, None, None, :]).reshape(nm, -1)
        else:
            Jm = (Pm[:, :, None] * _sym_grad(u, y)[:, None, :]).reshape(nm, -1)
        return r, np.hstack([Jb, Jm])

    n_par = len(q0)

    def model(q, jac):
        bp, Mp = unpack(q)
        cost, JTJ, g = 0.0, np.zeros((n_par, n_par)), np.zeros(n_par)
        if nv:
            c, A, gv = vector_normal(bp, Mp, jac)
            cost += c
            if jac:
                JTJ += A
                g += gv
        if nm:
            r, J = magnitude_rows(bp, Mp, jac)
            cost += float(r @ r)
            if jac:
                JTJ += J.T @ J
                g += J.T @ r
        return cost, (JTJ if jac else None), (g if jac else None), 3 * nv + nm

    q, cost, JTJ, lm = lm_solve(model, q0, max_iter=60)
    cov, cond, s2 = covariance(JTJ, cost, 3 * nv + nm)
    if not cond < MAX_REF_COND:
        raise InputError(source, f"joint temperature fit: the data do not determine the "
                                 f"degree-{degree} model (condition {cond:.3g}); temperature "
                                 f"spans {t_hi - t_lo:.1f} degC")
    sig = np.sqrt(np.maximum(np.diag(cov), 0))
    bp, Mp = unpack(q)
    bsig = sig[:nb].reshape(degree + 1, 3)
    if body_frame:
        Msig = sig[nb:].reshape(degree + 1, 3, 3)
    else:
        m6 = sig[nb:].reshape(degree + 1, 6)
        Msig = np.zeros((degree + 1, 3, 3))
        for k, (i, j) in enumerate(SYM_INDEX):
            Msig[:, i, j] = Msig[:, j, i] = m6[:, k]
    return (bp / scale[:, None], Mp / scale[:, None, None], bsig / scale[:, None],
            Msig / scale[:, None, None], lm)


def _fit_joint(name, S: _Samples, body_frame, degree, t_lo, t_hi, source):
    """Polynomial model fitted to all samples at once. Returns SensorCalibration."""
    if body_frame and S.is_vec.all():
        b, M, info = reference_fit(S.x, S.ref, S.T, degree, t_range_C=(t_lo, t_hi),
                                   source=source)
        return _make_cal(name, b, M, t_lo, t_hi, True, f"reference-vector joint, degree "
                         f"{degree}", info["b_poly_sigma_nT"], info["M_poly_sigma"])
    # initial values
    if body_frame:
        v = S.is_vec
        span = float(np.ptp(S.T[v]))
        dv = min(degree, _degree_for_span(span))
        b0, M0, _ = reference_fit(S.x[v], S.ref[v], S.T[v], dv, source=source)
    else:
        b0c, M0c, info = ellipsoid_fit(S.x, S.norm, source=source)
        b0, M0 = b0c[None, :], M0c[None]
        if degree == 0:
            return _make_cal(name, b0, M0, t_lo, t_hi, False, "ellipsoid, constant",
                             info["b_sigma_nT"][None], info["M_sigma"][None])
    b, M, bs, Ms, lm = _joint_nonlinear(S, degree, t_lo, t_hi, body_frame, (b0, M0), source)
    kind = "reference-vector + magnitude" if body_frame else "ellipsoid"
    return _make_cal(name, b, M, t_lo, t_hi, body_frame, f"{kind} joint, degree {degree}",
                     bs, Ms)


def _level_fits(S: _Samples, levels, body_frame, source, mask=None):
    """Constant calibration per temperature level -> list of (temp, b, M, b_sig, M_sig)."""
    out, dropped = [], []
    for lev in levels:
        idx = np.concatenate([s.index for s in lev])
        if mask is not None:
            idx = idx[mask[idx]]
        if len(idx) == 0:
            continue
        temp = float(np.mean(S.T[idx]))
        try:
            if body_frame:
                iv = idx[S.is_vec[idx]]
                if len(iv) == 0:
                    raise InputError(source, "no reference vectors at this level")
                b, M, info = reference_fit(S.x[iv], S.ref[iv], None, source=source)
                out.append((temp, b[0], M[0], info["b_poly_sigma_nT"][0],
                            info["M_poly_sigma"][0], len(iv)))
            else:
                b, M, info = ellipsoid_fit(S.x[idx], S.norm[idx], source=source)
                out.append((temp, b, M, info["b_sigma_nT"], info["M_sigma"], len(idx)))
        except InputError as e:
            dropped.append(f"level {temp:.1f} degC: {e.message}")
    return out, dropped


def _poly_over_levels(fits, degree, t_lo, t_hi):
    """Weighted polynomial of each coefficient over the level results."""
    temps = np.array([f[0] for f in fits])
    vals = np.array([np.concatenate([f[1], f[2].ravel()]) for f in fits])      # (L, 12)
    sigs = np.array([np.concatenate([f[3], f[4].ravel()]) for f in fits])
    sigs = np.where(sigs > 0, sigs, np.max(sigs) if np.max(sigs) > 0 else 1.0)
    tau = max(abs(t_lo - T_REF_C), abs(t_hi - T_REF_C), 1.0)
    V = _powers((temps - T_REF_C) / tau, degree)
    coef = np.zeros((degree + 1, 12))
    csig = np.zeros((degree + 1, 12))
    for c in range(12):
        w = 1.0 / sigs[:, c]
        A = V * w[:, None]
        sol, *_ = np.linalg.lstsq(A, vals[:, c] * w, rcond=None)
        cov = np.linalg.pinv(A.T @ A)
        dof = len(temps) - (degree + 1)
        chi2 = float(np.sum(((V @ sol - vals[:, c]) * w) ** 2))
        inflate = max(1.0, chi2 / dof) if dof > 0 else 1.0
        coef[:, c] = sol
        csig[:, c] = np.sqrt(np.maximum(np.diag(cov) * inflate, 0))
    scale = tau ** -np.arange(degree + 1)
    b = coef[:, :3] * scale[:, None]
    M = coef[:, 3:].reshape(degree + 1, 3, 3) * scale[:, None, None]
    bs = csig[:, :3] * scale[:, None]
    Ms = csig[:, 3:].reshape(degree + 1, 3, 3) * scale[:, None, None]
    return b, M, bs, Ms


def _fit_segments(name, S: _Samples, levels, body_frame, degree, t_lo, t_hi, source,
                  mask=None):
    fits, dropped = _level_fits(S, levels, body_frame, source, mask)
    if len(fits) < 2:
        raise InputError(source, f"segments method: {len(fits)} calibratable temperature "
                                 "level(s); at least 2 are needed"
                         + (f" ({'; '.join(dropped)})" if dropped else ""))
    deg = min(degree, len(fits) - 1)
    b, M, bs, Ms = _poly_over_levels(fits, deg, t_lo, t_hi)
    kind = "reference-vector" if body_frame else "ellipsoid"
    cal = _make_cal(name, b, M, t_lo, t_hi, body_frame,
                    f"{kind} per temperature segment, degree {deg} over {len(fits)} levels",
                    bs, Ms)
    return cal, fits, dropped


def _residuals(cal: SensorCalibration, S: _Samples):
    """(vector residuals (n_vec, 3), magnitude residuals (n,)) of a calibration on S."""
    z = cal.apply64(S.x, S.T)
    nz = np.linalg.norm(z, axis=1)
    return z[S.is_vec] - S.ref[S.is_vec], nz - S.norm


def _rms(a):
    a = np.asarray(a, float)
    return float(np.sqrt(np.mean(a ** 2))) if a.size else None


def _score(S: _Samples, cal):
    rv, rn = _residuals(cal, S)
    return {"rms_vector_nT": _rms(rv), "rms_norm_nT": _rms(rn), "n": int(S.n)}


# =======================================================================================
# Seed-001 known-vector method and seed-000 ellipsoid method, per temperature level
# =======================================================================================
def _floats(a):
    """JSON-able nested lists of float."""
    return np.asarray(a, float).tolist()


def _level_windows(S: _Samples, idx, file_offsets):
    """Where a level's samples come from: [file number, first time_s, last time_s] per
    run of consecutive used samples (file number: 0-based position in stats["files"]).
    The level holds exactly the samples in these windows that the fit used (usable, with
    a reference, no coil current)."""
    idx = np.sort(np.asarray(idx))
    if len(idx) == 0 or S.time_s is None:
        return []
    file_no = np.searchsorted(file_offsets, idx, side="right")
    cuts = np.nonzero((np.diff(idx) != 1) | (np.diff(file_no) != 0))[0] + 1
    return [[int(file_no[run[0]]), float(S.time_s[idx[run[0]]]), float(S.time_s[idx[run[-1]]])]
            for run in np.split(np.arange(len(idx)), cuts)]


def _subset_with_segments(S: _Samples, mask):
    """S restricted to mask, its segments re-indexed (samples outside mask dropped)."""
    new_index = np.cumsum(mask) - 1
    sub = S.subset(mask)
    for seg in S.segments:
        keep = seg.index[mask[seg.index]]
        if len(keep):
            sub.segments.append(Segment(index=new_index[keep], temp_C=seg.temp_C,
                                        temp_range_C=seg.temp_range_C,
                                        t_start_s=seg.t_start_s, t_stop_s=seg.t_stop_s,
                                        position=seg.position))
    return sub


def rotated_fit_M(fit):
    """M = W^-1 = (Q P R)^-1 of a RotatedFit and its 1-sigma (3, 3), propagated to first
    order from fit.cov (order k, e, delta, b): dM = -M dW M with dW/dk_i = E_ii P R,
    dW/de_j = Q dP/de_j R, dW/ddelta_j = Q P R [u_j]x (R_true = R exp([delta]x))."""
    M = np.linalg.inv(fit.W)
    PR = fit.P @ fit.R
    dW = []
    for i in range(3):
        E = np.zeros((3, 3))
        E[i, i] = 1.0
        dW.append(E @ PR)
    from generator.fit.analytic import _dP_de   # only the analytic method needs it (and scipy.optimize)

    dW += [fit.Q @ dP @ fit.R for dP in _dP_de(fit.e_rad)]
    for j in range(3):
        u = np.zeros(3)
        u[j] = 1.0
        dW.append(fit.W @ np.cross(np.eye(3), u))      # W [u]x: row i of [u]x is e_i x u
    J = np.zeros((9, 12))
    for c, d in enumerate(dW):
        J[:, c] = (-M @ d @ M).ravel()
    var = np.einsum("ic,cd,id->i", J, fit.cov, J)
    return M, np.sqrt(np.maximum(var, 0.0)).reshape(3, 3)


def _analytic_level(x_nT, ref_nT):
    """Seed 001 at one temperature: the plain model h = Q P B + b (for its residual) and
    the rotated one h = Q P R B + b. Returns (rotated fit, plain fit, M, M_sigma)."""
    from generator.fit.analytic import fit_analytic, fit_analytic_rotated

    plain = fit_analytic(x_nT, ref_nT)
    rot = fit_analytic_rotated(x_nT, ref_nT, analytic=plain)
    M, M_sig = rotated_fit_M(rot)
    return rot, plain, M, M_sig


def _analytic_level_stats(rot, plain):
    deg = np.degrees
    return {
        "k": _floats(rot.k), "k_sigma": _floats(rot.sigma_k),
        "e_deg": _floats(deg(rot.e_rad)), "e_sigma_deg": _floats(deg(rot.sigma_e_rad)),
        "R_rotvec_deg": _floats(deg(rot.rotvec_rad)),
        "R_rotvec_sigma_deg": _floats(deg(rot.sigma_rot_rad)),
        "R_angle_deg": float(deg(np.linalg.norm(rot.rotvec_rad))),
        "b_nT": _floats(rot.b_nT), "b_sigma_nT": _floats(rot.sigma_b_nT),
        "residual_rms_nT": float(rot.residual_rms_nT),
        "residual_rms_axis_nT": _floats(rot.residual_rms_axis_nT),
        "residual_rms_seed001_nT": float(plain.residual_rms_nT),
        "residual_rms_axis_seed001_nT": _floats(plain.residual_rms_axis_nT),
        "seed001_k": _floats(plain.k), "seed001_e_deg": _floats(deg(plain.e_rad)),
        "seed001_b_nT": _floats(plain.b_nT),
    }


def _file_offsets(per_file):
    return np.cumsum([f["used"] for f in per_file])


def _fit_sensor_analytic(name, S_all, datas, degree, say, notes, per_file, source):
    """The "analytic" method (see fit_sensor). Returns (cal, None), or (None, why) when
    it cannot be used and the caller falls back to auto."""
    S = _subset_with_segments(S_all, S_all.is_vec)
    my_notes = []
    no_vec = [f["source"] for f in per_file if f["used"] and "ref vectors" not in f["reference"]]
    if (~S_all.is_vec).any():
        my_notes.append(f"{int((~S_all.is_vec).sum())} magnitude-only samples not used by the "
                        "known-vector method" + (f" (files {', '.join(no_vec)})" if no_vec else ""))
    t_lo, t_hi = float(S.T.min()), float(S.T.max())
    span = t_hi - t_lo
    deg = min(degree, _degree_for_span(span))
    stats = {"files": per_file, "samples_used": int(S.n), "samples_vector": int(S.n),
             "samples_magnitude": 0, "temperature_range_C": [t_lo, t_hi],
             "degree": int(deg), "notes": notes,
             "model": "h = Q P R B + b per temperature level (seed 001 with a rotation R); "
                      "M = (Q P R)^-1; b, M polynomial over the levels, weighted by 1/sigma"}
    say(f"{name}: analytic known-vector method, {S.n} samples with reference vectors, "
        f"{t_lo:.1f}..{t_hi:.1f} degC")
    offsets = _file_offsets(per_file)
    if deg == 0:
        idx_all = np.arange(S.n)
        levels, stats["segments"] = [], {"found": len(S.segments), "levels": []}
        groups = [(None, idx_all)]
    else:
        levels, stats["segments"] = _temperature_levels(S, datas, deg)
        groups = [(lev, np.concatenate([s.index for s in lev])) for lev in levels]
    vec_index = np.nonzero(S_all.is_vec)[0]          # S index -> S_all index (for windows)
    fits, level_stats, dropped = [], [], []
    for lev, idx in groups:
        temp = float(np.mean(S.T[idx]))
        try:
            rot, plain, M, M_sig = _analytic_level(S.x[idx], S.ref[idx])
        except InputError as e:
            dropped.append(f"level {temp:.1f} degC: {e.message}")
            continue
        fits.append((temp, rot.b_nT, M, rot.sigma_b_nT, M_sig, len(idx)))
        entry = {"temp_C": temp, "samples": int(len(idx)),
                 "positions": sorted({int(s.position) for s in
                                      (lev if lev is not None else S.segments)}),
                 "windows_s": _level_windows(S_all, vec_index[idx], offsets)}
        entry.update(_analytic_level_stats(rot, plain))
        level_stats.append(entry)
    if dropped:
        my_notes.extend(dropped)
    if deg == 0:
        if not fits:
            return None, f"the known-vector fit failed: {'; '.join(dropped)}"
        _, b0, M0, b0_sig, M0_sig, _ = fits[0]
        b_sig, M_sig = _pad(b0_sig[None], M0_sig[None])
        cal = SensorCalibration.constant(name, b0, M0, T_REF_C, t_lo, t_hi, body_frame=True,
                                         method="analytic known-vector (seed 001 + R), constant",
                                         b_poly_sigma_nT=b_sig, M_poly_sigma=M_sig)
        stats["why"] = ("degree 0 requested" if degree == 0 else
                        f"reported temperature spans {span:.1f} degC: one constant fit of "
                        "all samples")
    else:
        if len(fits) < 2:
            return None, (f"{len(fits)} calibratable constant-temperature level(s) for a "
                          f"temperature span of {span:.1f} degC; the polynomial over levels "
                          "needs 2 or more" + (f" ({'; '.join(dropped)})" if dropped else ""))
        dl = min(deg, len(fits) - 1)
        b, M, bs, Ms = _poly_over_levels(fits, dl, t_lo, t_hi)
        cal = _make_cal(name, b, M, t_lo, t_hi, True,
                        f"analytic known-vector (seed 001 + R) per temperature level, degree "
                        f"{dl} over {len(fits)} levels", bs, Ms)
        stats["degree"] = int(dl)
    notes.extend(my_notes)
    stats["segments"]["level_fits"] = level_stats
    stats["fit"] = _score(S_all, cal)
    say(f"{name}: {cal.method}")
    cal.stats = stats
    return cal, None


def _fit_sensor_ellipsoid(name, S_all, datas, degree, say, notes, per_file, source):
    """The "ellipsoid" method (see fit_sensor): magnitudes only, per level."""
    n = S_all.n
    S = _Samples(S_all.x, S_all.T, np.full((n, 3), np.nan), S_all.norm, np.zeros(n, bool),
                 S_all.group, list(S_all.segments), time_s=S_all.time_s)
    t_lo, t_hi = float(S.T.min()), float(S.T.max())
    span = t_hi - t_lo
    deg = min(degree, _degree_for_span(span))
    stats = {"files": per_file, "samples_used": int(n), "samples_vector": 0,
             "samples_magnitude": int(n), "temperature_range_C": [t_lo, t_hi],
             "degree": int(deg), "notes": notes,
             "model": "|M (B~ - b)| = |B| per temperature level (seed 000 ellipsoid, M "
                      "symmetric: known up to a rotation); b, M polynomial over the levels"}
    if S_all.is_vec.any():
        notes.append(f"ellipsoid method: the reference vectors of {int(S_all.is_vec.sum())} "
                     "samples are used only through their magnitude")
    say(f"{name}: ellipsoid method, {n} samples, {t_lo:.1f}..{t_hi:.1f} degC")
    levels, stats["segments"] = _temperature_levels(S, datas, deg)
    offsets = _file_offsets(per_file)
    fits, level_stats, dropped = [], [], []
    for lev in levels:
        idx = np.concatenate([s.index for s in lev])
        temp = float(np.mean(S.T[idx]))
        try:
            b, M, info = ellipsoid_fit(S.x[idx], S.norm[idx], source=source)
        except InputError as e:
            dropped.append(f"level {temp:.1f} degC: {e.message}")
            continue
        fits.append((temp, b, M, info["b_sigma_nT"], info["M_sigma"], len(idx)))
        resid = np.linalg.norm((S.x[idx] - b) @ M.T, axis=1) - S.norm[idx]
        level_stats.append({
            "temp_C": temp, "samples": int(len(idx)),
            "positions": sorted({int(s.position) for s in lev}),
            "windows_s": _level_windows(S, idx, offsets),
            "b_nT": _floats(b), "b_sigma_nT": _floats(info["b_sigma_nT"]),
            "M": _floats(M), "M_sigma": _floats(info["M_sigma"]),
            "residual_rms_norm_nT": _rms(resid)})
    if dropped:
        notes.extend(dropped)
    if deg > 0 and len(fits) >= 2:
        dl = min(deg, len(fits) - 1)
        b, M, bs, Ms = _poly_over_levels(fits, dl, t_lo, t_hi)
        cal = _make_cal(name, b, M, t_lo, t_hi, False,
                        f"ellipsoid (magnitudes only) per temperature level, degree {dl} over "
                        f"{len(fits)} levels", bs, Ms)
        stats["degree"] = int(dl)
    else:
        if deg > 0:
            notes.append(f"ellipsoid method: {len(fits)} calibratable constant-temperature "
                         "level(s), the polynomial over levels needs 2; joint ellipsoid fit "
                         "of all samples instead")
        cal = _fit_joint(name, S, False, deg, t_lo, t_hi, source)
    stats["segments"]["level_fits"] = level_stats
    stats["fit"] = _score(S, cal)
    say(f"{name}: {cal.method}")
    cal.stats = stats
    return cal


# =======================================================================================
# Entry points
# =======================================================================================
def fit_sensor(name, datas, *, degree=POLY_DEGREE, progress=None,
               method="auto") -> SensorCalibration:
    """Temperature calibration of one sensor from all its files (list of FitData).

    degree: highest polynomial degree in temperature; the degree used is also limited to
    one per DEGREE_STEP_C of covered temperature span (a single temperature gives a
    constant calibration). Returns a SensorCalibration padded to POLY_DEGREE.

    method (FIT_METHODS):

    * "auto": reference vectors where the files carry them (held-out choice between the
      "joint" and "segments" temperature models), else magnitudes (ellipsoid). stats:
      files and exclusions, segments and levels found, the held-out comparison, the
      model chosen and why, and the fit RMS.
    * "analytic": seed 001 on the samples with reference vectors: per constant-
      temperature level the known-vector model with a rotation, h = Q P R B + b
      (fit_analytic_rotated), M = (Q P R)^-1 in the frame of the vectors; then a
      weighted polynomial of b and M over the levels. stats["segments"]["level_fits"]
      holds k, e, R, b with 1-sigma and the residual with and without R per level.
      Falls back to "auto" (stats["method_fallback"] says why) when no sample has a
      reference vector, or when a temperature-dependent fit finds fewer than 2 levels.
    * "ellipsoid": seed 000 from magnitudes only (|reference vector| where there is one),
      even where vectors exist: per level an ellipsoid fit, M symmetric (known only up to
      a rotation), then the polynomial over the levels.

    stats["method"] is the method used, stats["method_requested"] the one asked for.
    """
    if method not in FIT_METHODS:
        raise InputError(datas[0].source if datas else None,
                         f"fit: unknown method {method!r} (choose from "
                         f"{', '.join(FIT_METHODS)})")
    say = progress or (lambda msg: None)
    notes, per_file = [], []
    source = datas[0].source if datas else None
    S = _gather(name, datas, notes, per_file)
    fallback = None
    if method == "analytic":
        if S.is_vec.any():
            cal, fallback = _fit_sensor_analytic(name, S, datas, degree, say, notes,
                                                 per_file, source)
            if cal is not None:
                return _with_method(cal, "analytic", "analytic")
        else:
            fallback = ("no file carries reference vectors for this sensor: the known-vector "
                        "method needs them; fitted with auto")
        notes.append(f"analytic method not used: {fallback}")
        say(f"{name}: analytic method not used ({fallback})")
    elif method == "ellipsoid":
        cal = _fit_sensor_ellipsoid(name, S, datas, degree, say, notes, per_file, source)
        return _with_method(cal, "ellipsoid", "ellipsoid")
    cal = _fit_sensor_auto(name, S, datas, degree, say, notes, per_file, source)
    if fallback:
        cal.stats["method_fallback"] = fallback
    return _with_method(cal, method, "auto")


def _with_method(cal, requested, used):
    cal.stats["method_requested"] = requested
    cal.stats["method"] = used
    return cal


def _temperature_levels(S: _Samples, datas, deg):
    """Constant-temperature levels of the segments found in S (none for degree 0), and
    their description for stats."""
    quantum = max([temperature_quantum(d.temp_C) for d in datas] + [0.0])
    tol = max(2.0, 3.0 * quantum, DEGREE_STEP_C / 2)
    segs = S.segments
    levels = group_levels(segs, tol) if deg > 0 else []
    desc = {
        "found": len(segs),
        "levels": [{"temp_C": float(np.mean([s.temp_C for s in lev])),
                    "segments": len(lev),
                    "samples": int(sum(len(s.index) for s in lev)),
                    "positions": sorted({int(s.position) for s in lev})} for lev in levels],
    }
    return levels, desc


def _fit_sensor_auto(name, S, datas, degree, say, notes, per_file, source):
    """The "auto" method (see fit_sensor)."""
    body_frame = bool(S.is_vec.any())
    t_lo, t_hi = float(S.T.min()), float(S.T.max())
    span = t_hi - t_lo
    deg = min(degree, _degree_for_span(span))
    stats = {"files": per_file, "samples_used": int(S.n),
             "samples_vector": int(S.is_vec.sum()),
             "samples_magnitude": int((~S.is_vec).sum()),
             "temperature_range_C": [t_lo, t_hi], "degree": int(deg), "notes": notes}
    if body_frame and (~S.is_vec).any():
        notes.append("magnitude-only samples enter through |B| residuals; M stays in the "
                     "frame of the reference vectors")
    say(f"{name}: {S.n} samples, {t_lo:.1f}..{t_hi:.1f} degC, "
        f"{'reference vectors' if body_frame else 'magnitude only'}")

    # ---- temperature levels for the segments method
    levels, stats["segments"] = _temperature_levels(S, datas, deg)

    if deg == 0:
        cal = _fit_joint(name, S, body_frame, 0, t_lo, t_hi, source)
        stats["chosen"] = "constant"
        stats["why"] = ("degree 0 requested" if degree == 0 else
                        f"reported temperature spans {span:.1f} degC: a constant calibration "
                        f"(one polynomial degree per {DEGREE_STEP_C:g} degC of span)")
        stats["fit"] = _score(S, cal)
        cal.stats = stats
        return cal

    seg_ok = len(levels) >= 2
    if not seg_ok:
        stats["segments"]["unavailable"] = (f"{len(levels)} constant-temperature level(s) "
                                            "found; the segments method needs 2 or more")
    # ---- held-out comparison
    groups = np.unique(S.group)
    k = min(CV_FOLDS, len(groups))
    methods = ["joint"] + (["segments"] if seg_ok else [])
    held = {m: {"vec": [], "norm": [], "failed": []} for m in methods}
    if seg_ok and k >= 2:
        fold_of = {g: i % k for i, g in enumerate(groups)}
        fold = np.array([fold_of[g] for g in S.group])
        for f in range(k):
            train = fold != f
            Str, Ste = S.subset(train), S.subset(~train)
            lo, hi = float(Str.T.min()), float(Str.T.max())
            dgf = min(deg, _degree_for_span(hi - lo))
            for m in methods:
                try:
                    if m == "joint":
                        c = _fit_joint(name, Str, body_frame, dgf, lo, hi, source)
                    else:
                        c, _, _ = _fit_segments(name, S, levels, body_frame, dgf, lo, hi,
                                                source, mask=train)
                except InputError as e:
                    held[m]["failed"].append(f"fold {f + 1}: {e.message}")
                    continue
                rv, rn = _residuals(c, Ste)
                held[m]["vec"].append(rv)
                held[m]["norm"].append(rn)
        say(f"{name}: held-out comparison over {k} folds done")
    kinds = sorted({f["holdout_groups"] for f in per_file})
    scheme = "leave-positions-out" if kinds == ["static positions"] else \
        "held-out " + " and ".join(kinds)
    holdout = {"scheme": f"{scheme}, {k} folds",
               "metric": "vector RMS per axis" if body_frame else "|B| RMS"}
    scores = {}
    for m in methods:
        h = held[m]
        entry = {"failed_folds": h["failed"]}
        if h["norm"] and not h["failed"]:
            entry["rms_vector_nT"] = _rms(np.concatenate(h["vec"])) if body_frame else None
            entry["rms_norm_nT"] = _rms(np.concatenate(h["norm"]))
            scores[m] = entry["rms_vector_nT"] if body_frame else entry["rms_norm_nT"]
        holdout[m] = entry
    if scores:
        chosen = min(scores, key=scores.get)
        why = "smaller held-out error: " + ", ".join(f"{m} {v:.2f} nT" for m, v in
                                                      scores.items())
    else:
        chosen = "joint"
        why = ("segments method not available" if not seg_ok else
               "held-out comparison not possible") + "; joint fit of all samples"
    stats["holdout"] = holdout
    stats["chosen"] = chosen
    stats["why"] = why

    # ---- final fit on everything with the chosen method
    if chosen == "segments":
        cal, fits, dropped = _fit_segments(name, S, levels, body_frame, deg, t_lo, t_hi,
                                           source)
        stats["segments"]["level_fits"] = [
            {"temp_C": f[0], "samples": int(f[5]), "b_nT": [float(v) for v in f[1]],
             "b_sigma_nT": [float(v) for v in f[3]]} for f in fits]
        if dropped:
            notes.extend(dropped)
    else:
        cal = _fit_joint(name, S, body_frame, deg, t_lo, t_hi, source)
    stats["fit"] = _score(S, cal)
    say(f"{name}: {cal.method}; held-out winner {chosen}")
    cal.stats = stats
    return cal


def fit_unit(unit, telemetries, progress=None, method="auto") -> dict:
    """Fit every sensor of the unit from all telemetry files jointly.

    Each file contributes what it carries: reference vectors -> reference-vector rows,
    else ref_norm_nT (or the unit's lab_field_nT) -> magnitude rows. method: one of
    FIT_METHODS, see fit_sensor. Returns {sensor name: SensorCalibration}. Raises
    InputError when a sensor cannot be fitted or the method is unknown.
    """
    from generator.io import telemetry_csv as _telemetry
    if method not in FIT_METHODS:
        raise InputError(unit.path, f"fit: unknown method {method!r} (choose from "
                                    f"{', '.join(FIT_METHODS)})")
    if not telemetries:
        raise InputError(unit.path, "fit: no telemetry files given")
    pre = [(_telemetry.preprocess(tel, unit), tel) for tel in telemetries]
    out = {}
    for s in unit.sensors:
        datas = [fit_data_from(tel, data[s.name], unit) for data, tel in pre if s.name in data]
        if not datas:
            raise InputError(telemetries[0].path, f"fit: no file has data of sensor '{s.name}'")
        out[s.name] = fit_sensor(s.name, datas, progress=progress, method=method)
    return out
