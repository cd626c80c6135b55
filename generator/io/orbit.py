"""Where the unit was, and the geomagnetic field model along that track (ICD section 4).

A telemetry file with no ref_* columns but a position is calibrated against the field
model: this module turns the position into the reference magnitude `ref_norm_nT`.

Position, in order of preference:
1. GNSS columns: `lat_deg`, `lon_deg`, `alt_km` (geodetic, WGS-84), or `ecef_x_km`,
   `ecef_y_km`, `ecef_z_km` (Earth-fixed);
2. else SGP4 (the `sgp4` package, Vallado's implementation of Spacetrack Report #3)
   from the unit file's `[orbit] tle`, giving positions in TEME (true equator, mean
   equinox of date), rotated into Earth-fixed coordinates by the Greenwich mean sidereal
   time (teme_to_ecef_km).
Times: `[orbit] epoch_utc` (or a `# epoch_utc: ...` comment line of the file) plus `time_s`.

TEME -> ECEF (Vallado, Crawford, Hujsak & Kelso 2006, "Revisiting Spacetrack Report #3",
AIAA 2006-6753, eq. for teme2ecef): r_ecef = R3(GMST) r_teme with GMST the IAU-1982
Greenwich mean sidereal time (sgp4.propagation.gstime, the function SGP4 itself uses),
evaluated at UT1 taken as UTC. Left out, with their size at LEO: polar motion (< 15 m),
UT1 - UTC (< 0.9 s, i.e. < 0.42 km of Earth rotation at the equator); the field's
gradient at 500 km is ~ 3 |B| / r ~ 20 nT/km, so these stay below ~ 8 nT, far below
the error of SGP4 itself (~ 1 km at the TLE's epoch, growing by 1-3 km per day, i.e.
20 - 60 nT per day of TLE age: provenance records the TLE's age).

Field: IGRF-14 through ppigrf (generator/io/geomag.py), evaluated in geocentric spherical
coordinates from the Earth-fixed position (the magnitude needs no geodetic conversion).

Geomagnetic activity: where a `kp_index` column says Kp >= KP_DISTURBED the model misses
too much of the external field and the sample gets no reference (left out of the fit;
counted in the provenance).

The computed reference is cached (cache_path: keyed by a SHA-256 of the Earth-fixed
positions, the times, the model's coefficient file and the package's version) and its provenance kept in
Telemetry.meta["field_reference"] for the fit's report.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from generator.errors import InputError

WGS84_A_KM = 6378.137
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)

MAX_TIME_FROM_EPOCH_S = 200 * 365.25 * 86400.0   # beyond any field model's span
GEODETIC_COLUMNS = ("lat_deg", "lon_deg", "alt_km")
ECEF_COLUMNS = ("ecef_x_km", "ecef_y_km", "ecef_z_km")
REF_COLUMNS = ("ref_x_nT", "ref_y_nT", "ref_z_nT", "ref_norm_nT")

# Kp at and above which an interval is "disturbed" and left out. NOAA SWPC's scale calls
# Kp = 4 "active" and Kp >= 5 a geomagnetic storm (G1..G5); at Kp >= 4 the auroral
# electrojets and field-aligned currents perturb |B| at LEO by hundreds of nT, more than
# any calibration can absorb. (Main-field modellers are stricter, e.g. Kp <= 2o for the
# CHAOS models, Finlay et al. 2020, Earth Planets Space 72:156; that would leave out ~40 %
# of a typical orbit's data for a gain that the sensors' noise hides.)
KP_DISTURBED = 4.0

# The model's own |B| error along a LEO track in quiet conditions (Kp < 4), 1 sigma:
# main field: IGRF-14's uncertainty of the main field is ~ 10 nT at the ground, smaller
# at altitude, and its predicted secular variation errs by ~ 10 - 20 nT per year after
# the epoch (Alken et al. 2021, "IGRF-13", Earth Planets Space 73:49, section 6);
# crustal field above degree 13 at 400 - 600 km: ~ 5 - 20 nT (Maus 2010, MF7 / the
# World Digital Magnetic Anomaly Map at satellite altitude);
# external fields in quiet times: the magnetospheric ring current and tail ~ 10 - 30 nT
# at low and mid latitudes (Olsen et al. 2014, CHAOS-4), field-aligned currents in the
# auroral ovals up to ~ 100 nT in |B| (mostly across the field, so less in |B|).
# Taken together as MODEL_FLOOR_nT, a figure the report states next to the noise floor.
MODEL_FLOOR_nT = {"main_field": 10.0, "secular_variation_per_year": 15.0,
                  "crustal": 10.0, "external_quiet": 25.0}


def model_floor_nT(years_from_model_epoch: float = 0.0) -> float:
    """The model's |B| error 1-sigma (root sum of squares of MODEL_FLOOR_nT's parts, the
    secular variation's growing with the years since the model's last main-field epoch)."""
    f = MODEL_FLOOR_nT
    return math.sqrt(f["main_field"] ** 2 + f["crustal"] ** 2 + f["external_quiet"] ** 2
                     + (f["secular_variation_per_year"] * max(0.0, years_from_model_epoch)) ** 2)


# ---- coordinates ----------------------------------------------------------------------


def geodetic_to_ecef_km(lat_deg, lon_deg, alt_km) -> np.ndarray:
    """WGS-84 geodetic latitude, longitude (deg) and height (km) -> (N, 3) ECEF km."""
    lat, lon = np.radians(np.asarray(lat_deg, float)), np.radians(np.asarray(lon_deg, float))
    h = np.asarray(alt_km, float)
    n = WGS84_A_KM / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    return np.stack([(n + h) * np.cos(lat) * np.cos(lon), (n + h) * np.cos(lat) * np.sin(lon),
                     (n * (1.0 - WGS84_E2) + h) * np.sin(lat)], axis=-1)


def ecef_to_geodetic(ecef_km):
    """(N, 3) ECEF km -> (lat_deg, lon_deg, alt_km), WGS-84, by fixed-point iteration on
    the latitude (converges to < 1e-9 deg in a few steps anywhere above the ellipsoid's
    centre region; seven are taken)."""
    x, y, z = (np.asarray(ecef_km, float)[..., k] for k in range(3))
    p = np.hypot(x, y)

    def height(lat):
        n = WGS84_A_KM / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
        polar = np.abs(np.cos(lat)) <= 1e-9          # at a pole: |z| - b
        return n, np.where(polar, np.abs(z) - n * (1.0 - WGS84_E2),
                           p / np.where(polar, 1.0, np.cos(lat)) - n)

    lat = np.arctan2(z, p * (1.0 - WGS84_E2))
    for _ in range(7):
        n, h = height(lat)
        lat = np.arctan2(z, p * (1.0 - WGS84_E2 * n / (n + h)))
    return np.degrees(lat), np.degrees(np.arctan2(y, x)), height(lat)[1]


def ecef_to_spherical(ecef_km):
    """(N, 3) ECEF km -> (radius km, geocentric colatitude deg, east longitude deg)."""
    e = np.asarray(ecef_km, float)
    r = np.linalg.norm(e, axis=-1)
    return r, np.degrees(np.arccos(np.clip(e[..., 2] / r, -1.0, 1.0))), \
        np.degrees(np.arctan2(e[..., 1], e[..., 0]))


def julian_date(times_utc) -> tuple:
    """(jd whole part, fraction) of datetime64 times (UTC), as sgp4 takes them."""
    t = np.asarray(times_utc, dtype="datetime64[us]")
    days = (t - np.datetime64("2000-01-01T12:00:00", "us")) / np.timedelta64(86400, "s")
    jd = 2451545.0 + np.floor(days)
    return jd, days - np.floor(days)


def gmst_rad(times_utc) -> np.ndarray:
    """Greenwich mean sidereal time (IAU 1982, as SGP4 uses it), radians, UT1 = UTC."""
    from sgp4.propagation import gstime

    jd, fr = julian_date(times_utc)
    return np.array([gstime(a + b) for a, b in zip(np.ravel(jd), np.ravel(fr))])


def teme_to_ecef_km(r_teme_km, times_utc) -> np.ndarray:
    """TEME -> ECEF: rotation by GMST about the pole (polar motion left out; see the
    module docstring for its size)."""
    g = gmst_rad(times_utc)
    c, s = np.cos(g), np.sin(g)
    r = np.asarray(r_teme_km, float)
    return np.stack([c * r[:, 0] + s * r[:, 1], -s * r[:, 0] + c * r[:, 1], r[:, 2]], axis=1)


def sgp4_teme_km(tle, times_utc) -> np.ndarray:
    """SGP4 positions (N, 3) in TEME, km, from a two-line element set (WGS-72 constants,
    as the element sets are made). ValueError naming the first failing time."""
    from sgp4.api import WGS72, Satrec

    sat = Satrec.twoline2rv(tle[0], tle[1], WGS72)
    jd, fr = julian_date(times_utc)
    err, r, _ = sat.sgp4_array(np.ravel(jd).astype(float), np.ravel(fr).astype(float))
    bad = np.flatnonzero(err != 0)
    if bad.size:
        from sgp4.api import SGP4_ERRORS
        k = bad[0]
        raise ValueError(f"SGP4 fails at {np.asarray(times_utc)[k]}: "
                         f"{SGP4_ERRORS.get(int(err[k]), err[k])}")
    return np.asarray(r, float)


def tle_epoch_utc(tle) -> np.datetime64:
    """The element set's epoch (UTC)."""
    from sgp4.api import Satrec

    sat = Satrec.twoline2rv(tle[0], tle[1])
    days = (sat.jdsatepoch + sat.jdsatepochF - 2451545.0) * 86400.0
    return np.datetime64("2000-01-01T12:00:00", "us") + np.timedelta64(int(round(days * 1e6)), "us")


