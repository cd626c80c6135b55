"""The fit's side of the SET/RESET gyro compensation (generator.fit.setreset decides it).

The chain outputs B_chain = (I + c [w]x) M (x - b) where the compensation is on (chain.py:
"B += c (w x B)" after M, w the body rate). Fitting M to the reference B_ref and then
switching the compensation on would remove the rotation error twice: under a steady
turn (w constant in the body frame) the readings carry W (I - c [w]x) B, which a free M
already undoes. So where the compensation is on, M is fitted to the chain's output:

    (I + c [w_n]x) M (x_n - b) = B_ref_n   <=>   M (x_n - b) = (I + c [w_n]x)^-1 B_ref_n,

i.e. the reference vectors are replaced by (I + c [w_n]x)^-1 B_ref_n and the fit runs
as before. The transform is orthogonal to second order (|w| c ~ 1e-3 rad), so magnitudes
(ellipsoid rows) stay as they are. Rows without a measured rate keep their reference
(the chain is then run with the rates the caller supplies; a file without rate columns
has none). Boom sensors: the chain turns the rate by H^T, which is fitted after M; the
fit takes the body rate as it is (H near the identity: second order).
"""

from __future__ import annotations

import dataclasses

import numpy as np


def _rates_of(tel):
    """(N, 3) body rates of a telemetry file in deg/s, or None without rate columns."""
    if not tel.has("rate_x_dps", "rate_y_dps", "rate_z_dps"):
        return None
    return np.stack([np.asarray(tel.columns[f"rate_{c}_dps"], float) for c in "xyz"], axis=1)


def _field_of(datas):
    """Median reference magnitude over the files (vector norms where known, else the
    stated magnitude): the unit's field for the decision; None when there is none."""
    vals = []
    for d in datas:
        n = None
        if d.ref_body_nT is not None:
            n = np.linalg.norm(d.ref_body_nT, axis=1)
        if d.ref_norm_nT is not None:
            n = d.ref_norm_nT if n is None else np.where(np.isfinite(n), n, d.ref_norm_nT)
        if n is not None:
            m = np.asarray(n, float)[np.asarray(d.usable, bool)]
            vals.append(m[np.isfinite(m) & (m > 0)])
    vals = np.concatenate(vals) if vals else np.array([])
    return float(np.median(vals)) if len(vals) else None


def uncompensate(ref_nT, rate_dps, c_s_per_deg):
    """(I + c [w]x)^-1 B per row: the field the chain's M must produce so that the
    compensation B += c (w x B) gives B. Rows with a non-finite rate: unchanged."""
    B = np.asarray(ref_nT, float)
    w = np.asarray(rate_dps, float)
    ok = np.all(np.isfinite(w), axis=1) & np.all(np.isfinite(B), axis=1)
    out = B.copy()
    if not ok.any():
        return out
    k = float(c_s_per_deg) * w[ok]
    A = np.zeros((int(ok.sum()), 3, 3))
    A[:, 0, 1], A[:, 0, 2] = -k[:, 2], k[:, 1]
    A[:, 1, 0], A[:, 1, 2] = k[:, 2], -k[:, 0]
    A[:, 2, 0], A[:, 2, 1] = -k[:, 1], k[:, 0]
    A += np.eye(3)
    out[ok] = np.linalg.solve(A, B[ok][:, :, None])[:, :, 0]
    return out


def compensate_references(datas, rates, c_s_per_deg):
    """FitData with reference vectors replaced by uncompensate(...) where the file has
    rates (module docstring); the others as they are."""
    out = []
    for d, w in zip(datas, rates):
        if d.ref_body_nT is None or w is None:
            out.append(d)
            continue
        out.append(dataclasses.replace(d, ref_body_nT=uncompensate(d.ref_body_nT, w,
                                                                   c_s_per_deg)))
    return out
