"""Orbit telemetry for in-flight recalibration: a real published orbit, IGRF-14 as the
truth, the changes a unit goes through after launch, the orbital thermal cycle, noise.

The sensor and board models are the project simulator's (generator/campaign/simulate.py:
Truth, its sensor rendering, the board temperature lag, the telemetry writer); this
module adds what differs in orbit:

* position: SGP4 from a real two-line element set (ISS_TLE, VANGUARD1_TLE below, sources
  cited) through generator.io.orbit (TEME -> ECEF by GMST), the file written with the TLE
  in the unit file's [orbit] table, or with GNSS columns (lat/lon/alt or ECEF);
* field: IGRF-14 along the track (generator.io.geomag) plus what the model lacks
  (model_error_field): `model_error_nT` rms per axis, half fixed to the Earth (main-field
  error, crustal field), half fixed to the Sun (external fields, which repeat from orbit
  to orbit like the thermal cycle); during a disturbed interval (`storm`) a larger
  field fixed to the orbit, flagged in the kp_index column;
* attitude: a slow tumble (B-dot currents on every other sample, as the project's
  `flight` campaign);
* temperature: sunlit / eclipse from a low-precision solar position (Astronomical
  Almanac, accurate to ~0.01 deg) and the cylindrical Earth shadow;
* post-launch changes (post_launch): a bias shift of every sensor when the panels and the
  boom deploy (the magnetised hinges and harness), and a new current: a payload's supply
  current switching on and off (`payload_A`), coupling into the sensors.

Returns the truth of every sample (field, model field, temperatures) beside the CSV, so
the tests can compare a recalibration against both.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from generator.campaign.scenarios import Scenario, _board_temps
from generator.campaign.simulate import (ChannelBias, SquareWave, _render_sensor,
                                         write_telemetry_csv)
from generator.io import geomag, orbit

# The International Space Station, CelesTrak element set of 2008-09-20 12:25:40 UTC, as
# printed in the "Two-line element set" article's worked example (Wikipedia, from
# celestrak.org); checksums valid.
ISS_TLE = ("1 25544U 98067A   08264.51782528 -.00002182  00000-0 -11606-4 0  2927",
           "2 25544  51.6416 247.4627 0006703 130.5360 325.0288 15.72125391563537")
# Vanguard 1 (1958-002B), the SGP4 verification set's first satellite: Vallado, Crawford,
# Hujsak & Kelso 2006, "Revisiting Spacetrack Report #3", AIAA 2006-6753, SGP4-VER.TLE.
# Elliptical (perigee ~650 km, apogee ~3,800 km): the field spans 10,000 - 50,000 nT.
VANGUARD1_TLE = ("1 00005U 58002B   00179.78495062  .00000023  00000-0  28098-4 0  4753",
                 "2 00005  34.2682 348.7242 1859667 331.7664  19.3264 10.82419157413667")

EARTH_RADIUS_km = orbit.WGS84_A_KM
PAYLOAD_CHANNEL = "payload_A"


def sun_direction_eci(times_utc) -> np.ndarray:
    """Unit vector to the Sun in the mean-of-date equatorial frame (Astronomical Almanac
    low-precision formula, ~0.01 deg 1950-2050): (N, 3)."""
    jd, fr = orbit.julian_date(times_utc)
    n = jd + fr - 2451545.0
    L = np.radians(280.460 + 0.9856474 * n)
    g = np.radians(357.528 + 0.9856003 * n)
    lam = L + np.radians(1.915) * np.sin(g) + np.radians(0.020) * np.sin(2 * g)
    eps = np.radians(23.439 - 4e-7 * n)
    return np.stack([np.cos(lam), np.cos(eps) * np.sin(lam), np.sin(eps) * np.sin(lam)], axis=1)


def ned_to_ecef(field_ned, ecef_km) -> np.ndarray:
    """Geocentric north/east/down components (geomag.field_geocentric_nT) -> ECEF."""
    r, colat, lon = orbit.ecef_to_spherical(ecef_km)
    th, ph = np.radians(colat), np.radians(lon)
    e_r = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=1)
    e_th = np.stack([np.cos(th) * np.cos(ph), np.cos(th) * np.sin(ph), -np.sin(th)], axis=1)
    e_ph = np.stack([-np.sin(ph), np.cos(ph), np.zeros_like(ph)], axis=1)
    f = np.asarray(field_ned, float)
    return -f[:, [0]] * e_th + f[:, [1]] * e_ph - f[:, [2]] * e_r


def post_launch(truth, *, bias_shift_nT=None, rng=None):
    """A copy of the truth after launch: every sensor's offset b0 shifted (the deployment
    of panels and boom: magnetised hinges, new harness routing). bias_shift_nT: {sensor:
    (3,)} or None for random shifts of 200 - 600 nT (body) and 500 - 1500 nT (boom) per
    axis with random signs (from rng)."""
    new = copy.deepcopy(truth)
    rng = rng or np.random.default_rng(0)
    shifts = {}
    for name, st in new.sensors.items():
        if bias_shift_nT is not None:
            d = np.asarray(bias_shift_nT.get(name, (0.0, 0.0, 0.0)), float)
        else:
            lo, hi = (500.0, 1500.0) if st.frame == "boom" else (200.0, 600.0)
            d = rng.uniform(lo, hi, 3) * rng.choice([-1.0, 1.0], 3)
        st.b_poly_frame_nT = st.b_poly_frame_nT.copy()
        st.b_poly_frame_nT[0] = st.b_poly_frame_nT[0] + d
        shifts[name] = d.tolist()
    return new, shifts


def new_current(sensor, nT_per_A, *, period_s=1800.0, duty=0.3, current_A=0.5, phase_s=0.0):
    """The payload's supply current switching on and off, its field seen by `sensor`."""
    return ChannelBias(sensor, PAYLOAD_CHANNEL, tuple(nT_per_A),
                       SquareWave(period_s, duty, current_A, 0.0, phase_s, 3))


