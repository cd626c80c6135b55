"""The project's own simulator: a random but realistic unit, and its test campaigns as
ICD telemetry (spec/ICD.md section 2), for the demo and the tests.

Truth convention (the same as the shared example unit's), per sensor, in its frame axes:

    m = W(T) B_frame + b(T) + K i_coil (+ injected effects)
    W(T) = W0 + W1 dT + W2 dT^2,   b(T) = b0 + b1 dT + b2 dT^2 + b3 dT^3,   dT = T - t_ref_C

T is the true temperature of the sensor's board. B_frame = B_body, except for boom sensors
with the boom deployed: B_frame = H^T B_body (H = H_boom_to_body). An MMC5883 also adds its
bridge offset c(T) = c0 + c1 dT in its own axes, which flips with neither SET nor RESET:

    SET   = S m(t)          + c(T) + noise
    RESET = -S m'(t + delay) + c(T) + noise     (S: frame -> sensor axes, seed 000 eq. 1)

m' is the reading for the field the body sees `delay` later, i.e. the field rotated by
-rate * delay. counts = clip(round(value / lsb_nT) + zero_count, count_min, count_max).

Use:
    rng = np.random.default_rng(7)
    unit = make_example_unit()
    truth = random_truth(unit, rng)
    csv_path, arrays = simulate_campaign("rotation", unit, truth, rng, "out",
                                         effects=[ThermalLag("mmc2", tau_s=300.0)])
    paths = make_example("demo_out", seed=1)

Everything is deterministic for the generator passed in. Effects never draw random
numbers, so a campaign with and without an effect differs by the effect alone.

The simulated unit and how it is observed. The campaign kinds (chamber twelve positions
following the test program, rotation, coils, coil study,
orbit, yaw flight, planar turntable) are generator/campaign/scenarios.py: what the unit
lives through; this module is the unit (truth), its effects, its sensors and the files.

`magcal simulate` (generator/verbs/simulate.py, docs/simulate.md) is the command line.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from generator.campaign.board_thermal import first_order_lag
from generator.campaign.plan import twelve_positions  # noqa: F401  (the jig positions)
# the campaign kinds, and what the simulator's users take from there
from generator.campaign.scenarios import (COIL_STUDY_DISTANCES_CM, FAST_OPTIONS,  # noqa: F401
                                          LAB_FIELD_nT, LAB_INCLINATION_deg, SCENARIOS,
                                          Scenario, _unit_vector,
                                          boards_of, coil_study_sensors, plan_for)
from generator.io import parts as _parts
from generator.io.unit import SensorSpec, Unit

CAMPAIGNS = ("thermal_12pos", "rotation", "coils", "flight")   # the unit's campaigns
EXAMPLE_CAMPAIGNS = CAMPAIGNS + ("coil_study",)                  # make_example writes these
# further geometries for fit tests (simulate_campaign kinds; not part of make_example)
EXTRA_CAMPAIGNS = ("yaw_flight", "planar_rotation", "coil_study")

T_REF_C = 25.0
SET_RESET_DELAY_s = 0.012          # RESET reading is taken this long after the SET one
DEFAULT_NOISE_nT = {"MMC5883MA": 40.0, "MPU-9255": 250.0}
# MMC5883MA temperature output: the catalogue's step (0.7 degC/LSB), 0 = -75 degC
MMC_TEMP_STEP_C, MMC_TEMP_ZERO_C = _parts.temperature_lsb_C("MMC5883MA"), -75.0

# The coil study's test coil (seed 000: a magnetorquer at points 1-6, 5 to 30 cm from the
# magnetometer, 0.1 A): |field per ampere| at 30 cm on the coil's axis, the fall-off
# exponent (a dipole: 3) and the factor the solar panel adds (seed 000 at 30 cm and 0.1 A:
# 167.87 nT without the panel, 307.57 nT with it). Set with a truth override.
COIL_STUDY_DEFAULT = {"K_30cm_nT_per_A": 1678.7, "exponent": 3.0,
                      "panel_factor": 307.57 / 167.87}
COIL_STUDY_LIMITS = {"K_30cm_nT_per_A": (0.0, 1e7), "exponent": (0.5, 6.0),
                     "panel_factor": (0.0, 100.0)}


# ---------------------------------------------------------------------------------------
# Small helpers
# ---------------------------------------------------------------------------------------

def rotate_by_rate(v_nT, rate_dps, dt_s) -> np.ndarray:
    """Body-frame vector after the body turned at rate_dps for dt_s: exp(-[w]x dt) v."""
    rotvec = -np.radians(np.asarray(rate_dps, dtype=float)) * dt_s
    return Rotation.from_rotvec(np.atleast_2d(rotvec)).apply(np.atleast_2d(v_nT))


def frame_to_sensor(spec: SensorSpec, v_frame) -> np.ndarray:
    """Inverse of the axis mapping: frame[k] = sign[k] * sensor[idx[k]]."""
    idx, sign = spec.axis_map()
    v_frame = np.asarray(v_frame, dtype=float)
    out = np.empty_like(v_frame)
    out[:, list(idx)] = v_frame * np.asarray(sign, dtype=float)
    return out


def sensor_noise_nT(spec: SensorSpec, sensor_truth=None) -> float:
    """1-sigma noise of one axis of one reading: the truth's noise_nT where set, else the
    unit file's noise_nT, else the part's typical figure (catalogue), else 1/1000 of the
    sensor's full scale (a generic part without a figure)."""
    if sensor_truth is not None and sensor_truth.noise_nT is not None:
        return float(sensor_truth.noise_nT)
    if spec.noise_nT is not None:
        return float(spec.noise_nT)
    if spec.part in DEFAULT_NOISE_nT:
        return DEFAULT_NOISE_nT[spec.part]
    part = _parts.part(spec.part)
    return float(part.noise_nT) if part.noise_nT else 1e-3 * spec.full_scale_nT


