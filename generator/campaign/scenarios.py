"""What the simulated unit lives through in one campaign (generator/campaign/simulate.py):
the true field in the body frame, the board temperatures, rates, coil currents, static
positions and further telemetry columns, per campaign kind:

* thermal_12pos: the jig in the chamber following `magcal plan`'s program (holds from the
  boards' time constants), or the older fixed-hold program for quick tests;
* rotation, yaw_flight, planar_rotation: the unit turned by hand, flown, on a turntable;
* coils: magnetorquer current steps in static positions;
* coil_study: a magnetorquer at known distances, without and with the solar panel
  (docs/coil_study.md);
* flight: orbit telemetry.

A scenario function takes (unit, truth, rng, **options) and returns a Scenario; the truth
is read for its board time constants and self-heating (and the coil study's keys) only.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from generator.campaign.board_thermal import first_order_lag
from generator.campaign.plan import TestPlan, lab_field_ned, make_plan, twelve_positions

LAB_FIELD_nT = 51540.0            # field magnitude in the lab (seed 000)
LAB_INCLINATION_deg = 70.0


def _unit_vector(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _random_rotation(rng) -> Rotation:
    return Rotation.from_quat(_unit_vector(rng.normal(size=4)))


def _lab_field_nT(field_nT, inclination_deg) -> np.ndarray:
    """Lab field in north-east-down axes."""
    inc = math.radians(inclination_deg)
    return field_nT * np.array([math.cos(inc), 0.0, math.sin(inc)])


# ---------------------------------------------------------------------------------------
# Scenarios: what the unit lives through in one campaign
# ---------------------------------------------------------------------------------------

@dataclass
class Scenario:
    description: str
    time_s: np.ndarray                # (N,)
    b_body_nT: np.ndarray             # (N, 3) true field, body frame
    b_body_at: Callable               # times (M,) -> (M, 3) true field, body frame
    deployed: bool
    temp_board_C: dict                # "body"/"boom" -> (N,) true board temperature
    rate_dps: np.ndarray              # (N, 3) true body rate
    coil_A: np.ndarray                # (N, 3)
    position: np.ndarray | None       # (N,) int, or None: no position column
    columns: dict                     # further telemetry: name -> (values, decimals)
    extra_truth: dict = field(default_factory=dict)
    meta: dict = field(default_factory=dict)          # '# key: value' lines of the file
    extra_field_frame_nT: dict = field(default_factory=dict)  # sensor -> (N, 3) added field


def _static_field_at(time_s, b_body_nT):
    def at(t):
        i = np.clip(np.searchsorted(time_s, t, side="right") - 1, 0, len(time_s) - 1)
        return b_body_nT[i]
    return at


def _attitude_field_at(time_s, R_body_to_ref, field_ref_at):
    """Field in the body frame at any time: attitude slerped, reference field evaluated."""
    slerp = Slerp(time_s, Rotation.from_matrix(R_body_to_ref))

    def at(t):
        t = np.clip(np.asarray(t, dtype=float), time_s[0], time_s[-1])
        return slerp(t).inv().apply(field_ref_at(t))
    return at


def _board_temps(truth, time_s, ambient_C, tau_scale=1.0, initial_C=None):
    """Board temperatures lagging an ambient (chamber, room, orbit) temperature."""
    out = {}
    for board in ("body", "boom"):
        amb = ambient_C[board] if isinstance(ambient_C, dict) else ambient_C
        target = np.broadcast_to(amb, time_s.shape) + truth.board_self_heating_C[board]
        start = None if initial_C is None else initial_C + truth.board_self_heating_C[board]
        out[board] = first_order_lag(time_s, target, truth.board_tau_s[board] * tau_scale, start)
    return out


def _ref_vector_columns(b_body_nT, field_nT):
    n = len(b_body_nT)
    return {"ref_x_nT": (b_body_nT[:, 0], 1), "ref_y_nT": (b_body_nT[:, 1], 1),
            "ref_z_nT": (b_body_nT[:, 2], 1), "ref_norm_nT": (np.full(n, field_nT), 1)}


def _field_nT(unit, lab_field_nT) -> float:
    """The lab field magnitude of a campaign: the one given, else the unit file's
    lab_field_nT, else seed 000's lab."""
    if lab_field_nT is not None:
        return float(lab_field_nT)
    return float(unit.lab_field_nT) if unit.lab_field_nT else LAB_FIELD_nT


def boards_of(unit) -> tuple:
    """The boards (frames) that carry one of the unit's sensors."""
    return tuple(b for b in ("body", "boom") if any(s.frame == b for s in unit.sensors))


def plan_for(unit, truth, *, board_tau_scale=1.0, **plan_options) -> TestPlan:
    """The test program `magcal plan` writes for this unit, its holds computed from the
    slowest board's true time constant (what a lab measures on the first step and
    re-plans with); plan_options go to plan.make_plan (levels_C, sample_period_s,
    samples_per_segment, ...). The lab field is the unit's (else seed 000's)."""
    opts = {k: v for k, v in plan_options.items() if v is not None}
    tau_s = max(truth.board_tau_s[b] for b in boards_of(unit)) * board_tau_scale
    opts.setdefault("board_tau_min", tau_s / 60.0)
    opts["lab_field_nT"] = _field_nT(unit, opts.get("lab_field_nT"))
    return make_plan(unit, **opts)


