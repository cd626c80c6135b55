"""The white noise of a trace's reference vectors and the reference's sample steps: what
the time_offset effect (generator.trace.effects.TimeOffset) needs to take the errors in
variables out of its offset estimate. Its regressor, the reference's central rate
(ref_k+1 - ref_k-1) / 2 h, carries the reference's white noise, sigma_ref^2 / 2 h^2 per
axis on top of the true rate's square, which biases a least-squares dt towards 0 by
rate^2 / (rate^2 + sigma_ref^2 / 2 h^2) (review #20b F6: 0.82 with 60 nT at 1 Hz on the
test's tumble); the fit takes that noise out of the regressor's square
(generator.trace.model.SensorModel.fit).

sigma_ref^2 per file and axis: the second differences of the reference (whose variance is
6 sigma_ref^2 for white noise; generator.fit.reference.difference_noise_var) less what the
sensor's own second differences at the same and the neighbouring samples predict of them
(least squares, pooled over the files, all three sensor axes: the field's motion between
samples is in both, the reference's noise only in the reference). On a smooth reference
(a slow tumble logged at 1 Hz) the prediction is nothing and this is the reference's
difference noise; on a fast rotation logged at a few Hz (the simulator's hand rotation:
the field's curvature between samples is ~450 nT per axis, 200x the noise) the raw
difference noise is that curvature, not noise, and the prediction takes it out. What is
left is an UPPER bound of sigma_ref^2 where the motion dominates (the sensor's own noise
enters through the prediction: ~800 nT^2 for the simulator's 28 nT sensor and a
noise-free reference), where the regressor's true square is larger still (~10^8 nT^2/s^2
against a correction of ~10^4): negligible there.
"""

from __future__ import annotations

import numpy as np

from generator.fit.reference import difference_noise_var
from generator.trace.samples import VEC

MIN_DIFFERENCES = 30              # fewer second differences in a file: the pooled figure


def vector_runs(S) -> list:
    """Sample indices of runs of successive vector-reference samples (one telemetry row
    after the other in the same file), in time order."""
    iv = np.nonzero(S.kind == VEC)[0]
    if len(iv) == 0:
        return []
    iv = iv[np.argsort(S.order[iv], kind="stable")]
    brk = np.concatenate([[True], (np.diff(S.order[iv]) != 1)
                          | (np.diff(S.file_index[iv]) != 0)])
    return np.split(iv, np.nonzero(brk)[0][1:])


def _unshared(S, runs) -> list:
    """Per run (length >= 5, trimmed by one sample at each end), the reference less the
    least-squares prediction of its second differences from the sensor's at the sample and
    its two neighbours: series whose second differences are the reference's that the
    sensor does not share."""
    runs = [r for r in runs if len(r) >= 5]
    if not runs:
        return []

    def d2(a):
        return a[2:] - 2.0 * a[1:-1] + a[:-2]

    def shifted(x):
        return np.hstack([x[:-2], x[1:-1], x[2:]])

    Y = np.concatenate([d2(S.ref[r])[1:-1] for r in runs])
    X = np.concatenate([shifted(d2(S.x[r])) for r in runs])
    X = X - X.mean(axis=0)                   # a constant second difference is a ramp
    beta = np.linalg.lstsq(X, Y - Y.mean(axis=0), rcond=None)[0]       # (9, 3)
    return [(S.file_index[r[1:-1]], S.ref[r][1:-1] - shifted(S.x[r]) @ beta) for r in runs]


def reference_noise_var(S) -> dict:
    """{file index: (3,) sigma_ref^2 per axis (nT^2)} for the files of S with vector
    references (see the module docstring). A file with fewer than MIN_DIFFERENCES second
    differences takes the figure pooled over all files; none at all: 0."""
    cache = S.__dict__.setdefault("_reference_noise_cache", {})
    if "var" in cache:
        return cache["var"]
    parts = _unshared(S, vector_runs(S))
    out = {}

    def var(series):
        n = sum(max(len(a) - 2, 0) for a in series)
        v = difference_noise_var(series) if n >= 3 else None
        return None if v is None else np.maximum(v, 0.0)

    pooled = var([z for _, z in parts]) if parts else None
    for fi in np.unique(S.file_index[S.kind == VEC]):
        mine = [z for f, z in parts if f[0] == fi]
        n = sum(max(len(a) - 2, 0) for a in mine)
        v = var(mine) if n >= MIN_DIFFERENCES else None
        out[int(fi)] = v if v is not None else (pooled if pooled is not None else np.zeros(3))
    cache["var"] = out
    return out


def reference_steps(S) -> np.ndarray:
    """(n, 2) time to the next and from the previous reference sample (s): from the
    neighbouring samples of S where they are the neighbouring telemetry rows, else the
    file's median step between such rows (samples left out of S: a capped trace's
    draw); inf where a file has no two successive samples in S (no interpolation
    step known: no correction)."""
    cache = S.__dict__.setdefault("_reference_noise_cache", {})
    if "steps" in cache:
        return cache["steps"]
    out = np.full((S.n, 2), np.nan)
    runs = vector_runs(S)
    for r in runs:
        if len(r) >= 2:
            h = np.diff(S.time_s[r])
            out[r[:-1], 0] = h
            out[r[1:], 1] = h
    for fi in np.unique(S.file_index):
        sel = S.file_index == fi
        known = out[sel][np.isfinite(out[sel])]
        known = known[known > 0]
        med = float(np.median(known)) if len(known) else np.inf
        v = out[sel]
        v[~(np.isfinite(v) & (v > 0))] = med
        out[sel] = v
    cache["steps"] = out
    return out