def physical_decimals(spec: SensorSpec) -> int:
    """Decimals of a physical-unit column (ICD section 4): a resolution of 0.1 nT or finer."""
    return max(0, math.ceil(math.log10(spec.nT_per_input / 0.1) - 1e-9))


def report_temperature(part: str, temp_C) -> tuple[np.ndarray, int]:
    """(reported temperature, decimals): MMC5883 in 0.7 degC steps, other parts to 0.01."""
    t = np.asarray(temp_C, dtype=float)
    if part == "MMC5883MA":
        steps = np.round((t - MMC_TEMP_ZERO_C) / MMC_TEMP_STEP_C)
        return np.round(MMC_TEMP_ZERO_C + MMC_TEMP_STEP_C * steps, 1), 1
    return np.round(t, 2), 2


def _signed_uniform(rng, lo, hi, size):
    """Magnitude uniform in [lo, hi], random sign."""
    return rng.choice([-1.0, 1.0], size=size) * rng.uniform(lo, hi, size=size)


def _signed_log_uniform(rng, lo, hi, size):
    """Magnitude log-uniform in [lo, hi], random sign."""
    return rng.choice([-1.0, 1.0], size=size) * np.exp(rng.uniform(math.log(lo), math.log(hi), size))


# ---------------------------------------------------------------------------------------
# Truth: the parameters the calibration should recover
# ---------------------------------------------------------------------------------------

@dataclass
class SensorTruth:
    W_poly_frame: np.ndarray               # (3, 3, 3): W0, W1 (/degC), W2 (/degC^2)
    b_poly_frame_nT: np.ndarray            # (4, 3): b0..b3 (nT/degC^k)
    chip_offset_poly_sensor_nT: np.ndarray  # (2, 3): c0, c1 in sensor axes (zero for MPU)
    K_coil_frame_nT_per_A: np.ndarray      # (3, 3): column j = field per amp of coil j
    frame: str | None = None               # "body" / "boom" (not in the shared truth.json)
    noise_nT: float | None = None          # None: the unit file's, else the part's

    def W(self, dT) -> np.ndarray:
        d = np.asarray(dT, dtype=float)[..., None, None]
        return sum(self.W_poly_frame[k] * d**k for k in range(self.W_poly_frame.shape[0]))

    def b(self, dT) -> np.ndarray:
        d = np.asarray(dT, dtype=float)[..., None]
        return sum(self.b_poly_frame_nT[k] * d**k for k in range(self.b_poly_frame_nT.shape[0]))

    def chip_offset(self, dT) -> np.ndarray:
        d = np.asarray(dT, dtype=float)[..., None]
        c = self.chip_offset_poly_sensor_nT
        return sum(c[k] * d**k for k in range(c.shape[0]))

    def reading_frame_nT(self, field_frame_nT, dT, coil_A=None) -> np.ndarray:
        """m = W(T) B + b(T) + K i, frame axes, (N, 3)."""
        m = np.einsum("nij,nj->ni", self.W(dT), field_frame_nT) + self.b(dT)
        if coil_A is not None:
            m = m + np.asarray(coil_A) @ self.K_coil_frame_nT_per_A.T
        return m