def _thermal_12pos(unit, truth, rng, *, plan: TestPlan | None = None, levels_C=None,
                   hold_s=None, sample_period_s=None, samples_per_segment=None,
                   lab_field_nT=None, inclination_deg=None, room_C=None, board_tau_scale=1.0,
                   ramp_C_per_min=None, reposition_min=None, settle_tol_C=None):
    """Jig in a chamber, boom stowed, twelve static positions and the chamber's levels.

    Without hold_s: the program of `magcal plan` (`plan`, else plan_for the unit and truth
    with the options given): per position the ramps, the holds computed from the boards'
    time constants, and the return to room temperature, the set-point linear on the ramps,
    the boards lagging it with the truth's time constants; recording paused while the jig
    is turned (a time gap). With hold_s: the older shortened program, every level held
    hold_s (default levels -20..55 degC, 5 s samples), stepping without ramps, the boards'
    time constants times board_tau_scale (for quick tests whose holds are too short to
    settle)."""
    if hold_s is None:
        if plan is None:
            plan = plan_for(unit, truth, board_tau_scale=board_tau_scale, levels_C=levels_C,
                            sample_period_s=sample_period_s,
                            samples_per_segment=samples_per_segment, lab_field_nT=lab_field_nT,
                            inclination_deg=inclination_deg, room_C=room_C,
                            ramp_C_per_min=ramp_C_per_min, reposition_min=reposition_min,
                            settle_tol_C=settle_tol_C)
        return _thermal_program(truth, plan, board_tau_scale)
    levels_C = (-20.0, -5.0, 10.0, 25.0, 40.0, 55.0) if levels_C is None else levels_C
    sample_period_s = 5.0 if sample_period_s is None else sample_period_s
    inclination_deg = LAB_INCLINATION_deg if inclination_deg is None else inclination_deg
    room_C = 25.0 if room_C is None else room_C
    lab_field_nT = _field_nT(unit, lab_field_nT)
    n_hold = max(1, int(round(hold_s / sample_period_s)))
    positions = twelve_positions()
    b_lab = _lab_field_nT(lab_field_nT, inclination_deg)
    n_levels = len(levels_C)
    n = 12 * n_levels * n_hold
    time_s = np.arange(n) * float(sample_period_s)
    position = np.repeat(np.arange(1, 13), n_levels * n_hold)
    chamber_C = np.tile(np.repeat(np.asarray(levels_C, dtype=float), n_hold), 12)
    b_body = np.array([R.T @ b_lab for R in positions])[position - 1]
    return Scenario(
        description=(f"ground test: 12 static positions x chamber levels "
                     f"{', '.join(f'{v:g}' for v in levels_C)} degC, {hold_s:g} s holds"),
        time_s=time_s, b_body_nT=b_body, b_body_at=_static_field_at(time_s, b_body),
        deployed=False, temp_board_C=_board_temps(truth, time_s, chamber_C, board_tau_scale, room_C),
        rate_dps=np.zeros((n, 3)), coil_A=np.zeros((n, 3)), position=position,
        columns=_ref_vector_columns(b_body, lab_field_nT),
        extra_truth={"temp_chamber_C": chamber_C,
                     "board_tau_s": np.array([truth.board_tau_s["body"] * board_tau_scale,
                                              truth.board_tau_s["boom"] * board_tau_scale])})


def _thermal_program(truth, plan: TestPlan, board_tau_scale=1.0) -> Scenario:
    """The thermal twelve-position campaign as the plan's chamber program runs it."""
    dt = float(plan.sample_period_s)
    t_all = np.arange(0.0, plan.total_duration_s, dt)
    tc, Tc = plan.setpoint_profile(one_position=False)
    chamber_all = np.interp(t_all, tc, Tc)
    pos_all = np.zeros(len(t_all), dtype=int)
    for it in plan.chamber_program():
        if it["action"] != "reposition":            # the jig stands still in a position
            sel = (t_all >= it["start_s"]) & (t_all < it["start_s"] + it["duration_s"])
            pos_all[sel] = it["position"]
    scaled = SimpleNamespace(board_tau_s={b: v * board_tau_scale
                                          for b, v in truth.board_tau_s.items()},
                             board_self_heating_C=truth.board_self_heating_C)
    temps = _board_temps(scaled, t_all, chamber_all, 1.0, plan.room_C)
    keep = pos_all > 0                               # recording paused while turning
    time_s, position = t_all[keep], pos_all[keep]
    b_lab = lab_field_ned(plan.lab_field_nT, plan.inclination_deg)
    field_of = {p.number: np.asarray(p.R_body_to_ned, dtype=float).T @ b_lab
                for p in plan.positions}
    numbers = np.array(sorted(field_of))
    b_body = np.array([field_of[k] for k in numbers])[np.searchsorted(numbers, position)]
    holds = [s.hold_s / 60.0 for s in plan.steps]
    n = len(time_s)
    return Scenario(
        description=(f"ground test following the program: {len(plan.positions)} static "
                     f"positions x chamber levels {', '.join(f'{v:g}' for v in plan.levels_C)} "
                     f"degC, ramps {plan.ramp_C_per_min:g} degC/min, holds "
                     f"{min(holds):g}-{max(holds):g} min (board time constant "
                     f"{plan.board_tau_s / 60.0:.1f} min), {dt:g} s samples; recording paused "
                     "while the jig is turned"),
        time_s=time_s, b_body_nT=b_body, b_body_at=_static_field_at(time_s, b_body),
        deployed=False, temp_board_C={b: v[keep] for b, v in temps.items()},
        rate_dps=np.zeros((n, 3)), coil_A=np.zeros((n, 3)), position=position,
        columns=_ref_vector_columns(b_body, plan.lab_field_nT),
        extra_truth={"temp_chamber_C": chamber_all[keep],
                     "board_tau_s": np.array([scaled.board_tau_s["body"],
                                              scaled.board_tau_s["boom"]]),
                     "plan_json": np.array(json.dumps(plan.to_json_dict()))})

