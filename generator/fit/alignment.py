"""Agreement of the body and boom magnetometers: the alignment H (seed 000, eq. 2-3).

After the boom deploys, its board is slightly turned against the body. With calibrated
readings of the body reference sensor B1 (body frame) and of a boom sensor B2 (boom
frame) taken at the same instants, find the orthogonal H (boom -> body) minimising

    Phi(H) = sum_n w_n |B1_n - H B2_n|^2                                   [3]

This is Wahba's problem: with the attitude-profile matrix  B = sum_n w_n B1_n B2_n^T
and its SVD B = U S V^T,  H = U diag(1, 1, det(U V^T)) V^T.

Uncertainty. Write the estimate as H = exp([d]x) H_true, d a small rotation vector in
body axes. Linearising the residual r_n = B1_n - H B2_n in d gives r_n = e_n + [v_n]x d
(v_n = H B2_n, e_n the measurement noise of both sensors), so with isotropic noise of
unit-weight variance s^2 per axis the Fisher information is

    F = (1/s^2) sum_n w_n (|v_n|^2 I - v_n v_n^T)   ( = (tr(B H^T) I - B H^T)/s^2 )

and cov(d) = F^-1; s^2 is estimated from the residual scatter, sum w |r|^2 / (3N - 3).
That counts the N samples as independent. A residual that drifts with the samples (a
calibration that does not hold in this file: a reference sensor without temperature, an
effect the model lacks; a disturbance) is not N independent samples: d is driven by the
score g_n = w_n v_n x r_n (the gradient of Phi; its sum is zero at the optimum), and its
variance is F^-1 Var(sum g_n) F^-1, larger than the white-noise s^2 F0^-1 by the long-run
variance factor of g. That factor is estimated by non-overlapping batch means
(`long_run_inflation`: floor(sqrt(N)) consecutive batches, the sum of the squared batch
sums over the sum of the squared samples, at least 1); cov_stat is s^2 F0^-1 times it
(`correlation_inflation`, 1 for a white residual). It is the score's correlation that
counts, not the residual's (a residual whose own lag-1 correlation is small can still
carry a slow component along v that moves H), and batch means, not the AR(1) model of
the sensor fits (fit.reference._correlation_inflation): the score is white sensor noise
plus a slow drift, whose lag-1 correlation is the mixture's, moderate, while its long-run
variance is the drift's. Measured on review #19's unit "eight" (RM3100 reference without
temperature, seeds 5..12, error m = sqrt(d^T cov^-1 d) against the simulated truth,
chi_3: 3.37 at 99 %, mean m^2 3): white-noise sigma m 4.5..11.4 (mean m^2 68.5); AR(1)
factor 4..28, m 1.6..4.4 (mean m^2 6.6); batch means 29..42, m 0.9..2.2 (mean m^2 2.2).
Rows of cov are body axes; `sigma_rad` is its per-axis 1-sigma, `sigma_angle_deg` the
1-sigma of the rotation angle (cov projected on the rotation axis). An optional extra
covariance (e.g. from the calibrations' own uncertainty, see `calibration_rotation_cov`)
is added to give the total.

Figures of merit (seed 000), before (H = I) and after:
* per axis, the difference of the normalised projections B1/|B1| - H B2/|B2|, mean of
  its absolute value and its maximum, in % (seed: <= 0.5 % after);
* the angle between B1 and H B2, mean and max, deg (seed: <= 0.07 deg after).

`align_boom(unit, tel, calibrations)` does the whole step on a telemetry file taken with
the boom deployed (e.g. rotation.csv): calibrated fields of every sensor, H fitted from the
reference sensor (unit.boom_reference) and the boom sensor of the same part, the figures
for every boom sensor against the reference and against its same-part body partner.
The jig calibrations of boom sensors are in the jig (body) frame: M maps a boom sensor's
reading to the frame its board had in the jig, which after deployment is the boom frame,
turned by H against the body.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from generator.errors import InputError

# Seed 000 conclusions: after the agreement algorithm the normalised projections differ
# by no more than 0.5 % and the vectors by no more than 0.07 deg.
SEED_PROJ_DIFF_PCT = 0.5
SEED_ANGLE_DEG = 0.07

MIN_SAMPLES = 3
# note the widening when the score's drift more than doubles the variance (rho > 1/3):
# below that the sigma moves by less than 1.42x, within what one reads from a sigma
CORRELATION_NOTE = 2.0
# batch means need a few batches: floor(sqrt(16)) = 4
MIN_BATCH_SAMPLES = 16
MIN_SPREAD_DEG = 1.0


# =======================================================================================
# Small rotation helpers
# =======================================================================================
def rotvec_from_matrix(R) -> np.ndarray:
    """Rotation vector (rad) of a rotation matrix."""
    return Rotation.from_matrix(np.asarray(R, float)).as_rotvec()


def matrix_from_rotvec(rotvec_rad) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(rotvec_rad, float)).as_matrix()


def rotation_error_rad(H_est, H_ref) -> np.ndarray:
    """d with H_est = exp([d]x) H_ref: the error of H_est in body axes (rad), the same
    convention as AlignmentResult.cov_rad2."""
    return rotvec_from_matrix(np.asarray(H_est, float) @ np.asarray(H_ref, float).T)


def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


# =======================================================================================
# Figures of merit
# =======================================================================================
def angle_between_deg(a, b) -> np.ndarray:
    """Angle between rows of a and b (deg), by atan2 (accurate for small angles)."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    c = np.linalg.norm(np.cross(a, b), axis=-1)
    d = np.einsum("...i,...i->...", a, b)
    return np.degrees(np.arctan2(c, d))


