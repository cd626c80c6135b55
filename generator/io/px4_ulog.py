"""PX4 flight logs in: a ULog (.ulg, read with pyulog) or its CSV export (one
<topic>_<instance>.csv per topic, as `ulog2csv` writes it) -> a unit TOML skeleton and an
ICD telemetry CSV (`magcal import px4`).

What is taken from the log:
  * every `sensor_mag` instance i -> sensor `mag<i>`: x, y, z in gauss as PX4 publishes them
    (board rotation applied, PX4's calibration not applied: frame body, axes +x +y +z,
    input = "G"); its part from the device id (decode_device_id; unknown devtype -> generic
    with the range stated in GENERIC_RANGE_nT); its temperature where it reports one
    (temperature = false where every sample is NaN, as PX4 logs for e.g. the IST8310);
  * `vehicle_magnetometer` (PX4's calibrated, selected magnetometer) -> sensor `vmag`, part
    of the selected device (sensor_selection.mag_device_id) where known;
  * channels worth tracing, each held at its last logged value at every row (what the
    flight software saw at the magnetometer sample): battery current and voltage,
    actuator outputs that move, the armed flag, 5 V rail, baro temperature, and the body
    rate (ICD rate_x/y/z_dps);
  * reference (--reference): attitude: the IGRF field (generator.io.geomag) at the GNSS
    position and UTC time rotated into the body frame by vehicle_attitude (ref_x/y/z_nT
    and ref_norm_nT); norm: only ref_norm_nT; none: no reference and no position. With a
    reference, lat_deg, lon_deg, alt_km (ICD section 4) are written too.

Rows: the union of all magnetometer sample times (time_s from the first magnetometer sample
of the log), each sensor's cells filled at its own samples and empty at the others'.

as_counts_lsb_nT (a stop-gap for flight code that takes only counts): every sensor is
written as counts of that size (rounded), part "generic" with the real part's full scale
as range_nT, and a sensor without temperature gets a constant stand-in <s>_temp_C column
(STANDIN_TEMP_C, stated in the file). The physical-unit form is the default.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from generator.errors import InputError
from generator.io import parts as P
from generator.io.icd_write import (STANDIN_TEMP_C, Staging, unit_id_from, write_telemetry_csv,
                                     write_unit_toml)

GAUSS_nT = 1e5
GENERIC_RANGE_nT = 1.6e6           # unknown magnetometer: +-16 G assumed (edit in the TOML)
REFERENCES = ("attitude", "norm", "none")

# PX4 src/drivers/drv_sensor.h: DRV_MAG_DEVTYPE_* -> catalogue part
PX4_MAG_DEVTYPES = {
    0x01: "HMC5883L",      # DRV_MAG_DEVTYPE_HMC5883
    0x04: "MPU-9255",      # DRV_MAG_DEVTYPE_MPU9250 / AK8963
    0x05: "LIS3MDL",
    0x06: "IST8310",
    0x07: "RM3100",
    0x08: "QMC5883L",      # DRV_MAG_DEVTYPE_QMC5883
    0x09: "ICM-20948",     # DRV_MAG_DEVTYPE_AK09916
    0x43: "BMM150",
}
BUS_TYPES = {0: "unknown", 1: "I2C", 2: "SPI", 3: "UAVCAN", 4: "simulation", 5: "serial",
             6: "MAVLink"}


@dataclass(frozen=True)
class DeviceId:
    """PX4's 32-bit device id (union DeviceStructure): bus_type:3, bus:5, address:8, devtype:8."""
    devid: int
    bus_type: int
    bus: int
    address: int
    devtype: int

    @staticmethod
    def decode(devid) -> "DeviceId":
        d = int(devid)
        return DeviceId(d, d & 0x7, (d >> 3) & 0x1F, (d >> 8) & 0xFF, (d >> 16) & 0xFF)

    @property
    def part(self) -> str | None:
        return PX4_MAG_DEVTYPES.get(self.devtype)

    def describe(self) -> str:
        return (f"device id {self.devid} = devtype 0x{self.devtype:02x} "
                f"({self.part or 'not in the catalogue'}), "
                f"{BUS_TYPES.get(self.bus_type, self.bus_type)} bus {self.bus} "
                f"address 0x{self.address:02x}")