def _rotate_rows(vectors, rotvec) -> np.ndarray:
    """Rodrigues: rows of `vectors` rotated by the rotation vector (cheaper than scipy here)."""
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-15:
        return vectors
    k = rotvec / angle
    c, s = math.cos(angle), math.sin(angle)
    return vectors * c + np.cross(k, vectors) * s + np.outer(vectors @ k, k) * (1.0 - c)


def _random_in_cap(axis, cap_rad, rng, count) -> np.ndarray:
    """Directions uniform over the cap of half-angle cap_rad about the unit vector axis."""
    cos_alpha = rng.uniform(math.cos(min(cap_rad, math.pi)), 1.0, count)
    azimuth = rng.uniform(0.0, 2 * math.pi, count)
    p = _unit_vector(np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0]))
    q = np.cross(axis, p)
    sin_alpha = np.sqrt(1.0 - cos_alpha**2)
    return (cos_alpha[:, None] * axis + (sin_alpha * np.cos(azimuth))[:, None] * p
            + (sin_alpha * np.sin(azimuth))[:, None] * q)


def _wander_on_sphere(n, dt, rng, speed_rad_s, cap_axis, cap_rad):
    """Smooth random path d(t) of a unit vector staying within cap_rad of cap_axis, and a
    vector e(t) perpendicular to it carried along without twist.

    Like a person turning the unit by hand to cover every orientation: head for a target
    direction, and on reaching it pick the next one far from where the path has been."""
    axis = _unit_vector(cap_axis)
    d = _random_in_cap(axis, cap_rad, rng, 1)[0]
    e = _unit_vector(np.cross(d, rng.normal(size=3)))
    # The hand's intended velocity u wanders (correlation time tau_u) about the heading to
    # the target; the velocity v follows u with a short lag tau_v, so the rate is smooth.
    tau_u, tau_v = 1.5, 0.3
    u = rng.normal(size=3) * speed_rad_s
    v = u - (u @ d) * d
    band = max(0.2 * cap_rad, math.radians(3.0))        # soft wall inside the cap edge
    spring = 2.0 * (speed_rad_s / band) ** 2
    reached = math.cos(min(math.radians(20.0), cap_rad / 3))
    kicks = rng.normal(size=(n, 3)) * speed_rad_s * math.sqrt(2.0 * dt / tau_u)
    visited, target = [d], d
    out_d, out_e = np.empty((n, 3)), np.empty((n, 3))
    for k in range(n):
        out_d[k], out_e[k] = d, e
        if d @ target > reached:                       # next target: the least visited of 8
            candidates = _random_in_cap(axis, cap_rad, rng, 8)
            nearest = np.max(candidates @ np.array(visited).T, axis=1)
            target = candidates[np.argmin(nearest)]
        if k % 10 == 0:
            visited.append(d)
        heading = target - (target @ d) * d
        heading = heading / max(np.linalg.norm(heading), 1e-12)
        u = u + (speed_rad_s * heading - u) * (dt / tau_u) + kicks[k]
        v = v + (u - v) * (dt / tau_v)
        v = v - (v @ d) * d
        d, e, v = _rotate_rows(np.array([d, e, v]), np.cross(d, v) * dt)
        if cap_rad < math.pi:
            alpha = math.acos(min(1.0, max(-1.0, float(d @ axis))))
            toward = axis - (axis @ d) * d             # tangent direction back to the axis
            if alpha > cap_rad - band and np.linalg.norm(toward) > 1e-9:
                toward = toward / np.linalg.norm(toward)
                v = v + toward * spring * (alpha - cap_rad + band) * dt
                if alpha > cap_rad:                    # hard wall: back onto the edge, reflect
                    d, e, v = _rotate_rows(np.array([d, e, v]),
                                           np.cross(d, toward) * (alpha - cap_rad))
                    toward = _unit_vector(axis - (axis @ d) * d)
                    if v @ toward < 0:
                        v = v - 2.0 * (v @ toward) * toward
        e = _unit_vector(e - (e @ d) * d)
    return out_d, out_e