@dataclass
class Truth:
    t_ref_C: float
    H_boom_to_body: np.ndarray             # (3, 3) rotation, boom frame -> body frame
    sensors: dict                          # name -> SensorTruth, unit order
    board_tau_s: dict = field(default_factory=lambda: {"body": 900.0, "boom": 900.0})
    board_self_heating_C: dict = field(default_factory=lambda: {"body": 0.0, "boom": 0.0})
    # the coil study (campaign coil_study): a test coil at known distances; no random draw,
    # so that adding it changed no other campaign. See COIL_STUDY_DEFAULT.
    coil_study: dict = field(default_factory=lambda: dict(COIL_STUDY_DEFAULT))

    def true_field_frame(self, sensor, B_body_nT, deployed: bool) -> np.ndarray:
        """True field in the sensor's frame. sensor: a SensorSpec or a name."""
        frame = sensor.frame if isinstance(sensor, SensorSpec) else self.sensors[sensor].frame
        if frame is None:
            raise ValueError(f"frame of sensor {sensor!r} unknown: pass its SensorSpec")
        B = np.asarray(B_body_nT, dtype=float)
        return B @ self.H_boom_to_body if (frame == "boom" and deployed) else B.copy()

    def to_json(self, simulation: dict | None = None) -> dict:
        """truth.json; `simulation` (simulation_record) records how the run was made: its
        seed and magcal version, so that it can be reproduced."""
        note = ("m_frame = W(T) B_frame + b(T) + K i_coil; W(T)=W0+W1 dT+W2 dT^2, "
                "b(T)=sum b_k dT^k, dT=T-t_ref")
        return {
            "t_ref_C": self.t_ref_C,
            "H_boom_to_body": self.H_boom_to_body.tolist(),
            "sensors": {
                name: {
                    "W_poly_frame": s.W_poly_frame.tolist(),
                    "b_poly_frame_nT": s.b_poly_frame_nT.tolist(),
                    "chip_offset_poly_sensor_nT": s.chip_offset_poly_sensor_nT.tolist(),
                    "K_coil_frame_nT_per_A": s.K_coil_frame_nT_per_A.tolist(),
                    "frame": s.frame,
                    **({"noise_nT": s.noise_nT} if s.noise_nT is not None else {}),
                    "note": note,
                }
                for name, s in self.sensors.items()
            },
            "board_tau_s": dict(self.board_tau_s),
            "board_self_heating_C": dict(self.board_self_heating_C),
            "coil_study": dict(self.coil_study),
            **({"simulation": dict(simulation)} if simulation is not None else {}),
        }

    @staticmethod
    def from_json(d: dict, unit: Unit | None = None) -> "Truth":
        """Reads this simulator's truth.json and the shared one (frames then come from
        `unit` when given)."""
        sensors = {}
        for name, s in d["sensors"].items():
            frame = s.get("frame")
            if frame is None and unit is not None and name in unit.sensor_names:
                frame = unit.sensor(name).frame
            sensors[name] = SensorTruth(
                W_poly_frame=np.array(s["W_poly_frame"], dtype=float),
                b_poly_frame_nT=np.array(s["b_poly_frame_nT"], dtype=float),
                chip_offset_poly_sensor_nT=np.array(
                    s.get("chip_offset_poly_sensor_nT", np.zeros((2, 3))), dtype=float),
                K_coil_frame_nT_per_A=np.array(
                    s.get("K_coil_frame_nT_per_A", np.zeros((3, 3))), dtype=float),
                frame=frame, noise_nT=s.get("noise_nT"),
            )
        truth = Truth(t_ref_C=float(d["t_ref_C"]),
                      H_boom_to_body=np.array(d["H_boom_to_body"], dtype=float),
                      sensors=sensors)
        truth.board_tau_s.update(d.get("board_tau_s", {}))
        truth.board_self_heating_C.update(d.get("board_self_heating_C", {}))
        truth.coil_study.update(d.get("coil_study", {}))
        return truth


def simulation_record(seed: int, **how) -> dict:
    """truth.json's "simulation" entry: the seed, the magcal version that drew the unit and
    its campaigns, and `how` (the options of the run). The same seed, options and version
    give the same bytes."""
    from generator import __version__
    return {"seed": int(seed), "magcal_version": __version__, **how}


def load_truth(path, unit: Unit | None = None) -> Truth:
    return Truth.from_json(json.loads(Path(path).read_text()), unit)


def random_truth(unit: Unit, rng: np.random.Generator) -> Truth:
    """Random, realistic parameters for every sensor of the unit."""
    H = Rotation.from_rotvec(_unit_vector(rng.normal(size=3))
                             * math.radians(rng.uniform(1.0, 3.0))).as_matrix()
    board_tau_s = {"body": float(rng.uniform(600, 1200)), "boom": float(rng.uniform(600, 1200))}
    heating_C = {"body": float(rng.uniform(0.5, 2.0)), "boom": float(rng.uniform(0.0, 0.8))}
    # Coil coupling is set by where a board sits: one base per board, a spread per sensor.
    K_base = {"body": _signed_log_uniform(rng, 1000.0, 10000.0, (3, 3)),     # nT/A
              "boom": _signed_log_uniform(rng, 100.0, 2000.0, (3, 3))}       # 30 cm away
    sensors = {}
    for s in unit.sensors:
        eye = np.eye(3)
        W0 = np.diag(rng.uniform(0.93, 1.07, 3)) + (1 - eye) * rng.uniform(-0.02, 0.02, (3, 3))
        W1 = np.diag(_signed_uniform(rng, 1e-4, 3e-4, 3)) + (1 - eye) * rng.uniform(-3e-5, 3e-5, (3, 3))
        W2 = np.diag(_signed_uniform(rng, 1e-6, 3e-6, 3)) + (1 - eye) * rng.uniform(-3e-7, 3e-7, (3, 3))
        b = np.array([rng.uniform(-3000.0, 3000.0, 3),
                      _signed_uniform(rng, 1.0, 10.0, 3),
                      _signed_uniform(rng, 0.01, 0.2, 3),
                      _signed_uniform(rng, 1e-4, 4e-3, 3)])
        K = K_base[s.frame] * rng.uniform(0.8, 1.2, (3, 3))
        chip = np.array([rng.uniform(-8000.0, 8000.0, 3), rng.uniform(-20.0, 20.0, 3)])
        if not _parts.part(s.part).set_reset:
            chip[:] = 0.0
        sensors[s.name] = SensorTruth(np.array([W0, W1, W2]), b, chip, K, frame=s.frame)
    return Truth(T_REF_C, H, sensors, board_tau_s, heating_C)