def figures_of_merit(B1_nT, B2_nT, H=None) -> dict:
    """The seed's agreement figures of B1 (body) and H B2 (H = I: 'before').

    Returns {"proj_diff_mean_pct": [x, y, z], "proj_diff_max_pct": [x, y, z],
    "angle_mean_deg", "angle_max_deg", "angle_rms_deg", "angle_p95_deg", "n"}; the
    projection difference is B1/|B1| - H B2/|B2| per body axis, in % (mean of |.|, max |.|).
    """
    B1 = np.asarray(B1_nT, float)
    B2 = np.asarray(B2_nT, float)
    if H is not None:
        B2 = B2 @ np.asarray(H, float).T
    u1 = B1 / np.linalg.norm(B1, axis=1, keepdims=True)
    u2 = B2 / np.linalg.norm(B2, axis=1, keepdims=True)
    dp = np.abs(u1 - u2) * 100.0
    ang = angle_between_deg(B1, B2)
    return {
        "proj_diff_mean_pct": [float(v) for v in dp.mean(axis=0)],
        "proj_diff_max_pct": [float(v) for v in dp.max(axis=0)],
        "angle_mean_deg": float(ang.mean()),
        "angle_max_deg": float(ang.max()),
        "angle_rms_deg": float(np.sqrt(np.mean(ang ** 2))),
        "angle_p95_deg": float(np.percentile(ang, 95)),
        "n": int(B1.shape[0]),
    }


def figures_table(before: dict, after: dict, title: str = "") -> str:
    """Markdown table: figure | before | after | seed (after)."""
    rows = [f"{title}" if title else None,
            "| figure | before | after | seed 000 (after) |",
            "|---|---:|---:|---:|"]
    rows = [r for r in rows if r is not None]
    for i, ax in enumerate("xyz"):
        rows.append(f"| normalised projection diff {ax}, mean % | "
                    f"{before['proj_diff_mean_pct'][i]:.4f} | "
                    f"{after['proj_diff_mean_pct'][i]:.4f} | <= {SEED_PROJ_DIFF_PCT} |")
    for i, ax in enumerate("xyz"):
        rows.append(f"| normalised projection diff {ax}, max % | "
                    f"{before['proj_diff_max_pct'][i]:.4f} | {after['proj_diff_max_pct'][i]:.4f} |"
                    f" <= {SEED_PROJ_DIFF_PCT} |")
    rows.append(f"| angle between vectors, mean deg | {before['angle_mean_deg']:.4f} | "
                f"{after['angle_mean_deg']:.4f} | <= {SEED_ANGLE_DEG} |")
    rows.append(f"| angle between vectors, max deg | {before['angle_max_deg']:.4f} | "
                f"{after['angle_max_deg']:.4f} | <= {SEED_ANGLE_DEG} |")
    return "\n".join(rows)