# ---- the track of a telemetry file ----------------------------------------------------


@dataclass
class Track:
    time_utc: np.ndarray          # (N,) datetime64[us]
    ecef_km: np.ndarray           # (N, 3), NaN where the position is missing
    source: str                   # "GNSS lat/lon/alt columns", "GNSS ECEF columns", "SGP4 ..."
    notes: tuple = ()


def epoch_of(tel, unit):
    """(epoch datetime64, where it came from) or (None, None)."""
    orbit = (getattr(unit, "extra", None) or {}).get("orbit") or {}
    text, where = orbit.get("epoch_utc"), "[orbit] epoch_utc"
    for k in ("epoch_utc", "utc_at_time_0"):        # the latter: magcal import's files
        if text is None and k in tel.meta:
            text, where = tel.meta[k], f"'# {k}:' comment"
    if text is None:
        return None, None
    try:
        t = _dt.datetime.fromisoformat(str(text).strip().replace("Z", "+00:00"))
    except ValueError:
        raise InputError(tel.path, f"{where}: {text!r} is not an ISO UTC time") from None
    if t.tzinfo is not None:
        t = t.astimezone(_dt.timezone.utc).replace(tzinfo=None)
    return np.datetime64(t, "us"), where


def wants_field_model(tel, unit) -> bool:
    """True when the file carries no ref_* column but a position (columns, or [orbit] with
    a TLE): ICD section 4 says the toolchain computes the reference itself."""
    if any(c in tel.columns for c in REF_COLUMNS):
        return False
    orbit = (getattr(unit, "extra", None) or {}).get("orbit") or {}
    return (any(c in tel.columns for c in GEODETIC_COLUMNS + ECEF_COLUMNS)
            or bool(orbit.get("tle")))