# Keys a truth.json written by simulate carries besides the parameters, accepted in an
# override so that a run's truth.json can be given back (--truth): "simulation" (the record
# of that run: seed, version, options) is ignored -- the seed of the new run is --seed;
# "t_ref_C" must be the simulator's (its polynomials are in T - t_ref_C); per sensor,
# "frame" must be the unit file's and "note" is ignored.
TRUTH_RECORD_KEYS = ("simulation", "t_ref_C")


def override_truth(truth: Truth, d: dict, unit: Unit, source=None) -> Truth:
    """The truth with the values of `d` (a partial truth: the keys of truth.json, see
    docs/simulate.md) put in place of the drawn ones; InputError naming the key on an
    unknown sensor or key, a wrong shape, a non-finite number or an impossible value.
    A whole truth.json of a simulate run is accepted (TRUTH_RECORD_KEYS)."""
    from generator.errors import InputError

    def arr(v, key, shapes):
        try:
            a = np.asarray(v, dtype=float)
        except (TypeError, ValueError):
            raise InputError(source, f"key {key}: not an array of numbers") from None
        if a.shape not in shapes:
            raise InputError(source, f"key {key}: shape {a.shape}, expected "
                                     + " or ".join(str(x) for x in shapes))
        if not np.isfinite(a).all():
            raise InputError(source, f"key {key}: not finite")
        return a

    def num(v, key, lo, hi):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                or not lo <= v <= hi:
            raise InputError(source, f"key {key}: {v!r} is not a number in [{lo:g}, {hi:g}]")
        return float(v)

    if not isinstance(d, dict):
        raise InputError(source, "a truth override is a table of keys (see docs/simulate.md)")
    known = {"H_boom_to_body", "board_tau_s", "board_self_heating_C", "sensors", "coil_study"}
    for k in d:
        if k not in known | set(TRUTH_RECORD_KEYS):
            raise InputError(source, f"key {k}: unknown; known keys: {', '.join(sorted(known))}"
                                     f" (and {', '.join(TRUTH_RECORD_KEYS)} of a truth.json)")
    # a truth.json written by simulate: its record-only keys (module TRUTH_RECORD_KEYS)
    if "t_ref_C" in d and num(d["t_ref_C"], "t_ref_C", -150.0, 200.0) != truth.t_ref_C:
        raise InputError(source, f"key t_ref_C: {d['t_ref_C']!r}; the simulator's "
                                 f"polynomials are in T - {truth.t_ref_C:g} degC")
    if "simulation" in d and not isinstance(d["simulation"], dict):
        raise InputError(source, "key simulation: a table (the record of a simulate run)")
    sensors = {n: SensorTruth(**{f.name: getattr(st, f.name) for f in fields(st)})
               for n, st in truth.sensors.items()}
    out = Truth(truth.t_ref_C, truth.H_boom_to_body.copy(), sensors, dict(truth.board_tau_s),
                dict(truth.board_self_heating_C), dict(truth.coil_study))
    if "H_boom_to_body" in d:
        H = arr(d["H_boom_to_body"], "H_boom_to_body", [(3, 3)])
        if not np.allclose(H @ H.T, np.eye(3), atol=1e-6) or np.linalg.det(H) < 0:
            raise InputError(source, "key H_boom_to_body: not a rotation matrix")
        out.H_boom_to_body = H
    for key, lo, hi in (("board_tau_s", 0.0, 1e6), ("board_self_heating_C", -50.0, 50.0)):
        v = d.get(key, {})
        if not isinstance(v, dict):
            raise InputError(source, f"key {key}: a table {{body = .., boom = ..}}")
        for b, x in v.items():
            if b not in ("body", "boom"):
                raise InputError(source, f"key {key}.{b}: boards are body and boom")
            getattr(out, key)[b] = num(x, f"{key}.{b}", lo, hi)
    cs = d.get("coil_study", {})
    if not isinstance(cs, dict):
        raise InputError(source, "key coil_study: a table (see docs/simulate.md)")
    for k, x in cs.items():
        lim = COIL_STUDY_LIMITS.get(k)
        if lim is None:
            raise InputError(source, f"key coil_study.{k}: unknown; known keys: "
                                     f"{', '.join(COIL_STUDY_LIMITS)}")
        out.coil_study[k] = num(x, f"coil_study.{k}", *lim)
    sens = d.get("sensors", {})
    if not isinstance(sens, dict):
        raise InputError(source, "key sensors: a table of sensors by name")
    for name, sd in sens.items():
        if name not in sensors:
            raise InputError(source, f"key sensors.{name}: unit {unit.id} has no sensor "
                                     f"{name!r} ({', '.join(unit.sensor_names)})")
        if not isinstance(sd, dict):
            raise InputError(source, f"key sensors.{name}: a table of parameters")
        st = sensors[name]
        for k, v in sd.items():
            key = f"sensors.{name}.{k}"
            if k == "W_poly_frame":
                st.W_poly_frame = arr(v, key, [(j, 3, 3) for j in (1, 2, 3)])
                if abs(np.linalg.det(st.W_poly_frame[0])) < 0.1:
                    raise InputError(source, f"key {key}: W0 is (nearly) singular")
            elif k == "b_poly_frame_nT":
                st.b_poly_frame_nT = arr(v, key, [(j, 3) for j in (1, 2, 3, 4)])
            elif k == "chip_offset_poly_sensor_nT":
                st.chip_offset_poly_sensor_nT = arr(v, key, [(1, 3), (2, 3)])
            elif k == "K_coil_frame_nT_per_A":
                st.K_coil_frame_nT_per_A = arr(v, key, [(3, 3)])
            elif k == "noise_nT":
                st.noise_nT = num(v, key, 0.0, 1e6)
            elif k == "frame":            # recorded by truth.json: must be the unit's
                if v != unit.sensor(name).frame:
                    raise InputError(source, f"key {key}: {v!r}, the unit file has sensor "
                                             f"{name!r} on the {unit.sensor(name).frame} "
                                             "board: a truth of another unit?")
            elif k == "note":             # truth.json's explanation of the model: ignored
                pass
            else:
                raise InputError(source, f"key {key}: unknown; known: W_poly_frame, "
                                         "b_poly_frame_nT, chip_offset_poly_sensor_nT, "
                                         "K_coil_frame_nT_per_A, noise_nT (and frame, note "
                                         "of a truth.json)")
    return out