# =======================================================================================
# The fit
# =======================================================================================
@dataclass
class AlignmentResult:
    """H (boom -> body) with its uncertainty and the seed's figures before and after."""

    H: np.ndarray                      # (3, 3) orthogonal, det +1, boom -> body
    rotvec_rad: np.ndarray             # rotation vector of H (body axes)
    angle_deg: float                   # rotation angle of H
    cov_stat_rad2: np.ndarray          # (3, 3) covariance of d (H = exp([d]x) H_true), noise
    cov_rad2: np.ndarray               # (3, 3) total: cov_stat + extra (calibrations)
    residual_sigma_nT: float           # unit-weight residual scatter per axis (sqrt s^2)
    residual_rms_axis_nT: np.ndarray   # (3,) RMS of B1 - H B2 per body axis
    n_samples: int
    spread_deg: float                  # RMS angle of the field directions about their main one
    before: dict                       # figures_of_merit with H = I
    after: dict                        # figures_of_merit with H
    noise_floor_angle_mean_deg: float  # mean angle expected from the residual noise alone
    notes: list = field(default_factory=list)
    correlation_inflation: float = 1.0  # variance factor of cov_stat for the score's drift

    @property
    def sigma_rad(self) -> np.ndarray:
        """1-sigma per body axis of the small rotation error (rad)."""
        return np.sqrt(np.diag(self.cov_rad2))

    @property
    def sigma_deg(self) -> np.ndarray:
        return np.degrees(self.sigma_rad)

    @property
    def sigma_stat_deg(self) -> np.ndarray:
        return np.degrees(np.sqrt(np.diag(self.cov_stat_rad2)))

    @property
    def sigma_angle_deg(self) -> float:
        """1-sigma of the rotation angle of H (covariance projected on its axis)."""
        a = self.rotvec_rad
        n = np.linalg.norm(a)
        if n == 0.0:
            # no preferred axis: the largest per-axis sigma
            return float(np.degrees(np.sqrt(np.linalg.eigvalsh(self.cov_rad2).max())))
        a = a / n
        return float(np.degrees(np.sqrt(a @ self.cov_rad2 @ a)))

    def table(self, title: str = "") -> str:
        axis = self.rotvec_rad / max(np.linalg.norm(self.rotvec_rad), 1e-300)
        head = (f"H: rotation {self.angle_deg:.4f} +- {self.sigma_angle_deg:.4f} deg about "
                f"{np.round(axis, 4).tolist()}"
                f"; per-axis 1-sigma {np.round(self.sigma_deg, 5).tolist()} deg; "
                f"N = {self.n_samples}, residual {self.residual_sigma_nT:.1f} nT/axis; "
                f"noise-floor mean angle {self.noise_floor_angle_mean_deg:.4f} deg")
        return (title + "\n" if title else "") + head + "\n" + figures_table(self.before,
                                                                              self.after)

    def to_dict(self) -> dict:
        return {
            "H_boom_to_body": self.H.tolist(),
            "rotvec_deg": np.degrees(self.rotvec_rad).tolist(),
            "angle_deg": self.angle_deg,
            "sigma_angle_deg": self.sigma_angle_deg,
            "sigma_axis_deg": self.sigma_deg.tolist(),
            "sigma_axis_stat_deg": self.sigma_stat_deg.tolist(),
            "cov_rad2": self.cov_rad2.tolist(),
            "correlation_inflation": self.correlation_inflation,
            "residual_sigma_nT": self.residual_sigma_nT,
            "residual_rms_axis_nT": self.residual_rms_axis_nT.tolist(),
            "n_samples": self.n_samples,
            "spread_deg": self.spread_deg,
            "before": self.before,
            "after": self.after,
            "seed": {"proj_diff_max_pct": SEED_PROJ_DIFF_PCT, "angle_max_deg": SEED_ANGLE_DEG},
            "noise_floor_angle_mean_deg": self.noise_floor_angle_mean_deg,
            "notes": list(self.notes),
        }