NO_EPOCH = ("a position but no ref_* column, and no [orbit] epoch_utc in the unit file (nor "
            "a '# epoch_utc:' line): the field model needs the UTC of time_s = 0")


def require_field_reference(tel) -> None:
    """InputError when the file needs the field model's reference and could not get it
    (a fit must not fall back to the unit's lab field for orbit data)."""
    if "field_reference_missing" in tel.meta:
        raise InputError(tel.path, tel.meta["field_reference_missing"])


def track_of(tel, unit) -> Track:
    """Times and Earth-fixed positions of every sample (see the module docstring)."""
    epoch, where = epoch_of(tel, unit)
    if epoch is None:
        raise InputError(tel.path, NO_EPOCH)
    t_s = np.asarray(tel.time_s, float)
    with np.errstate(invalid="ignore"):
        far = np.flatnonzero(np.abs(t_s) > MAX_TIME_FROM_EPOCH_S)
    if far.size:
        i = far[0]
        raise InputError(tel.path, f"{t_s[i]:g} s from {where} is more than 200 years: "
                                   "no field model covers it", line=int(tel.line_numbers[i]),
                         column="time_s")
    times = epoch + np.round(np.nan_to_num(t_s) * 1e6).astype("timedelta64[us]")
    for cols, kind in ((GEODETIC_COLUMNS, "lat/lon/alt"), (ECEF_COLUMNS, "ECEF")):
        present = [c for c in cols if c in tel.columns]
        if present and len(present) < 3:
            missing = next(c for c in cols if c not in tel.columns)
            raise InputError(tel.path, f"position: {', '.join(present)} without {missing}",
                             column=missing)
        if present:
            if kind == "ECEF":
                ecef = np.stack([tel.columns[c] for c in cols], axis=1).astype(float)
                _check_radius(tel, ecef, cols[0])
            else:
                ecef = geodetic_to_ecef_km(*(tel.columns[c] for c in cols))
            return Track(times, ecef, f"GNSS {kind} columns ({where} + time_s)")
    tle = ((unit.extra or {}).get("orbit") or {}).get("tle")
    # (two lines of two objects are refused when the unit file is read: io/unitfile.py)
    ok = np.isfinite(tel.time_s)
    try:
        teme = sgp4_teme_km(tle, times[ok])
        tle_epoch = tle_epoch_utc(tle)
    except (ValueError, ArithmeticError, IndexError) as e:   # elements SGP4 cannot use
        raise InputError(unit.path, f"[orbit] tle: {e}") from None
    ecef = np.full((tel.n, 3), np.nan)
    ecef[ok] = teme_to_ecef_km(teme, times[ok])
    age_d = (times[ok] - tle_epoch) / np.timedelta64(86400, "s")
    notes = []
    if age_d.size and np.max(np.abs(age_d)) > 3.0:
        notes.append(f"the TLE is up to {np.max(np.abs(age_d)):.1f} days from the samples: "
                     "SGP4 errs by ~1-3 km per day of age, ~20-60 nT of |B| per day")
    return Track(times, ecef, f"SGP4 from the [orbit] TLE (catalogue {tle[0][2:7].strip()}, "
                              f"TLE age {age_d.min():+.2f} .. {age_d.max():+.2f} days; "
                              f"{where} + time_s)", tuple(notes))


