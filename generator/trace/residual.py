"""What is left after a trace, against the noise floor (issue 17, honesty).

The noise floor of a sensor's residual is the data's own sample-to-sample noise: the
robust spread of first differences of the residual rows along time (per axis / kind
and per file, 1.4826 MAD / sqrt(2): a slow structure or a few jumps hardly move it; the
files' variances pooled by their rows),
reported beside the part's noise (the unit's `noise_nT`, divided by sqrt(2) for a
SET/RESET part, which averages two readings). The floor used is the data's where it can
be measured (it includes the reference's noise), else the part's.

A residual is "at the noise" when its mean square is consistent with the floor's square:
under white noise at the floor, mean(r^2) / floor^2 follows F(n, d) (n the residual rows;
d the degrees of freedom of the floor's own estimate: infinite for the part's stated
noise, 0.37 x half the differences for the data's, the efficiency of the MAD with each
sample shared by two differences), and the residual is at the noise unless the ratio
exceeds the upper NOISE_ALPHA quantile of F. Otherwise it is "above the noise". Such a
residual, with no catalogue effect left that explains it, is listed as `unexplained`
with what it follows most: for each quantity (time, temperature, the channels, the field
direction, the body rates, the coil currents) the correlation ratio eta^2, the share of
the residual's variance explained by its mean in N_BINS quantile bins of the quantity
(nonlinear relations, steps and jumps included). A quantity that does not vary explains
nothing; by chance alone eta^2 is about N_BINS / n.
"""

from __future__ import annotations

import math

import numpy as np

from generator.trace.crossval import _lag1
from generator.trace.samples import SensorSamples

NOISE_ALPHA = 1e-3        # upper-tail probability of the at-the-noise test (module doc)
MAD_EFFICIENCY = 0.37     # asymptotic efficiency of the MAD against the standard deviation
N_BINS = 10               # quantile bins of a quantity (correlation ratio)
MAD_TO_SIGMA = 1.4826     # MAD of a normal variable -> its standard deviation
# a file's own noise estimate needs enough differences: the MAD's relative standard error
# is ~sqrt(1 / (0.37 n)), 15 % at 120 differences; smaller files are pooled together
MIN_FILE_DIFFS = 120


def per_sample(S: SensorSamples, r) -> np.ndarray:
    """Residual rows -> (n, 3) per sample (magnitude rows in column 0, NaN elsewhere)."""
    out = np.full((S.n, 3), np.nan)
    iv, im, ip = S.idx
    nv, nm = 3 * len(iv), len(im)
    if len(iv):
        out[iv] = r[:nv].reshape(-1, 3)
    if len(im):
        out[im, 0] = r[nv:nv + nm]
    if len(ip):
        out[ip] = r[nv + nm:].reshape(-1, 3)
    return out


def data_noise_nT(S: SensorSamples, r, n_diff=None) -> float | None:
    """The residual's own sample-to-sample noise (RMS over rows), from robust first
    differences along time within each file; None with too few samples. n_diff: a list
    that receives the number of differences used.

    The spread is estimated per (axis / kind, file) and the variances pooled weighted by
    the rows: files recorded at different noise levels (another sensor mode, another
    vehicle) have a mean square that is the rows' mean of their variances, which one MAD
    over the pooled differences would put near the majority's (review #20c N9: a 10 nT and
    a 100 nT file gave a floor near 10 nT and tens of nT "unexplained"). A file with fewer
    than MIN_FILE_DIFFS differences on an axis joins the pool of such small files."""
    rs, ax = S.row_sample, S.row_axis
    var, cnt = 0.0, 0
    nd = 0
    for a in range(4):
        sel = np.nonzero(ax == a)[0]
        if len(sel) < 3:
            continue
        o = sel[np.argsort(S.order[rs[sel]], kind="stable")]
        f = S.file_index[rs[o]]
        same = f[1:] == f[:-1]
        d = np.diff(r[o])[same]
        if len(d) < 2:
            continue
        fd = f[1:][same]                              # the file of each difference
        files, n_d = np.unique(fd, return_counts=True)
        rows = np.bincount(f, minlength=int(f.max()) + 1)
        small = files[n_d < MIN_FILE_DIFFS]
        groups = [fd == k for k in files[n_d >= MIN_FILE_DIFFS]]
        if len(small):
            groups.append(np.isin(fd, small))
        for g in groups:
            dg = d[g]
            if len(dg) < 2:
                continue
            mad = float(np.median(np.abs(dg - np.median(dg))))
            s = MAD_TO_SIGMA * mad / math.sqrt(2.0)
            n_rows = int(rows[np.unique(fd[g])].sum())
            var += s * s * n_rows
            cnt += n_rows
            nd += len(dg)
    if n_diff is not None:
        n_diff.append(nd)
    return math.sqrt(var / cnt) if cnt else None


