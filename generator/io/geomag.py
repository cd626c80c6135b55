"""The geomagnetic field model: IGRF (International Geomagnetic Reference Field) through the
maintained package ppigrf (IGRF-14 coefficients; Laundal, github.com/IAGA-VMOD/ppigrf).

    field_ned_nT(lat_deg, lon_deg, alt_km, time_utc)  -> (N, 3) north, east, down, nT

One place for the model, shared by every user (the PX4 importer's reference, orbit work).
Inputs are geodetic (WGS-84) latitude and longitude in degrees and height above the
ellipsoid in km, as GNSS receivers and ICD section 4's lat_deg/lon_deg/alt_km give them.

Time: the model's coefficients change by at most ~150 nT per year (secular variation), i.e.
under 0.5 nT per day, so the model is evaluated once per UTC day of the samples (at that
day's 00:00), which keeps long logs fast; finer time steps change nothing a magnetometer
calibration can see. Crustal fields and external (ionospheric, magnetospheric) fields are not
in the model: tens to hundreds of nT in quiet conditions, more in storms (kp_index).
"""

from __future__ import annotations

import datetime as _dt

import numpy as np

IGRF_REFERENCE_RADIUS_KM = 6371.2


def _as_datetimes(time_utc, n):
    """A list of n timezone-naive UTC datetimes from a datetime, a numpy datetime64 (or
    array), an ISO string, or a sequence of those."""
    def one(t):
        if isinstance(t, str):
            t = _dt.datetime.fromisoformat(t.replace("Z", "+00:00"))
        if isinstance(t, np.datetime64):
            t = t.astype("datetime64[us]").astype(_dt.datetime)
        if isinstance(t, _dt.datetime):
            if t.tzinfo is not None:
                t = t.astimezone(_dt.timezone.utc).replace(tzinfo=None)
            return t
        if isinstance(t, _dt.date):
            return _dt.datetime(t.year, t.month, t.day)
        raise TypeError(f"not a UTC time: {t!r}")

    if isinstance(time_utc, (str, _dt.date, np.datetime64)):
        return [one(time_utc)] * n
    arr = np.asarray(time_utc)
    if arr.ndim == 0:
        return [one(arr.item() if arr.dtype.kind != "M" else arr[()])] * n
    out = [one(t) for t in (arr if arr.dtype.kind == "M" else list(time_utc))]
    if len(out) != n:
        raise ValueError(f"{len(out)} times for {n} positions")
    return out


def field_ned_nT(lat_deg, lon_deg, alt_km, time_utc, *, max_degree=13, coeff_file=None):
    """IGRF main field at geodetic positions: (N, 3) array of north, east, down in nT.

    lat_deg, lon_deg, alt_km: scalars or arrays of one length N (broadcast together);
    time_utc: one time for all, or N times (datetime, numpy datetime64 or ISO string).
    max_degree: truncation of the expansion (13 = the full model; 1 = the dipole).
    coeff_file: another .shc coefficient file of ppigrf (default: the newest IGRF).
    """
    import ppigrf

    lat, lon, h = np.broadcast_arrays(np.atleast_1d(np.asarray(lat_deg, float)),
                                      np.atleast_1d(np.asarray(lon_deg, float)),
                                      np.atleast_1d(np.asarray(alt_km, float)))
    lat, lon, h = (np.ravel(a) for a in (lat, lon, h))
    n = lat.shape[0]
    if not (np.all(np.abs(lat) <= 90.0) and np.all(np.isfinite(lon)) and np.all(np.isfinite(h))):
        raise ValueError("latitude must be within +-90 deg and every coordinate finite")
    times = _as_datetimes(time_utc, n)
    days = [_dt.datetime(t.year, t.month, t.day) for t in times]
    kw = {"max_degree": max_degree}
    if coeff_file is not None:
        kw["coeff_fn"] = str(coeff_file)
    out = np.empty((n, 3))
    day_of = np.array([d.toordinal() for d in days])
    for ordinal in np.unique(day_of):
        k = np.flatnonzero(day_of == ordinal)
        day = _dt.datetime.fromordinal(int(ordinal))
        Be, Bn, Bu = ppigrf.igrf(lon[k], lat[k], h[k], day, **kw)
        out[k, 0] = np.ravel(Bn)
        out[k, 1] = np.ravel(Be)
        out[k, 2] = -np.ravel(Bu)
    return out


def ppigrf_coefficient_file(name: str):
    """Path of a coefficient file shipped with ppigrf (e.g. "IGRF13.shc")."""
    import os

    import ppigrf
    return os.path.join(os.path.dirname(ppigrf.__file__), name)