def decode_device_id(devid) -> DeviceId:
    return DeviceId.decode(devid)


# --------------------------------------------------------------------------- log reading

def topics_from_ulog(path) -> tuple[dict, dict]:
    """({topic: {instance: {field: array}}}, info) of a ULog file."""
    from pyulog import ULog

    import contextlib
    import io

    chatter = io.StringIO()      # pyulog prints its warnings on stdout: keep them off it
    try:
        with contextlib.redirect_stdout(chatter):
            u = ULog(str(path))
    except FileNotFoundError:
        raise InputError(path, "cannot read PX4 log: no such file") from None
    except Exception as e:       # pyulog raises plain exceptions on a corrupt file
        raise InputError(path, f"not a readable ULog file: {type(e).__name__}: {e}") from None
    topics: dict = {}
    for d in u.data_list:
        topics.setdefault(d.name, {})[d.multi_id] = {k: np.asarray(v) for k, v in d.data.items()}
    info = {"hardware": str(u.msg_info_dict.get("ver_hw", "")),
            "software": str(u.msg_info_dict.get("ver_sw_branch", ""))}
    return topics, info


def topics_from_csv_folder(folder) -> tuple[dict, dict]:
    """The same structure from a folder of `<topic>_<instance>.csv` files (ulog2csv)."""
    folder = Path(folder)
    topics: dict = {}
    for p in sorted(folder.glob("*_[0-9]*.csv")):
        topic, _, inst = p.stem.rpartition("_")
        if not inst.isdigit():
            continue
        try:
            d = np.genfromtxt(p, delimiter=",", names=True, deletechars="", dtype=float)
        except (OSError, ValueError) as e:
            raise InputError(p, f"not a PX4 CSV export: {e}") from None
        topics.setdefault(topic, {})[int(inst)] = {k: np.atleast_1d(d[k]) for k in d.dtype.names}
    if not topics:
        raise InputError(folder, "no <topic>_<instance>.csv files (a PX4 ulog2csv export)")
    return topics, {}


def read_topics(path):
    p = Path(path)
    if p.is_dir():
        return topics_from_csv_folder(p)
    if not p.exists():
        raise InputError(p, "cannot read PX4 log: no such file or folder")
    return topics_from_ulog(p)


# --------------------------------------------------------------------------- conversion

def _hold(t_src, v_src, t):
    """Zero-order hold of (t_src, v_src) at times t; NaN before the first sample."""
    k = np.searchsorted(t_src, t, side="right") - 1
    out = np.asarray(v_src, float)[np.clip(k, 0, len(t_src) - 1)]
    return np.where(k >= 0, out, np.nan)


def _mag_xyz(d):
    if "x" in d:
        return np.stack([d["x"], d["y"], d["z"]], axis=1).astype(float)
    return np.stack([d[f"magnetometer_ga[{k}]"] for k in range(3)], axis=1).astype(float)


@dataclass
class _Mag:
    name: str
    t_us: np.ndarray
    gauss: np.ndarray           # (n, 3)
    temp_C: np.ndarray | None   # None: reports no temperature
    device: DeviceId | None
    note: str


def _magnetometers(topics) -> list:
    mags = []
    for inst, d in sorted(topics.get("sensor_mag", {}).items()):
        dev = DeviceId.decode(d["device_id"][0]) if "device_id" in d and len(d["device_id"]) else None
        T = d.get("temperature")
        T = None if T is None or not np.isfinite(np.asarray(T, float)).any() else np.asarray(T, float)
        mags.append(_Mag(f"mag{inst}", np.asarray(d["timestamp"], float), _mag_xyz(d), T, dev,
                         f"sensor_mag instance {inst}"))
    vm = topics.get("vehicle_magnetometer", {}).get(0)
    if vm is not None and len(vm["timestamp"]):
        dev = None
        if "device_id" in vm:
            dev = DeviceId.decode(vm["device_id"][0])
        elif "sensor_selection" in topics:
            dev = DeviceId.decode(topics["sensor_selection"][0]["mag_device_id"][0])
        mags.append(_Mag("vmag", np.asarray(vm["timestamp"], float), _mag_xyz(vm), None, dev,
                         "vehicle_magnetometer (PX4's calibrated, selected magnetometer)"))
    return mags