def part_noise_nT(spec) -> float | None:
    n = getattr(spec, "noise_nT", None)
    if n is None:
        return None
    return float(n) / math.sqrt(2.0) if getattr(spec, "set_reset", False) else float(n)


def noise_floor(S: SensorSamples, r) -> dict:
    from scipy import stats as sps
    nd = []
    data = data_noise_nT(S, r, nd)
    part = part_noise_nT(S.spec)
    floor = data if data is not None else part
    if magnitude_only(S) and part and (floor is None or floor < part):
        floor = part    # magnitudes alone can be contracted below the noise: not a floor
    rms = float(np.sqrt(np.mean(r * r))) if r.size else float("nan")
    out = {"residual_rms_nT": rms, "data_noise_nT": data, "part_noise_nT": part,
           "floor_nT": floor, "source": "data" if floor == data else "part"}
    out["ratio"] = rms / floor if floor else None
    out["rms_above_noise_nT"] = math.sqrt(max(rms * rms - floor * floor, 0.0)) if floor \
        else None
    n = int(r.size)
    d = MAD_EFFICIENCY * nd[0] / 2.0 if out["source"] == "data" and nd else math.inf
    limit = (float(sps.chi2.isf(NOISE_ALPHA, n)) / n if math.isinf(d) else
             float(sps.f.isf(NOISE_ALPHA, n, max(d, 1.0)))) if n else math.inf
    out["at_noise_limit_ratio"] = math.sqrt(limit)     # the largest ratio at the noise
    out["at_noise"] = bool(floor) and n > 0 and (rms / floor) ** 2 <= limit
    return out


def quantities(S: SensorSamples, B_cal=None) -> dict:
    """The quantities a residual may follow, per sample: name -> (n,)."""
    q = {"time_s": S.time_s.astype(float), "temperature_C": S.temp_C.astype(float)}
    for c, v in S.channels.items():
        q[c] = np.asarray(v, float)
    if B_cal is not None:
        nrm = np.linalg.norm(B_cal, axis=1)
        ok = nrm > 0
        for k, a in enumerate("xyz"):
            q[f"field direction {a}"] = np.where(ok, B_cal[:, k] / np.where(ok, nrm, 1), 0.0)
    if S.rate_frame_dps is not None:
        w = np.asarray(S.rate_frame_dps, float)
        q["rate magnitude_dps"] = np.linalg.norm(w, axis=1)
        for k, a in enumerate("xyz"):
            if f"rate_{a}_dps" not in q:      # the rate column itself is a channel already
                q[f"rate {a}_dps"] = w[:, k]
    if S.coil is not None:
        for k in range(S.coil.shape[1]):
            q[f"coil {k}"] = np.asarray(S.coil[:, k], float)
    return q


def correlation_ratio(v, q, n_bins=N_BINS) -> float:
    """eta^2 of the per-sample residual v (n, k) over the quantity q (n,): the share of
    its variance (about its mean, all columns) taken by its means in quantile bins of q."""
    ok = np.isfinite(q) & np.isfinite(v).all(axis=1)
    v, q = v[ok], q[ok]
    if len(q) < 2 * n_bins or np.ptp(q) == 0:
        return 0.0
    edges = np.unique(np.quantile(q, np.linspace(0, 1, n_bins + 1)))
    if len(edges) < 2:
        return 0.0
    b = np.clip(np.searchsorted(edges, q, side="right") - 1, 0, len(edges) - 2)
    dev = v - v.mean(axis=0)
    sst = float(np.sum(dev * dev))
    if sst <= 0:
        return 0.0
    cnt = np.bincount(b)
    ssb = 0.0
    for k in range(v.shape[1]):
        s = np.bincount(b, weights=dev[:, k])
        nz = cnt > 0
        ssb += float(np.sum(s[nz] ** 2 / cnt[nz]))
    return ssb / sst


def correlates(S: SensorSamples, r, B_cal=None, top=6) -> list:
    """What the residual follows most, strongest first: [{quantity, eta2}]."""
    v = per_sample(S, r)
    cols = [k for k in range(3) if np.isfinite(v[:, k]).any()]
    v = np.nan_to_num(v[:, cols])
    out = [{"quantity": name, "eta2": round(correlation_ratio(v, q), 4)}
           for name, q in quantities(S, B_cal).items()]
    out.sort(key=lambda d: -d["eta2"])
    return out[:top]