def _along_track_error(phase, rng, rms_per_axis, harmonics=6):
    """A smooth field along the orbit, fixed to the orbit (harmonics of the orbital phase
    with random amplitudes), rms_per_axis per axis: a storm's disturbance."""
    k = np.arange(1, harmonics + 1)
    amp = rng.normal(size=(harmonics, 3)) / k[:, None]
    ph = rng.uniform(0, 2 * math.pi, size=(harmonics, 3))
    amp *= rms_per_axis / math.sqrt(0.5 * np.sum(amp ** 2) / 3.0)
    return np.sum(amp[None] * np.sin(k[None, :, None] * phase[:, None, None] + ph[None]), axis=1)


def _field_on_sphere(u, rng, rms_per_axis, waves=12, wavenumber=(2.0, 8.0)):
    """A smooth random field over directions u (N, 3 unit vectors): a sum of plane waves
    sin(s k.u + phi) with random directions k, wavenumbers s (per Earth radius: 2 .. 8,
    wavelengths ~5,000 - 20,000 km, the scale of the main-field and the large crustal
    errors at LEO), random amplitudes per axis; scaled to rms_per_axis over u."""
    k = rng.normal(size=(waves, 3))
    k /= np.linalg.norm(k, axis=1, keepdims=True)
    k *= rng.uniform(*wavenumber, size=(waves, 1))
    amp = rng.normal(size=(waves, 3))
    ph = rng.uniform(0, 2 * math.pi, size=waves)
    f = np.sin(u @ k.T + ph) @ amp
    return f * (rms_per_axis / max(float(np.sqrt(np.mean(f ** 2))), 1e-12))