def _check_pair(B1, B2, weights, source, min_samples):
    B1 = np.asarray(B1, dtype=float)
    B2 = np.asarray(B2, dtype=float)
    for name, a in (("B_body_nT", B1), ("B_boom_nT", B2)):
        if a.ndim != 2 or a.shape[1] != 3:
            raise InputError(source, f"alignment: {name} must have shape (N, 3), got {a.shape}")
    if B1.shape != B2.shape:
        raise InputError(source, f"alignment: B_body_nT {B1.shape} and B_boom_nT {B2.shape} "
                                 "must hold the same samples")
    n = B1.shape[0]
    if n < min_samples:
        raise InputError(source, f"alignment: {n} sample pair(s); at least {min_samples} "
                                 "needed to fit H and its uncertainty")
    for name, a in (("B_body_nT", B1), ("B_boom_nT", B2)):
        bad = ~np.isfinite(a).all(axis=1)
        if bad.any():
            raise InputError(source, f"alignment: {name} has {int(bad.sum())} non-finite "
                                     f"row(s), first at index {int(np.argmax(bad))}; drop "
                                     "unusable samples first")
        zero = np.linalg.norm(a, axis=1) == 0.0
        if zero.any():
            raise InputError(source, f"alignment: {name} has {int(zero.sum())} zero vector(s), "
                                     f"first at index {int(np.argmax(zero))}")
    if weights is None:
        w = np.ones(n)
    else:
        w = np.asarray(weights, dtype=float)
        if w.shape != (n,):
            raise InputError(source, f"alignment: weights must have shape ({n},), got {w.shape}")
        if not np.isfinite(w).all() or (w < 0).any() or w.sum() <= 0:
            raise InputError(source, "alignment: weights must be finite, >= 0 and not all zero")
    return B1, B2, w


def direction_spread_deg(B_nT, weights=None):
    """(spread, main direction): the RMS angle (deg, small-angle) of the field directions
    about their principal direction, sqrt(1 - lambda_max) of the weighted scatter matrix
    of unit vectors. Near 0: all vectors parallel."""
    B = np.asarray(B_nT, float)
    w = np.ones(B.shape[0]) if weights is None else np.asarray(weights, float)
    u = B / np.linalg.norm(B, axis=1, keepdims=True)
    S = (u * w[:, None]).T @ u / w.sum()
    lam, vec = np.linalg.eigh(S)
    spread = np.sqrt(max(0.0, 1.0 - lam[-1]))
    return float(np.degrees(np.arcsin(min(1.0, spread)))), vec[:, -1]


def long_run_inflation(g) -> float:
    """Long-run variance factor of a series g (N, k) in time order: Var(sum g) over the
    white-noise value sum |g - mean|^2, by non-overlapping batch means with floor(sqrt(N))
    batches (the usual batch count: each batch long against the correlation, enough of
    them for the estimate). At least 1 (below is the estimate's noise for a white g, whose
    factor has relative sd sqrt(2 / (k B))); 1 for fewer than MIN_BATCH_SAMPLES samples."""
    g = np.asarray(g, float)
    g = g.reshape(len(g), -1) - np.mean(g, axis=0).reshape(1, -1)
    den = float(np.sum(g * g))
    if len(g) < MIN_BATCH_SAMPLES or den <= 0.0:
        return 1.0
    sums = np.array([b.sum(axis=0) for b in np.array_split(g, int(np.sqrt(len(g))))])
    return max(1.0, float(np.sum(sums * sums)) / den)


