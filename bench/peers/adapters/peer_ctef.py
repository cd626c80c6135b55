"""Adapter: `ctef` from PyPI (Cayley transform ellipsoid fitting, Melikechi & Dunson).

API (ctef/ctef.py, 0.0.4): ctef(X, k=None, w=0.5, w_axis=10, ...) -> dict with 'center'
and 'Lambda_inv' = diag(a) R V^T, which maps (x - center) onto the unit sphere; it
minimises sum (|Lambda_inv (x - c)|^2 - 1)^2 with scipy's trust-region-reflective
least_squares inside bounds set from the data's principal-axis box (the centre may move at
most w = 0.5 half-widths from the box centre). Defaults are used, as a user would. The
optimiser's stop reason goes into the result's note.
"""

from _protocol import run


def fit(x):
    from ctef.ctef import ctef
    result = ctef(x)
    stop = result["result"]
    note = f"least_squares status {stop.status}: {stop.message.split(' termination')[0]}"
    return result["center"], result["Lambda_inv"], note


if __name__ == "__main__":
    raise SystemExit(run("ctef", "ctef", fit))