def _rates_from_attitude(time_s, R_body_to_ref):
    """Body rate (deg/s) from an attitude history, central differences."""
    R = Rotation.from_matrix(R_body_to_ref)
    i0 = np.r_[0, np.arange(len(time_s) - 2), len(time_s) - 2]
    i1 = np.r_[1, np.arange(2, len(time_s)), len(time_s) - 1]
    rotvec = (R[i0].inv() * R[i1]).as_rotvec()
    return np.degrees(rotvec / (time_s[i1] - time_s[i0])[:, None])


def _rotation(unit, truth, rng, *, duration_s=400.0, sample_rate_hz=10.0, speed_dps=20.0,
              coverage_cap_deg=180.0, cap_axis_body=(0.0, 0.0, 1.0), lab_field_nT=None,
              inclination_deg=LAB_INCLINATION_deg, room_C=25.0, gyro_noise_dps=0.03):
    """Hand rotation at room temperature, boom deployed. The field direction in the body
    frame wanders smoothly over the sphere, or within coverage_cap_deg of cap_axis_body."""
    lab_field_nT = _field_nT(unit, lab_field_nT)
    dt = 1.0 / sample_rate_hz
    n = int(round(duration_s * sample_rate_hz))
    time_s = np.arange(n) * dt
    d, e = _wander_on_sphere(n, dt, rng, math.radians(speed_dps), cap_axis_body,
                             math.radians(coverage_cap_deg))
    # twist about the lab field: white noise through two lags (1.5 s, 0.3 s), rms rate
    # about speed/2
    white = rng.normal(size=n) * 0.5 * math.radians(speed_dps) * math.sqrt(2.0 * 1.5 / dt)
    twist_rate = first_order_lag(time_s, first_order_lag(time_s, white, 1.5, 0.0), 0.3, 0.0)
    twist_rad = np.cumsum(twist_rate * dt)
    b_lab = _lab_field_nT(lab_field_nT, inclination_deg)
    b_hat = b_lab / lab_field_nT
    n1 = np.array([0.0, 1.0, 0.0])                 # east: perpendicular to the lab field
    n2 = np.cross(b_hat, n1)
    l1 = np.cos(twist_rad)[:, None] * n1 + np.sin(twist_rad)[:, None] * n2
    lab_triad = np.stack([np.broadcast_to(b_hat, (n, 3)), l1, np.cross(b_hat, l1)], axis=2)
    body_triad = np.stack([d, e, np.cross(d, e)], axis=2)
    R = lab_triad @ np.transpose(body_triad, (0, 2, 1))      # body -> lab
    b_body = lab_field_nT * d
    rate = _rates_from_attitude(time_s, R)
    gyro = rate + rng.normal(size=(n, 3)) * gyro_noise_dps
    cap = "" if coverage_cap_deg >= 180 else f", field within {coverage_cap_deg:g} deg of body {tuple(cap_axis_body)}"
    return Scenario(
        description=f"ground test: hand rotation at room temperature, boom deployed{cap}",
        time_s=time_s, b_body_nT=b_body,
        b_body_at=_attitude_field_at(time_s, R, lambda t: np.tile(b_lab, (len(t), 1))),
        deployed=True, temp_board_C=_board_temps(truth, time_s, room_C, 1.0, room_C),
        rate_dps=rate, coil_A=np.zeros((n, 3)), position=np.zeros(n, dtype=int),
        columns={"rate_x_dps": (gyro[:, 0], 3), "rate_y_dps": (gyro[:, 1], 3),
                 "rate_z_dps": (gyro[:, 2], 3), "ref_norm_nT": (np.full(n, lab_field_nT), 1)})


def _smooth_noise(time_s, rng, rms, tau_s):
    """Zero-mean smooth random signal: white noise through two first-order lags (tau_s,
    tau_s/5), scaled to the given rms over the record."""
    white = rng.normal(size=len(time_s))
    v = first_order_lag(time_s, first_order_lag(time_s, white, tau_s, 0.0), tau_s / 5, 0.0)
    v = v - np.mean(v)
    sd = float(np.std(v))
    return v * (rms / sd) if sd > 0 else v


def _attitude_campaign(time_s, R_body_to_lab, b_lab, rng, *, attitude_noise_deg,
                       gyro_noise_dps, lab_field_nT):
    """Field, rates and telemetry columns of a moving unit whose attitude is known from an
    estimator: ref_x/y/z_nT are the lab field rotated by the estimated attitude (true
    attitude times a white error of attitude_noise_deg per axis)."""
    n = len(time_s)
    R = Rotation.from_matrix(R_body_to_lab)
    b_body = R.inv().apply(np.tile(b_lab, (n, 1)))
    err = Rotation.from_rotvec(rng.normal(size=(n, 3)) * math.radians(attitude_noise_deg))
    ref = (R * err).inv().apply(np.tile(b_lab, (n, 1)))
    rate = _rates_from_attitude(time_s, R_body_to_lab)
    gyro = rate + rng.normal(size=(n, 3)) * gyro_noise_dps
    columns = {"rate_x_dps": (gyro[:, 0], 3), "rate_y_dps": (gyro[:, 1], 3),
               "rate_z_dps": (gyro[:, 2], 3)}
    columns.update(_ref_vector_columns(ref, lab_field_nT))
    return b_body, rate, columns