def wahba_svd(B1_nT, B2_nT, weights=None) -> np.ndarray:
    """H minimising sum w |B1 - H B2|^2 over rotations: U diag(1, 1, det(U V^T)) V^T."""
    B1 = np.asarray(B1_nT, float)
    B2 = np.asarray(B2_nT, float)
    w = np.ones(B1.shape[0]) if weights is None else np.asarray(weights, float)
    Bp = (B1 * w[:, None]).T @ B2
    U, _, Vt = np.linalg.svd(Bp)
    d = np.linalg.det(U @ Vt)
    return U @ np.diag([1.0, 1.0, d]) @ Vt


def fit_H(B_body_nT, B_boom_nT, weights=None, *, extra_cov_rad2=None,
          min_samples: int = MIN_SAMPLES, min_spread_deg: float = MIN_SPREAD_DEG,
          source=None) -> AlignmentResult:
    """Fit the boom -> body alignment H from simultaneous calibrated field pairs.

    B_body_nT (N, 3): reference sensor, body frame; B_boom_nT (N, 3): boom sensor, boom
    frame; weights (N,) optional relative weights (e.g. 1/variance). extra_cov_rad2: a
    (3, 3) covariance (body axes, rad^2) added to the statistical one (calibration
    uncertainty). Raises InputError on too few samples, non-finite or zero vectors, bad
    weights, or field directions too close to one direction (the rotation about it is
    then undetermined).
    """
    B1, B2, w = _check_pair(B_body_nT, B_boom_nT, weights, source, min_samples)
    n = B1.shape[0]
    notes = []
    for name, a in (("B_body_nT", B1), ("B_boom_nT", B2)):
        spread, axis = direction_spread_deg(a, w)
        if spread < min_spread_deg:
            raise InputError(source, (
                f"alignment: the {n} {name} vectors all lie within {spread:.3g} deg (RMS) of "
                f"one direction {np.round(axis, 3).tolist()} (need >= {min_spread_deg} deg): "
                "the rotation about that direction is undetermined; use data in which the "
                "field takes several directions (e.g. a rotation campaign)"))
    spread = min(direction_spread_deg(B1, w)[0], direction_spread_deg(B2, w)[0])

    H = wahba_svd(B1, B2, w)
    v = B2 @ H.T
    r = B1 - v
    dof = 3 * n - 3
    s2 = float(np.sum(w[:, None] * r ** 2) / dof)
    vv = np.einsum("n,ni,nj->ij", w, v, v)
    F0 = np.trace(vv) * np.eye(3) - vv            # sum w (|v|^2 I - v v^T)
    cond = np.linalg.cond(F0)
    if not np.isfinite(cond) or cond > 1e12:
        raise InputError(source, "alignment: the information matrix is singular (field "
                                 "directions do not span enough of the sphere): the "
                                 "rotation about the common direction is undetermined")
    # the score's serial correlation: a drifting residual is fewer independent samples
    infl = long_run_inflation(w[:, None] * np.cross(v, r))
    if infl > CORRELATION_NOTE:
        notes.append(f"the residual drifts along the samples (batch means of the fit's "
                     f"score: {infl:.1f}x the variance of a white residual): the {n} samples "
                     f"count as {n / infl:.0f} independent ones, sigma widened "
                     f"x{np.sqrt(infl):.1f}; the calibrations do not hold exactly in this "
                     "file (e.g. a sensor without temperature)")
    cov_stat = s2 * infl * np.linalg.inv(F0)
    cov_stat = 0.5 * (cov_stat + cov_stat.T)
    cov = cov_stat.copy()
    if extra_cov_rad2 is not None:
        extra = np.asarray(extra_cov_rad2, float)
        if extra.shape != (3, 3) or not np.isfinite(extra).all():
            raise InputError(source, "alignment: extra_cov_rad2 must be a finite (3, 3) matrix")
        cov = cov + 0.5 * (extra + extra.T)
        notes.append("sigma includes the calibrations' rotation uncertainty")
    if s2 == 0.0:
        notes.append("residual is exactly zero: noise-free input, sigma is zero")

    # mean angle from noise alone: the residual component perpendicular to the field has
    # two axes of variance s^2 each -> Rayleigh mean s sqrt(pi/2), relative to |B|
    Bmag = np.sqrt(np.mean(np.sum(B1 ** 2, axis=1)))
    floor = float(np.degrees(np.sqrt(s2) * np.sqrt(np.pi / 2) / Bmag))

    rv = rotvec_from_matrix(H)
    return AlignmentResult(
        H=H, rotvec_rad=rv, angle_deg=float(np.degrees(np.linalg.norm(rv))),
        cov_stat_rad2=cov_stat, cov_rad2=cov,
        residual_sigma_nT=float(np.sqrt(s2)),
        residual_rms_axis_nT=np.sqrt(np.mean(r ** 2, axis=0)),
        n_samples=int(n), spread_deg=float(spread),
        before=figures_of_merit(B1, B2, None), after=figures_of_merit(B1, B2, H),
        noise_floor_angle_mean_deg=floor, notes=notes, correlation_inflation=float(infl))


