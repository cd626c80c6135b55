"""Calibration from known field vectors: B_ref = M(T) (B~ - b(T)), fitted as that model.

The estimator minimises the calibrated-minus-reference residual itself,

    r_n = M(T_n) (B~_n - b(T_n)) - B_ref_n,      cost = sum_n r_n^T r_n / v_n

(b and M polynomials in dT = clamp(T) - t_ref), never a regression of the raw reading on
the reference followed by an inversion (that inverts a badly determined matrix whenever
one reference direction hardly varies, e.g. a flight turning mostly in yaw).

1. Start: the same model in the parametrisation where it is linear, B_ref = M(T) B~ + c(T)
   (c = -M b), solved row by row by least squares with the prior as extra rows; then
   b(T) = -M(T)^-1 c(T) (exact at degree 0; a polynomial projection on Chebyshev nodes over
   the calibrated range otherwise).
2. Gauss-Newton in the flight parametrisation (b_poly, M_poly) from there. J^T W J comes
   from the reading's moments (reading_moments, normal_matrix), and each iterate's cost
   and gradient from sums centred on the run's start (ResidualStats): an iterate costs no
   pass over the samples; the run's result is evaluated per sample (vector_normal).
3. Errors in variables. The noise of the readings x (the sensor's stated noise_nT) adds
   noise_nT^2 |M(T)|_F^2 to every expected |r|^2; it is subtracted from the cost (adjusted
   least squares), so a reading axis that carries only noise does not look determined
   (plain least squares would fit that column of M to the noise, shrinking it to ~0).
   The residual also carries the sensor noise mapped through M and the
   reference's own noise (an attitude estimate, a field model). Neither is known per sample
   in the telemetry, so each file (`group`) gets its effective variance
   v_g = mean |r|^2 / 3 of its residuals, and the fit is repeated with weights 1/v_g: a
   file whose reference is noisier counts less.
4. Observability: with the prior sigma s (`Prior`: a ground calibration, or the part's
   nominal M = I, b = 0 with `PART_PRIOR_SIGMA`), the whitened Fisher information
   F~ = S J^T V^-1 J S (S = diag s) is split by its eigenvalues. It is judged once, at the
   prior's M with the offset that fits the mean, and from the spread of the TRUE reading:
   the cross-moments of the reading x and of the reading the reference implies,
   x_hat = b + M0^-1 B (_split_information; their noises are independent, so neither
   the reading's noise nor the reference's counts as signal -- on a near-static record
   the regression of B on x would otherwise fit M to the reading's noise, det M ~ 0). The
   effective variance V counts serially correlated residuals as fewer samples
   (_correlation_inflation). A direction with lambda >= 1 carries more information from
   the data than from the prior and is fitted; a direction with lambda < 1 (the data
   determine it worse than the prior already does, or contradict it weakly) is held at
   the prior: the start is projected onto the fitted subspace and the Gauss-Newton steps
   stay in it. Exception: where the data alone determine a mirrored M of plausible size
   (linear start det M <= -min_abs_det), nothing is held, so that sanity refuses the
   reflection instead of the split hiding it. Each parameter's data fraction is the
   squared length of its whitened unit vector in the fitted subspace; >= 0.5 reads
   "data", else "prior" (that parameter is then mostly the prior's value). The
   covariance is S (V_f L_f^-1 V_f^T + V_p V_p^T) S: the data's where fitted, the prior's
   where held. The reading noise is the unit file's figure, else the part catalogue's
   typical one (fit.samples.field_noise_nT); only a part with neither (generic) has it
   estimated from the second differences of the first pass's residuals
   (_reading_noise_var) for the errors-in-variables term. The data bound the figure from
   above: the second differences of the readings (noise plus the field's motion between
   samples) and, after the first pass, of its residual mapped back to the reading (noise
   plus the reference's white noise) each give an upper bound of the reading noise; the
   smaller, per axis, is the data bound (data_noise_var_bound). The correction never
   subtracts more than the quietest axis's bound (clipped_noise_var: a catalogue figure
   above a quiet unit's real noise would make a barely moving axis's corrected moment
   negative and M a reflection). The figure's own uncertainty
   (NOISE_VAR_UNCERTAINTY, CATALOGUE_NOISE_VAR_UNCERTAINTY), and at least the gap up to
   the largest data bound where the figure is below it (noise_var_sigma: a figure stated
   too small), is a systematic error of that
   correction, which does not average down with N: where the reading barely moves along
   an axis (a yaw-only flight's vertical) the correction is large and so is its error;
   it enters the split (a direction the systematic moves by more than the prior's
   1-sigma is held) and the covariance (_noise_var_systematic). A linear start that is
   a reflection counts as a mirrored reference only where the directions the data
   determine make it one (_mirror_is_determined); the fitted directions' information
   is floored at the prior's (_solve_floored), so no fitted coefficient gets a 1-sigma
   of 0 from an over-corrected moment.
5. The reported temperature's reporting step (0.7 degC for the MMC5883's on-chip sensor)
   is an error common to every sample reported with one value (a chamber hold), which
   does not average down like the reading noise: its q^2/12 is propagated through the
   fit's response into the covariance (_temperature_error_cov), for degree > 0 (a
   constant model does not use the temperature).

Passes over the samples per fit: a fixed number (moments, the linear start's sums, each
Gauss-Newton run's start and result, the per-file variances), none per iterate; the
held-out comparison's fits skip the temperature-error covariance (uncertainty=False).

The fit is written once, as a generator (reference_fit_steps) that hands out its
Gauss-Newton runs: reference_fit does them one by one (_gauss_newton); fit.reference_batch
stacks those of many constant fits (the held-out comparison's per-level fits).

Public: reference_fit, reference_fit_steps, gauss_newton_result, Prior, nominal_prior,
PART_PRIOR_SIGMA, parameter_names, min_abs_det.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from generator.errors import InputError
from generator.fit.calibration import POLY_DEGREE
from generator.fit.ellipsoid import distinct_rows

T_REF_C = 25.0
MAX_REF_COND = 1e10        # condition number of the column-scaled reference-fit design

# The part's nominal calibration M = I, b = 0 and its 1-sigma per polynomial degree k
# (units nT/degC^k and 1/degC^k). Degree 0: offsets up to ~1e5 nT (1 G: the hard iron
# of a vehicle next to motors or a magnet, which reaches a few G, plus the MPU-9255
# factory offset; the MMC5883 bridge offset is removed by SET/RESET). A narrower offset
# prior makes a large mean mismatch look like a change of M: where M is not determined
# (a near-static record) the offset of the mean must go to b, not into M), sensitivity and cross-axis terms within ~10 % (datasheet sensitivity
# tolerance and axis alignment, with soft iron). Temperature terms: offset drift up to
# ~20 nT/degC and sensitivity drift up to ~0.1 %/degC, their curvature a few % of that per
# degC. The simulator's units (campaign.simulate.random_truth) lie within 1 sigma.
PART_PRIOR_SIGMA = {
    "default": {"b_nT": (1.0e5, 20.0, 0.5, 0.01), "M": (0.1, 1.0e-3, 2.0e-5, 5.0e-7)},
}
# Whitened eigenvalue at and above which a direction is taken from the data: there the
# data's information equals the prior's (posterior variance at most half the prior's).
FISHER_THRESHOLD = 1.0
DATA_FRACTION = 0.5        # a parameter is "data" when this much of it lies in the fitted subspace
# The stated reading noise is known only so well (a datasheet figure, or a measurement of
# a few hundred samples): its variance to about +-25 %. A direction counts as determined
# only with that margin taken off the information, so that a reading axis whose signal
# is below half its noise (rms) is not "determined" by a misstated noise level.
NOISE_VAR_UNCERTAINTY = 0.25
# Where a reading-noise figure came from (fit.samples.field_noise_nT, NoiseFigure.source).
NOISE_STATED = "stated"
NOISE_CATALOGUE = "part catalogue (typical)"
# The catalogue's figure is the datasheet's TYPICAL noise (parts.toml: never a guaranteed
# or a measured one, some read off a resolution): a given unit's noise scatters around
# it, taken as +-25 % in sigma, i.e. +-50 % in variance (1.22^2 = 1.5).
CATALOGUE_NOISE_VAR_UNCERTAINTY = 0.5
GN_MAX_ITER = 30
# Serial correlation of residuals at most this (n_eff >= n / 199): beyond it the residual is
# a constant offset, which b takes, not a sample-to-sample statistic.
MAX_RHO = 0.99


@dataclass
class Prior:
    """Prior of the flight coefficients: values and 1-sigma, polynomials in dT (degree K-1)."""
    b_poly_nT: np.ndarray        # (K, 3)
    M_poly: np.ndarray           # (K, 3, 3)
    b_sigma_nT: np.ndarray       # (K, 3)
    M_sigma: np.ndarray          # (K, 3, 3)
    source: str = "part nominal"
    t_range_C: tuple | None = None   # the prior's calibrated range (a ground calibration)

    def truncated(self, degree):
        """This prior for a degree-`degree` model (missing degrees: nominal 0, part sigma)."""
        K = degree + 1
        nom = nominal_prior(degree)
        b, M = nom.b_poly_nT.copy(), nom.M_poly.copy()
        bs, Ms = nom.b_sigma_nT.copy(), nom.M_sigma.copy()
        k = min(K, len(self.b_poly_nT))
        b[:k], M[:k] = self.b_poly_nT[:k], self.M_poly[:k]
        # a zero or missing sigma (an unfitted degree padded with zeros) keeps the part's
        ps, pM = np.asarray(self.b_sigma_nT[:k], float), np.asarray(self.M_sigma[:k], float)
        bs[:k] = np.where(ps > 0, ps, bs[:k])
        Ms[:k] = np.where(pM > 0, pM, Ms[:k])
        return Prior(b, M, bs, Ms, self.source, self.t_range_C)


def nominal_prior(degree, part="default") -> Prior:
    s = PART_PRIOR_SIGMA.get(part, PART_PRIOR_SIGMA["default"])
    K = degree + 1
    M = np.zeros((K, 3, 3))
    M[0] = np.eye(3)
    bs = np.repeat(np.asarray(s["b_nT"][:K], float)[:, None], 3, axis=1)
    Ms = np.broadcast_to(np.asarray(s["M"][:K], float)[:, None, None], (K, 3, 3)).copy()
    return Prior(np.zeros((K, 3)), M, bs, Ms, "part nominal (M = I, b = 0)")


def parameter_names(degree):
    """Names of the flight coefficients in fit order: b<k>_<axis>, then M<k>_<row><col>."""
    ax = "xyz"
    return ([f"b{k}_{ax[l]}" for k in range(degree + 1) for l in range(3)]
            + [f"M{k}_{ax[a]}{ax[c]}" for k in range(degree + 1) for a in range(3)
               for c in range(3)])


def _group_labels(group, n):
    """0..G-1 per sample in the order of np.unique(group) (zeros without groups, or where
    every sample is of one group: the usual single file, without a sort)."""
    if group is None:
        return np.zeros(n, int)
    g = np.asarray(group)
    if n and np.all(g == g.flat[0]):
        return np.zeros(n, np.intp)
    return np.unique(g, return_inverse=True)[1]


def _by_group(a, grp):
    """[a[grp == g] for g in np.unique(grp)], without the sort and copies for one group."""
    grp = np.asarray(grp)
    if len(grp) and grp.flat[0] == grp.min() == grp.max():
        return [a]
    return [a[grp == g] for g in np.unique(grp)]


def _powers(dT_scaled, degree):
    """[1, d, d^2, ...] per sample, (N, degree+1)."""
    P = np.empty((len(dT_scaled), degree + 1))
    P[:, 0] = 1.0
    for k in range(1, degree + 1):          # in place: no temporary column per power
        np.multiply(P[:, k - 1], dT_scaled, out=P[:, k])
    return P


def _temperature_powers(P, top):
    """[1, d, ..., d^top] per sample (N, top+1) from the powers P (P[:, 1] = d)."""
    d = P[:, 1] if P.shape[1] > 1 else np.zeros(len(P))
    return _powers(d, top)


MOMENT_CHUNK = 1 << 15     # samples per block of reading_moments' sums


def reading_moments(P, x, w=None, x_cross=None, grp=None, both=False):
    """Sufficient statistics of the regressor for J^T W J of the vector rows (vector_normal):
    with d the scaled temperature (P[:, 1]) and w the weights,
        W[p] = sum w d^p,  X[p] = sum w d^p x,  XX[p] = sum w d^p x x^T
    for the powers that J^T W J needs (degree K-1: p up to 4K-4, 3K-3, 2K-2). J^T W J of
    M(T)(x - b(T)) - B depends on the samples only through these (its entries are
    polynomials in d, linear and quadratic in x), so it is assembled in a time independent
    of N, and the same statistics serve every iterate.

    x_cross: a second reading of the same true reading (reference_fit's x_hat): X is then
    that of m = (x + x_cross) / 2 and XX the symmetrised cross moment (x x_c^T + x_c x^T)/2
    (_split_information). grp: (N,) labels 0..G-1: a list of G dicts, one per group (each
    group's sums; one pass over the samples, one matrix product). both: x_cross given,
    the pair (plain, cross) from the same pass."""
    n, K = P.shape
    w = None if w is None else np.broadcast_to(np.asarray(w, float), (n,))
    grp_a = np.zeros(n, int) if grp is None else np.asarray(grp)
    n_grp = int(grp_a.max()) + 1 if n else 1
    ncol = 25 if both else 13
    sums = np.zeros((n_grp, 4 * K - 3, ncol))
    for a in range(0, n, MOMENT_CHUNK):      # bounded temporaries whatever N
        sl = slice(a, min(a + MOMENT_CHUNK, n))
        D = _temperature_powers(P[sl], 4 * K - 4)
        if w is not None:
            D *= w[sl, None]
        xs = x[sl]
        # H = [1, x, x x^T] (13 columns), or [1, m, x x_c^T] or both (25), written in place,
        # a product column at a time from contiguous axes (a broadcast over 3 x 3 runs
        # inner loops of 3)
        H = np.empty((len(xs), ncol))
        H[:, 0] = 1.0
        c = 1
        xT = xs.T.copy()
        if x_cross is None or both:
            H[:, 1:4] = xs
            _outer_columns(xT, xT, H, 4)
            c = 13
        if x_cross is not None:
            xc = x_cross[sl]
            m = H[:, c:c + 3]
            np.add(xs, xc, out=m)
            m *= 0.5
            _outer_columns(xT, xc.T.copy(), H, c + 3)
        g = grp_a[sl]
        if g[0] == g[-1] and (len(g) < 3 or np.all(g[1:] >= g[:-1])):
            sums[g[0]] += D.T @ H           # one file in this chunk (the usual case)
        else:
            for k in np.unique(g):
                m = g == k
                sums[k] += D[m].T @ H[m]
    def unpack(S_, c0, cross):
        XX = S_[:2 * K - 1, c0 + 3:c0 + 12].reshape(2 * K - 1, 3, 3)
        if cross:
            XX = 0.5 * (XX + XX.transpose(0, 2, 1))
        return {"W": S_[:, 0], "X": S_[:3 * K - 2, c0:c0 + 3], "XX": XX}

    if both:
        out = ([unpack(S_, 1, False) for S_ in sums], [unpack(S_, 13, True) for S_ in sums])
        return out if grp is not None else (out[0][0], out[1][0])
    out = [unpack(S_, 1, x_cross is not None) for S_ in sums]
    return out if grp is not None else out[0]


def _outer_columns(aT, bT, out, c0):
    """out[:, c0 + 3 i + j] = a_i b_j per sample (aT, bT: (3, N), contiguous rows): the
    row-major outer products a b^T, the same values as a broadcast product."""
    for i in range(3):
        for j in range(3):
            np.multiply(aT[i], bT[j], out=out[:, c0 + 3 * i + j])


def normal_matrix(mom, bp, Mp, eiv_var=0.0):
    """J^T W J of the vector rows r_n = M(T_n)(x_n - b(T_n)) - B_n (parameters b[k,l], then
    M[k,a,c]) from reading_moments; the same matrix as the per-sample sums (vector_normal's
    docstring) up to rounding. With y = x - b(T), every block depends on (k, m) only
    through s = k + m:
        M-M  delta_aa' A_s[c,d],   A_s = sum w d^s y y^T
        b-b  Q_s[l,p],             Q_s = sum w d^s M(T)^T M(T)
        M-b  -R_s[c,a,l],          R_s = sum w d^s y_c M(T)[a,l]
    and b(T), M(T) are polynomials in d, so each is a combination of the moments."""
    K = len(bp)
    W, X, XX = mom["W"], mom["X"], mom["XX"]
    ns = 2 * K - 1
    MtM = np.einsum("jil,kip->jklp", Mp, Mp)                  # M_j^T M_j'
    bb_ = bp[:, None, :, None] * bp[None, :, None, :]          # b_j b_j'^T
    sj = np.add.outer(np.arange(ns), np.arange(K))            # s + j
    Wjj = W[sj[:, :, None] + np.arange(K)]                    # W[s + j + i], (ns, K, K)
    Xs = X[sj]                                                # X[s + j], (ns, K, 3)
    Xb = np.einsum("sjc,jd->scd", Xs, bp)                     # sum_j X[s+j] b_j^T
    A = XX[:ns] - Xb - Xb.transpose(0, 2, 1) + np.einsum("sji,jicd->scd", Wjj, bb_)
    Q = np.einsum("sji,jilp->slp", Wjj, MtM)
    # R_s[c,a,l] = sum_j X[s+j]_c M_j[a,l] - sum_{j,j'} W[s+j+j'] b_j'[c] M_j[a,l]
    Yj = Xs - Wjj @ bp                                        # (ns, K, 3): per s, j
    R = np.einsum("sjc,jal->scal", Yj, Mp)
    idx = np.add.outer(np.arange(K), np.arange(K))            # s = k + m
    nb = 3 * K
    out = np.zeros((12 * K, 12 * K))
    out[:nb, :nb] = Q[idx].transpose(0, 2, 1, 3).reshape(nb, nb)   # b-b [k,l,m,p]
    Mb = -R[idx].transpose(0, 3, 2, 1, 4).reshape(9 * K, nb)       # M-b [k,a,c,m,l]
    out[nb:, :nb] = Mb
    out[:nb, nb:] = Mb.T
    # M-M: delta_aa' A_{k+m}[c,d], i.e. [k,a,c,m,a',d] zero unless a = a'
    MM = out[nb:, nb:].reshape(K, 3, 3, K, 3, 3)
    MM[:, _AX3, :, :, _AX3, :] = A[idx].transpose(0, 2, 1, 3)   # [k,c,m,d] for every a
    if eiv_var:     # - eiv_var sum w P_k P_m on the diagonal of each (k, m) block
        MMf = out[nb:, nb:].reshape(K, 9, K, 9)
        MMf[:, _AX9, :, _AX9] -= eiv_var * W[idx]       # each element once, as per i
    return out


_AX3, _AX9 = np.arange(3), np.arange(9)
_EYE3 = np.eye(3)


class ReadingStats:
    """reading_moments of one sample set per file group (unweighted), for weights that are
    constant within each group (reference_fit's errors-in-variables weights): the
    weighted statistics are then a combination of the groups', with no pass over the
    samples. `cross` holds those of (x, x_hat) for _split_information."""

    def __init__(self, P, x, grp, x_hat=None):
        grp = np.asarray(grp)
        self.n_grp = int(grp.max()) + 1 if len(grp) else 0
        self.first = np.array([np.flatnonzero(grp == g)[0] for g in range(self.n_grp)])
        if x_hat is None:
            self.vec, self.cross = reading_moments(P, x, grp=grp), []
        else:           # one pass for both
            self.vec, self.cross = reading_moments(P, x, x_cross=x_hat, grp=grp, both=True)

    def weighted(self, w, cross=False):
        """The moments with per-sample weights w (constant within each group)."""
        parts = self.cross if cross else self.vec
        wg = np.asarray(w, float)[self.first]
        return {k: sum(wg[g] * parts[g][k] for g in range(self.n_grp)) for k in parts[0]}


class ResidualStats:
    """The weighted cost and gradient of the vector rows in a time independent of N, for
    the iterates of one Gauss-Newton run (same samples, same weights).

    Around a start (b0, M0) with per-sample residual r0_n, the residual at any (b, M) is
    r_n = r0_n + L phi_n EXACTLY: phi_n = [d^k x_n (k < K), d^s (s <= 2K-2)] and
    L = [M_k - M0_k | -(E_s - E0_s)], E_s = sum_{k+j=s} M_k b_j (M(T)b(T)'s coefficients).
    So cost = sum w |r0|^2 + 2 tr(L sum w phi r0^T) + tr(L (sum w phi phi^T) L^T) and
    J^T W r follows from dcost/dL by the chain rule; the sums are taken once (one pass
    over the samples). Centred on the start, the sums hold residual-sized terms (not
    |B|^2), so the cost keeps the precision of a per-sample sum to ~1e-13 relative; the
    run's final evaluation (r per sample, what the fit reports) stays vector_normal's."""

    def __init__(self, P, x, B, w, bp0, Mp0, mom):
        """mom: reading_moments(P, x, w) (sum w phi phi^T is made of them)."""
        n, K = P.shape
        self.K, self.bp0, self.Mp0 = K, bp0, Mp0
        self.E0 = self._E(bp0, Mp0)
        w = np.broadcast_to(np.asarray(w, float), (n,))
        nphi = 3 * K + 2 * K - 1
        W, X, XX = mom["W"], mom["X"], mom["XX"]
        G = np.empty((nphi, nphi))                # sum w phi phi^T from the moments
        kk = np.add.outer(np.arange(K), np.arange(K))
        G[:3 * K, :3 * K] = XX[kk].transpose(0, 2, 1, 3).reshape(3 * K, 3 * K)
        ks = np.add.outer(np.arange(K), np.arange(2 * K - 1))
        G[:3 * K, 3 * K:] = X[ks].transpose(0, 2, 1).reshape(3 * K, 2 * K - 1)
        G[3 * K:, :3 * K] = G[:3 * K, 3 * K:].T
        G[3 * K:, 3 * K:] = W[np.add.outer(np.arange(2 * K - 1), np.arange(2 * K - 1))]
        self.Gpp = G
        self.a = 0.0
        Gx = np.zeros((K, 3, 3))                  # sum w d^k x_c r0_a  [k, c, a]
        Gd = np.zeros((2 * K - 1, 3))             # sum w d^s r0_a
        for a in range(0, n, MOMENT_CHUNK):      # bounded temporaries whatever N
            sl = slice(a, min(a + MOMENT_CHUNK, n))
            Ps = P[sl]
            y0 = x[sl] - Ps @ bp0
            r0 = -B[sl]
            for j in range(K):
                r0 = r0 + Ps[:, j:j + 1] * (y0 @ Mp0[j].T)
            wr0 = r0 * w[sl, None]
            self.a += float(np.sum(wr0 * r0))
            Gd += _temperature_powers(Ps, 2 * K - 2).T @ wr0
            Gx += (Ps.T @ (x[sl, :, None] * wr0[:, None, :]).reshape(-1, 9)).reshape(K, 3, 3)
        self.Gpr = np.concatenate([Gx.reshape(3 * K, 3), Gd])    # sum w phi r0^T

    def _E(self, bp, Mp):
        K = self.K
        E = np.zeros((2 * K - 1, 3))
        for k in range(K):
            E[k:k + K] += bp @ Mp[k].T           # E[k + j] += M_k b_j
        return E

    def cost_grad(self, bp, Mp, jac=True, eiv_var=0.0, W=None):
        """(cost, J^T W r) at (bp, Mp): vector_normal's cost and gradient (eiv_var, W:
        the errors-in-variables term and the moments' W, as there)."""
        K = self.K
        L = np.concatenate([(Mp - self.Mp0).transpose(1, 0, 2).reshape(3, 3 * K),
                            -(self._E(bp, Mp) - self.E0).T], axis=1)      # (3, nphi)
        LG = L @ self.Gpp
        cost = self.a + 2.0 * float(np.sum(L * self.Gpr.T)) + float(np.sum(LG * L))
        idx = np.add.outer(np.arange(K), np.arange(K)) if eiv_var else None
        if eiv_var:
            Mf = Mp.reshape(K, 9)
            cost -= eiv_var * float(np.sum(W[idx] * (Mf @ Mf.T)))
        if not jac:
            return cost, None
        Gr = self.Gpr.T + LG                                   # d(cost/2)/dL, (3, nphi)
        GM = Gr[:, :3 * K].reshape(3, K, 3).transpose(1, 0, 2)   # [k, a, c]
        Ge = Gr[:, 3 * K:]                                     # [a, s]
        H = np.stack([Ge[:, k:k + K] for k in range(K)])       # H[k, a, j] = Ge[a, k + j]
        gM = GM - H @ bp                                       # - sum_j Ge[a,k+j] b_j[c]
        gb = -np.einsum("kaj,kal->jl", H, Mp)                  # - sum_{a,k} Ge[a,k+j] M_k[a,l]
        if eiv_var:
            gM = gM - eiv_var * (W[idx] @ Mp.reshape(K, 9)).reshape(K, 3, 3)
        return cost, np.concatenate([gb.reshape(-1), gM.reshape(-1)])


def vector_normal(P, x, B, bp, Mp, jac=True, w=None, eiv_var=0.0, mom=None):
    """Vector rows r_n = M(T_n)(x_n - b(T_n)) - B_n with weights w_n: weighted cost and, in
    closed form, J^T W J and J^T W r (params b[k,l], then M[k,a,c]); no (3N x p) Jacobian
    is formed. P: (N, K) powers of dT. Returns (cost, JTJ, g, r).

    J^T W J comes from the regressor's sufficient statistics (reading_moments, normal_matrix:
    independent of N); pass `mom` (reading_moments(P, x, w)) to reuse them across calls
    with the same samples and weights. The cost, r and J^T W r stay per-sample sums (at a
    good fit they are small differences of large terms, which moments would lose).

    eiv_var: variance of the noise in each axis of x (errors in variables). The noise in x
    adds eiv_var |M(T_n)|_F^2 to the expected |r_n|^2 whatever the parameters; it is
    subtracted from the cost (and its derivatives), so that noise in the readings is not
    taken for signal (adjusted least squares: without it, a reading axis that carries only
    noise would make its column of M look determined and shrink it towards 0)."""
    n, K = P.shape
    y = x - P @ bp
    r = -B
    for j in range(K):                                        # M(T_n) y_n
        r = r + P[:, j:j + 1] * (y @ Mp[j].T)
    w = np.ones(n) if w is None else np.broadcast_to(np.asarray(w, float), (n,))
    rw = r * w[:, None]
    cost = float(np.einsum("ni,ni->", rw, r))
    if eiv_var or jac:
        if mom is None:
            mom = reading_moments(P, x, w)
        W = mom["W"]
    if eiv_var:
        Mf = Mp.reshape(K, 9)
        idx = np.add.outer(np.arange(K), np.arange(K))
        cost -= eiv_var * float(np.sum(W[idx] * (Mf @ Mf.T)))    # sum w |M(T_n)|_F^2
    if not jac:
        return cost, None, None, r
    JTJ = normal_matrix(mom, bp, Mp, eiv_var)
    # J^T W r: gb[k] = -sum w P_k M(T_n)^T r_n, gM[k,a,c] = sum w P_k r_a y_c (BLAS)
    u = np.zeros_like(x)
    for j in range(K):
        u += P[:, j:j + 1] * (rw @ Mp[j])                    # w M(T_n)^T r_n
    gb = -(P.T @ u)
    gM = (P.T @ (rw[:, :, None] * y[:, None, :]).reshape(n, 9)).reshape(K, 3, 3)
    if eiv_var:
        idx = np.add.outer(np.arange(K), np.arange(K))
        gM = gM - eiv_var * (W[idx] @ Mp.reshape(K, 9)).reshape(K, 3, 3)
    return cost, JTJ, np.concatenate([gb.reshape(-1), gM.reshape(-1)]), r


def _solve_M(P, Mp, v):
    """M(T_n)^-1 v_n (N, 3), M(T) = sum_k P_k Mp[k]: one solve with many right-hand sides
    where M has no temperature terms (the constant fits, a nominal prior), else per
    sample by the adjugate (_solve3)."""
    if len(Mp) == 1 or not np.any(Mp[1:]):
        if np.array_equal(Mp[0], _EYE3):
            # M = I (the nominal prior): the solve's values (it may flip the sign of an
            # exact 0, which no sum with a nonzero term sees), without LAPACK per row block
            return v.copy()
        return np.linalg.solve(Mp[0], v.T).T
    out = _solve3(Mp.reshape(len(Mp), 9).T @ P.T, v)
    if out is None:
        return np.linalg.solve(np.einsum("nk,kij->nij", P, Mp), v[:, :, None])[:, :, 0]
    return out


# _solve3 solves by the adjugate only where |det M| >= this fraction of the product of
# M's row norms (Hadamard's bound: 1 for orthogonal rows, -> 0 as M becomes singular):
# there the 3x3 inverse's rounding error is a few float64 ulps of the result, as LU's
CLOSED_SOLVE_MIN_ORTHOGONALITY = 1e-3


def _solve3(Mt, v):
    """M_n^-1 v_n (N, 3) for N 3x3 matrices given as their 9 entries row by row, (9, N)
    (contiguous rows), by the adjugate: adj(M) v / det M, in whole-array operations (a
    per-sample LAPACK solve costs ~6x as much). The same solution as LU up to rounding
    (float64 round-off, a few ulps where M is well conditioned); None where some M is
    near singular (CLOSED_SOLVE_MIN_ORTHOGONALITY), so that the caller solves by LU."""
    a, b, c, d, e, f, g, h, i = Mt
    A, B, C = e * i - f * h, f * g - d * i, d * h - e * g      # cofactors of row 0
    det = a * A + b * B + c * C
    rows = np.sqrt((a * a + b * b + c * c) * (d * d + e * e + f * f)
                   * (g * g + h * h + i * i))
    with np.errstate(invalid="ignore", divide="ignore"):
        if not np.all(np.abs(det) >= CLOSED_SOLVE_MIN_ORTHOGONALITY * rows) \
                or not np.all(rows > 0):
            return None
    v0, v1, v2 = v.T
    out = np.empty((3, len(v0)))
    out[0] = A * v0 + (c * h - b * i) * v1 + (b * f - c * e) * v2
    out[1] = B * v0 + (a * i - c * g) * v1 + (c * d - a * f) * v2
    out[2] = C * v0 + (b * g - a * h) * v1 + (a * e - b * d) * v2
    out /= det
    return out.T


def _linear_design(P, x, sl):
    """Rows [P_k x, P_k] (N, 4K) of the linear model B = M(T) x + c(T), samples sl."""
    K = P.shape[1]
    Ps, xs = P[sl], x[sl]
    A = np.empty((len(Ps), 4 * K))        # written a contiguous product column at a time
    PT, xT = Ps.T.copy(), xs.T.copy()
    for k in range(K):
        for c in range(3):
            np.multiply(PT[k], xT[c], out=A[:, 3 * k + c])
    A[:, 3 * K:] = Ps
    return A


def _linear_sums(P, x, B):
    """The linear model's normal-equation sums per block of samples (bounded memory
    whatever N), unweighted: (A^T A, A^T B, P^T P)."""
    n, K = P.shape
    G = np.zeros((4 * K, 4 * K))
    AtB = np.zeros((4 * K, 3))
    for a in range(0, n, MOMENT_CHUNK):
        sl = slice(a, min(a + MOMENT_CHUNK, n))
        A = _linear_design(P, x, sl)
        G += A.T @ A
        AtB += A.T @ B[sl]
    # the design of a single block is kept for _linear_residual_var (no second build)
    return G, AtB, G[3 * K:, 3 * K:].copy(), (A if n <= MOMENT_CHUNK else None)


def _linear_residual_var(P, x, B, sums):
    """Residual variance per axis of the unconstrained linear model B = M(T) x + c(T)
    (least squares) from _linear_sums (columns scaled to unit diagonal; the minimum-norm
    solution where they are singular, whose residual is the least-squares one); the
    residual itself summed per block of samples (no (N x 4K) decomposition)."""
    n, K = P.shape
    G, AtB, _, A_one = sums
    col = np.sqrt(np.diag(G))
    col[col == 0] = 1.0
    sol = np.linalg.lstsq(G / np.outer(col, col), AtB / col[:, None], rcond=None)[0] \
        / col[:, None]
    ssr = 0.0
    for a in range(0, n, MOMENT_CHUNK):
        sl = slice(a, min(a + MOMENT_CHUNK, n))
        A = _linear_design(P, x, sl) if A_one is None else A_one
        ssr += float(np.sum((B[sl] - A @ sol) ** 2))
    return ssr / max(3 * (n - 4 * K), 1)


def _cheb_nodes(lo, hi, degree):
    if hi - lo < 1e-12:
        return np.array([lo])
    n = max(4 * (degree + 1), 16)
    c = np.cos(np.pi * (np.arange(n) + 0.5) / n)
    return 0.5 * (lo + hi) + 0.5 * (hi - lo) * c


def _linear_start(sums, w, prior_s, degree, lo_s, hi_s, eiv_var=0.0):
    """Step 1: B = M(T) x + c(T), least squares per output row with the prior as extra
    rows (the prior of c = -M b taken as -M0 b0 with b's sigma), the noise of x taken out
    of the normal matrix (eiv_var, see vector_normal); then b = -M^-1 c. sums:
    _linear_sums of the samples; w: their common weight (the first pass's 1 / v0)."""
    K = degree + 1
    b0, M0, bs, Ms = prior_s
    c0 = np.zeros((K, 3))
    c0[0] = -M0[0] @ b0[0]
    G, AtB, PtP = (w * a for a in sums[:3])
    if eiv_var:
        G[:3 * K, :3 * K] -= eiv_var * np.kron(PtP, np.eye(3))
    Mk = np.zeros((K, 3, 3))
    ck = np.zeros((K, 3))
    for i in range(3):
        u0 = np.concatenate([M0[:, i, :].reshape(-1), c0[:, i]])
        s = np.concatenate([Ms[:, i, :].reshape(-1), bs[:, i]])
        D = np.diag(1.0 / s ** 2)
        u = np.linalg.lstsq(G + D, AtB[:, i] + D @ u0, rcond=None)[0]
        Mk[:, i, :] = u[:3 * K].reshape(K, 3)
        ck[:, i] = u[3 * K:]
    g = _cheb_nodes(lo_s, hi_s, degree)
    Pg = _powers(g, degree)
    M_g = np.einsum("gk,kij->gij", Pg, Mk)
    c_g = Pg @ ck
    b_g = -np.linalg.solve(M_g, c_g[:, :, None])[:, :, 0]
    if Pg.shape == (1, 1) and Pg[0, 0] == 1.0:
        return b_g, M_g         # one node (a constant fit): the projection is 1, exactly
    proj = np.linalg.pinv(Pg)
    return proj @ b_g, np.einsum("qg,gij->qij", proj, M_g)


def reference_fit(field_frame_nT, ref_body_nT, temp_C=None, degree=POLY_DEGREE, *,
                  t_ref_C=T_REF_C, t_range_C=None, source=None, prior: Prior | None = None,
                  group=None, noise_nT=None, uncertainty=True):
    """Calibration from known field vectors: B_ref = M(T) (B~ - b(T)) (module docstring;
    the arguments and the result: reference_fit_steps). reference_fit_steps holds the
    fit; its Gauss-Newton runs are done here, one after the other (_gauss_newton);
    fit.reference_batch runs those of many constant fits together."""
    steps = reference_fit_steps(field_frame_nT, ref_body_nT, temp_C, degree,
                                t_ref_C=t_ref_C, t_range_C=t_range_C, source=source,
                                prior=prior, group=group, noise_nT=noise_nT,
                                uncertainty=uncertainty)
    try:
        run = next(steps)
        while True:
            run = steps.send(_gauss_newton(*run))
    except StopIteration as done:
        return done.value


def reference_fit_steps(field_frame_nT, ref_body_nT, temp_C=None, degree=POLY_DEGREE, *,
                        t_ref_C=T_REF_C, t_range_C=None, source=None,
                        prior: Prior | None = None, group=None, noise_nT=None,
                        uncertainty=True):
    """reference_fit as a generator: it yields the arguments of each Gauss-Newton run
    (a tuple for _gauss_newton), is sent that run's (theta, JTJ, cost, r), and returns
    reference_fit's result (StopIteration.value). Raises InputError as reference_fit.

    Calibration from known field vectors: B_ref = M(T) (B~ - b(T)) (module docstring).

    field_frame_nT: (N, 3) uncalibrated readings in frame axes; ref_body_nT: (N, 3)
    reference field (body frame); temp_C: (N,) reported temperature, or None for a
    constant calibration (degree 0). Only finite rows may be passed. prior: Prior (default
    the part's nominal); group: (N,) file labels for the errors-in-variables weights;
    noise_nT: the sensor's stated per-axis noise (recorded next to the estimate).
    Returns (b_poly_nT (degree+1, 3), M_poly (degree+1, 3, 3), info), polynomials in
    dT = clamp(T, t_range) - t_ref_C (t_range defaults to the data's range). info:
    b_poly_sigma_nT, M_poly_sigma (1-sigma, the posterior covariance), parameters (per
    coefficient: value, sigma, prior, source "data"/"prior", data_fraction), unobservable
    (the directions held at the prior), residual_sigma_nT (per frame axis, of the reading
    model x - b - M^-1 B), residual_rms_nT (per body axis, calibrated), cond, cost.
    uncertainty=False (the held-out comparison's fits, which use only the coefficients):
    the same coefficients, bit for bit, without the temperature reporting step's
    covariance (item 5: a pass over the samples per reported value), so the 1-sigma is
    the readings' noise alone, and without residual_sigma_nT and cond (None).
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
    K = degree + 1
    p = 12 * K
    if n * 3 <= p:
        raise InputError(source, f"reference fit: {n} samples for {p} unknowns")
    # at least 4 distinct reference directions: rows spread evenly over the data usually
    # show them already, and then all rows do (the same verdict without rounding every
    # row on each of a campaign's ~150 fits); otherwise all rows are counted
    n_dir = distinct_rows(B[::max(1, n // 256)], 1.0, at_most=4)
    if n_dir < 4:
        n_dir = distinct_rows(B, 1.0, at_most=4)
    if n_dir < 4:
        raise InputError(source, f"reference fit: the reference field takes only {n_dir} "
                                 "distinct values; at least 4 directions not in one plane "
                                 "are needed")
    tau = max(abs(t_lo - t_ref_C), abs(t_hi - t_ref_C), 1.0)
    dts = (np.clip(T, t_lo, t_hi) - t_ref_C) / tau
    P = _powers(dts, degree)
    scale = tau ** np.arange(K)                     # coefficient in scaled dT = value * tau^k
    pr = (prior or nominal_prior(degree)).truncated(degree)
    prior_s = (pr.b_poly_nT * scale[:, None], pr.M_poly * scale[:, None, None],
               pr.b_sigma_nT * scale[:, None], pr.M_sigma * scale[:, None, None])
    theta0 = np.concatenate([prior_s[0].ravel(), prior_s[1].ravel()])
    S = np.concatenate([prior_s[2].ravel(), prior_s[3].ravel()])
    lo_s, hi_s = (t_lo - t_ref_C) / tau, (t_hi - t_ref_C) / tau
    grp = _group_labels(group, n)
    n_grp = int(grp.max()) + 1

    def unpack(th):
        return th[:3 * K].reshape(K, 3), th[3 * K:].reshape(K, 3, 3)

    # Where the information is judged: at the prior's M with the offset that fits the mean
    # (degree 0; the rest at the prior), from the spread of the TRUE reading (errors in
    # variables). The reading x carries its noise, the reading the reference implies,
    # x_hat = b + M0(T)^-1 B, carries the reference's (attitude, field model); each alone
    # counts its noise as signal. Their cross-covariance does not (the two noises are
    # independent): _split_information. Not at the linear start either: a
    # regression of the reference on noisy readings that hardly move shrinks M towards 0
    # (regression dilution), and at such an M the offset looks undetermined and M
    # determined -- the reverse of the truth.
    b0_obs, M0_obs = unpack(theta0.copy())
    ref_read = _solve_M(P, M0_obs, B)                                   # M0(T)^-1 B
    b0_obs[0] = np.mean(x - P[:, 1:] @ b0_obs[1:] - ref_read, axis=0)
    x_hat = P @ b0_obs + ref_read
    stats = ReadingStats(P, x, grp, x_hat)        # J^T W J's sufficient statistics per file
    # the reading noise: stated, else estimated after the first pass (_reading_noise_var);
    # never beyond the readings' own sample-to-sample scatter (data_noise_var_bound)
    bound_var = data_noise_var_bound(x, grp)
    n_diff = n - 2 * n_grp
    eiv_var = clipped_noise_var(float(noise_nT) ** 2 if noise_nT else 0.0,
                                bound_var)
    noise_from = noise_source(noise_nT) or "none"
    theta_obs = np.concatenate([b0_obs.ravel(), M0_obs.ravel()])
    # pass 1 with a common variance, pass 2 with each file's effective variance
    v_grp = np.ones(n_grp)
    theta = None
    for _pass in range(2):
        if theta is None:
            # the common variance: residual of the unconstrained linear model
            sums = _linear_sums(P, x, B)
            v0 = max(_linear_residual_var(P, x, B, sums), 1e-6)
            w = np.full(n, 1.0 / v0)
            bs0, Ms0 = _linear_start(sums, 1.0 / v0, prior_s, degree, lo_s, hi_s, eiv_var)
            theta = np.concatenate([bs0.ravel(), Ms0.ravel()])
            # a mirrored reference (swapped or negated columns) gives a cross-information
            # with strongly negative directions, which the split would hold at the prior
            # and so hide: where the data alone determine a plausible-size reflection,
            # nothing is held and the reflection is returned (sanity gives it exit 2)
            mirrored = np.linalg.det(Ms0[0]) <= -min_abs_det()
        # unobservable directions held at the prior (not single parameters: the combination
        # the data miss is rarely one coefficient, and holding a whole coefficient would
        # throw away what the data say about the rest of it)
        free = np.ones(p, bool)
        # the noise figure's own uncertainty: a systematic error of the errors-in-variables
        # correction, which does not average down with N (_noise_var_systematic)
        # (pass 1: the figure's own; the data bound's gap only from pass 2, when the
        # residual's scatter, free of the field's motion, has tightened the bound)
        D_sys = _noise_var_systematic(stats.weighted(w)["W"], unpack(theta_obs)[1], eiv_var,
                                      noise_var_sigma(eiv_var, noise_nT,
                                                      bound_var if _pass else None))
        F_split = _split_information(P, x, x_hat, B, unpack(theta_obs), w, stats)
        split = _eig_split(F_split, S, everything=False, systematic=D_sys)
        if mirrored and _pass == 0:
            # a mirror that only weakly determined directions make (an errors-in-variables
            # correction as large as a reading axis's spread) is no mirrored reference:
            # those directions are held like any weak one (_mirror_is_determined)
            mirrored = _mirror_is_determined(theta, theta0, S, split, unpack)
        if mirrored:
            split = _eig_split(F_split, S, everything=True, systematic=D_sys)
        theta, JTJ, cost, r = yield (P, x, B, w, theta, theta0, S, unpack, free, eiv_var,
                                     split, stats)
        ev, EV, fitted = split
        if _pass == 1:
            break
        # the first pass's residual mapped back to the reading: its scatter is a second
        # upper bound of the reading noise (it carries the reference's noise, but not the
        # field's motion); the data bound is the smaller of the two, per axis
        res_var = _reading_noise_var(_solve_M(P, unpack(theta)[1], r), grp)
        if res_var is not None:
            bound_var = res_var if bound_var is None else np.minimum(bound_var, res_var)
        if not noise_nT:
            eiv_var = clipped_noise_var(0.0 if res_var is None else float(np.mean(res_var)),
                                        bound_var)
            noise_from = "estimated from second differences of the first pass's residuals"
        else:
            eiv_var = clipped_noise_var(float(noise_nT) ** 2,
                                        bound_var)
        # errors-in-variables: each file's effective variance (sensor noise through M plus
        # the reference's own), dof-corrected over all files
        dof_scale = 3 * n / max(3 * n - int(fitted.sum()), 1)
        for g in range(n_grp):
            # one file: all of r (as its copy would be: contiguous), not a copy
            rg = r if n_grp == 1 and r.flags.c_contiguous else r[grp == g]
            v_grp[g] = max(float(np.mean(rg ** 2)) * dof_scale, 1e-6) \
                * _correlation_inflation(rg)
        w = 1.0 / v_grp[grp]
    # said only beyond the bound's own estimation error (DIFF_VAR_REL_SE, 3 sigma)
    if noise_nT and eiv_var * (1.0 + 3.0 * DIFF_VAR_REL_SE / np.sqrt(max(n_diff, 1))) \
            < float(noise_nT) ** 2:
        noise_from += (", clipped to the readings' own sample-to-sample scatter "
                       f"({np.sqrt(eiv_var):.4g} nT)")
    # covariance of the posterior (module docstring), in scaled units; held: the prior's.
    # The split is pass 2's (judged with the final weights w); where nothing is held,
    # theta is pass 2's result and so are its cost, J^T W J and residuals.
    Vf, Vp = EV[:, fitted], EV[:, ~fitted]
    if Vp.shape[1]:
        zp = Vp.T @ ((theta - theta0) / S)
        theta = theta - S * (Vp @ zp)      # exactly at the prior where held
        # its cost and residuals per sample, J^T W J from the moments (no gradient)
        mom_w = stats.weighted(w)
        cost, _, _, r = vector_normal(P, x, B, *unpack(theta), False, w, eiv_var, mom_w)
        JTJ = normal_matrix(mom_w, *unpack(theta), eiv_var)
    Fv = Vf.T @ (JTJ * np.outer(S, S)) @ Vf
    A = (Vf @ _solve_floored(Fv, Vf.T)) * np.outer(S, S)     # the fit's linear response
    C = A + (Vp @ Vp.T) * np.outer(S, S)
    temp_err = None
    sig_noise = np.sqrt(np.maximum(np.diag(C), 0))     # the readings' noise alone
    # the fitted coefficients' response to the noise variance being off by its own 1-sigma
    # (per reading axis, independent): dtheta = -A dg/dsigma^2 (implicit function theorem
    # on the gradient of the adjusted cost)
    D_fit = _noise_var_systematic(stats.weighted(w)["W"], unpack(theta)[1], eiv_var,
                                  noise_var_sigma(eiv_var, noise_nT, bound_var))
    G_sys = A @ D_fit
    C = C + G_sys @ G_sys.T
    if degree > 0 and uncertainty:
        C_T, temp_err = _temperature_error_cov(P, x, unpack(theta), w, T, grp, tau,
                                               (t_lo, t_hi), A)
        C = C + C_T
    sig = np.sqrt(np.maximum(np.diag(C), 0))
    frac = np.sum(Vf ** 2, axis=1)
    z = (theta - theta0) / S
    bp_s, Mp_s = unpack(theta)
    b_poly, M_poly = bp_s / scale[:, None], Mp_s / scale[:, None, None]
    bsig = sig[:3 * K].reshape(K, 3) / scale[:, None]
    Msig = sig[3 * K:].reshape(K, 3, 3) / scale[:, None, None]
    names = parameter_names(degree)
    unscale = np.concatenate([np.repeat(scale, 3), np.repeat(scale, 9)])
    th_val, th0, s_val = theta / unscale, theta0 / unscale, S / unscale
    params = [{"name": nm, "value": float(th_val[i]), "sigma": float(sig[i] / unscale[i]),
               "prior": float(th0[i]), "prior_sigma": float(s_val[i]),
               "data_fraction": float(frac[i]),
               "source": "data" if frac[i] >= DATA_FRACTION else "prior"}
              for i, nm in enumerate(names)]
    unobs = []
    for j in np.nonzero(~fitted)[0]:
        v = EV[:, j]
        top = np.argsort(-np.abs(v))[:4]
        unobs.append({"information_vs_prior": float(ev[j]),
                      "direction": {names[i]: round(float(v[i]), 3) for i in top
                                    if abs(v[i]) > 0.2},
                      # whitened unit vector (coefficient / prior sigma) and the fit's
                      # component along it (0: held at the prior)
                      "vector": [float(a) for a in v], "offset_from_prior": float(v @ z)})
    # residuals: calibrated (body axes) and of the reading model (frame axes, W r)
    res_sigma = cond = None
    if uncertainty:
        T_c = np.clip(T, t_lo, t_hi) - t_ref_C
        Pp = _powers(T_c, degree)
        read_res = _solve_M(Pp, M_poly, r)
        dof = max(3 * n - int(fitted.sum()), 1) / 3
        res_sigma = np.sqrt(np.sum(read_res ** 2, axis=0) / dof)
        col = np.sqrt(np.diag(JTJ))
        col[col == 0] = 1.0
        Gn = JTJ / np.outer(col, col)
        try:                       # LAPACK may not converge on a near-degenerate design
            evn = np.linalg.eigvalsh(Gn) if np.all(np.isfinite(Gn)) else None
        except np.linalg.LinAlgError:
            evn = None
        cond = (float(np.sqrt(evn[-1] / evn[0])) if evn is not None and evn[0] > 0
                else float("inf"))
    info = {
        "n": int(n), "degree": int(degree), "cond": cond, "t_range_C": (t_lo, t_hi),
        "b_poly_sigma_nT": bsig, "M_poly_sigma": Msig,
        # the part of the 1-sigma from the readings' noise alone (without the temperature
        # reporting error): what a design-only prediction (campaign.check) can compare with
        "b_poly_sigma_noise_nT": sig_noise[:3 * K].reshape(K, 3) / scale[:, None],
        "M_poly_sigma_noise": sig_noise[3 * K:].reshape(K, 3, 3) / scale[:, None, None],
        "residual_sigma_nT": res_sigma,
        "residual_rms_nT": np.sqrt(np.mean(r ** 2, axis=0)),
        "cost": float(np.sum(r ** 2)),
        "parameters": params, "unobservable": unobs,
        "prior_source": pr.source,
        "noise": {"stated_nT": None if noise_nT is None else float(noise_nT),
                  "variance_uncertainty": noise_var_uncertainty(noise_nT),
                  "reading_nT": float(np.sqrt(eiv_var)), "reading_from": noise_from,
                  # the readings' own second-difference scatter per axis: an upper bound
                  # of their noise (data_noise_var_bound)
                  "data_bound_nT": (None if bound_var is None
                                    else np.sqrt(bound_var).tolist()),
                  "variance_sigma_nT2": noise_var_sigma(eiv_var, noise_nT, bound_var),
                  "effective_per_file_nT": np.sqrt(v_grp).tolist()},
        "temperature_error": temp_err,
        "estimator": "calibrated-minus-reference least squares (linear start, Gauss-Newton), "
                     "per-file errors-in-variables weights, unobservable directions held at "
                     "the prior",
    }
    return b_poly, M_poly, info


def _temperature_error_cov(P, x, bM, w, T, grp, tau, t_range, A):
    """Covariance the reported temperature's reporting step adds to the coefficients
    (scaled units; module docstring, item 5). A temperature reported in steps of q
    (segments.temperature_quantum, per file) is off by a uniform error of variance q^2/12,
    and that error is the SAME for every sample reported with the same value while the
    true temperature stays in the step (a chamber hold: thousands of samples), so it does
    not average down with N like the reading noise. Each (file, reported value) is taken
    as one error e_v, independent between values (conservative within a step where the
    true temperature moves, as on a ramp). To first order it moves the residuals by
    D_n e_v, D_n = dr_n/dT (temperature_derivative), and the estimate by -A J^T W D e_v
    (A the fit's response, the data part of the covariance). Returns (C_T, figures)."""
    key, var_b, fig = temperature_bins(T, grp)
    Hb = temperature_error_rows(P, x, bM, w, T, key, len(var_b), tau, t_range)
    Q = (Hb * var_b[:, None]).T @ Hb
    C_T = A @ Q @ A.T
    return 0.5 * (C_T + C_T.T), fig


def temperature_error_rows(P, x, bM, w, T, key, n_bins, tau, t_range):
    """Per bin v (key: the bin of each sample) the sum of the rows J_n^T w_n D_n
    (vector_gradient_rows of temperature_derivative), (n_bins, 12 K). A bin holds one
    reported temperature (temperature_bins: one file, one value), so P_n, M(T_n), b(T_n)
    and their derivatives are the bin's, and D_n = M'(T)(x_n - b(T)) - M(T) b'(T) is
    linear in the reading: the sums need only the bin's sum w, sum w x and sum w x x^T
    (one pass over the samples, 13 columns), not a (N, 12 K) row per sample."""
    n, K = P.shape
    w = np.broadcast_to(np.ones(n) if w is None else np.asarray(w, float), (n,))
    S = np.zeros((n_bins, 13))
    for a in range(0, n, MOMENT_CHUNK):     # in blocks: bounded temporaries
        sl = slice(a, min(a + MOMENT_CHUNK, n))
        xs, ws = x[sl], w[sl]
        H = np.empty((len(xs), 13))
        H[:, 0] = ws
        np.multiply(ws[:, None], xs, out=H[:, 1:4])
        _outer_columns(H[:, 1:4].T.copy(), xs.T.copy(), H, 4)      # (w x) x^T
        _bin_sums(S, key[sl], H)
    first = np.zeros(n_bins, np.intp)          # a sample of each bin: its T and powers
    first[key[::-1]] = np.arange(n)[::-1]
    Pb, Tb = P[first], T[first]
    bp, Mp = bM
    inside = (Tb >= t_range[0]) & (Tb <= t_range[1])
    dts = Pb[:, 1] if K > 1 else np.zeros(n_bins)
    dPb = np.zeros_like(Pb)
    for k in range(1, K):
        dPb[:, k] = k * dts ** (k - 1) / tau
    dPb[~inside] = 0.0
    Mb = (Pb @ Mp.reshape(K, 9)).reshape(-1, 3, 3)
    dMb = (dPb @ Mp.reshape(K, 9)).reshape(-1, 3, 3)
    bb, Mdb = Pb @ bp, np.einsum("vij,vj->vi", Mb, dPb @ bp)      # b(T), M(T) b'(T)
    s0, s1, s2 = S[:, 0], S[:, 1:4], S[:, 4:13].reshape(-1, 3, 3)
    Y1 = s1 - s0[:, None] * bb                                     # sum w y, y = x - b(T)
    Y2 = (s2 - s1[:, :, None] * bb[:, None, :] - bb[:, :, None] * s1[:, None, :]
          + s0[:, None, None] * bb[:, :, None] * bb[:, None, :])    # sum w y y^T
    SD = np.einsum("vij,vj->vi", dMb, Y1) - s0[:, None] * Mdb       # sum w D
    SDy = np.einsum("vij,vjk->vik", dMb, Y2) - Mdb[:, :, None] * Y1[:, None, :]  # sum w D y^T
    gb = -Pb[:, :, None] * np.einsum("vil,vi->vl", Mb, SD)[:, None, :]     # [k, l]
    gM = Pb[:, :, None, None] * SDy[:, None, :, :]                         # [k, a, c]
    return np.concatenate([gb.reshape(n_bins, -1), gM.reshape(n_bins, -1)], axis=1)


def temperature_derivative(P, x, bM, T, tau, t_range):
    """d r_n / dT_n (N, 3) of r = M(T)(x - b(T)) - B: M'(T)(x - b(T)) - M(T) b'(T); P the
    powers of the scaled dT (P[:, 1] = dT / tau), bM the scaled (b_poly, M_poly); zero
    where T is clamped (outside t_range)."""
    n, K = P.shape
    inside = (T >= t_range[0]) & (T <= t_range[1])
    dts = P[:, 1] if K > 1 else np.zeros(n)
    dP = np.zeros_like(P)
    for k in range(1, K):
        dP[:, k] = k * dts ** (k - 1) / tau
    dP[~inside] = 0.0
    bp, Mp = bM
    MT = (P @ Mp.reshape(K, 9)).reshape(n, 3, 3)
    dM = (dP @ Mp.reshape(K, 9)).reshape(n, 3, 3)
    y = x - P @ bp
    return np.einsum("nij,nj->ni", dM, y) - np.einsum("nij,nj->ni", MT, dP @ bp)


def vector_gradient_rows(P, x, bM, w, D):
    """Per sample J_n^T w_n D_n (N, 12 K) for vector rows (parameters b[k,l], then
    M[k,a,c]; vector_normal's gradient formulas with r replaced by D)."""
    n, K = P.shape
    bp, Mp = bM
    MT = (P @ Mp.reshape(K, 9)).reshape(n, 3, 3)
    y = x - P @ bp
    w = np.ones(n) if w is None else np.broadcast_to(w, (n,))
    out = np.empty((n, 12 * K))       # written in place: no (N, K, 3, 3) temporaries
    gb = out[:, :3 * K].reshape(n, K, 3)
    np.multiply(w[:, None, None] * P[:, :, None],
                np.einsum("nil,ni->nl", MT, D)[:, None, :], out=gb)
    np.negative(gb, out=gb)
    wP = w[:, None] * P
    gM = out[:, 3 * K:].reshape(n, K, 3, 3)
    for k in range(K):
        np.multiply((wP[:, k, None] * D)[:, :, None], y[:, None, :], out=gM[:, k])
    return out


def temperature_bin_information(G, T, grp):
    """Q = sum over (file, reported value) bins v of (q_f^2 / 12) h_v h_v^T, h_v the sum
    of the rows of G (per-sample J^T W D) in the bin; q_f the file's reporting step (the
    sensor's over all files where the file reports a single value; temperature_bins)."""
    key, var_b, fig = temperature_bins(T, grp)
    Hb = _bin_sums(np.zeros((len(var_b), G.shape[1])), key, G)
    return (Hb * var_b[:, None]).T @ Hb, fig


def temperature_bins(T, grp):
    """The (file, reported value) bins of temperature_bin_information: (bin of each sample
    (N,), q_f^2 / 12 per bin, figures). Bins in the order of np.unique over the rows
    (file, T)."""
    from generator.fit.segments import quantum_of_values

    grp = np.zeros(len(T), int) if grp is None else np.asarray(grp)
    n_grp = int(grp.max()) + 1
    # T is finite (reference_fit): its distinct values, sorted, serve the step of all
    # files (temperature_quantum of T) and, with one file, that file's and the bins
    t_vals, t_idx = np.unique(T, return_inverse=True)
    t_idx = np.ravel(t_idx)
    # a file reporting one value only (a rotation at room temperature) shows no step of
    # its own: the sensor's step from all its files
    q_all = quantum_of_values(t_vals)
    q = []
    for g in range(n_grp):
        u = t_vals if n_grp == 1 else np.unique(T[grp == g])
        q.append(quantum_of_values(u) if len(u) > 1 else q_all)
    q = np.array(q)
    if n_grp == 1:          # the bins are the values (np.unique of t_idx is t_idx's own)
        key = t_idx
    else:
        _, key = np.unique(grp.astype(np.int64) * len(t_vals) + t_idx, return_inverse=True)
        key = np.asarray(key).ravel()
    var_b = np.zeros(int(key.max()) + 1)
    var_b[key] = (q ** 2 / 12.0)[grp]
    return key, var_b, {
        "quantum_C_per_file": q.tolist(), "values": int(len(var_b)),
        "note": "temperature reporting step: q^2/12 per reported value, common to its "
                "samples"}


def _bin_sums(Hb, key, G):
    """Hb[v] += sum of the rows of G whose key is v (a sort and reduceat: np.add.at is
    ~50x slower on 10^5 rows); returns Hb."""
    order = np.argsort(key, kind="stable")
    ks = key[order]
    starts = np.flatnonzero(np.diff(ks, prepend=-1))
    Hb[ks[starts]] += np.add.reduceat(G[order], starts, axis=0)
    return Hb


def _split_information(P, x, x_hat, B, bM, w, stats: ReadingStats | None = None):
    """J^T W J with the regressor's second moments replaced by the symmetrised cross
    moments of x and x_hat (two readings of the same true reading with independent
    noises: their cross-covariance is the true reading's). J^T W J is a constant plus a
    linear plus a quadratic form in the regressor, so with m = (x + x_hat) / 2 the
    cross version is 2 J(m) - (J(x) + J(x_hat)) / 2. Not positive definite where the
    two disagree (a negative cross-covariance: the reading does not follow the
    reference); such directions fall below FISHER_THRESHOLD and are held."""
    mom = stats.weighted(w, cross=True) if stats else reading_moments(P, x, w, x_cross=x_hat)
    return normal_matrix(mom, *bM)


def _reading_noise_var(d, grp):
    """Variance of the reading noise per axis (3,) (None with too few samples), for a part
    with no figure (the mean over the axes) and as a bound of a figure
    (data_noise_var_bound): difference_noise_var of d, the first pass's residuals mapped
    back to the reading (M^-1 r), within each file. Only what changes
    from sample to sample counts: a slow drift (of the reading, or of a fit that is still
    diluted) is not noise of the reading (it goes to the residual's correlation,
    _correlation_inflation). The reference's own noise is counted in too: an
    overestimate, whose adjusted-least-squares bias is that variance over the reading's
    spread -- negligible where M is determined, and where it is not, observability holds M
    at the prior (its systematic, NOISE_VAR_UNCERTAINTY, is in the split)."""
    return difference_noise_var(_by_group(d, grp))


# Second differences beyond this many of their own standard deviations are outliers
# (a glitch, a reference jump), left out of difference_noise_var; for normal noise the
# cut loses 6e-7 of the variance.
DIFF_CLIP_SIGMAS = 5.0


def difference_noise_var(series) -> np.ndarray | None:
    """Per-axis variance of the white (sample-to-sample) noise of series: a list of
    (n_i, k) arrays in time order (one per file; or (n_i,) for one axis). From the second
    differences e_{n+1} - 2 e_n + e_{n-1}, whose variance is 6 sigma^2 for white noise
    and which cancel an offset and a ramp (a field or residual that changes steadily
    between samples is not noise), as the mean square about their mean after an
    iterative DIFF_CLIP_SIGMAS clip. The mean square, not a median of absolute values:
    quantised readings make the differences whole multiples of the step, and where the
    noise is below one step most of them are 0, so a median (MAD) sees less than the
    noise, or nothing; the mean square of quantised readings is the noise's plus the
    step's q^2/12 when the signal moves by more than a step between samples (the
    quantisation error is then uniform and independent; that is the figure
    fit.samples.field_noise_nT states for counts). None with fewer than 3 differences."""
    dd = []
    for a in series:
        a = np.asarray(a, float)
        a = a.reshape(len(a), -1)
        if len(a) >= 3:
            dd.append(a[2:] - 2.0 * a[1:-1] + a[:-2])
    if not dd or sum(len(a) for a in dd) < 3:
        return None
    d = np.ascontiguousarray(np.concatenate(dd).T)        # (k, n): an axis contiguous
    keep = None                                           # None: every difference
    for _ in range(5):
        if keep is None:          # every difference: one reduction per axis row (the same
            mu = np.mean(d, axis=1)                       # pairwise sums as per row)
            dev = d - mu[:, None]
            var = np.mean(dev ** 2, axis=1)
        else:
            kept = [a[m] for a, m in zip(d, keep)]
            mu = np.array([np.mean(a) for a in kept])
            var = np.array([np.mean((a - m) ** 2) for a, m in zip(kept, mu)])
            dev = d - mu[:, None]
        new = np.abs(dev) <= (DIFF_CLIP_SIGMAS * np.sqrt(var))[:, None]
        if new.all() if keep is None else np.array_equal(new, keep):
            break
        keep = new
    return var / 6.0


def _correlation_inflation(r):
    """Variance inflation of a file's residuals for their serial correlation: with lag-1
    autocorrelation rho (samples in time order), n samples carry the information of
    n (1 - rho) / (1 + rho) independent ones (AR(1) effective sample size; exact for a
    slowly varying regressor, a lower bound of the information otherwise), so the
    effective variance is v (1 + rho) / (1 - rho). White residuals (rho ~ 0, the model
    right and the noise white) leave v as it is; a residual that drifts (disturbance,
    an estimator's attitude error, a model that does not hold) does not count as n
    independent samples. rho is clipped to [0, MAX_RHO]."""
    r = r - np.mean(r, axis=0)
    den = float(np.sum(r[:-1] * r[:-1]))
    if len(r) < 3 or den <= 0:
        return 1.0
    rho = min(max(float(np.sum(r[1:] * r[:-1])) / den, 0.0), MAX_RHO)
    return (1.0 + rho) / (1.0 - rho)


def _eig_split(JTJ, S, margin=None, everything=False, systematic=None):
    """Eigen-split of the whitened information; margin: information to take off first
    (NOISE_VAR_UNCERTAINTY x the noise of x, errors in variables); everything: fit all
    directions (a mirrored reference, reference_fit); systematic: (p, m) columns d_j, the
    gradient's change for a 1-sigma error of each source of a systematic error common to
    all samples (_noise_var_systematic).

    With a systematic error the data's estimate has the covariance F^-1 + F^-1 D D^T F^-1
    (F the information, D the columns whitened), and so the information
    F_eff = F - D (I + D^T F^-1 D)^-1 D^T (Woodbury): a direction whose estimate the
    systematic moves by more than the prior's 1-sigma carries less information than the
    prior and is held. Computed on F's positive eigen-subspace (the rest is below
    FISHER_THRESHOLD already)."""
    F = (JTJ if margin is None else JTJ - margin) * np.outer(S, S)
    ev, EV = np.linalg.eigh(F)
    if systematic is not None and np.any(systematic) and not everything:
        pos = ev > 1e-12 * max(float(ev[-1]), 1e-300)
        Ep, lp = EV[:, pos], ev[pos]
        Dp = Ep.T @ (systematic * S[:, None])              # whitened, in the eigenbasis
        K_ = np.eye(Dp.shape[1]) + Dp.T @ (Dp / lp[:, None])
        Fp = np.diag(lp) - Dp @ np.linalg.solve(K_, Dp.T)
        lq, U = np.linalg.eigh(0.5 * (Fp + Fp.T))
        ev = np.concatenate([ev[~pos], lq])
        EV = np.concatenate([EV[:, ~pos], Ep @ U], axis=1)
        order = np.argsort(ev)
        ev, EV = ev[order], EV[:, order]
    return ev, EV, (ev >= FISHER_THRESHOLD) | everything


def data_noise_var_bound(x, grp):
    """(3,) per reading axis, an UPPER bound of the reading noise's variance from the
    data themselves: difference_noise_var of the readings within each file. Second
    differences cancel the field's offset and ramp; what is left is the reading's white
    noise plus the curvature of the field's own motion between samples (B (omega dt)^2:
    14 nT for 45 uT turning 1 deg per sample), so it is never below the noise. None with
    too few samples."""
    grp = np.zeros(len(x), int) if grp is None else np.asarray(grp)
    return difference_noise_var(_by_group(x, grp))


# Relative standard error of difference_noise_var's variance from n second differences of
# white noise, times sqrt(n): their lag correlations are -2/3 and 1/6, so the mean square
# has variance 2 (1 + 2 (4/9 + 1/36)) / n = 3.89 / n of its mean squared.
DIFF_VAR_REL_SE = float(np.sqrt(2.0 * (1.0 + 2.0 * (4.0 / 9.0 + 1.0 / 36.0))))


def clipped_noise_var(var, bound_var) -> float:
    """The errors-in-variables variance: var (a figure squared, or an estimate), but never
    above the quietest axis's data bound (data_noise_var_bound). Subtracting more noise
    than the readings carry makes the corrected second moment of a weakly excited reading
    axis (a 2 deg tilt: the vertical reading moves by ~1 uT) too small or negative, which
    turns that column of M into a large or mirrored one. One variance for all axes: the
    quietest axis's bound, so that no axis is over-corrected (an axis noisier than that
    keeps a dilution bias of the difference over its spread, small where it is excited).
    The bound's own estimate, not its upper confidence limit: subtracting even a few %
    too much on a barely moving axis bends M far more than the same too little (the
    moment's relative error is the excess over the axis's true spread)."""
    if bound_var is None or not var:
        return float(var or 0.0)
    return float(min(var, float(np.min(bound_var))))


def noise_var_sigma(eiv_var, noise_nT, bound_var) -> float:
    """1-sigma of the errors-in-variables variance eiv_var (per axis): the figure's own
    relative uncertainty (noise_var_uncertainty), and at least the distance to the largest
    data bound (data_noise_var_bound): the readings' noise lies between the figure and
    that bound when the figure is below it (a figure stated too small, or the reference's
    or the motion's share of the scatter), so the whole gap is the error the correction
    may make. Conservative: the information and the covariance count with it."""
    s = noise_var_uncertainty(noise_nT) * eiv_var
    if bound_var is not None and eiv_var:
        s = max(s, float(np.max(bound_var)) - eiv_var)
    return float(s)


def _noise_var_systematic(W, Mp, eiv_var, var_sigma):
    """(p, 3): per reading axis c, the change of the adjusted cost's gradient g (J^T W r
    with the errors-in-variables term, vector_normal) when that axis's noise variance is
    off by its own 1-sigma, var_sigma (noise_var_sigma). The term is
    -eiv_var sum_n w_n |M(T_n)|_F^2 = -sum_c sigma_c^2 sum_{k,m} W[k+m] sum_a M_k[a,c] M_m[a,c],
    so dg/dsigma_c^2 is -sum_m W[k+m] M_m[a,c] on M[k, a, c] and 0 elsewhere. Each axis
    independently (a part's axes need not share one noise). Zeros without a noise."""
    K = len(Mp)
    out = np.zeros((12 * K, 3))
    if not eiv_var or not var_sigma:
        return out
    idx = np.add.outer(np.arange(K), np.arange(K))
    WM = np.einsum("km,mac->kac", W[idx], Mp)
    for c in range(3):
        g = np.zeros((K, 3, 3))
        g[:, :, c] = -WM[:, :, c]
        out[3 * K:, c] = g.ravel() * var_sigma
    return out


def noise_source(noise_nT) -> str | None:
    """Where a noise figure came from: NOISE_STATED, NOISE_CATALOGUE (a
    fit.samples.NoiseFigure's source), None (no figure). A plain number counts as stated."""
    if not noise_nT:
        return None
    return getattr(noise_nT, "source", NOISE_STATED)


def noise_var_uncertainty(noise_nT) -> float:
    """Relative 1-sigma of the noise VARIANCE of a figure from noise_source's sources."""
    return (CATALOGUE_NOISE_VAR_UNCERTAINTY if noise_source(noise_nT) == NOISE_CATALOGUE
            else NOISE_VAR_UNCERTAINTY)


def min_abs_det(part="default") -> float:
    """Smallest |det M| plausible for the part: singular values at least 1 - 3 s (s the
    prior's 1-sigma of M). A negative det of that size is a mirrored reference (a
    reflection); one nearer 0 is a degenerate fit (M not determined by the data)."""
    s = PART_PRIOR_SIGMA.get(part, PART_PRIOR_SIGMA["default"])["M"][0]
    return (1.0 - 3.0 * s) ** 3


def _solve_floored(Fv, R):
    """Fv^-1 R for the whitened information Fv of the fitted directions, with Fv's
    eigenvalues floored at FISHER_THRESHOLD (the prior's own information) where one falls
    below it. The split judged these directions on the cross information; the adjusted
    least squares' information (errors-in-variables term subtracted) can still fall below
    the prior's, or below 0, in a direction whose reading axis barely moves: its inverse
    would give a 1-sigma of 0 (a negative variance clipped) or an unbounded response.
    There the data determine the direction no better than the prior, so the prior's
    1-sigma is the honest figure. Where every eigenvalue is above it, a plain solve."""
    lam, U = np.linalg.eigh(0.5 * (Fv + Fv.T))
    if len(lam) == 0 or lam[0] >= FISHER_THRESHOLD:
        return np.linalg.solve(Fv, R)
    return U @ ((U.T @ R) / np.maximum(lam, FISHER_THRESHOLD)[:, None])


def _mirror_is_determined(theta, theta0, S, split, unpack) -> bool:
    """Whether the linear start theta's reflection (det M0 <= -min_abs_det) lies in
    directions the data determine: the start with its weak directions (whitened
    information |lambda| < FISHER_THRESHOLD: the data say less about them than the prior)
    put back at the prior still has det M0 <= -min_abs_det. A mirrored reference
    (swapped or negated ref columns) makes directions whose information is strongly
    NEGATIVE (the reading moves against the reference: lambda <= -FISHER_THRESHOLD) and
    keeps its reflection there; a sign flipped by a weakly excited reading axis (the
    vertical of a yaw-only flight) is gone once that axis is held."""
    ev, EV, fitted = split
    keep = fitted | (ev <= -FISHER_THRESHOLD)
    Vk = EV[:, keep]
    z = (theta - theta0) / S
    th = theta0 + S * (Vk @ (Vk.T @ z))
    return bool(np.linalg.det(unpack(th)[1][0]) <= -min_abs_det())


def _noise_margin(W, K, eiv_var):
    """NOISE_VAR_UNCERTAINTY x the information the noise of x would fake, on the M block;
    W: the moments' sum w d^p (sum_n w P_k P_m = W[k + m])."""
    out = np.zeros((12 * K, 12 * K))
    if eiv_var:
        PtP = W[np.add.outer(np.arange(K), np.arange(K))]
        out[3 * K:, 3 * K:] = NOISE_VAR_UNCERTAINTY * eiv_var * np.kron(PtP, np.eye(9))
    return out


def _gauss_newton(P, x, B, w, theta, theta0, S, unpack, free, eiv_var=0.0, split=None,
                  stats: ReadingStats | None = None):
    """Gauss-Newton on the weighted cost in whitened coordinates z = (theta - theta0)/S of
    the free parameters (the others stay at the prior), restricted to the directions the
    data determine (module docstring). Returns (theta, JTJ of all parameters, cost, r)."""
    f = np.nonzero(free)[0]
    S_f, th0_f = S[f], theta0[f]
    theta = theta.copy()
    theta[~free] = theta0[~free]

    def at(z):
        th = theta.copy()
        th[f] = th0_f + S_f * z
        return th

    z = (theta[f] - th0_f) / S_f
    # J^T W J's statistics and the cost's and gradient's (ResidualStats, centred on the
    # start): the same every iterate, so an iterate costs no pass over the samples
    mom = stats.weighted(w) if stats else reading_moments(P, x, w)
    rs = ResidualStats(P, x, B, w, *unpack(at(z)), mom)
    # the split is judged here only when not given (or not over all parameters)
    margin = None
    if split is None or len(f) != len(S):
        margin = _noise_margin(mom["W"], P.shape[1], eiv_var)[np.ix_(f, f)]

    def vector_normal_(th, jac):
        bp, Mp = unpack(th)
        cost, g = rs.cost_grad(bp, Mp, jac, eiv_var, mom["W"])
        return cost, (normal_matrix(mom, bp, Mp, eiv_var) if jac else None), g

    first = True
    SS = np.outer(S_f, S_f)
    for _ in range(GN_MAX_ITER):
        cost, JTJ, g = vector_normal_(at(z), True)
        if split is not None and len(f) == len(S):
            ev, EV, fitted = split          # judged once, at the prior (reference_fit)
        else:
            ev, EV, fitted = _eig_split(JTJ[np.ix_(f, f)], S_f, margin)
        Vf = EV[:, fitted]
        Jw = JTJ[np.ix_(f, f)] * SS            # whitened J^T W J of the free parameters
        evj = np.einsum("pi,pq,qi->i", Vf, Jw, Vf)
        if first:               # the start's component where the data say nothing: the prior
            z = Vf @ (Vf.T @ z)
            cost, JTJ, g = vector_normal_(at(z), True)
            first = False
            Jw = JTJ[np.ix_(f, f)] * SS
        Fv = Vf.T @ Jw @ Vf
        dz = -Vf @ np.linalg.solve(Fv, Vf.T @ (S_f * g[f]))
        step = 1.0
        while step > 1e-4:
            z_new = z + step * dz
            c_new = vector_normal_(at(z_new), False)[0]
            if c_new <= cost + 1e-12 * abs(cost):
                break
            step *= 0.5
        else:
            break
        d = Vf.T @ (z_new - z)
        done = float(np.sum(evj * d * d)) < 1e-10    # the step moves chi^2 by < 1e-10
        z = z_new
        if done:
            break
    return gauss_newton_result(P, x, B, w, at(z), unpack, eiv_var, mom)


def gauss_newton_result(P, x, B, w, theta, unpack, eiv_var, mom):
    """A Gauss-Newton run's result at its last iterate theta: (theta, J^T W J, cost, r),
    the cost and residuals per sample (what the fit reports); the gradient is not needed."""
    cost, _, _, r = vector_normal(P, x, B, *unpack(theta), False, w, eiv_var, mom)
    return theta, normal_matrix(mom, *unpack(theta), eiv_var), cost, r