# ---------------------------------------------------------------------------------------
# Injected effects: what the calibration model lacks, for residual tracing
# ---------------------------------------------------------------------------------------

@dataclass
class EffectContext:
    """What an effect may look at, for one sensor, all samples (N)."""
    sensor: SensorSpec
    truth: SensorTruth
    t_ref_C: float
    time_s: np.ndarray               # (N,)
    temp_C: np.ndarray               # (N,) true board temperature
    field_frame_nT: np.ndarray       # (N, 3) true field, frame axes
    coil_A: np.ndarray               # (N, 3)
    reading_frame_nT: np.ndarray     # (N, 3) model reading so far (W B + b + K i + earlier effects)
    channels: dict                   # telemetry channel name -> (N,) values
    field_frame_at: Callable         # times (M,) -> (M, 3) true field, frame axes


@dataclass
class SquareWave:
    """A synthetic telemetry channel, e.g. a thermostat-driven heater current."""
    period_s: float = 900.0
    duty: float = 0.4
    high: float = 0.3
    low: float = 0.0
    phase_s: float = 0.0
    decimals: int = 3

    def values(self, time_s) -> np.ndarray:
        on = np.mod(np.asarray(time_s) - self.phase_s, self.period_s) < self.duty * self.period_s
        return np.where(on, self.high, self.low)


class Effect:
    """Base: adds nothing. Subclasses are dataclasses with a `sensor` field."""
    name = "none"

    def params(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "sensor"}

    def to_dict(self) -> dict:
        p = self.params()
        for k, v in p.items():
            if isinstance(v, SquareWave):
                p[k] = asdict(v)
            elif isinstance(v, (tuple, np.ndarray)):
                p[k] = np.asarray(v, dtype=float).tolist()
        return {"effect": self.name, "sensor": self.sensor, **p}

    def channels(self, time_s) -> dict:
        """New telemetry columns this effect brings: name -> (values, decimals)."""
        return {}

    def reset_delay_s(self, delay_s: float) -> float:
        return delay_s

    def frame_nT(self, ctx: EffectContext) -> np.ndarray:
        """Contribution to the frame-axis reading, (N, 3) nT."""
        return np.zeros_like(ctx.field_frame_nT)


@dataclass
class ChannelBias(Effect):
    """Bias linear in a telemetry channel; `source` creates the channel if it is new."""
    sensor: str
    channel: str
    nT_per_unit: tuple
    source: SquareWave | None = None
    name = "channel_bias"

    def channels(self, time_s):
        return {} if self.source is None else {
            self.channel: (self.source.values(time_s), self.source.decimals)}

    def frame_nT(self, ctx):
        return ctx.channels[self.channel][:, None] * np.asarray(self.nT_per_unit, dtype=float)


def heater_bias(sensor, nT_per_A, period_s=900.0, duty=0.4, current_A=0.3, phase_s=0.0):
    """A heater switching `current_A` on and off, its field seen by `sensor`."""
    return ChannelBias(sensor, "heater_A", tuple(nT_per_A),
                       SquareWave(period_s, duty, current_A, 0.0, phase_s, 3))