# An Earth-fixed position must lie between the deepest point below the WGS-84 ellipsoid
# (the polar radius 6356.75 km less ~11 km of ocean trench) and the highest altitude the
# geodetic columns accept (telemetry_csv.GEO_LIMITS, 100,000 km).
ECEF_RADIUS_KM = (6345.0, WGS84_A_KM + 100000.0)


def _check_radius(tel, ecef, column) -> None:
    r = np.linalg.norm(ecef, axis=1)
    with np.errstate(invalid="ignore"):
        bad = np.flatnonzero(np.isfinite(r) & ((r < ECEF_RADIUS_KM[0]) | (r > ECEF_RADIUS_KM[1])))
    if bad.size:
        i = bad[0]
        raise InputError(tel.path, f"the position is {r[i]:.3f} km from the Earth's centre, "
                                   f"outside {ECEF_RADIUS_KM[0]:g} .. {ECEF_RADIUS_KM[1]:g} km "
                                   "(not kilometres?)", line=int(tel.line_numbers[i]),
                         column=column)


# ---- the field along the track, cached -------------------------------------------------


def cache_path(key: str) -> Path | None:
    """Where a computed reference is kept: $MAGCAL_CACHE/geomag, else
    $XDG_CACHE_HOME/magcal/geomag or ~/.cache/magcal/geomag (None: no cache)."""
    env = os.environ.get("MAGCAL_CACHE")
    if env:
        base = Path(env).absolute()
    else:
        xdg = os.environ.get("XDG_CACHE_HOME")
        base = (Path(xdg) if xdg and Path(xdg).is_absolute() else Path.home() / ".cache") / "magcal"
    return base / "geomag" / f"{key}.npz"