def _yaw_flight(unit, truth, rng, *, duration_s=600.0, sample_rate_hz=10.0, yaw_rate_dps=30.0,
                tilt_max_deg=12.0, attitude_noise_deg=0.1, lab_field_nT=None,
                inclination_deg=LAB_INCLINATION_deg, room_C=25.0, gyro_noise_dps=0.03):
    """A multicopter-like flight: the body turns mostly in yaw (a smooth random yaw rate of
    rms yaw_rate_dps), roll and pitch wander smoothly and stay under tilt_max_deg (the tilt
    of body z from the vertical never exceeds it). The vertical field component hardly
    changes. Reference vectors from an attitude estimate (attitude_noise_deg per axis).
    Constant surroundings at room_C, no boom (B_frame = B_body for every sensor)."""
    lab_field_nT = _field_nT(unit, lab_field_nT)
    dt = 1.0 / sample_rate_hz
    n = int(round(duration_s * sample_rate_hz))
    time_s = np.arange(n) * dt
    yaw = np.cumsum(_smooth_noise(time_s, rng, math.radians(yaw_rate_dps), 5.0)) * dt
    # roll, pitch: smooth, each rms tilt_max/3, then limited so the tilt stays below max
    roll = _smooth_noise(time_s, rng, math.radians(tilt_max_deg) / 3.0, 3.0)
    pitch = _smooth_noise(time_s, rng, math.radians(tilt_max_deg) / 3.0, 3.0)
    tilt = np.hypot(roll, pitch)
    lim = 0.98 * math.radians(tilt_max_deg)
    shrink = np.where(tilt > lim, lim / np.maximum(tilt, 1e-12), 1.0)
    roll, pitch = roll * shrink, pitch * shrink
    R = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1)).as_matrix()
    b_lab = _lab_field_nT(lab_field_nT, inclination_deg)
    b_body, rate, columns = _attitude_campaign(time_s, R, b_lab, rng,
                                               attitude_noise_deg=attitude_noise_deg,
                                               gyro_noise_dps=gyro_noise_dps,
                                               lab_field_nT=lab_field_nT)
    tilt_deg = np.degrees(np.arccos(np.clip(R[:, 2, 2], -1.0, 1.0)))
    return Scenario(
        description=f"yaw-dominated flight: yaw rate rms {yaw_rate_dps:g} deg/s, tilt under "
                    f"{tilt_max_deg:g} deg, attitude estimate +-{attitude_noise_deg:g} deg",
        time_s=time_s, b_body_nT=b_body,
        b_body_at=_attitude_field_at(time_s, R, lambda t: np.tile(b_lab, (len(t), 1))),
        deployed=False, temp_board_C=_board_temps(truth, time_s, room_C, 1.0, room_C),
        rate_dps=rate, coil_A=np.zeros((n, 3)), position=None, columns=columns,
        extra_truth={"tilt_deg": tilt_deg})


def _planar_rotation(unit, truth, rng, *, duration_s=600.0, sample_rate_hz=10.0,
                     rate_dps=20.0, wobble_deg=2.0, axis_body=(0.0, 1.0, 0.0),
                     attitude_noise_deg=0.02, lab_field_nT=None,
                     inclination_deg=LAB_INCLINATION_deg, room_C=25.0, gyro_noise_dps=0.03):
    """A turntable turning the unit about one body axis (axis_body) held perpendicular to
    the lab field, with a smooth wobble of that axis (rms wobble_deg/2, under wobble_deg):
    the field direction in the body frame stays near one plane (the plane normal to
    axis_body). Reference vectors from the table's encoder (attitude_noise_deg).
    Constant surroundings at room_C, boom stowed."""
    lab_field_nT = _field_nT(unit, lab_field_nT)
    dt = 1.0 / sample_rate_hz
    n = int(round(duration_s * sample_rate_hz))
    time_s = np.arange(n) * dt
    b_lab = _lab_field_nT(lab_field_nT, inclination_deg)
    a_body = _unit_vector(axis_body)
    a_lab = _unit_vector(np.cross(b_lab, [0.0, 0.0, 1.0]) if abs(b_lab[2]) < lab_field_nT
                         else np.array([0.0, 1.0, 0.0]))      # horizontal, normal to the field
    # body -> lab: a_body onto a_lab, then the table angle about a_lab, then the wobble
    align = Rotation.align_vectors([a_lab], [a_body])[0]
    speed = math.radians(rate_dps) * (1.0 + 0.2 * _smooth_noise(time_s, rng, 1.0, 10.0))
    angle = np.cumsum(speed) * dt
    wob = np.stack([_smooth_noise(time_s, rng, math.radians(wobble_deg) / 2.0, 5.0)
                    for _ in range(3)], axis=1)
    wob -= np.outer(wob @ a_lab, a_lab)                      # tilt the axis, not the angle
    mag = np.linalg.norm(wob, axis=1)
    lim = 0.98 * math.radians(wobble_deg)
    wob *= np.where(mag > lim, lim / np.maximum(mag, 1e-12), 1.0)[:, None]
    R = (Rotation.from_rotvec(wob) * Rotation.from_rotvec(np.outer(angle, a_lab))
         * align).as_matrix()
    b_body, rate, columns = _attitude_campaign(time_s, R, b_lab, rng,
                                               attitude_noise_deg=attitude_noise_deg,
                                               gyro_noise_dps=gyro_noise_dps,
                                               lab_field_nT=lab_field_nT)
    return Scenario(
        description=f"near-planar rotation: turntable about body {tuple(axis_body)} at "
                    f"{rate_dps:g} deg/s, wobble under {wobble_deg:g} deg",
        time_s=time_s, b_body_nT=b_body,
        b_body_at=_attitude_field_at(time_s, R, lambda t: np.tile(b_lab, (len(t), 1))),
        deployed=False, temp_board_C=_board_temps(truth, time_s, room_C, 1.0, room_C),
        rate_dps=rate, coil_A=np.zeros((n, 3)), position=None, columns=columns,
        extra_truth={"out_of_plane_deg": np.degrees(np.arcsin(np.clip(
            b_body @ a_body / lab_field_nT, -1.0, 1.0)))})