# =======================================================================================
# Calibration uncertainty -> rotation uncertainty
# =======================================================================================
def calibration_rotation_cov(cal, temp_C) -> np.ndarray:
    """Covariance (rad^2, the sensor's calibrated frame) of the small rotation carried by
    the uncertainty of M(T): the antisymmetric part of dM M^-1, with dM from
    cal.M_poly_sigma evaluated at the mean temperature (coefficients taken independent).
    Zero when the calibration has no sigma."""
    if cal.M_poly_sigma is None:
        return np.zeros((3, 3))
    dT = float(np.mean(cal.dT(np.asarray(temp_C, float))))
    powers = dT ** np.arange(cal.M_poly_sigma.shape[0])
    var_M = np.einsum("k,kij->ij", powers ** 2, np.asarray(cal.M_poly_sigma, float) ** 2)
    Minv = np.linalg.inv(cal.M_at(np.array([dT + cal.t_ref_C]))[0])
    # omega = vee((E - E^T)/2), E = dM Minv; propagate element variances linearly
    cov = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            if var_M[i, j] == 0.0:
                continue
            dM = np.zeros((3, 3))
            dM[i, j] = 1.0
            E = dM @ Minv
            A = 0.5 * (E - E.T)
            g = np.array([A[2, 1], A[0, 2], A[1, 0]])
            cov += var_M[i, j] * np.outer(g, g)
    return cov


# =======================================================================================
# The whole step on a unit's telemetry
# =======================================================================================
@dataclass
class BoomAlignment:
    reference: str                     # body-frame reference sensor (unit.boom_reference)
    fit_sensor: str                    # boom sensor H was fitted from
    result: AlignmentResult            # the fit (H, sigma, figures of the fit pair)
    pairs: dict                        # "body/boom" -> {"before": figs, "after": figs} with H
    cross_checks: dict                 # "body/boom" -> AlignmentResult fitted on that pair
    fields_nT: dict                    # sensor -> (N, 3) calibrated field (own frame) used
    mask: np.ndarray                   # (N,) samples used
    notes: list = field(default_factory=list)

    @property
    def H(self) -> np.ndarray:
        return self.result.H

    def table(self) -> str:
        out = [self.result.table(f"### H fitted from {self.reference} / {self.fit_sensor}")]
        for key, p in self.pairs.items():
            if key == f"{self.reference}/{self.fit_sensor}":
                continue                      # the fit pair: in the table above
            out.append(figures_table(p["before"], p["after"],
                                     f"### {key} with H from {self.reference}/{self.fit_sensor}"))
        for key, r in self.cross_checks.items():
            out.append(f"cross-check: H fitted from {key} alone: angle {r.angle_deg:.4f} +- "
                       f"{r.sigma_angle_deg:.4f} deg; differs from the main H by "
                       f"{np.degrees(np.linalg.norm(rotation_error_rad(r.H, self.H))):.4f} deg")
        out.extend(f"note: {n}" for n in self.notes)
        return "\n\n".join(out)

    def to_dict(self) -> dict:
        return {"reference": self.reference, "fit_sensor": self.fit_sensor,
                "result": self.result.to_dict(), "pairs": self.pairs,
                "cross_checks": {k: v.to_dict() for k, v in self.cross_checks.items()},
                "n_samples": int(self.mask.sum()), "notes": list(self.notes)}