@dataclass
class ThermalLag(Effect):
    """The sensing element's temperature lags the reported (board) temperature."""
    sensor: str
    tau_s: float
    name = "thermal_lag"

    def frame_nT(self, ctx):
        t_element = first_order_lag(ctx.time_s, ctx.temp_C, self.tau_s)
        lagged = ctx.truth.reading_frame_nT(ctx.field_frame_nT, t_element - ctx.t_ref_C)
        return lagged - ctx.truth.reading_frame_nT(ctx.field_frame_nT, ctx.temp_C - ctx.t_ref_C)


@dataclass
class QuarticBias(Effect):
    """b4 dT^4, beyond the cubic bias of the calibration model."""
    sensor: str
    b4_nT_per_C4: tuple
    name = "quartic_bias"

    def frame_nT(self, ctx):
        return ((ctx.temp_C - ctx.t_ref_C) ** 4)[:, None] * np.asarray(self.b4_nT_per_C4, dtype=float)


@dataclass
class CubicNonlinearity(Effect):
    """Per axis a_k (m_k / 50 uT)^3, m the reading; a_k in nT."""
    sensor: str
    nT_at_50uT: tuple
    name = "cubic_nonlinearity"

    def frame_nT(self, ctx):
        return np.asarray(self.nT_at_50uT, dtype=float) * (ctx.reading_frame_nT / 50000.0) ** 3


@dataclass
class BiasStep(Effect):
    """A bias step at time_s (magnetisation event)."""
    sensor: str
    time_s: float
    step_nT: tuple
    name = "bias_step"

    def frame_nT(self, ctx):
        return (ctx.time_s >= self.time_s)[:, None] * np.asarray(self.step_nT, dtype=float)


@dataclass
class SetResetDelay(Effect):
    """The RESET reading taken delay_s after the SET one (rotation error with rate)."""
    sensor: str
    delay_s: float
    name = "set_reset_delay"

    def reset_delay_s(self, delay_s):
        return self.delay_s


@dataclass
class TimeOffset(Effect):
    """The magnetometer samples the field offset_s after its time stamp (and the
    reference)."""
    sensor: str
    offset_s: float
    name = "time_offset"

    def frame_nT(self, ctx):
        shifted = ctx.field_frame_at(ctx.time_s + self.offset_s)
        W = ctx.truth.W(ctx.temp_C - ctx.t_ref_C)
        return np.einsum("nij,nj->ni", W, shifted - ctx.field_frame_nT)


EFFECTS = {cls.name: cls for cls in (ChannelBias, ThermalLag, QuarticBias, CubicNonlinearity,
                                     BiasStep, SetResetDelay, TimeOffset)}


def effect_from_dict(d: dict) -> Effect:
    """Inverse of Effect.to_dict()."""
    d = dict(d)
    cls = EFFECTS[d.pop("effect")]
    if d.get("source") is not None:
        d["source"] = SquareWave(**d["source"])
    return cls(**d)


# ---------------------------------------------------------------------------------------
# Sensor model: true field -> raw counts
# ---------------------------------------------------------------------------------------

def _to_counts(spec: SensorSpec, value_nT) -> np.ndarray:
    counts = np.round(value_nT / spec.lsb_nT) + spec.zero_count
    return np.clip(counts, spec.count_min, spec.count_max).astype(np.int64)


def _to_raw(spec: SensorSpec, value_nT) -> tuple:
    """(column values, decimals): integer counts (decimals None), or for a physical-unit
    input (ICD section 4) the value in that unit, clipped at the full scale."""
    if spec.counts:
        return _to_counts(spec, value_nT), None
    fs = spec.full_scale_nT
    return np.clip(value_nT, -fs, fs) / spec.nT_per_input, physical_decimals(spec)


def _render_sensor(spec, truth, sc: Scenario, effects, channels, rng, delay_s, noise_scale):
    """Raw telemetry columns of one sensor: name -> (values, decimals)."""
    st = truth.sensors[spec.name]
    temp_C = sc.temp_board_C[spec.frame]
    dT = temp_C - truth.t_ref_C
    B_frame = truth.true_field_frame(spec, sc.b_body_nT, sc.deployed)
    m = st.reading_frame_nT(B_frame, dT, sc.coil_A)
    if spec.name in sc.extra_field_frame_nT:            # e.g. the coil study's test coil
        m = m + sc.extra_field_frame_nT[spec.name]

    ctx = EffectContext(spec, st, truth.t_ref_C, sc.time_s, temp_C, B_frame, sc.coil_A, m, channels,
                        lambda t: truth.true_field_frame(spec, sc.b_body_at(t), sc.deployed))
    added = np.zeros_like(m)
    for e in effects:
        if e.sensor == spec.name:
            delay_s = e.reset_delay_s(delay_s)
            added = added + e.frame_nT(ctx)
            ctx.reading_frame_nT = m + added
    chip = st.chip_offset(dT)
    sigma = sensor_noise_nT(spec, st) * noise_scale
    cols = {}
    if spec.set_reset:
        B_reset = truth.true_field_frame(spec, rotate_by_rate(sc.b_body_nT, sc.rate_dps, delay_s),
                                         sc.deployed)
        m_reset = st.reading_frame_nT(B_reset, dT, sc.coil_A) + added
        if spec.name in sc.extra_field_frame_nT:
            m_reset = m_reset + sc.extra_field_frame_nT[spec.name]
        set_nT = frame_to_sensor(spec, m + added) + chip + rng.normal(size=m.shape) * sigma
        reset_nT = -frame_to_sensor(spec, m_reset) + chip + rng.normal(size=m.shape) * sigma
        for kind, v in (("set", set_nT), ("reset", reset_nT)):
            raw, dec = _to_raw(spec, v)
            for k, ax in enumerate("xyz"):
                cols[f"{spec.name}_{kind}_{ax}"] = (raw[:, k], dec)
    else:
        v = frame_to_sensor(spec, m + added) + chip + rng.normal(size=m.shape) * sigma
        raw, dec = _to_raw(spec, v)
        for k, ax in enumerate("xyz"):
            cols[f"{spec.name}_{ax}"] = (raw[:, k], dec)
    if spec.temperature:
        reported, decimals = report_temperature(spec.part, temp_C)
        cols[f"{spec.name}_temp_C"] = (reported, decimals)
    return cols