def _coils(unit, truth, rng, *, positions=(1, 5, 9), steps_mA=(25, 50, 75, 100), hold_s=10.0,
           sample_period_s=1.0, lab_field_nT=None, inclination_deg=LAB_INCLINATION_deg,
           room_C=25.0):
    """Static in the jig; in each position each magnetorquer steps 0, +a, -a, ... and back
    to 0 while the others are off."""
    lab_field_nT = _field_nT(unit, lab_field_nT)
    n_hold = max(1, int(round(hold_s / sample_period_s)))
    levels_A = [0.0] + [s * sign / 1000.0 for s in steps_mA for sign in (1, -1)] + [0.0]
    coil_rows, pos_rows = [], []
    for p in positions:
        for axis in range(3):
            for level in levels_A:
                row = np.zeros(3)
                row[axis] = level
                coil_rows += [row] * n_hold
                pos_rows += [p] * n_hold
    coil_A = np.round(np.array(coil_rows), 4)
    position = np.array(pos_rows, dtype=int)
    n = len(position)
    time_s = np.arange(n) * float(sample_period_s)
    b_lab = _lab_field_nT(lab_field_nT, inclination_deg)
    b_body = np.array([R.T @ b_lab for R in twelve_positions()])[position - 1]
    columns = {"coil_x_A": (coil_A[:, 0], 4), "coil_y_A": (coil_A[:, 1], 4),
               "coil_z_A": (coil_A[:, 2], 4)}
    columns.update(_ref_vector_columns(b_body, lab_field_nT))
    return Scenario(
        description=f"ground test: magnetorquer current steps +-{min(steps_mA)}..{max(steps_mA)} mA, "
                    f"static, positions {', '.join(str(p) for p in positions)}",
        time_s=time_s, b_body_nT=b_body, b_body_at=_static_field_at(time_s, b_body),
        deployed=False, temp_board_C=_board_temps(truth, time_s, room_C, 1.0, room_C),
        rate_dps=np.zeros((n, 3)), coil_A=coil_A, position=position, columns=columns)



COIL_STUDY_DISTANCES_CM = (5.0, 10.0, 15.0, 20.0, 25.0, 30.0)   # seed 000 points 1-6


def coil_study_sensors(unit) -> tuple:
    """The sensor the coil study's distances are measured to: the first boom sensor (the
    seed's boom magnetometer), else the first sensor."""
    boom = [s.name for s in unit.sensors if s.frame == "boom"]
    return (boom[0] if boom else unit.sensors[0].name,)