def model_error_field(e_ecef_km, r_teme_km, sun_eci, rng, rms_per_axis):
    """What IGRF lacks along the track, (N, 3) in ECEF axes, rms_per_axis per axis, half
    the variance in each of two parts: fixed to the Earth (the main field's error and the
    crustal field: a function of the Earth-fixed position, so the Earth turning under the
    orbit makes it differ from orbit to orbit) and fixed to the Sun (external fields:
    ring current, magnetopause, ionosphere; a function of the position in a frame with x
    towards the Sun, so it repeats from orbit to orbit like the thermal cycle)."""
    u_e = e_ecef_km / np.linalg.norm(e_ecef_km, axis=1, keepdims=True)
    x = sun_eci / np.linalg.norm(sun_eci, axis=1, keepdims=True)
    z = np.cross(x, np.array([0.0, 0.0, 1.0]))
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    y = np.cross(z, x)
    u_t = r_teme_km / np.linalg.norm(r_teme_km, axis=1, keepdims=True)
    u_s = np.stack([np.sum(u_t * x, 1), np.sum(u_t * y, 1), np.sum(u_t * z, 1)], axis=1)
    part = rms_per_axis / math.sqrt(2.0)
    return _field_on_sphere(u_e, rng, part) + _field_on_sphere(u_s, rng, part)