# ---------------------------------------------------------------------------------------
# Telemetry CSV and campaigns
# ---------------------------------------------------------------------------------------

def _time_decimals(time_s) -> int:
    for d in range(4):
        if np.allclose(time_s * 10**d, np.round(time_s * 10**d), atol=1e-6):
            return d
    return 3


def write_telemetry_csv(path, comment_lines, columns: dict) -> None:
    """columns: name -> (values, decimals); decimals None for integers."""
    names = list(columns)
    fmt = ",".join("%d" if dec is None else f"%.{dec}f" for _, dec in columns.values())
    data = np.column_stack([
        np.asarray(v, dtype=float) if dec is None else np.round(np.asarray(v, dtype=float), dec) + 0.0
        for v, dec in columns.values()])
    lines = [f"# {c}" for c in comment_lines] + [",".join(names)]
    lines += [fmt % tuple(row) for row in data.tolist()]
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


def simulate_campaign(kind: str, unit: Unit, truth: Truth, rng: np.random.Generator, out_dir,
                      effects=(), *, name: str | None = None, fast: bool = False,
                      set_reset_delay_s: float = SET_RESET_DELAY_s, noise_scale: float = 1.0,
                      **options):
    """Simulate one campaign and write `<name>.csv` (ICD telemetry) and `<name>.truth.npz`.

    kind: one of CAMPAIGNS; options go to the scenario (see _thermal_12pos, _rotation,
    _coils, _flight). fast: a small campaign (FAST_OPTIONS, under the given options).
    effects: Effect objects.
    noise_scale scales sensor noise (0: noiseless; the same random numbers are drawn).
    Returns (csv path, per-sample truth arrays: time_s, b_body_nT, temp_body_C, temp_boom_C,
    rate_body_dps, coil_A, ...).
    """
    if kind not in SCENARIOS:
        raise ValueError(f"unknown campaign {kind!r}; one of "
                         f"{', '.join(CAMPAIGNS + EXTRA_CAMPAIGNS)}")
    for e in effects:
        if e.sensor not in unit.sensor_names:
            raise ValueError(f"effect {e.name}: unit {unit.id} has no sensor {e.sensor!r}")
    name = name or kind
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)

    if fast:
        options = {**FAST_OPTIONS[kind], **options}
    sc = SCENARIOS[kind](unit, truth, rng, **options)
    time_cols = {"time_s": (sc.time_s, _time_decimals(sc.time_s))}
    if sc.position is not None:
        time_cols["position"] = (sc.position, None)
    channels = dict(sc.columns)
    for e in effects:
        for ch, value in e.channels(sc.time_s).items():
            if ch in channels or ch in time_cols:
                raise ValueError(f"effect {e.name}: channel {ch!r} already in the campaign")
            channels[ch] = value
    # effects see the channels as written (rounded to their telemetry resolution)
    channel_values = {k: np.asarray(v, dtype=float) if dec is None else np.round(v, dec)
                      for k, (v, dec) in {**time_cols, **channels}.items()}
    for e in effects:
        if isinstance(e, ChannelBias) and e.channel not in channel_values:
            raise ValueError(f"effect {e.name}: no channel {e.channel!r} in campaign {kind} "
                             f"(give it a source)")

    sensor_cols = {}
    for spec in unit.sensors:
        sensor_cols.update(_render_sensor(spec, truth, sc, effects, channel_values, rng,
                                          set_reset_delay_s, noise_scale))
    comments = [f"campaign: {kind}", f"unit: {unit.id}", "source: generator.campaign.simulate",
                f"description: {sc.description}"] + [f"{k}: {v}" for k, v in sc.meta.items()]
    csv_path = out_dir / f"{name}.csv"
    write_telemetry_csv(csv_path, comments, {**time_cols, **sensor_cols, **channels})

    arrays = {"time_s": sc.time_s, "b_body_nT": sc.b_body_nT,
              "temp_body_C": sc.temp_board_C["body"], "temp_boom_C": sc.temp_board_C["boom"],
              "rate_body_dps": sc.rate_dps, "coil_A": sc.coil_A,
              "deployed": np.array(sc.deployed), "set_reset_delay_s": np.array(set_reset_delay_s),
              **sc.extra_truth,
              "effects_json": np.array(json.dumps([e.to_dict() for e in effects]))}
    np.savez_compressed(out_dir / f"{name}.truth.npz", **arrays)
    return csv_path, arrays