def field_along(track: Track, *, use_cache: bool = True, path=None, lines=None,
                where: str = "[orbit] epoch_utc") -> tuple:
    """IGRF field (N, 3) north/east/down (geocentric local frame) in nT along the track,
    NaN where the position is missing, and its provenance dict. path, lines (the input
    file and its samples' line numbers) and where (the epoch's origin) name the input in
    the message of a time outside the model's span. An unreadable cache entry (damaged,
    truncated, not a .npz at all) is recomputed and replaced atomically."""
    from generator.io import geomag

    info = geomag.model_info()
    ok = np.all(np.isfinite(track.ecef_km), axis=1)
    h = hashlib.sha256()
    h.update(f"{info['coefficient_sha256']} {info['package']} {info['package_version']}"
             .encode())
    h.update(np.ascontiguousarray(track.time_utc.astype("int64")).tobytes())
    h.update(np.ascontiguousarray(np.where(ok[:, None], track.ecef_km, 0.0)).tobytes())
    key = h.hexdigest()
    prov = {**info, "position_source": track.source, "cache_key": key[:16],
            "samples": int(track.time_utc.shape[0]), "notes": list(track.notes)}
    cached = cache_path(key) if use_cache else None
    if cached is not None and cached.is_file():
        try:
            with np.load(cached) as z:
                field = np.asarray(z["field_nT"], float)
            if field.shape == (track.time_utc.shape[0], 3):
                return field, {**prov, "cache": "hit"}
        except Exception:       # noqa: BLE001 -- any unreadable entry (BadZipFile,
            pass                # EOFError, a pickle, ...) is only a cache miss: recomputed
    times = track.time_utc[ok].astype(_dt.datetime)
    try:
        geomag.check_model_dates(list(times))
    except ValueError as e:
        lo, hi = geomag.model_span()
        bad = np.flatnonzero([not (lo <= t <= hi) for t in times])
        line = None
        if lines is not None and bad.size:
            line = int(np.asarray(lines)[np.flatnonzero(ok)[bad[0]]])
        raise InputError(path, f"time_s + {where}: field model: {e}", line=line,
                         column="time_s") from None
    field = np.full((track.time_utc.shape[0], 3), np.nan)
    if ok.any():
        r, colat, lon = ecef_to_spherical(track.ecef_km[ok])
        field[ok] = geomag.field_geocentric_nT(r, colat, lon, list(times))
    if cached is not None:
        try:
            cached.parent.mkdir(parents=True, exist_ok=True)
            tmp = cached.with_name(f".{cached.stem}.{os.getpid()}.tmp.npz")
            np.savez(tmp, field_nT=field, provenance=json.dumps(prov))
            os.replace(tmp, cached)
        except OSError:
            pass                            # no cache: computed each time, never an error
    return field, {**prov, "cache": "miss" if cached is not None else "off"}