def _coil_study(unit, truth, rng, *, distances_cm=COIL_STUDY_DISTANCES_CM, panels=(0, 1),
                steps_mA=(100, 50), hold_s=10.0, sample_period_s=1.0, position=1,
                lab_field_nT=None, inclination_deg=LAB_INCLINATION_deg, room_C=25.0,
                other_offset_cm=10.0, test_sensors=None, coil="coil_x_A"):
    """Coil interference at known distances (docs/coil_study.md): the jig static in one
    position at room temperature, a magnetorquer taken out (its current column `coil`,
    as in flight, so that every tool leaves its driven samples out) on a rail at each
    distance (column coil_distance_cm, to the sensors in test_sensors) without and with
    the solar panel in place (column panel 0/1), stepped 0, +a, -a, ... 0.

    The coil's field per ampere at a sensor under test, in its frame axes, is
    K(r) = K_30cm (30 cm / r)^exponent x (panel_factor with the panel) u, u a fixed unit
    direction (the coil's axis, drawn from rng); the unit's other sensors sit
    other_offset_cm further away. K_30cm, exponent, panel_factor: truth.coil_study."""
    lab_field_nT = _field_nT(unit, lab_field_nT)
    test_sensors = tuple(test_sensors or coil_study_sensors(unit))
    cs = truth.coil_study
    n_hold = max(1, int(round(hold_s / sample_period_s)))
    levels_A = [0.0] + [m * sg / 1000.0 for m in steps_mA for sg in (1, -1)] + [0.0]
    rows = [(r, pnl, lv) for pnl in panels for r in distances_cm for lv in levels_A]
    dist = np.repeat([r for r, _, _ in rows], n_hold).astype(float)
    panel = np.repeat([pnl for _, pnl, _ in rows], n_hold).astype(int)
    current = np.round(np.repeat([lv for _, _, lv in rows], n_hold), 4)
    n = len(current)
    time_s = np.arange(n) * float(sample_period_s)
    b_lab = _lab_field_nT(lab_field_nT, inclination_deg)
    b_body = np.tile(twelve_positions()[position - 1].T @ b_lab, (n, 1))
    u = _unit_vector(rng.normal(size=3))
    per_A = {}
    for spec in unit.sensors:
        r = dist if spec.name in test_sensors else dist + other_offset_cm
        mag = (cs["K_30cm_nT_per_A"] * (30.0 / r) ** cs["exponent"]
               * np.where(panel == 1, cs["panel_factor"], 1.0))
        per_A[spec.name] = mag[:, None] * u
    columns = {coil: (current, 4), "coil_distance_cm": (dist, 1),
               "panel": (panel, None)}
    columns.update(_ref_vector_columns(b_body, lab_field_nT))
    return Scenario(
        description=(f"ground test: coil interference at {', '.join(f'{r:g}' for r in distances_cm)} "
                     f"cm from {', '.join(test_sensors)}, without and with the solar panel, "
                     f"+-{', '.join(str(m) for m in steps_mA)} mA, static in position {position}"),
        time_s=time_s, b_body_nT=b_body, b_body_at=_static_field_at(time_s, b_body),
        deployed=False, temp_board_C=_board_temps(truth, time_s, room_C, 1.0, room_C),
        rate_dps=np.zeros((n, 3)), coil_A=np.zeros((n, 3)),
        position=np.full(n, position, dtype=int), columns=columns,
        extra_truth={"coil_direction_frame": u,
                     "coil_study_json": np.array(json.dumps(dict(cs)))},
        meta={"coil_test_sensor": ", ".join(test_sensors)},
        extra_field_frame_nT={k: v * current[:, None] for k, v in per_A.items()})

EARTH_RADIUS_km = 6371.2
EARTH_MU_km3_s2 = 398600.4418
EARTH_RATE_rad_s = 7.2921159e-5
DIPOLE_nT = 30000.0                      # equatorial surface field of the dipole
DIPOLE_POLE_COLAT_deg, DIPOLE_POLE_LON_deg = 9.7, -72.6