# ---------------------------------------------------------------------------------------
# Example unit
# ---------------------------------------------------------------------------------------

def make_example_unit(unit_id: str = "demo_sat") -> Unit:
    """The SamSat-ION mounting (ICD section 1, seed 000 eq. 1)."""
    def mmc(name, frame, axes):
        return SensorSpec(name, "MMC5883MA", frame, axes, 25.0, 32768, True, 40.0)

    def mpu(name, frame, axes):
        return SensorSpec(name, "MPU-9255", frame, axes, 150.0, 0, False, 250.0)

    return Unit(id=unit_id, lab_field_nT=LAB_FIELD_nT, float_type="float32", boom_reference="mmc1",
                sensors=(mmc("mmc1", "body", ("+z", "+y", "+x")),
                         mpu("mpu1", "body", ("-z", "-y", "-x")),
                         mpu("mpu2", "body", ("-z", "+y", "+x")),
                         mmc("mmc2", "boom", ("-y", "-z", "-x")),
                         mpu("mpu3", "boom", ("-y", "-z", "+x"))))


def write_unit_toml(unit: Unit, path) -> None:
    """Write an ICD section 1 unit file."""
    q = json.dumps      # a TOML basic string for these plain names
    lines = ["# Flight unit description (ICD section 1), written by generator.campaign.simulate",
             "[unit]", f"id = {q(unit.id)}"]
    if unit.lab_field_nT is not None:
        lines.append(f"lab_field_nT = {float(unit.lab_field_nT)!r}")
    lines.append(f"float = {q(unit.float_type)}")
    if unit.boom_reference:
        lines += ["", "[boom]", f"reference = {q(unit.boom_reference)}"]
    for s in unit.sensors:
        lines += ["", "[[sensor]]", f"name = {q(s.name)}", f"part = {q(s.part)}",
                  f"frame = {q(s.frame)}", f"axes = [{', '.join(q(a) for a in s.axes)}]",
                  f"lsb_nT = {float(s.lsb_nT)!r}", f"zero_count = {int(s.zero_count)}",
                  f"set_reset = {'true' if s.set_reset else 'false'}"]
        if s.noise_nT is not None:
            lines.append(f"noise_nT = {float(s.noise_nT)!r}")
        if s.input != "counts":                         # ICD section 4 keys where used
            lines.append(f"input = {q(s.input)}")
        if not s.temperature:
            lines.append("temperature = false")
        if s.range_nT is not None:
            lines.append(f"range_nT = {float(s.range_nT)!r}")
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


# Campaign options for make_example sizes: "example" runs in a few seconds and still
# spans the temperature range; "full" is the real campaign length.
EXAMPLE_SIZES = {
    "fast": {k: {"fast": True} for k in EXAMPLE_CAMPAIGNS},
    "example": {
        # the program of `magcal plan` (holds from the boards' time constants) at 30 s
        # samples, 20 per segment (the segment finder's 10 min): ~4 days of chamber time
        "thermal_12pos": {"sample_period_s": 60.0, "samples_per_segment": 10},
        "rotation": {"duration_s": 300.0},
        "coils": {"hold_s": 5.0},
        "flight": {"duration_s": 3 * 3600.0},
    },
    "full": {k: {} for k in CAMPAIGNS},
}


def make_example(out_dir, seed: int = 0, size: str = "example") -> dict:
    """Write unit.toml, truth.json and the campaigns of EXAMPLE_CAMPAIGNS (with .truth.npz)
    to out_dir (the coil study last: the others keep their random streams).
    Returns {"unit": path, "truth": path, <campaign>: csv path, <campaign>_truth: npz path}."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    unit = make_example_unit()
    truth_seed, *campaign_seeds = np.random.SeedSequence(seed).spawn(1 + len(EXAMPLE_CAMPAIGNS))
    truth = random_truth(unit, np.random.default_rng(truth_seed))
    paths = {"unit": out_dir / "unit.toml", "truth": out_dir / "truth.json"}
    write_unit_toml(unit, paths["unit"])
    record = simulation_record(seed, by="generator.campaign.simulate.make_example",
                               size=size, campaigns=list(EXAMPLE_CAMPAIGNS))
    paths["truth"].write_text(json.dumps(truth.to_json(record), indent=1) + "\n",
                              encoding="utf-8")
    for kind, ss in zip(EXAMPLE_CAMPAIGNS, campaign_seeds):
        csv_path, _ = simulate_campaign(kind, unit, truth, np.random.default_rng(ss), out_dir,
                                        **EXAMPLE_SIZES[size].get(kind, {}))
        paths[kind] = csv_path
        paths[f"{kind}_truth"] = out_dir / f"{kind}.truth.npz"
    return paths