def attach_field_reference(tel, unit):
    """ICD section 4: a file with a position and no ref_* column gets `ref_norm_nT` from
    the field model along its track (NaN where the position is missing or Kp >=
    KP_DISTURBED); tel.meta["field_reference"] holds the provenance. Other files are
    returned unchanged. Returns tel."""
    if not wants_field_model(tel, unit):
        _kp_on_own_reference(tel)
        return tel
    if epoch_of(tel, unit)[0] is None:
        # positions are still channels (apply, check need no reference); a fit refuses
        # the file (require_field_reference) rather than take the lab field for orbit data
        tel.meta["field_reference_missing"] = NO_EPOCH
        return tel
    track = track_of(tel, unit)
    field, prov = field_along(track, path=tel.path, lines=tel.line_numbers,
                              where=epoch_of(tel, unit)[1])
    norm = np.linalg.norm(field, axis=1)
    kp = tel.columns.get("kp_index")
    if kp is not None:
        disturbed = np.isfinite(kp) & (kp >= KP_DISTURBED)
        norm = np.where(disturbed, np.nan, norm)
        prov["kp_left_out"] = int(disturbed.sum())
        prov["kp_threshold"] = KP_DISTURBED
        _all_disturbed(tel, disturbed, np.isfinite(np.linalg.norm(field, axis=1)))
    years = _years_after_last_epoch(track.time_utc)
    prov["model_floor_nT"] = round(model_floor_nT(years), 1)
    tel.columns["ref_norm_nT"] = norm
    tel.meta["field_reference"] = prov
    return tel


def _all_disturbed(tel, disturbed, has_reference) -> None:
    """Every sample with a reference is disturbed: a fit has nothing left to calibrate
    against; say so (require_field_reference refuses it), rather than 'no samples'."""
    if has_reference.any() and np.all(disturbed[has_reference]):
        tel.meta["field_reference_missing"] = (
            f"kp_index: every one of the {int(has_reference.sum())} samples is disturbed "
            f"(Kp >= {KP_DISTURBED:g}) and left out: no quiet interval to calibrate "
            "against the field model (docs/orbit.md)")


def _kp_on_own_reference(tel) -> None:
    """ICD section 4 honours kp_index whatever the reference: a file with its own
    ref_norm_nT (and no reference vectors) has its disturbed samples' reference set to
    NaN, so they are left out too; tel.meta["kp_left_out"] says how many."""
    kp = tel.columns.get("kp_index")
    norm = tel.columns.get("ref_norm_nT")
    if kp is None or norm is None or any(c in tel.columns for c in REF_COLUMNS[:3]):
        return
    kp = np.asarray(kp, float)
    norm = np.asarray(norm, float)
    disturbed = np.isfinite(kp) & (kp >= KP_DISTURBED)
    tel.columns["ref_norm_nT"] = np.where(disturbed, np.nan, norm)
    tel.meta["kp_left_out"] = {"samples": int(disturbed.sum()), "threshold": KP_DISTURBED}
    _all_disturbed(tel, disturbed, np.isfinite(norm))


def _years_after_last_epoch(times) -> float:
    """Years from the model's last main-field epoch (IGRF-14: 2025.0; before it the model
    interpolates between main-field models, after it the secular variation is a
    prediction) to the middle of the samples; 0 before that epoch."""
    from generator.io import geomag

    if not len(times):
        return 0.0
    mid = times[len(times) // 2].astype(_dt.datetime)
    _, end = geomag.model_span()
    last_main = _dt.datetime(end.year - 5, 1, 1)          # the SV covers the last 5 years
    return max(0.0, (mid - last_main).total_seconds() / (365.25 * 86400.0))


def describe(prov: dict) -> str:
    """One sentence of provenance for the report."""
    s = (f"|B| reference computed from {prov['model']} ({prov['package']} "
         f"{prov['package_version']}, {prov['coefficient_file']} sha256 "
         f"{prov['coefficient_sha256'][:12]}) at positions from {prov['position_source']}; "
         f"model floor ~{prov.get('model_floor_nT', float('nan')):g} nT 1-sigma")
    if "kp_left_out" in prov:
        s += f"; {prov['kp_left_out']} samples with Kp >= {prov['kp_threshold']:g} left out"
    for n in prov.get("notes", ()):
        s += f"; {n}"
    return s