def _channels(topics, t_us) -> dict:
    out = {}

    def add(name, topic_inst, field, scale=1.0):
        tt, d = topic_inst
        if field in d:
            v = np.asarray(d[field], float) * scale
            if np.isfinite(v).any() and np.nanmax(v) > np.nanmin(v):   # constant: no information
                out[name] = _hold(tt, v, t_us)

    for topic, insts in topics.items():
        for inst, d in insts.items():
            if "timestamp" not in d or not len(d["timestamp"]):
                continue
            ti = (np.asarray(d["timestamp"], float), d)
            if topic == "battery_status":
                add(f"battery{inst}_current_A", ti, "current_a")
                add(f"battery{inst}_voltage_V", ti, "voltage_v")
            elif topic == "actuator_outputs":
                for k in range(16):
                    add(f"act{inst}_out{k}", ti, f"output[{k}]")
            elif topic == "actuator_motors" and inst == 0:       # PX4 v1.14+: -1..1 commands
                for k in range(12):
                    add(f"motor{k}_cmd", ti, f"control[{k}]")
            elif topic == "actuator_armed" and inst == 0:
                add("armed", ti, "armed")
            elif topic == "system_power" and inst == 0:
                add("power_5v_V", ti, "voltage5v_v")
            elif topic == "vehicle_air_data" and inst == 0:
                add("baro_temp_C", ti, "baro_temp_celcius")
            elif topic == "vehicle_angular_velocity" and inst == 0:
                for k, a in enumerate("xyz"):
                    add(f"rate_{a}_dps", ti, f"xyz[{k}]", np.degrees(1.0))
    return out


def _gps(topics):
    """vehicle_gps_position (PX4 up to v1.13; v1.14+ also publishes sensor_gps) instance 0."""
    for name in ("vehicle_gps_position", "sensor_gps"):
        g = topics.get(name, {}).get(0)
        if g is not None and len(g.get("timestamp", ())):
            return g
    return None


def _utc_of(topics, path):
    """(t_us -> UTC datetime64[us]) from the GNSS receiver's time_utc_usec."""
    g = _gps(topics)
    if g is None or "time_utc_usec" not in g:
        raise InputError(path, "no vehicle_gps_position with time_utc_usec: no UTC time and "
                               "position for the field model (use --reference none)")
    ok = np.asarray(g["time_utc_usec"], float) > 0
    if not ok.any():
        raise InputError(path, "vehicle_gps_position has no UTC time (no fix): use "
                               "--reference none")
    offset = float(np.median(np.asarray(g["time_utc_usec"], float)[ok]
                             - np.asarray(g["timestamp"], float)[ok]))
    return lambda t_us: (np.datetime64(0, "us") + (np.asarray(t_us) + offset).astype("int64")
                         .astype("timedelta64[us]"))


def _position(topics, t_us, path):
    g = _gps(topics)
    fix = np.asarray(g.get("fix_type", np.full(len(g["timestamp"]), 3)), float) >= 3
    if not fix.any():
        raise InputError(path, "the GNSS receiver has no 3D fix in this log: use --reference none")
    t = np.asarray(g["timestamp"], float)[fix]
    if "latitude_deg" in g:                                 # PX4 v1.14+: degrees and metres
        lat = np.asarray(g["latitude_deg"], float)[fix]
        lon = np.asarray(g["longitude_deg"], float)[fix]
        alt_mm = 1e3 * np.asarray(g.get("altitude_ellipsoid_m", g.get("altitude_msl_m")),
                                  float)[fix]
    else:                                                   # 1e-7 deg and mm
        lat = np.asarray(g["lat"], float)[fix] * 1e-7
        lon = np.asarray(g["lon"], float)[fix] * 1e-7
        alt_mm = np.asarray(g.get("alt_ellipsoid", g["alt"]), float)[fix]
        if not np.any(alt_mm):
            alt_mm = np.asarray(g["alt"], float)[fix]      # MSL: within ~100 m of the ellipsoid
    inside = (t_us >= t[0]) & (t_us <= t[-1])
    f = lambda v: np.where(inside, np.interp(t_us, t, v), np.nan)
    return f(lat), f(lon), f(alt_mm * 1e-6)


