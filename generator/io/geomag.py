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
import os

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


def _day_weights(times):
    """(day ordinal, weight of the next day's 00:00) per time: the field at t is
    (1 - w) F(day) + w F(day + 1), exact for IGRF (its Gauss coefficients are linear in
    time between the 5-year epochs, which fall on a 1 January 00:00, so a day never
    straddles two epochs; the field is linear in the coefficients)."""
    day = np.array([t.toordinal() for t in times])
    frac = np.array([(t - _dt.datetime(t.year, t.month, t.day)).total_seconds() / 86400.0
                     for t in times])
    return day, frac


def _per_day(times, evaluate):
    """Sum over the UTC days of the times: evaluate(index, datetime) -> (k, 3) field at
    that day's 00:00 for the samples `index`; linearly weighted to each sample's time."""
    day_of, frac = _day_weights(times)
    out = None
    for ordinal in np.unique(day_of):
        k = np.flatnonzero(day_of == ordinal)
        f0 = evaluate(k, _dt.datetime.fromordinal(int(ordinal)))
        w = frac[k][:, None]
        val = f0 * (1.0 - w)
        if np.any(w > 0):
            val = val + w * evaluate(k, _dt.datetime.fromordinal(int(ordinal) + 1))
        if out is None:
            out = np.empty((len(times), 3))
        out[k] = val
    return out


def check_model_dates(times, coeff_file=None) -> None:
    """ValueError unless every time lies within the coefficient file's span (IGRF-14:
    1900.0 to 2030.0): the model is not extrapolated."""
    lo, hi = model_span(coeff_file)
    bad = [t for t in times if not (lo <= t <= hi)]
    if bad:
        raise ValueError(f"time {bad[0].isoformat()} is outside the field model's span "
                         f"{lo.date()} .. {hi.date()}")


def field_ned_nT(lat_deg, lon_deg, alt_km, time_utc, *, max_degree=13, coeff_file=None):
    """IGRF main field at geodetic positions: (N, 3) array of north, east, down in nT.

    lat_deg, lon_deg, alt_km: scalars or arrays of one length N (broadcast together);
    time_utc: one time for all, or N times (datetime, numpy datetime64 or ISO string).
    max_degree: truncation of the expansion (13 = the full model; 1 = the dipole).
    coeff_file: another .shc coefficient file of ppigrf (default: the newest IGRF).
    The time of each sample is honoured exactly (_per_day: two evaluations per UTC day).
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
    kw = {"max_degree": max_degree}
    if coeff_file is not None:
        kw["coeff_fn"] = str(coeff_file)

    def at(k, day):
        Be, Bn, Bu = ppigrf.igrf(lon[k], lat[k], h[k], day, **kw)
        return np.stack([np.ravel(Bn), np.ravel(Be), -np.ravel(Bu)], axis=1)
    return _per_day(times, at)


def field_geocentric_nT(r_km, colat_deg, lon_deg, time_utc, *, max_degree=13, coeff_file=None):
    """IGRF main field at geocentric spherical positions (radius km, colatitude and east
    longitude in degrees): (N, 3) array of north (-B_theta), east (B_phi), down (-B_r) in
    nT, the local geocentric frame. Times as for field_ned_nT, honoured exactly."""
    import ppigrf

    r, th, ph = np.broadcast_arrays(np.atleast_1d(np.asarray(r_km, float)),
                                    np.atleast_1d(np.asarray(colat_deg, float)),
                                    np.atleast_1d(np.asarray(lon_deg, float)))
    r, th, ph = (np.ravel(a) for a in (r, th, ph))
    if not (np.all(r > 0) and np.all((th >= 0) & (th <= 180)) and np.all(np.isfinite(ph))):
        raise ValueError("radius must be positive, colatitude within 0..180 deg, all finite")
    times = _as_datetimes(time_utc, r.shape[0])
    kw = {"max_degree": max_degree}
    if coeff_file is not None:
        kw["coeff_fn"] = str(coeff_file)

    def at(k, day):
        Br, Bt, Bp = ppigrf.igrf_gc(r[k], th[k], ph[k], day, **kw)
        return np.stack([-np.ravel(Bt), np.ravel(Bp), -np.ravel(Br)], axis=1)
    return _per_day(times, at)


def model_span(coeff_file=None):
    """(first, last) datetime the coefficient file covers."""
    import ppigrf

    g, _ = _read_shc(str(coeff_file or ppigrf.ppigrf.shc_fn))
    return g.index[0].to_pydatetime(), g.index[-1].to_pydatetime()


def _read_shc(path):
    import ppigrf
    key = str(path)
    if key not in _SHC_CACHE:
        _SHC_CACHE[key] = ppigrf.ppigrf.read_shc(key)
    return _SHC_CACHE[key]


_SHC_CACHE: dict = {}


def model_info(coeff_file=None) -> dict:
    """Provenance of the field model: model name from the coefficient file's header, its
    SHA-256, the package and its version (recorded with every computed reference)."""
    import hashlib
    from importlib import metadata

    import ppigrf

    path = str(coeff_file or ppigrf.ppigrf.shc_fn)
    with open(path, "rb") as f:
        data = f.read()
    head = data.decode("ascii", "replace").splitlines()
    name = next((ln.lstrip("# ").strip() for ln in head[:3] if ln.startswith("#")), "")
    lo, hi = model_span(coeff_file)
    return {"model": name.replace(" ", "-") if name.startswith("IGRF") else name,
            "coefficient_file": os.path.basename(path),
            "coefficient_sha256": hashlib.sha256(data).hexdigest(),
            "package": "ppigrf", "package_version": metadata.version("ppigrf"),
            "span_utc": [lo.isoformat(), hi.isoformat()]}


def ppigrf_coefficient_file(name: str):
    """Path of a coefficient file shipped with ppigrf (e.g. "IGRF13.shc")."""
    import ppigrf
    return os.path.join(os.path.dirname(ppigrf.__file__), name)