def _flight(unit, truth, rng, *, duration_s=6 * 3600.0, sample_period_s=2.0, altitude_km=550.0,
            inclination_deg=97.5, beta_angle_deg=20.0, tumble_dps=2.0, model_error_nT=50.0,
            bdot_gain_A_per_nT_s=5e-5, coil_max_A=0.1, gyro_noise_dps=0.02,
            temp_sun_C=(28.0, 35.0), temp_eclipse_C=(12.0, -20.0),
            panel_max_A=0.45):
    """Orbit telemetry: tilted-dipole field (the model; the true field adds a smooth error
    of rms model_error_nT), slow tumble, B-dot currents on every other sample, eclipses
    from geometry drive the board temperatures and the solar array current.
    temp_sun_C, temp_eclipse_C: (body, boom) board surroundings in sun and in eclipse."""
    n = int(round(duration_s / sample_period_s))
    time_s = np.arange(n) * float(sample_period_s)
    r_km = EARTH_RADIUS_km + altitude_km
    mean_motion = math.sqrt(EARTH_MU_km3_s2 / r_km**3)
    inc = math.radians(inclination_deg)
    raan = math.asin(min(1.0, math.sin(math.radians(beta_angle_deg)) / math.sin(inc)))
    sun_eci = np.array([1.0, 0.0, 0.0])
    arg_lat0, gmst0 = rng.uniform(0, 2 * math.pi), rng.uniform(0, 2 * math.pi)
    err_amp = rng.normal(size=(4, 3))
    err_phase = rng.uniform(0, 2 * math.pi, size=(4, 3))
    err_amp *= model_error_nT / math.sqrt(0.5 * np.sum(err_amp**2) / 3)  # rms per axis

    def position_km(t):
        u = arg_lat0 + mean_motion * t
        return r_km * np.stack([
            np.cos(raan) * np.cos(u) - np.sin(raan) * np.sin(u) * math.cos(inc),
            np.sin(raan) * np.cos(u) + np.cos(raan) * np.sin(u) * math.cos(inc),
            np.sin(u) * math.sin(inc)], axis=-1)

    def model_eci_nT(t):
        r = position_km(t)
        r_hat = _unit_vector(r)
        colat, lon = math.radians(DIPOLE_POLE_COLAT_deg), math.radians(DIPOLE_POLE_LON_deg)
        lon_eci = lon + gmst0 + EARTH_RATE_rad_s * np.asarray(t)
        pole = np.stack([math.sin(colat) * np.cos(lon_eci), math.sin(colat) * np.sin(lon_eci),
                         np.full_like(lon_eci, math.cos(colat))], axis=-1)
        scale = DIPOLE_nT * (EARTH_RADIUS_km / r_km) ** 3
        return -scale * (3 * np.sum(pole * r_hat, axis=-1, keepdims=True) * r_hat - pole)

    def true_eci_nT(t):
        u = (arg_lat0 + mean_motion * np.asarray(t))[:, None, None]
        k = np.arange(1, 5)[None, :, None]
        return model_eci_nT(t) + np.sum(err_amp * np.sin(k * u + err_phase), axis=1)

    # slow tumble: the body rate cones about body z with a 10 min period
    w0_rad_s = _unit_vector(rng.normal(size=3)) * math.radians(tumble_dps)
    q0 = _random_rotation(rng)

    def rate_rad_s(t):
        return Rotation.from_rotvec(np.outer(np.asarray(t) * 2 * math.pi / 600.0, [0, 0, 1])).apply(w0_rad_s)

    steps = Rotation.from_rotvec(rate_rad_s(time_s[:-1] + sample_period_s / 2) * sample_period_s)
    attitude = [q0]
    for k in range(n - 1):
        attitude.append(attitude[-1] * steps[k])
    R = Rotation.concatenate(attitude).as_matrix()                 # body -> ECI
    b_body_at = _attitude_field_at(time_s, R, true_eci_nT)
    b_body = np.einsum("nji,nj->ni", R, true_eci_nT(time_s))
    rate = np.degrees(rate_rad_s(time_s))

    # B-dot on odd samples: i = -gain dB/dt, clipped
    dbdt = (b_body_at(time_s + 0.5) - b_body_at(time_s - 0.5)) / 1.0
    coil_A = np.clip(-bdot_gain_A_per_nT_s * dbdt, -coil_max_A, coil_max_A)
    coil_A[0::2] = 0.0
    coil_A = np.round(coil_A, 4) + 0.0

    def sunlit(t):
        r = position_km(t)
        along = r @ sun_eci
        across = np.linalg.norm(r - along[:, None] * sun_eci, axis=1)
        return (along > 0) | (across > EARTH_RADIUS_km)

    # board temperatures: one orbit of pre-roll so the cycle starts settled
    period_s = 2 * math.pi / mean_motion
    n_pre = int(math.ceil(period_s / sample_period_s))
    t_all = np.arange(-n_pre, n) * float(sample_period_s)
    lit_all = sunlit(t_all)
    ambient = {b: np.where(lit_all, sun, eclipse)         # (body, boom) board ambients
               for b, sun, eclipse in zip(("body", "boom"), temp_sun_C, temp_eclipse_C)}
    temps = {b: v[n_pre:] for b, v in _board_temps(truth, t_all, ambient, 1.0,
                                                   None).items()}
    lit = lit_all[n_pre:]
    sun_body = np.einsum("nji,j->ni", R, sun_eci)
    normals = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], dtype=float)
    sa_A = lit * panel_max_A * np.clip(sun_body @ normals.T, 0, None).sum(axis=1)
    sa_A = np.clip(sa_A + rng.normal(size=n) * 0.003, 0, None) * lit
    bus_V = 7.4 + 0.6 * np.minimum(sa_A / 0.6, 1.0) + rng.normal(size=n) * 0.005
    gyro = rate + rng.normal(size=(n, 3)) * gyro_noise_dps
    ref_norm = np.linalg.norm(model_eci_nT(time_s), axis=1)
    columns = {"coil_x_A": (coil_A[:, 0], 4), "coil_y_A": (coil_A[:, 1], 4),
               "coil_z_A": (coil_A[:, 2], 4), "rate_x_dps": (gyro[:, 0], 3),
               "rate_y_dps": (gyro[:, 1], 3), "rate_z_dps": (gyro[:, 2], 3),
               "ref_norm_nT": (ref_norm, 1), "sa_current_A": (sa_A, 3),
               "bus_voltage_V": (bus_V, 3)}
    return Scenario(
        description=(f"orbit telemetry: {altitude_km:g} km, {inclination_deg:g} deg, "
                     f"{duration_s / 3600:g} h, {1 / sample_period_s:g} Hz, tilted dipole model"),
        time_s=time_s, b_body_nT=b_body, b_body_at=b_body_at, deployed=True,
        temp_board_C=temps, rate_dps=rate, coil_A=coil_A, position=None, columns=columns,
        extra_truth={"sunlit": lit.astype(np.int8), "ref_model_nT": ref_norm})


SCENARIOS = {"thermal_12pos": _thermal_12pos, "rotation": _rotation, "coils": _coils,
             "flight": _flight, "coil_study": _coil_study, "yaw_flight": _yaw_flight, "planar_rotation": _planar_rotation}

# fast=True: a few hundred samples per campaign, for quick tests (explicit options win).
FAST_OPTIONS = {
    "thermal_12pos": {"levels_C": (-20.0, 25.0, 55.0), "hold_s": 60.0,
                      "board_tau_scale": 60.0 / 1800.0},
    "rotation": {"duration_s": 120.0, "sample_rate_hz": 5.0},
    "coils": {"positions": (1, 9), "hold_s": 3.0},
    "coil_study": {"distances_cm": (5.0, 15.0, 30.0), "hold_s": 3.0},
    "flight": {"duration_s": 5760.0, "sample_period_s": 10.0},
    "yaw_flight": {"duration_s": 120.0, "sample_rate_hz": 5.0},
    "planar_rotation": {"duration_s": 120.0, "sample_rate_hz": 5.0},
}