def _coil_currents(tel):
    from generator.fit.coils import coil_columns
    names = coil_columns(tel)
    if not names:
        return [], None
    return names, np.column_stack([tel.columns[c] for c in names])


def calibrated_fields(unit, tel, calibrations, coil_K_nT_per_A=None, data=None,
                      mask_of=None):
    """{sensor: (N, 3) calibrated field in the sensor's own frame (body or boom)} and the
    common usable mask of the sensors named in mask_of (default: every calibrated one).
    coil_K_nT_per_A: optional {sensor: (3, ncoil)} subtracted before M with the file's
    coil_*_A columns (sorted by name); without it samples with any non-zero coil current
    are left out. data: preprocess(tel, unit) if already done. A sensor without a
    temperature (temperature = false) is calibrated at its constant model's t_ref (the
    fit's stand-in, telemetry.SensorData.temp_or), not at NaN."""
    if data is None:
        from generator.io import telemetry_csv as _telemetry
        data = _telemetry.preprocess(tel, unit)
    coil_names, coil_A = _coil_currents(tel)
    mask = np.ones(tel.n, dtype=bool)
    out = {}
    for s in unit.sensors:
        if s.name not in calibrations:
            continue
        sd = data[s.name]
        x = sd.field_frame_nT.copy()
        if coil_A is not None:
            K = None if coil_K_nT_per_A is None else coil_K_nT_per_A.get(s.name)
            if K is not None:
                K = np.asarray(K, float)
                if K.shape != (3, len(coil_names)):
                    raise InputError(tel.path, f"alignment: K for {s.name} has shape {K.shape}, "
                                               f"the file has coils {coil_names}")
                x = x - np.nan_to_num(coil_A) @ K.T
        out[s.name] = calibrations[s.name].apply64(
            x, sd.temp_or(calibrations[s.name].t_ref_C))
        if mask_of is None or s.name in mask_of:
            mask &= sd.usable & np.isfinite(out[s.name]).all(axis=1)
    if coil_A is not None and coil_K_nT_per_A is None:
        mask &= np.all(np.nan_to_num(coil_A, nan=1.0) == 0.0, axis=1)
    return out, mask


