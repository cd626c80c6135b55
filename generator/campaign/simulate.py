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

Size: one module of one idea, the simulated unit and how it is observed; the campaign
kinds (chamber twelve positions following the test program, rotation, coils, coil study,
orbit, yaw flight, planar turntable) share its sensor and environment models. It is past
1300 lines: the coil study (issue 19) was the kind after which the scenarios were to move
into their own module (generator/campaign/scenarios.py, with Truth and Scenario staying
here); that split is still to do.

`magcal simulate` (generator/verbs/simulate.py, docs/simulate.md) is the command line.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from generator.campaign.board_thermal import first_order_lag
from generator.campaign.plan import (TestPlan, lab_field_ned, make_plan,
                                     twelve_positions)   # the test program
from generator.io import parts as _parts
from generator.io.unit import SensorSpec, Unit

CAMPAIGNS = ("thermal_12pos", "rotation", "coils", "flight")   # the unit's campaigns
EXAMPLE_CAMPAIGNS = CAMPAIGNS + ("coil_study",)                  # make_example writes these
# further geometries for fit tests (simulate_campaign kinds; not part of make_example)
EXTRA_CAMPAIGNS = ("yaw_flight", "planar_rotation", "coil_study")

T_REF_C = 25.0
LAB_FIELD_nT = 51540.0            # field magnitude in the lab (seed 000)
LAB_INCLINATION_deg = 70.0
SET_RESET_DELAY_s = 0.012          # RESET reading is taken this long after the SET one
DEFAULT_NOISE_nT = {"MMC5883MA": 40.0, "MPU-9255": 250.0}
MMC_TEMP_STEP_C, MMC_TEMP_ZERO_C = 0.7, -75.0   # MMC5883MA temperature output: 0.7 degC/LSB

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


def _unit_vector(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _random_rotation(rng) -> Rotation:
    return Rotation.from_quat(_unit_vector(rng.normal(size=4)))


def _signed_uniform(rng, lo, hi, size):
    """Magnitude uniform in [lo, hi], random sign."""
    return rng.choice([-1.0, 1.0], size=size) * rng.uniform(lo, hi, size=size)


def _signed_log_uniform(rng, lo, hi, size):
    """Magnitude log-uniform in [lo, hi], random sign."""
    return rng.choice([-1.0, 1.0], size=size) * np.exp(rng.uniform(math.log(lo), math.log(hi), size))


def _lab_field_nT(field_nT, inclination_deg) -> np.ndarray:
    """Lab field in north-east-down axes."""
    inc = math.radians(inclination_deg)
    return field_nT * np.array([math.cos(inc), 0.0, math.sin(inc)])


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

    def to_json(self) -> dict:
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


def override_truth(truth: Truth, d: dict, unit: Unit, source=None) -> Truth:
    """The truth with the values of `d` (a partial truth: the keys of truth.json, see
    docs/simulate.md) put in place of the drawn ones; InputError naming the key on an
    unknown sensor or key, a wrong shape, a non-finite number or an impossible value."""
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
        if k not in known:
            raise InputError(source, f"key {k}: unknown; known keys: {', '.join(sorted(known))}")
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
            else:
                raise InputError(source, f"key {key}: unknown; known: W_poly_frame, "
                                         "b_poly_frame_nT, chip_offset_poly_sensor_nT, "
                                         "K_coil_frame_nT_per_A, noise_nT")
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
    scaled = Truth(truth.t_ref_C, truth.H_boom_to_body, truth.sensors,
                   {b: v * board_tau_scale for b, v in truth.board_tau_s.items()},
                   truth.board_self_heating_C)
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
    paths["truth"].write_text(json.dumps(truth.to_json(), indent=1) + "\n", encoding="utf-8")
    for kind, ss in zip(EXAMPLE_CAMPAIGNS, campaign_seeds):
        csv_path, _ = simulate_campaign(kind, unit, truth, np.random.default_rng(ss), out_dir,
                                        **EXAMPLE_SIZES[size].get(kind, {}))
        paths[kind] = csv_path
        paths[f"{kind}_truth"] = out_dir / f"{kind}.truth.npz"
    return paths