# ---- degenerate solutions -------------------------------------------------------------
MAX_SHRINK = 0.05   # least share of the reference's field variation a refit may lose
#   A trace adds terms to a model whose overall scale the reference already fixes (to
#   parts in 1e3 with reference vectors, to the magnitude's accuracy with |B| only); none
#   of the catalogue's effects changes the calibrated field's spread by several percent.
#   A refit that does is contracting the calibration toward a constant vector, which
#   shrinks the noise with the field (magnitude-only data: a constant vector of the
#   reference's length fits |B| perfectly).


def field_variation_nT(B) -> float:
    """RMS deviation of field vectors (n, 3) from their mean."""
    B = np.asarray(B, float)
    if len(B) < 2:
        return 0.0
    return float(np.sqrt(np.sum(np.var(B, axis=0))))


def _judged_rows(S: SensorSamples):
    """The samples whose calibrated spread is checked: those with reference vectors,
    else those with a reference magnitude. Static-position rows are not: there the true
    field is constant, a calibration rightly shrinks their spread, and M is held at the
    baseline (no contraction is possible)."""
    iv, im, _ = S.idx
    return iv if len(iv) >= 2 else im


def reference_variation_nT(S: SensorSamples, B_baseline) -> tuple:
    """(variation, what it is): the reference vectors' own where the samples carry them,
    else, for magnitude rows, the baseline calibration's (the scale the baseline pinned to
    the reference magnitude); 0 where neither (no check)."""
    iv, _, _ = S.idx
    sel = _judged_rows(S)
    if len(sel) < 2:
        return 0.0, "nothing (static positions only)"
    if len(iv) >= 2:
        return field_variation_nT(S.ref[iv]), "the reference vectors"
    return field_variation_nT(np.asarray(B_baseline)[sel]), "the baseline calibration"


def shrinks(B_new, S: SensorSamples, ref_var: float) -> bool:
    sel = _judged_rows(S)
    if len(sel) < 2 or ref_var <= 0:
        return False
    return field_variation_nT(np.asarray(B_new)[sel]) < (1.0 - MAX_SHRINK) * ref_var


# ---- overfitting: a magnitude-only residual below the part's noise -----------------------
BELOW_NOISE_ALPHA = 1e-3  # lower-tail probability of chi^2 below which a residual is
#   too small to be noise: with only |B| known, a calibration contracted toward a constant
#   vector shrinks the residual below the part's own noise (the field the part reads
#   carries that noise on every axis, so |B_cal| - |B| cannot be quieter than it).


def magnitude_only(S: SensorSamples) -> bool:
    iv, im, ip = S.idx
    return len(im) > 0 and not len(iv) and not len(ip)


def below_part_noise(S: SensorSamples, r, n_params: int = 0) -> str:
    """Why the magnitude-only residual r is statistically below the part's stated noise
    ("" if it is not, if the rows are not magnitude-only, or the noise is not stated):
    n_eff mean(r^2) / sigma^2 under the BELOW_NOISE_ALPHA quantile of chi^2 with n_eff - n_params
    degrees of freedom, n_eff the rows deflated by the residual's lag-1 autocorrelation
    (rho clipped to [0, 0.99]), sigma the part's noise (`part_noise_nT`)."""
    from scipy import stats as sps
    sigma = part_noise_nT(S.spec)
    if not magnitude_only(S) or not sigma or r.size < 3:
        return ""
    rho = min(max(_lag1(r, S), 0.0), 0.99)
    n_eff = r.size * (1 - rho) / (1 + rho)
    dof = n_eff - n_params
    if dof < 1:
        return ""
    q = n_eff * float(np.mean(r * r)) / (sigma * sigma)
    lo = float(sps.chi2.ppf(BELOW_NOISE_ALPHA, dof))
    if q >= lo:
        return ""
    rms = float(np.sqrt(np.mean(r * r)))
    return (f"overfitting: with magnitudes only, the residual ({rms:.1f} nT rms) is below the "
            f"part's stated noise ({sigma:.1f} nT; chi^2 {q:.0f} < {lo:.0f}, its "
            f"{BELOW_NOISE_ALPHA:g} quantile for {dof:.0f} effective rows): the calibration "
            "is contracting toward a constant vector")