def align_boom(unit, tel, calibrations, *, fit_sensor=None, coil_K_nT_per_A=None,
               include_calibration_sigma: bool = True, min_spread_deg: float = MIN_SPREAD_DEG
               ) -> BoomAlignment:
    """Fit H from a telemetry file taken with the boom deployed (e.g. rotation.csv).

    calibrations: {sensor: SensorCalibration} (the jig calibrations: boom sensors map to
    their board's frame). H is fitted from the reference sensor (unit.boom_reference) and
    fit_sensor (default: the boom sensor of the reference's part, else the least noisy
    boom sensor); every boom sensor gets this H (one board). Figures before/after are
    given for each boom sensor against the reference and, for a boom sensor of another
    part, against the first body sensor of its own part; those pairs are also fitted
    alone as cross-checks.
    """
    src = tel.path
    ref = unit.boom_reference
    booms = [s for s in unit.sensors if s.frame == "boom"]
    if not booms:
        raise InputError(unit.path, "alignment: the unit has no boom sensors")
    if ref is None:
        raise InputError(unit.path, "alignment: the unit has no [boom] reference sensor")
    ref_spec = unit.sensor(ref)
    if fit_sensor is None:
        same = [s for s in booms if s.part == ref_spec.part]
        pool = same or booms
        fit_sensor = min(pool, key=lambda s: (s.noise_nT or np.inf)).name
    elif fit_sensor not in [s.name for s in booms]:
        raise InputError(unit.path, f"alignment: {fit_sensor!r} is not a boom sensor")
    needed = {ref, fit_sensor}
    missing = [n for n in needed if n not in calibrations]
    if missing:
        raise InputError(src, f"alignment: no calibration for {', '.join(sorted(missing))}")

    notes = []
    for n in sorted(needed):
        if not calibrations[n].body_frame:
            notes.append(f"{n}: calibration is magnitude-only (M symmetric, its rotation "
                         "unknown): H then also absorbs that sensor's unknown rotation")
    from generator.io import telemetry_csv as _telemetry
    data = _telemetry.preprocess(tel, unit)
    # H from the samples both sensors of the fit have (another sensor's gaps, e.g. no
    # reading at all, do not remove them); each cross-check pair uses its own
    fields, mask = calibrated_fields(unit, tel, calibrations, coil_K_nT_per_A, data,
                                     mask_of=needed)
    if mask.sum() < tel.n:
        notes.append(f"{tel.n - int(mask.sum())} of {tel.n} samples unusable or with coil "
                     "current, left out")
    temp_all = {n: data[n].temp_or(calibrations[n].t_ref_C) for n in fields}
    temps = {n: temp_all[n][mask] for n in fields}

    def cal_cov(body_name, boom_name, H, m=slice(None)):
        if not include_calibration_sigma:
            return None
        c1 = calibration_rotation_cov(calibrations[body_name], temps[body_name][m])
        c2 = calibration_rotation_cov(calibrations[boom_name], temps[boom_name][m])
        return c1 + H @ c2 @ H.T

    B1 = fields[ref][mask]
    B2 = fields[fit_sensor][mask]
    first = fit_H(B1, B2, min_spread_deg=min_spread_deg, source=src)
    result = fit_H(B1, B2, extra_cov_rad2=cal_cov(ref, fit_sensor, first.H),
                   min_spread_deg=min_spread_deg, source=src)
    H = result.H
    notes.extend(f"H: {n}" for n in result.notes)   # e.g. its sigma widened for a drift

    pairs, checks = {}, {}
    for b in booms:
        if b.name not in fields:
            continue
        partners = [ref]
        if b.part != ref_spec.part:
            same = [s.name for s in unit.sensors
                    if s.frame == "body" and s.part == b.part and s.name in fields]
            if same:
                partners.append(same[0])
        for p in partners:
            key = f"{p}/{b.name}"
            pm = np.isfinite(fields[p][mask]).all(axis=1) & \
                np.isfinite(fields[b.name][mask]).all(axis=1) & data[p].usable[mask] & \
                data[b.name].usable[mask]
            P1, P2 = fields[p][mask][pm], fields[b.name][mask][pm]
            pairs[key] = {"before": figures_of_merit(P1, P2, None),
                          "after": figures_of_merit(P1, P2, H)}
            if b.name != fit_sensor or p != ref:
                r0 = fit_H(P1, P2, min_spread_deg=min_spread_deg, source=src)
                checks[key] = fit_H(P1, P2, extra_cov_rad2=cal_cov(p, b.name, r0.H, pm),
                                    min_spread_deg=min_spread_deg, source=src)
    if any(unit.sensor(k.split("/")[0]).set_reset != unit.sensor(k.split("/")[1]).set_reset
           for k in pairs):
        notes.append("pairs mixing a SET/RESET sensor with a plain one compare readings that "
                     "are not simultaneous (the SET/RESET field is the mean of two readings "
                     "taken t_delay apart): while the unit turns this shows up as an apparent "
                     "rotation; H is fitted from a same-part pair")
    return BoomAlignment(reference=ref, fit_sensor=fit_sensor, result=result, pairs=pairs,
                         cross_checks=checks, fields_nT=fields, mask=mask, notes=notes)