def orbit_scenario(unit, truth, rng, *, tle=ISS_TLE, epoch_utc=None, duration_s=6 * 3600.0,
                   sample_period_s=10.0, tumble_dps=2.0, model_error_nT=20.0, storm=None,
                   bdot_gain_A_per_nT_s=5e-5, coil_max_A=0.1, gyro_noise_dps=0.02,
                   temp_sun_C=(30.0, 40.0), temp_eclipse_C=(10.0, -25.0)):
    """Scenario + extras of an orbit campaign (see the module docstring).

    epoch_utc: numpy datetime64 of time_s = 0 (default: half a day after the TLE's epoch).
    storm: None or (start_s, duration_s, extra_rms_nT, kp): a disturbed interval where
    the external field adds extra_rms_nT per axis and kp_index reads kp (else 1.7)."""
    ep_tle = orbit.tle_epoch_utc(tle)
    epoch = ep_tle + np.timedelta64(43200, "s") if epoch_utc is None else \
        np.datetime64(epoch_utc, "us")
    n = int(round(duration_s / sample_period_s))
    time_s = np.arange(n) * float(sample_period_s)

    def utc(t):
        return epoch + np.round(np.asarray(t, float) * 1e6).astype("timedelta64[us]")

    def ecef_at(t):
        tt = utc(t)
        return orbit.teme_to_ecef_km(orbit.sgp4_teme_km(tle, tt), tt)

    # the model along a fine grid (1 s), interpolated: the field changes by < 0.1 nT
    # between the grid points' linear interpolation and the truth at 7.7 km/s
    grid = np.arange(-60.0, duration_s + 60.0, 1.0)
    e_grid = ecef_at(grid)
    r, colat, lon = orbit.ecef_to_spherical(e_grid)
    model_grid = ned_to_ecef(geomag.field_geocentric_nT(r, colat, lon,
                                                        list(utc(grid).astype(object))), e_grid)
    teme_grid = orbit.sgp4_teme_km(tle, utc(grid))
    # orbital phase: the argument of latitude's unwrapped angle in the orbit plane
    h = np.cross(teme_grid[0], teme_grid[len(grid) // 4])
    h /= np.linalg.norm(h)
    x0 = teme_grid[0] / np.linalg.norm(teme_grid[0])
    y0 = np.cross(h, x0)
    phase = np.unwrap(np.arctan2(teme_grid @ y0, teme_grid @ x0))
    err = model_error_field(e_grid, teme_grid, sun_direction_eci(utc(grid)), rng,
                            model_error_nT)
    kp = np.full(grid.shape, 1.7)
    if storm is not None:
        s0, sd, extra, kp_storm = storm
        inside = (grid >= s0) & (grid < s0 + sd)
        err = err + inside[:, None] * _along_track_error(phase * 3.0, rng, extra)
        kp[inside] = kp_storm
    true_grid = model_grid + err

    def interp(t, v):
        return np.stack([np.interp(t, grid, v[:, k]) for k in range(v.shape[1])], axis=1)

    def true_ecef_at(t):
        return interp(np.asarray(t, float), true_grid)

    # slow tumble: body rate cones about body z with a 10 min period
    w0 = rng.normal(size=3)
    w0 *= math.radians(tumble_dps) / np.linalg.norm(w0)
    q0 = Rotation.random(random_state=int(rng.integers(2**31)))

    def rate_rad_s(t):
        return Rotation.from_rotvec(np.outer(np.asarray(t) * 2 * math.pi / 600.0,
                                             [0, 0, 1])).apply(w0)
    steps = Rotation.from_rotvec(rate_rad_s(time_s[:-1] + sample_period_s / 2) * sample_period_s)
    att = [q0]
    for k in range(n - 1):
        att.append(att[-1] * steps[k])
    R = Rotation.concatenate(att)                          # body -> ECEF
    from scipy.spatial.transform import Slerp
    slerp = Slerp(time_s, R)

    def b_body_at(t):
        t = np.clip(np.asarray(t, float), time_s[0], time_s[-1])
        return slerp(t).inv().apply(true_ecef_at(t))
    b_body = R.inv().apply(true_ecef_at(time_s))
    rate = np.degrees(rate_rad_s(time_s))
    dbdt = b_body_at(time_s + 0.5) - b_body_at(time_s - 0.5)
    coil_A = np.clip(-bdot_gain_A_per_nT_s * dbdt, -coil_max_A, coil_max_A)
    coil_A[0::2] = 0.0
    coil_A = np.round(coil_A, 4) + 0.0

    # sunlit / eclipse (cylindrical shadow) drives the boards' surroundings
    period_s = 86400.0 / float(tle[1][52:63])
    n_pre = int(math.ceil(period_s / sample_period_s))
    t_all = np.arange(-n_pre, n) * float(sample_period_s)
    teme_all = orbit.sgp4_teme_km(tle, utc(t_all))
    sun = sun_direction_eci(utc(t_all))
    along = np.sum(teme_all * sun, axis=1)
    across = np.linalg.norm(teme_all - along[:, None] * sun, axis=1)
    lit_all = (along > 0) | (across > EARTH_RADIUS_km)
    ambient = {b: np.where(lit_all, s, e) for b, s, e in
               zip(("body", "boom"), temp_sun_C, temp_eclipse_C)}
    temps = {b: v[n_pre:] for b, v in _board_temps(truth, t_all, ambient).items()}
    lit = lit_all[n_pre:]

    e_s = ecef_at(time_s)
    model_s = interp(time_s, model_grid)
    true_s = true_ecef_at(time_s)
    kp_s = np.interp(time_s, grid, kp)
    gyro = rate + rng.normal(size=(n, 3)) * gyro_noise_dps
    columns = {"coil_x_A": (coil_A[:, 0], 4), "coil_y_A": (coil_A[:, 1], 4),
               "coil_z_A": (coil_A[:, 2], 4), "rate_x_dps": (gyro[:, 0], 3),
               "rate_y_dps": (gyro[:, 1], 3), "rate_z_dps": (gyro[:, 2], 3),
               "kp_index": (kp_s, 2)}
    sc = Scenario(
        description=(f"orbit telemetry from TLE {tle[0][2:7].strip()} at "
                     f"{str(epoch)[:19]}Z, {duration_s / 3600:g} h, every "
                     f"{sample_period_s:g} s, IGRF-14 + {model_error_nT:g} nT/axis "
                     "field the model lacks"),
        time_s=time_s, b_body_nT=b_body, b_body_at=b_body_at, deployed=True,
        temp_board_C=temps, rate_dps=rate, coil_A=coil_A, position=None, columns=columns,
        extra_truth={"sunlit": lit.astype(np.int8),
                     "model_norm_nT": np.linalg.norm(model_s, axis=1),
                     "true_norm_nT": np.linalg.norm(true_s, axis=1),
                     "ecef_km": e_s, "kp_index": kp_s})
    return sc, epoch


def write_orbit_unit(unit, path, epoch, tle=None) -> Path:
    """The unit file with an [orbit] table (epoch, and the TLE when given)."""
    from generator.campaign.simulate import write_unit_toml
    write_unit_toml(unit, path)
    ep = str(np.datetime64(epoch, "us"))[:26]
    text = Path(path).read_text() + f'\n[orbit]\nepoch_utc = "{ep}Z"\n'
    if tle is not None:
        text += f'tle = ["{tle[0]}", "{tle[1]}"]\n'
    Path(path).write_text(text, encoding="utf-8")
    return Path(path)


def simulate_orbit(unit, truth, rng, out_dir, *, name="orbit", position="tle", effects=(),
                   noise_scale=1.0, **options):
    """Write <name>.csv (ICD telemetry, no ref_* columns), <name>.unit.toml (with [orbit])
    and <name>.truth.npz. position: "tle" (no position columns: SGP4 from the unit
    file's TLE), "gnss" (lat_deg/lon_deg/alt_km columns) or "ecef" (ecef_*_km columns).
    options: orbit_scenario's. Returns {"csv", "unit", "truth_npz", "arrays", "epoch"}."""
    from generator.campaign.simulate import SET_RESET_DELAY_s
    if position not in ("tle", "gnss", "ecef"):
        raise ValueError(f"position: {position!r} is not tle, gnss or ecef")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    tle = options.get("tle", ISS_TLE)
    sc, epoch = orbit_scenario(unit, truth, rng, **options)
    time_cols = {"time_s": (sc.time_s, 1)}
    channels = dict(sc.columns)
    if position == "gnss":
        lat, lon, h = orbit.ecef_to_geodetic(sc.extra_truth["ecef_km"])
        channels.update(lat_deg=(lat, 6), lon_deg=(lon, 6), alt_km=(h, 4))
    elif position == "ecef":
        for k, a in enumerate("xyz"):
            channels[f"ecef_{a}_km"] = (sc.extra_truth["ecef_km"][:, k], 4)
    for e in effects:
        channels.update(e.channels(sc.time_s))
    values = {k: np.asarray(v, float) if d is None else np.round(v, d)
              for k, (v, d) in {**time_cols, **channels}.items()}
    sensor_cols = {}
    for spec in unit.sensors:
        sensor_cols.update(_render_sensor(spec, truth, sc, effects, values, rng,
                                          SET_RESET_DELAY_s, noise_scale))
    csv_path = out_dir / f"{name}.csv"
    write_telemetry_csv(csv_path, [f"campaign: orbit", f"unit: {unit.id}",
                                   "source: generator.campaign.simulate_orbit",
                                   f"description: {sc.description}"],
                        {**time_cols, **sensor_cols, **channels})
    unit_path = write_orbit_unit(unit, out_dir / f"{name}.unit.toml", epoch,
                                 tle if position == "tle" else None)
    arrays = {"time_s": sc.time_s, "b_body_nT": sc.b_body_nT,
              "temp_body_C": sc.temp_board_C["body"], "temp_boom_C": sc.temp_board_C["boom"],
              "coil_A": sc.coil_A, **sc.extra_truth,
              "effects_json": np.array(json.dumps([e.to_dict() for e in effects]))}
    npz = out_dir / f"{name}.truth.npz"
    np.savez_compressed(npz, **arrays)
    return {"csv": csv_path, "unit": unit_path, "truth_npz": npz, "arrays": arrays,
            "epoch": epoch}
