"""Adapter: a PX4 ulog CSV export (sensor_mag_<i>.csv, actuator_outputs_0.csv, ...) read
into the toolchain's unit and telemetry."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from generator.errors import InputError
from generator.io.telemetry import Telemetry
from generator.io.unit import SensorSpec, Unit


PX4_GAUSS_nT = 1e5


def px4_log_telemetry(folder, *, lsb_nT=2.0, average_s=None):
    """Read a PX4 ulog CSV export into the toolchain's structures: (Unit, Telemetry).

    Every sensor_mag_<i>.csv becomes a sensor `mag<i>` (frame body, axes as logged, no
    SET/RESET; part MPU-9255 stands for "a 3-axis part without SET/RESET"); its x, y, z
    (gauss, already calibrated by PX4) become counts of lsb_nT, its chip temperature
    <s>_temp_C. The vehicle stands still: one static position (position = 1), no field
    reference (lab_field_nT unknown). actuator_outputs_0.csv outputs that move (motor
    PWM, us) become channels motor<k>_pwm_us, their mean motors_mean_pwm_us, and
    actuator_armed_0.csv `armed`, each held at its last logged value (the channel as the
    flight software sees it at the magnetometer sample).

    average_s None: one merged time line (s from the first magnetometer sample), one row
    per magnetometer sample, the other sensors' cells empty. average_s > 0: one row per
    interval of that length, every sensor's readings and temperature and every channel
    averaged over the interval (the field is constant while the vehicle stands still;
    averaging removes most of the vibration noise and keeps anything slower).
    """
    folder = Path(folder)
    mags = sorted(folder.glob("sensor_mag_*.csv"),
                  key=lambda p: int(p.stem.rsplit("_", 1)[1]))
    if not mags:
        raise InputError(folder, "no sensor_mag_<i>.csv files")

    def load(p):
        try:
            return np.genfromtxt(p, delimiter=",", names=True, deletechars="")
        except (OSError, ValueError) as e:
            raise InputError(p, f"not a PX4 CSV export: {e}") from None

    logs = [(int(p.stem.rsplit("_", 1)[1]), load(p)) for p in mags]
    for p, (_, d) in zip(mags, logs):
        missing = [c for c in ("timestamp", "x", "y", "z", "temperature")
                   if c not in (d.dtype.names or ())]
        if missing:
            raise InputError(p, f"missing column(s) {', '.join(missing)}")
    t0 = min(float(d["timestamp"][0]) for _, d in logs)
    t_cat = np.concatenate([(d["timestamp"] - t0) * 1e-6 for _, d in logs])
    o = np.argsort(t_cat, kind="stable")
    t_all = t_cat[o]
    row_of = np.empty(len(o), int)
    row_of[o] = np.arange(len(o))           # every sample its own row, in time order
    starts = np.cumsum([0] + [len(d) for _, d in logs])
    held = {}

    def hold(p, names, out_names):
        if not p.exists():
            return
        d = load(p)
        t = (d["timestamp"] - t0) * 1e-6
        for nm, on in zip(names, out_names):
            v = np.asarray(d[nm], float)
            if np.ptp(v) > 0:
                held[on] = (t, v)

    ao = folder / "actuator_outputs_0.csv"
    if ao.exists():
        hdr = ao.read_text().split("\n", 1)[0].strip().split(",")
        outs = [h for h in hdr if h.startswith("output[")]
        hold(ao, outs, [f"motor{int(h[7:-1]) + 1}_pwm_us" for h in outs])
        motors = [k for k in held if k.startswith("motor")]
        if len(motors) > 1:
            t = held[motors[0]][0]
            held["motors_mean_pwm_us"] = (t, np.mean([held[k][1] for k in motors], axis=0))
    hold(folder / "actuator_armed_0.csv", ["armed"], ["armed"])

    def at(name, times):
        t, v = held[name]
        k = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 1)
        return v[k]

    sensors = [SensorSpec(f"mag{i}", "MPU-9255", "body", ("+x", "+y", "+z"), float(lsb_nT),
                          0, False, None) for i, _ in logs]
    if average_s:
        edges = np.arange(0.0, t_all[-1] + average_s, average_s)
        nb = len(edges) - 1
        cols = {"time_s": 0.5 * (edges[:-1] + edges[1:]), "position": np.ones(nb)}
        for i, d in logs:
            t = (d["timestamp"] - t0) * 1e-6
            b = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, nb - 1)
            cnt = np.bincount(b, minlength=nb).astype(float)
            with np.errstate(invalid="ignore"):
                for a in "xyz":
                    m = np.bincount(b, d[a] * PX4_GAUSS_nT, nb) / cnt
                    cols[f"mag{i}_{a}"] = np.round(m / lsb_nT, 3)
                cols[f"mag{i}_temp_C"] = np.bincount(b, d["temperature"], nb) / cnt
        tb = np.clip(np.searchsorted(edges, t_all, side="right") - 1, 0, nb - 1)
        cnt = np.bincount(tb, minlength=nb).astype(float)
        for name in held:
            with np.errstate(invalid="ignore"):
                cols[name] = np.bincount(tb, at(name, t_all), nb) / cnt
        keep = cnt > 0
        cols = {k: v[keep] for k, v in cols.items()}
        n = int(keep.sum())
    else:
        n = len(t_all)
        cols = {"time_s": t_all, "position": np.ones(n)}
        for k, (i, d) in enumerate(logs):
            row = row_of[starts[k]:starts[k + 1]]
            for a in "xyz":
                v = np.full(n, np.nan)
                v[row] = np.round(d[a] * PX4_GAUSS_nT / lsb_nT)
                cols[f"mag{i}_{a}"] = v
            T = np.full(n, np.nan)
            T[row] = d["temperature"]
            cols[f"mag{i}_temp_C"] = T
        for name in held:
            cols[name] = at(name, t_all)
    unit = Unit(id="px4_" + "".join(c if c.isalnum() else "_" for c in folder.name.lower()),
                sensors=tuple(sensors), lab_field_nT=None, float_type="float32",
                boom_reference=None, path=str(folder))
    meta = {"source": "PX4 ulog CSV export", "position": "vehicle standing still"}
    if average_s:
        meta["averaged_s"] = str(average_s)
    tel = Telemetry(str(folder) + (f" ({average_s:g} s means)" if average_s else ""), cols,
                    np.arange(1, n + 1), meta)
    return unit, tel