def _quat_rows(topics, t_us, path):
    a = topics.get("vehicle_attitude", {}).get(0)
    if a is None:
        raise InputError(path, "no vehicle_attitude: --reference attitude needs the estimator's "
                               "attitude (use --reference norm)")
    q = np.stack([np.asarray(a[f"q[{k}]"], float) for k in range(4)], axis=1)
    return np.stack([_hold(np.asarray(a["timestamp"], float), q[:, k], t_us)
                     for k in range(4)], axis=1)


def ned_to_body(q_wxyz, v_ned):
    """PX4's vehicle_attitude q (w, x, y, z) rotates body (FRD) into NED: v_ned = R(q) v_body,
    so v_body = R(q)^T v_ned. Row-wise for (N, 4) and (N, 3)."""
    q = np.asarray(q_wxyz, float)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    R = np.empty((len(q), 3, 3))
    R[:, 0, 0] = 1 - 2 * (y * y + z * z); R[:, 0, 1] = 2 * (x * y - w * z); R[:, 0, 2] = 2 * (x * z + w * y)
    R[:, 1, 0] = 2 * (x * y + w * z); R[:, 1, 1] = 1 - 2 * (x * x + z * z); R[:, 1, 2] = 2 * (y * z - w * x)
    R[:, 2, 0] = 2 * (x * z - w * y); R[:, 2, 1] = 2 * (y * z + w * x); R[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return np.einsum("nji,nj->ni", R, np.asarray(v_ned, float))


def convert_log(path, *, reference="attitude", as_counts_lsb_nT=None, position=None,
                only=None):
    """One log -> (sensors: list of TOML dicts, columns: dict, meta: dict)."""
    if reference not in REFERENCES:
        raise InputError(None, f"--reference {reference!r} is not one of {', '.join(REFERENCES)}")
    topics, info = read_topics(path)
    mags = _magnetometers(topics)
    if not mags:
        raise InputError(path, "no sensor_mag or vehicle_magnetometer topic in the log")
    if only:
        names = [m.name for m in mags]
        unknown = [n for n in only if n not in names]
        if unknown:
            raise InputError(path, f"--only: no magnetometer {unknown[0]!r} in the log "
                                   f"(it has {', '.join(names)})")
        mags = [m for m in mags if m.name in only]
    t_all = np.concatenate([m.t_us for m in mags])
    order = np.argsort(t_all, kind="stable")
    t_us = t_all[order]
    row = np.empty(len(order), int)
    row[order] = np.arange(len(order))
    t0 = t_us[0]
    cols = {"time_s": (t_us - t0) * 1e-6}
    if position is not None:                   # the vehicle stood still: one static position
        cols["position"] = np.full(len(t_us), float(position))
    sensors = []
    start = 0
    for m in mags:
        rows = row[start:start + len(m.t_us)]
        start += len(m.t_us)
        part = (m.device.part if m.device else None) or P.GENERIC
        cat = P.part(part)
        full_scale = cat.range_nT if not cat.generic else GENERIC_RANGE_nT
        comment = [f"{m.name}: {m.note}"]
        if m.device:
            comment.append(m.device.describe())
        s = {"_comment": comment, "name": m.name, "part": part, "frame": "body",
             "axes": ["+x", "+y", "+z"]}
        if as_counts_lsb_nT:
            lsb = float(as_counts_lsb_nT)
            s["_comment"].append(f"written as counts of {lsb:g} nT (--as-counts); part {part}")
            s.update(part=P.GENERIC, input="counts", lsb_nT=lsb, zero_count=0,
                     range_nT=float(full_scale))
            values = np.round(m.gauss * GAUSS_nT / lsb)
        else:
            s["input"] = "G"
            if cat.generic:
                s["range_nT"] = float(full_scale)
                s["_comment"].append(f"range_nT: an assumption ({full_scale:g} nT); set the part's")
            values = m.gauss
        for k, a in enumerate("xyz"):
            v = np.full(len(t_us), np.nan)
            v[rows] = values[:, k]
            cols[f"{m.name}_{a}"] = v
        if m.temp_C is not None:
            T = np.full(len(t_us), np.nan)
            T[rows] = m.temp_C
            cols[f"{m.name}_temp_C"] = T
        elif as_counts_lsb_nT:
            cols[f"{m.name}_temp_C"] = np.where(np.isin(np.arange(len(t_us)), rows),
                                                STANDIN_TEMP_C, np.nan)
            s["_comment"].append(f"no temperature: {m.name}_temp_C is a constant stand-in "
                                 f"({STANDIN_TEMP_C:g} degC), not a reading")
        else:
            s["temperature"] = False
        sensors.append(s)
    cols.update(_channels(topics, t_us))
    meta = {"source": f"PX4 log {Path(path).name}", "reference": reference}
    if info.get("hardware"):
        meta["hardware"] = info["hardware"]
    if reference != "none":
        utc = _utc_of(topics, path)(t_us)
        lat, lon, alt_km = _position(topics, t_us, path)
        ok = np.isfinite(lat)
        if not ok.any():
            raise InputError(path, "no magnetometer sample lies inside the GNSS track: "
                                   "use --reference none")
        from generator.io.geomag import field_ned_nT
        ned = np.full((len(t_us), 3), np.nan)
        ned[ok] = field_ned_nT(lat[ok], lon[ok], alt_km[ok], utc[ok])
        cols.update(lat_deg=lat, lon_deg=lon, alt_km=alt_km)
        if reference == "attitude":
            q = _quat_rows(topics, t_us, path)
            good = ok & np.isfinite(q).all(axis=1)
            body = np.full((len(t_us), 3), np.nan)
            body[good] = ned_to_body(q[good], ned[good])
            for k, a in enumerate("xyz"):
                cols[f"ref_{a}_nT"] = body[:, k]
        cols["ref_norm_nT"] = np.linalg.norm(ned, axis=1)
        meta["utc_at_time_0"] = str(utc[0]) + "Z"
        meta["field_model"] = "IGRF (ppigrf) at the GNSS position"
    return sensors, cols, meta


def _unit_id(paths) -> str:
    return unit_id_from("px4_", Path(paths[0]).stem)


def import_px4(paths, out_dir, *, reference="attitude", as_counts_lsb_nT=None,
               unit_id=None, field_nT=None, position=None, only=None) -> dict:
    """`magcal import px4`: writes DIR/unit.toml and DIR/<log>.csv per log. Returns paths."""
    stems = [Path(p).stem for p in paths]
    dup = sorted({x for x in stems if stems.count(x) > 1})
    if dup:
        raise InputError(None, f"two logs named {dup[0]!r}: their CSV files would collide; "
                               "rename one")
    first = None
    results = []
    for p in paths:
        sensors, cols, meta = convert_log(p, reference=reference, position=position,
                                          as_counts_lsb_nT=as_counts_lsb_nT, only=only)
        key = [(s["name"], s["part"]) for s in sensors]
        if first is None:
            first = (p, sensors, key)
        elif key != first[2]:
            raise InputError(p, f"its magnetometers {key} differ from those of {first[0]} "
                                f"{first[2]}: import the logs of one vehicle setup together")
        results.append((p, cols, meta))
    uid = unit_id or _unit_id(paths)
    header = [f"Unit file skeleton written by `magcal import px4` from {len(paths)} log(s) "
              f"on {_dt.date.today().isoformat()}.",
              "Check part, frame and axes; add noise_nT, [boom], [requirements] as needed."]
    with Staging(out_dir) as st:
        names = []
        for p, cols, meta in results:
            meta = {"unit": uid, **meta}
            names.append(write_telemetry_csv(st.dir / (Path(p).stem + ".csv"), cols,
                                             meta=meta).name)
        write_unit_toml(st.dir / "unit.toml", uid, first[1], header=header,
                        unit_keys={"lab_field_nT": float(field_nT)} if field_nT else None)
        return st.commit("unit.toml", names)
