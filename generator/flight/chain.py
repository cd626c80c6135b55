"""The correction chain: its one definition.

Everything that knows the chain's structure reads it from here:

* :func:`sensor_kernel`, the chain as the equations below write it, and its folded form:
  :func:`fold_sensor_coeffs` (every constant folded once per table: the count scale and
  axis signs into b, K, M, H M for boom sensors, the squared band limits) and
  :func:`folded_sensor_kernel` (the chain on those); test_flight_bound.py checks that
  both give the same outputs;
* the CasADi SX expressions (``codegen.py`` emits C with CasADi's CodeGenerator from
  :func:`folded_sensor_kernel` on the prepared vector, one kernel per sensor); the
  prepare step ``<unit>_table_prepare`` (templates/magcal.c.j2) is
  :func:`fold_sensor_coeffs` written as C loops, operation for operation (the same
  scalar operations in the same order; test_prepare.py compares its bits with
  :func:`prepare_sensor` on every kind of sensor and option);
* the Python reference (:func:`reference_sensor`), which runs the very same
  :func:`prepare_sensor` (the fold) and :func:`folded_sensor_kernel` on numpy float32
  values, so every + - * / is the same IEEE operation, in the same order, as in the
  generated C;
* the coefficient layout (:class:`ChainSpec` blocks, in order): the C coefficient
  arrays, the uplink table payload and the docs are all made from it.

Per sensor, per sample (seed 000, fig. 30; equations [4], [1], [7], [5]):

    SET/RESET   field_s = (set - reset) * 0.5 * lsb       offset_s = ((set + reset) * 0.5 - zero) * lsb
    or plain    field_s = (count - zero) * lsb
    or physical field_s = value * scale      (input nT/uT/mG/G: scale 1/1e3/100/1e5 nT per unit)
    axes        field_f[k] = sign[k] * field_s[idx[k]]   (eq. 1; a sign swaps the subtraction)
    lag         T_el += dt / (tau + dt) (T - T_el), state between calls      (option: thermal_lag)
    temperature T = clamp(T_el or temp_C, t_min, t_max),  dT = T - t_ref     (clamp in the wrapper)
                (a sensor with temperature = false: no T, no clamp, b and M constant)
    b(T)        b_i(T)  = ((b3_i dT + b2_i) dT + b1_i) dT + b0_i             (Horner, eq. 7)
    M(T)        m_ij(T) = ((m3_ij dT + m2_ij) dT + m1_ij) dT + m0_ij
    offset      x_i = field_f_i - b_i(T)
    coils       x_i -= K_i0 i_0 + K_i1 i_1 + ...                             (when coils are in the chain)
    channels    x_i -= C_i0 ch_0 + C_i1 ch_1 + ...                           (option: channels)
    lagged ch.  chf_j += dt / (tau_j + dt) (ch_j - chf_j), state between calls;
                x_i -= C_lag_i0 chf_0 + ...                                (option: lagged_channels)
    ch. scale   x_i -= g_ij ch_j x_i, for j = 0, 1, ... in turn             (option: channel_scale)
    cubic       x_i -= n_i x_i x_i x_i                                      (option: nonlinear)
    calibrate   B_i = m_i0 x_0 + m_i1 x_1 + m_i2 x_2                        (eq. 5)
    SET/RESET   B += c (w x B), w the body rate in the board frame          (option: sr_compensation)
    boom        B_body_i = H_i0 B_0 + H_i1 B_1 + H_i2 B_2                    (boom sensors, eq. 2-3)
    band        B.B - field_min^2 and field_max^2 - B.B, both >= 0 when plausible

Units of 1 to 8 sensors, any mix (ICD section 4):

    physical input  input = "nT" | "uT" | "mG" | "G": the flight API takes real numbers in
                    that unit (<unit>_<s>_raw_t.field_uT[3], ...; SET/RESET: set_field_uT,
                    reset_field_uT); the chain multiplies by a constant (nT 1, uT 1000,
                    mG 100, G 100000, each exact in float32) instead of (count - zero) lsb,
                    so the sensor has no lsb_nT, zero_count blocks; SATURATED when a reading
                    is beyond +-range_nT / scale (range_nT of the unit file, else the part's),
                    NONFINITE when a reading is NaN or infinite.
    no temperature  temperature = false: b and M are constant (one term each, no t_ref_C,
                    t_min_C, t_max_C blocks), nothing is clamped (TEMP_CLAMPED never set),
                    the raw struct keeps a temp_C field that is ignored (documented there);
                    no thermal lag.
    boom, no H fit  a unit whose boom sensors have no body-frame reference (or no boom
                    campaign) gets H = identity; coefficients.json fit.boom_alignment and
                    the generated header say so, and those fields stay in the boom frame.

The kernels use only + - * / (and the wrappers only comparisons), so float32 results are
reproducible bit for bit on any IEEE-754 machine that rounds each operation to nearest
(C built without FMA contraction: -ffp-contract=off).

Status bits (the wrapper, C and Python alike): a sample with a non-finite temperature or
current (or physical reading) gets zeros and STATUS_NONFINITE; a count at a rail of the
part's range, or a physical reading with |value| beyond the full scale, gets
STATUS_SATURATED; a temperature outside the calibrated range is clamped to it for the
polynomials and gets STATUS_TEMP_EXTRAPOLATED, informational: the sample stays valid; it
also gets STATUS_TEMP_CLAMPED (invalid) when it lies further outside than the sensor's
temp_margin_C, the distance at which the error's growth outside the range (estimated by
the fit, fit.thermal.extrapolation_growth) reaches the unit's requirement ([requirements]
field_error_nT; none stated: margin 0, every sample outside is invalid); |B| outside the
band gets STATUS_IMPLAUSIBLE; `select` adds STATUS_DISAGREE. ``valid`` is
``status & ~STATUS_INFO_MASK == 0`` (is_valid): informational bits do not invalidate.

Size: the chain's one definition (the arithmetic, the layout, the options, the status
rules and the float32 reference); keeping it in one module is the point: nothing is
written twice.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

import numpy as np

from generator.io.unit import PARTS, SensorSpec, Unit

CHAIN_VERSION = 1  # bump when the meaning of an existing block or stage changes

STATUS_NONFINITE = 0x01      # a non-finite temperature or current: outputs are zeros
STATUS_SATURATED = 0x02      # a count at a rail of the part's range
STATUS_TEMP_CLAMPED = 0x04   # temperature outside the calibrated range, clamped to it
STATUS_IMPLAUSIBLE = 0x08    # |B| outside [field_min_nT, field_max_nT]
STATUS_DISAGREE = 0x10       # disagrees with most other valid sensors (set by select)
STATUS_NO_OFFSET = 0x20      # SET-only reading with no stored SET/RESET offset yet
STATUS_TEMP_EXTRAPOLATED = 0x40   # temperature outside the calibrated range (informational)
# Bits that say something about a sample without making it invalid.
STATUS_INFO_MASK = STATUS_TEMP_EXTRAPOLATED
STATUS_BITS = {
    "NONFINITE": STATUS_NONFINITE,
    "SATURATED": STATUS_SATURATED,
    "TEMP_CLAMPED": STATUS_TEMP_CLAMPED,
    "IMPLAUSIBLE": STATUS_IMPLAUSIBLE,
    "DISAGREE": STATUS_DISAGREE,
    "NO_OFFSET": STATUS_NO_OFFSET,
    "TEMP_EXTRAPOLATED": STATUS_TEMP_EXTRAPOLATED,
}

# Reason codes of the selected vector for attitude control (see select_reference).
SELECT_CONFIRMED = 0     # chosen sensor agrees with at least one other valid sensor
SELECT_SINGLE = 1        # chosen sensor is the only valid one: nothing to compare with
SELECT_UNCONFIRMED = 2   # chosen sensor disagrees with the only other valid sensor
SELECT_NONE = 3          # no valid sensor: zero vector
SELECT_REASONS = {"CONFIRMED": SELECT_CONFIRMED, "SINGLE": SELECT_SINGLE,
                  "UNCONFIRMED": SELECT_UNCONFIRMED, "NONE": SELECT_NONE}


@dataclass(frozen=True)
class Block:
    """One named block of coefficients, stored row-major in the flat coefficient vector."""

    name: str
    shape: tuple
    unit: str
    kind: str   # what plausibility range applies (table validation), see tables
    doc: str

    @property
    def size(self) -> int:
        return int(np.prod(self.shape)) if self.shape else 1


@dataclass(frozen=True)
class Input:
    name: str
    size: int
    unit: str
    doc: str


@dataclass(frozen=True)
class SensorOptions:
    """Optional stages of one sensor's chain (the flight forms of traced effects).

    channels: telemetry columns whose linear coupling C (nT per unit, frame axes) is
        subtracted like the coils' (heater currents, bus voltage, flags, ...);
    thermal_lag: the element temperature follows the reported one through a first-order
        filter, T_el += dt / (tau + dt) (T - T_el), kept in the sensor's state;
    nonlinear: per-axis cubic of the reading, x_i -= n_i x_i^3 after the offsets;
    sr_compensation: SET/RESET rotation error, B += c (w x B) after M, w the body rate in
        the board frame, c = (SET->RESET delay) / 2 * pi / 180 (s rad/deg);
    channel_scale: scale factors that follow the channels, after their offsets and before
        the cubic, channel by channel: x_i -= g_ij ch_j x_i (block g_per_unit, 3 x the
        channels; a channel that only scales has a zero column of C_nT_per_unit).
        Written into the structure (and so the layout hash) only where it is set;
    lagged_channels: telemetry columns whose coupling acts through a first-order filter
        (a heater warming a board): ch_f += dt / (tau_j + dt) (ch - ch_f) per channel,
        kept in the sensor's state (the thermal lag's recursion and rules: the first
        sample, a NULL state or a non-finite result start it at ch), then
        x_i -= C_lag_ij ch_f_j after the other channels' offsets (blocks C_lag_nT_per_unit,
        lag_channel_tau_s). Written into the structure only where used.
    """

    channels: tuple = ()
    thermal_lag: bool = False
    nonlinear: bool = False
    sr_compensation: bool = False
    channel_scale: bool = False
    lagged_channels: tuple = ()

    @property
    def kernel_channels(self) -> tuple:
        """The kernel's `channels` input: the channels, then the lagged ones (filtered)."""
        return tuple(self.channels) + tuple(self.lagged_channels)

    def to_dict(self) -> dict:
        d = {"channels": list(self.channels), "thermal_lag": self.thermal_lag,
             "nonlinear": self.nonlinear, "sr_compensation": self.sr_compensation}
        if self.channel_scale:       # only where used: older structures keep their hash
            d["channel_scale"] = True
        if self.lagged_channels:
            d["lagged_channels"] = list(self.lagged_channels)
        return d

    @staticmethod
    def from_dict(d: dict) -> "SensorOptions":
        return SensorOptions(tuple(d.get("channels", ())), bool(d.get("thermal_lag", False)),
                             bool(d.get("nonlinear", False)),
                             bool(d.get("sr_compensation", False)),
                             bool(d.get("channel_scale", False)),
                             tuple(d.get("lagged_channels", ())))


NO_OPTIONS = SensorOptions()
MAX_POLY_DEGREE = 5
MAX_SENSORS = 8   # the flight API's int8/uint8 indices and the C's pair tables assume few

# Physical inputs (ICD section 4): nT per unit of the sensor's `input`. Each is exact in
# float32, so "value x scale" is one correctly rounded multiplication, C and Python alike.
INPUT_SCALE_nT = {"nT": 1.0, "uT": 1000.0, "mG": 100.0, "G": 100000.0}
INPUT_KINDS = ("counts",) + tuple(INPUT_SCALE_nT)


def is_valid(status):
    """ICD valid: no status bit but the informational ones (STATUS_INFO_MASK); works on
    scalars and arrays."""
    return (np.asarray(status).astype(np.int64) & ~STATUS_INFO_MASK) == 0


def is_physical(sensor: SensorSpec) -> bool:
    """Whether the sensor's readings are real numbers in a physical unit (not counts)."""
    return sensor.input != "counts"


def input_scale_nT(sensor: SensorSpec) -> float:
    """nT per unit of a physical-input sensor's readings."""
    try:
        return INPUT_SCALE_nT[sensor.input]
    except KeyError:
        raise ValueError(f"sensor '{sensor.name}': input '{sensor.input}' is not one of "
                         f"{', '.join(INPUT_KINDS)}") from None


def range_nT(sensor: SensorSpec) -> float:
    """Full-scale field per axis of a physical-input sensor (saturation when |value| is
    beyond it): the unit file's range_nT, else the part's catalogue entry."""
    if sensor.range_nT is not None:
        r = float(sensor.range_nT)
    else:
        r = PARTS.get(sensor.part, {}).get("range_nT")
        if r is None:
            raise ValueError(f"sensor '{sensor.name}': input '{sensor.input}' needs range_nT "
                             f"(the part '{sensor.part}' declares no full-scale range)")
        r = float(r)
    if not (np.isfinite(r) and r > 0):
        raise ValueError(f"sensor '{sensor.name}': range_nT {r!r} is not a positive number")
    return r


def saturation_limit(sensor: SensorSpec) -> float:
    """|reading| beyond which a physical-input sample is saturated, in the input's unit
    (float64; the flight code and the reference round it once to their float type)."""
    return range_nT(sensor) / input_scale_nT(sensor)


@dataclass(frozen=True)
class ChainSpec:
    """The structure of the chain for one unit: what the layout hash covers.

    poly_degree: degree of b(T) and M(T) in dT (seed: cubic; at most MAX_POLY_DEGREE).
    coils: names of the telemetry columns of the magnetorquer currents whose coupling
        K (nT/A, one column per coil) is subtracted; empty when the chain has no coils.
    sensor_options: ((sensor name, SensorOptions), ...) for sensors with optional stages.
    """

    unit: Unit
    poly_degree: int = 3
    coils: tuple = ()
    sensor_options: tuple = ()

    def __post_init__(self):
        if not 0 <= self.poly_degree <= MAX_POLY_DEGREE:
            raise ValueError(f"poly_degree {self.poly_degree} outside 0..{MAX_POLY_DEGREE}")
        names = set(self.unit.sensor_names)
        if not 1 <= len(names) <= MAX_SENSORS or len(names) != len(self.unit.sensors):
            raise ValueError(f"a unit has 1 to {MAX_SENSORS} sensors with distinct names "
                             f"({len(self.unit.sensors)} given)")
        for name, o in self.sensor_options:
            if name not in names:
                raise ValueError(f"sensor_options names unknown sensor '{name}'")
            if o.channel_scale and not o.channels:
                raise ValueError(f"sensor '{name}': channel_scale needs channels")
            for lst in (o.channels, o.lagged_channels):
                if len(set(lst)) != len(lst):
                    raise ValueError(f"sensor '{name}': a channel is named twice")
            if o.thermal_lag and not self.unit.sensor(name).temperature:
                raise ValueError(f"sensor '{name}' has no temperature: no thermal lag")
        for s in self.unit.sensors:
            if is_physical(s):
                saturation_limit(s)   # raises on an unknown input kind or a missing range

    def opts(self, sensor) -> SensorOptions:
        name = sensor if isinstance(sensor, str) else sensor.name
        for n, o in self.sensor_options:
            if n == name:
                return o
        return NO_OPTIONS

    def has_state(self, sensor) -> bool:
        """Whether the sensor's calls keep a state (stored offset, filtered temperature)."""
        o = self.opts(sensor)
        return sensor.set_reset or o.thermal_lag or bool(o.lagged_channels)

    @property
    def aux_channels(self) -> tuple:
        """All channels any sensor uses, in first-use order: the aux struct's fields."""
        out = []
        for s in self.unit.sensors:
            for c in self.opts(s).kernel_channels:
                if c not in out:
                    out.append(c)
        return tuple(out)

    @property
    def needs_rate(self) -> bool:
        return any(self.opts(s).sr_compensation for s in self.unit.sensors)

    @property
    def needs_dt(self) -> bool:
        return any(self.opts(s).thermal_lag or self.opts(s).lagged_channels
                   for s in self.unit.sensors)

    @property
    def has_aux(self) -> bool:
        return bool(self.coils or self.aux_channels or self.needs_rate or self.needs_dt)

    # ---- structure -------------------------------------------------------------------
    @property
    def has_boom(self) -> bool:
        return any(s.frame == "boom" for s in self.unit.sensors)

    def degree(self, sensor: SensorSpec) -> int:
        """Degree of the sensor's b(T), M(T): 0 (constant) for a sensor with no temperature."""
        return self.poly_degree if sensor.temperature else 0

    def sensor_blocks(self, sensor: SensorSpec) -> tuple:
        n = self.degree(sensor) + 1
        blocks = []
        if not is_physical(sensor):   # physical inputs: a constant scale, no lsb and zero
            blocks += [Block("lsb_nT", (), "nT/count", "lsb", "field per count"),
                       Block("zero_count", (), "count", "zero_count", "count at zero field")]
        if sensor.temperature:
            blocks += [
                Block("t_ref_C", (), "degC", "temp", "reference temperature of the polynomials"),
                Block("t_min_C", (), "degC", "temp", "lowest calibrated temperature (clamp)"),
                Block("t_max_C", (), "degC", "temp", "highest calibrated temperature (clamp)"),
                Block("temp_margin_C", (), "degC", "temp_margin",
                      "distance outside [t_min_C, t_max_C] still valid (TEMP_EXTRAPOLATED); "
                      "beyond it TEMP_CLAMPED"),
                Block("b_poly_nT", (n, 3), "nT/degC^k", "offset_poly",
                      "offset b(T) = sum_k b_poly_nT[k] dT^k, frame axes"),
                Block("M_poly", (n, 3, 3), "1/degC^k", "matrix_poly",
                      "calibration matrix M(T) = sum_k M_poly[k] dT^k"),
            ]
        else:
            blocks += [
                Block("b_poly_nT", (1, 3), "nT", "offset_poly",
                      "offset b, frame axes (no temperature: constant)"),
                Block("M_poly", (1, 3, 3), "1", "matrix_poly",
                      "calibration matrix M (no temperature: constant)"),
            ]
        if self.coils:
            blocks.append(Block("K_nT_per_A", (3, len(self.coils)), "nT/A", "coupling",
                                "magnetorquer coupling, one column per coil, frame axes"))
        o = self.opts(sensor)
        if o.channels:
            blocks.append(Block("C_nT_per_unit", (3, len(o.channels)), "nT/unit", "coupling",
                                "coupling of telemetry channels " + ", ".join(o.channels)))
        if o.lagged_channels:
            nl = len(o.lagged_channels)
            blocks.append(Block("C_lag_nT_per_unit", (3, nl), "nT/unit", "coupling",
                                "coupling of lagged telemetry channels "
                                + ", ".join(o.lagged_channels)))
            blocks.append(Block("lag_channel_tau_s", (nl,), "s", "time_constant",
                                "time constants of the lagged channels' first-order filters"))
        if o.channel_scale:
            blocks.append(Block("g_per_unit", (3, len(o.channels)), "1/unit", "scale_coupling",
                                "scale factor per unit of telemetry channels "
                                + ", ".join(o.channels) + ": x_i -= g_ij ch_j x_i"))
        if o.thermal_lag:
            blocks.append(Block("lag_tau_s", (), "s", "time_constant",
                                "thermal lag of the sensing element behind the reported T"))
        if o.nonlinear:
            blocks.append(Block("cubic_per_nT2", (3,), "1/nT^2", "nonlinearity",
                                "per-axis cubic of the reading, x -= n x^3"))
        if o.sr_compensation:
            blocks.append(Block("sr_comp_s_per_deg", (), "s rad/deg", "sr_delay",
                                "SET->RESET delay / 2 * pi/180: B += c (w x B)"))
        blocks.append(Block("agree_nT", (), "nT", "tolerance",
                            "expected scatter for the cross-sensor agreement check"))
        return tuple(blocks)

    def unit_blocks(self) -> tuple:
        blocks = [
            Block("field_min_nT", (), "nT", "field_band", "lowest plausible |B|"),
            Block("field_max_nT", (), "nT", "field_band", "highest plausible |B|"),
        ]
        if self.has_boom:
            blocks.append(Block("H_boom_to_body", (3, 3), "1", "rotation",
                                "orthogonal boom->body alignment (seed 000 eq. 2-3)"))
        return tuple(blocks)

    def sensor_inputs(self, sensor: SensorSpec, set_only=False) -> tuple:
        u = sensor.input if is_physical(sensor) else "count"
        if set_only:
            raw = Input("raw_counts", 6, u,
                        f"SET x,y,z, then the stored bridge offset x,y,z ({u})")
        elif sensor.set_reset:
            raw = Input("raw_counts", 6, u, "SET x,y,z then RESET x,y,z, sensor axes")
        else:
            raw = Input("raw_counts", 3, u, "x, y, z, sensor axes")
        ins = [raw]
        if sensor.temperature:
            ins.append(Input("temp_C", 1, "degC", "element temperature, already clamped"))
        if self.coils:
            ins.append(Input("coil_A", len(self.coils), "A", "magnetorquer currents"))
        o = self.opts(sensor)
        if o.kernel_channels:
            ins.append(Input("channels", len(o.kernel_channels), "as named",
                             ", ".join(o.channels) + (
                                 ("; filtered: " if o.channels else "filtered: ")
                                 + ", ".join(o.lagged_channels) if o.lagged_channels
                                 else "")))
        if o.sr_compensation:
            ins.append(Input("rate_dps", 3, "deg/s", "body angular rate"))
        return tuple(ins)

    def sensor_outputs(self, sensor: SensorSpec, set_only=False) -> tuple:
        outs = [Input("field_body_nT", 3, "nT", "calibrated field, body frame"),
                Input("band_margin_nT2", 2, "nT^2",
                      "|B|^2 - field_min^2 and field_max^2 - |B|^2: both >= 0 when plausible")]
        if sensor.set_reset and not set_only:
            outs.append(Input("chip_offset_nT", 3, "nT", "SET/RESET bridge offset, sensor axes"))
            outs.append(Input("offset_counts", 3, "count",
                              "(SET + RESET) / 2: the offset stored for SET-only readings"))
        return tuple(outs)

    def fallback_order(self) -> tuple:
        """Sensor indices in the order the attitude system takes them: lower-noise parts
        first (MMC5883 before MPU-9255, other parts after them), boom before body (farther
        from the magnetorquers and the electronics), then unit order. SamSat-ION: mmc2,
        mmc1, mpu3, mpu1, mpu2.

        Any count works. One sensor: nothing to cross-check; select returns its vector
        (SINGLE) when its status is 0, else zeros (NONE), and never sets DISAGREE. Two
        sensors: neither has two others to be outvoted by, so DISAGREE is never set; the
        first valid one in this order is CONFIRMED when they agree, UNCONFIRMED when not.
        Three to eight: a sensor that agrees with fewer than half (and has at least two)
        valid others gets DISAGREE and is skipped."""
        rank = {"MMC5883MA": 0, "MPU-9255": 1}
        sensors = list(enumerate(self.unit.sensors))
        sensors.sort(key=lambda e: (rank.get(e[1].part, 9), 0 if e[1].frame == "boom" else 1,
                                    e[0]))
        return tuple(i for i, _ in sensors)

    def n_sensor_coeffs(self, sensor) -> int:
        return sum(b.size for b in self.sensor_blocks(sensor))

    def n_unit_coeffs(self) -> int:
        return sum(b.size for b in self.unit_blocks())

    def offsets(self, blocks) -> dict:
        out, k = {}, 0
        for b in blocks:
            out[b.name] = k
            k += b.size
        return out

    # ---- identity ----------------------------------------------------------------------
    def structure(self) -> dict:
        """Everything the generated code depends on except coefficient values."""
        return {
            "chain_version": CHAIN_VERSION,
            "float": self.unit.float_type,
            "poly_degree": self.poly_degree,
            "coils": list(self.coils),
            "sensors": [
                {
                    "name": s.name, "part": s.part, "frame": s.frame, "axes": list(s.axes),
                    "set_reset": s.set_reset, "options": self.opts(s).to_dict(),
                    "blocks": [[b.name, list(b.shape)] for b in self.sensor_blocks(s)],
                    # version-2 keys only where they differ from version 1 (same hash)
                    **({"input": s.input, "saturation": saturation_limit(s)}
                       if is_physical(s) else {}),
                    **({"temperature": False} if not s.temperature else {}),
                }
                for s in self.unit.sensors
            ],
            "unit_blocks": [[b.name, list(b.shape)] for b in self.unit_blocks()],
        }

    def layout_hash(self) -> int:
        """32-bit hash of the structure: a table is only accepted by code generated for it."""
        text = json.dumps(self.structure(), sort_keys=True, separators=(",", ":"))
        return int.from_bytes(hashlib.sha256(text.encode()).digest()[:4], "little")

    def to_dict(self) -> dict:
        return {"poly_degree": self.poly_degree, "coils": list(self.coils),
                "sensor_options": {n: o.to_dict() for n, o in self.sensor_options}}

    @staticmethod
    def from_dict(unit: Unit, d: dict) -> "ChainSpec":
        opts = tuple((n, SensorOptions.from_dict(o))
                     for n, o in d.get("sensor_options", {}).items())
        return ChainSpec(unit, poly_degree=int(d.get("poly_degree", 3)),
                         coils=tuple(d.get("coils", ())), sensor_options=opts)


# ---- the kernel: one definition, run on CasADi SX or on numpy float32 -----------------


class CoeffView:
    """Block access into a flat coefficient vector (values or symbols), row-major."""

    def __init__(self, flat, blocks):
        self._flat = flat
        self._blocks = {b.name: b for b in blocks}
        k = 0
        self._offsets = {}
        for b in blocks:
            self._offsets[b.name] = k
            k += b.size

    def scalar(self, name):
        return self._flat[self._offsets[name]]

    def get(self, name):
        b = self._blocks[name]
        k0 = self._offsets[name]
        vals = [self._flat[k0 + i] for i in range(b.size)]
        return _nest(vals, b.shape)


def _nest(vals, shape):
    if len(shape) <= 1:
        return vals if shape else vals[0]
    step = int(np.prod(shape[1:]))
    return [_nest(vals[i * step:(i + 1) * step], shape[1:]) for i in range(shape[0])]


def _horner(poly, dT):
    """poly[k] is the dT^k coefficient: ((p3 dT + p2) dT + p1) dT + p0."""
    acc = poly[-1]
    for k in range(len(poly) - 2, -1, -1):
        acc = acc * dT + poly[k]
    return acc


def _couple(matrix, values):
    """Field of linear couplings, per axis: matrix[i][0] v0 + matrix[i][1] v1 + ..."""
    out = []
    for row in matrix:
        acc = row[0] * values[0]
        for j in range(1, len(values)):
            acc = acc + row[j] * values[j]
        out.append(acc)
    return out


def _dot3(row, v):
    return row[0] * v[0] + row[1] * v[1] + row[2] * v[2]


def lag_kernel(temp_C, temp_el_C, dt_s, tau_s):
    """Thermal lag: the element temperature after dt_s, first-order with time constant tau_s
    (backward Euler, stable for any dt >= 0)."""
    return temp_el_C + dt_s / (tau_s + dt_s) * (temp_C - temp_el_C)


def sensor_kernel(spec: ChainSpec, sensor: SensorSpec, raw, temp_C, coil_A, c: CoeffView,
                  u: CoeffView, half, set_only=False, channels=(), rate_dps=()):
    """The arithmetic of the chain for one sensor and one sample, as the equations write
    it (the flight code and the reference run its folded form, fold_sensor_coeffs +
    folded_sensor_kernel, which gives the same outputs up to the rounding of the folded
    constants; test_flight_bound.py).

    raw, coil_A: lists of scalars; temp_C: scalar (already clamped; unused by a sensor with
    no temperature); c, u: coefficient
    views; half: the constant 0.5 in the backend's type. Works on any scalar type with
    + - * (CasADi SX, numpy float32/float64 arrays). Returns {output name: [scalars]}.
    set_only: a SET/RESET sensor read after SET only; raw[3:6] is the stored offset
    (SET + RESET) / 2 in counts from the last pair. With a fresh offset the result equals
    the pair's bit for bit: (s - (s + r) * 0.5) and (s - r) * 0.5 are both exact here.
    """
    out = {}
    # counts -> nT, sensor axes (seed 000 eq. 4 for SET/RESET)
    # axis mapping to the board frame (seed 000 eq. 1): frame axis k is sensor axis idx[k]
    # with sign[k]; a negative sign swaps the operands of the first subtraction, which is
    # the exact negation (a - b = -(b - a)) without an instruction of its own.
    idx, sign = sensor.axis_map()

    def diff(a, b, k):
        return a - b if sign[k] > 0 else b - a

    if is_physical(sensor):
        # physical input (ICD section 4): a constant scale to nT, no zero point; a negative
        # axis is the exact negation -v (written so in C and Python alike)
        const = type(half)
        scale = const(input_scale_nT(sensor))

        def signed(v, k):
            return v if sign[k] > 0 else -v

        if set_only:
            s, o = raw[0:3], raw[3:6]
            field_f = [diff(s[idx[k]], o[idx[k]], k) * scale for k in range(3)]
        elif sensor.set_reset:
            s, r = raw[0:3], raw[3:6]
            half_scale = const(input_scale_nT(sensor) * 0.5)   # exact: a power-of-two step
            field_f = [diff(s[idx[k]], r[idx[k]], k) * half_scale for k in range(3)]
            offset_in = [(s[i] + r[i]) * half for i in range(3)]
            out["chip_offset_nT"] = [offset_in[i] * scale for i in range(3)]
            out["offset_counts"] = offset_in
        else:
            field_f = [signed(raw[idx[k]], k) * scale for k in range(3)]
    else:
        lsb = c.scalar("lsb_nT")
        zero = c.scalar("zero_count")
        if set_only:
            s, o = raw[0:3], raw[3:6]
            field_f = [diff(s[idx[k]], o[idx[k]], k) * lsb for k in range(3)]
        elif sensor.set_reset:
            s, r = raw[0:3], raw[3:6]
            # (d * 0.5) * lsb == d * (lsb * 0.5) bit for bit: both halvings are exact
            half_lsb = lsb * half
            field_f = [diff(s[idx[k]], r[idx[k]], k) * half_lsb for k in range(3)]
            offset_counts = [(s[i] + r[i]) * half for i in range(3)]
            out["chip_offset_nT"] = [(offset_counts[i] - zero) * lsb for i in range(3)]
            out["offset_counts"] = offset_counts
        else:
            field_f = [diff(raw[idx[k]], zero, k) * lsb for k in range(3)]
    b_poly = c.get("b_poly_nT")           # [k][i]
    M_poly = c.get("M_poly")              # [k][i][j]
    if sensor.temperature:
        # temperature polynomials by Horner (eq. 7)
        dT = temp_C - c.scalar("t_ref_C")
        n = spec.degree(sensor) + 1
        b = [_horner([b_poly[k][i] for k in range(n)], dT) for i in range(3)]
        M = [[_horner([M_poly[k][i][j] for k in range(n)], dT) for j in range(3)]
             for i in range(3)]
    else:   # no temperature: constant b and M
        b = [b_poly[0][i] for i in range(3)]
        M = [[M_poly[0][i][j] for j in range(3)] for i in range(3)]
    # offset and magnetorquer interference
    x = [field_f[i] - b[i] for i in range(3)]
    if spec.coils:
        coil_nT = _couple(c.get("K_nT_per_A"), coil_A)
        x = [x[i] - coil_nT[i] for i in range(3)]
    o = spec.opts(sensor)
    if o.channels:   # linear coupling of other telemetry channels (traced effects)
        ch_nT = _couple(c.get("C_nT_per_unit"), list(channels[:len(o.channels)]))
        x = [x[i] - ch_nT[i] for i in range(3)]
    if o.lagged_channels:   # channels through their first-order filters (the wrapper)
        nch = len(o.channels)
        chl_nT = _couple(c.get("C_lag_nT_per_unit"), list(channels[nch:]))
        x = [x[i] - chl_nT[i] for i in range(3)]
    if o.channel_scale:   # scale factors following the channels, channel by channel
        g = c.get("g_per_unit")
        for j in range(len(o.channels)):
            x = [x[i] - g[i][j] * channels[j] * x[i] for i in range(3)]
    if o.nonlinear:  # per-axis cubic of the reading
        n3 = c.get("cubic_per_nT2")
        x = [x[i] - n3[i] * x[i] * x[i] * x[i] for i in range(3)]
    # calibration (eq. 5)
    B = [_dot3(M[i], x) for i in range(3)]
    if o.sr_compensation:
        # SET/RESET rotation error: the RESET reading sees the field turned by -w dt, so
        # the pair gives W (B - (w x B) dt / 2): after M it is B - c (w x B), c = dt / 2,
        # exactly; undo it with the body rate in the board frame (boom: H^T w).
        k = c.scalar("sr_comp_s_per_deg")
        w = list(rate_dps)
        if sensor.frame == "boom":
            H = u.get("H_boom_to_body")
            w = [H[0][i] * rate_dps[0] + H[1][i] * rate_dps[1] + H[2][i] * rate_dps[2]
                 for i in range(3)]
        wB = [w[1] * B[2] - w[2] * B[1], w[2] * B[0] - w[0] * B[2], w[0] * B[1] - w[1] * B[0]]
        B = [B[i] + k * wB[i] for i in range(3)]
    # boom -> body (eq. 2-3)
    if sensor.frame == "boom":
        H = u.get("H_boom_to_body")
        B = [_dot3(H[i], B) for i in range(3)]
    out["field_body_nT"] = B
    # plausibility band of |B|: both margins >= 0 when plausible
    norm2 = B[0] * B[0] + B[1] * B[1] + B[2] * B[2]
    f_min, f_max = u.scalar("field_min_nT"), u.scalar("field_max_nT")
    out["band_margin_nT2"] = [norm2 - f_min * f_min, f_max * f_max - norm2]
    return out


# ---- the folded chain: the same arithmetic, every constant folded at table-load time ----
#
# What a call must compute once the coefficients are known (issue 20 item 5): the scale of
# a count (lsb, lsb/2, the physical unit's factor) and the axis signs fold into the columns
# of M and the offsets (b, K, C, the cubic) are divided by them, a plain count's zero point
# joins the offset, a boom sensor's H multiplies every term of M(T) (unless the SET/RESET
# rate compensation sits between M and H), and constants are squared once. Its operation
# count is the lower bound the flight code is measured against (arm_measure.flop_bound).
# The stages are those of sensor_kernel, in its order; test_flight_bound.py checks that
# both give the same field for every option.


# the optional stages folded_sensor_kernel reproduces (thermal_lag acts on the temperature
# before the kernel: nothing to fold)
_FOLDED_OPTIONS = ("channels", "thermal_lag", "nonlinear", "sr_compensation", "channel_scale",
                   "lagged_channels")


def _axis_scales(sensor: SensorSpec, c: CoeffView, half, set_only):
    """sigma_k, the factor from the per-call difference v_k (sensor axis idx[k]) to the
    frame-axis field in nT: field_f_k = sigma_k (v_k - zero) (plain counts) or sigma_k v_k."""
    _, sign = sensor.axis_map()
    pair = sensor.set_reset and not set_only
    if is_physical(sensor):
        scale = type(half)(input_scale_nT(sensor) * (0.5 if pair else 1.0))
    else:
        scale = c.scalar("lsb_nT") * half if pair else c.scalar("lsb_nT")
    return [scale if sign[k] > 0 else -scale for k in range(3)]


def fold_sensor_coeffs(spec: ChainSpec, sensor: SensorSpec, c: CoeffView, u: CoeffView, half,
                       set_only=False) -> dict:
    """(The flight code's `<unit>_table_prepare`, templates/magcal.c.j2, is this function in
    C, operation for operation: change both; host_tests/test_prepare.py compares the bits.)
    The folded coefficients of one sensor's chain from its table blocks (any scalar
    type): {name: value or nested lists}. b_poly, K, C are divided by sigma (a count's
    zero point kept apart, subtracted from the count), the cubic multiplied by sigma^2, M's
    columns by sigma and, for a boom sensor without rate compensation, M premultiplied by
    H; field_min^2, field_max^2."""
    o = spec.opts(sensor)
    unknown = [k for k, v in o.to_dict().items() if v and k not in _FOLDED_OPTIONS]
    if unknown:   # a stage sensor_kernel has and the folded form lacks: no silent bound
        raise ValueError(f"sensor '{sensor.name}': the folded chain has no form of the "
                         f"stage(s) {', '.join(unknown)}; add it to folded_sensor_kernel")
    sig = _axis_scales(sensor, c, half, set_only)
    n = spec.degree(sensor) + 1
    b_poly, M_poly = c.get("b_poly_nT"), c.get("M_poly")
    f = {"b_poly": [[b_poly[k][i] / sig[i] for i in range(3)] for k in range(n)]}
    M = [[[M_poly[k][i][j] * sig[j] for j in range(3)] for i in range(3)] for k in range(n)]
    fold_H = sensor.frame == "boom" and not o.sr_compensation
    if fold_H:
        H = u.get("H_boom_to_body")
        M = [[[_dot3(H[i], [M[k][0][j], M[k][1][j], M[k][2][j]]) for j in range(3)]
              for i in range(3)] for k in range(n)]
    f["M_poly"] = M
    if spec.coils:
        K = c.get("K_nT_per_A")
        f["K"] = [[K[i][j] / sig[i] for j in range(len(spec.coils))] for i in range(3)]
    if o.channels:
        C = c.get("C_nT_per_unit")
        f["C"] = [[C[i][j] / sig[i] for j in range(len(o.channels))] for i in range(3)]
    if o.lagged_channels:   # the filter acts on the channel: only the coupling scales
        CL = c.get("C_lag_nT_per_unit")
        f["C_lag"] = [[CL[i][j] / sig[i] for j in range(len(o.lagged_channels))]
                      for i in range(3)]
    if o.channel_scale:     # x_i -= g_ij ch_j x_i is the same in any scale of x_i
        f["g"] = c.get("g_per_unit")
    if o.nonlinear:
        n3 = c.get("cubic_per_nT2")
        f["cubic"] = [n3[i] * (sig[i] * sig[i]) for i in range(3)]
    if o.sr_compensation:
        f["sr_comp"] = c.scalar("sr_comp_s_per_deg")
    if sensor.frame == "boom" and not fold_H:
        f["H"] = u.get("H_boom_to_body")
    if sensor.temperature:
        f["t_ref_C"] = c.scalar("t_ref_C")
    if sensor.set_reset and not set_only:   # the bridge offset output stays in nT
        f["offset_scale"] = type(half)(input_scale_nT(sensor)) if is_physical(sensor) \
            else c.scalar("lsb_nT")
    # a count's zero point is subtracted from the count on every call, not folded into
    # b(T): count - zero is exact (integers below 2^24), while a constant term of b(T)
    # holding a large zero (8,388,608 for a 24-bit offset-binary part) would round the
    # temperature terms added to it to its ulp (review #20d F2: up to 0.8 nT)
    if not is_physical(sensor) and not set_only:
        f["zero_count"] = c.scalar("zero_count")
    f_min, f_max = u.scalar("field_min_nT"), u.scalar("field_max_nT")
    f["field_min2"], f["field_max2"] = f_min * f_min, f_max * f_max
    return f


# ---- the prepared coefficients: the fold as a flat vector ------------------------------
#
# The flight code runs the folded chain: `<unit>_table_prepare` computes each kernel's
# folded coefficients once (when a table is activated, at init, or for the compiled-in
# defaults at generate time) and the kernels read them. The flat order is the order of
# fold_sensor_coeffs' entries, each row-major (prepared_leaves); prepared_view turns a flat
# vector back into fold_sensor_coeffs' structure.


def prepared_leaves(f) -> list:
    """The scalars of a fold (fold_sensor_coeffs), in the prepared vector's order."""
    if isinstance(f, dict):
        return [x for k in f for x in prepared_leaves(f[k])]
    if isinstance(f, (list, tuple)):
        return [x for e in f for x in prepared_leaves(e)]
    return [f]


def fold_shape(spec: ChainSpec, sensor: SensorSpec, set_only=False):
    """fold_sensor_coeffs' structure (entries and nesting) of one kernel, values None."""
    c = CoeffView([np.float64(1.0)] * spec.n_sensor_coeffs(sensor), spec.sensor_blocks(sensor))
    u = CoeffView([np.float64(1.0)] * spec.n_unit_coeffs(), spec.unit_blocks())
    f = fold_sensor_coeffs(spec, sensor, c, u, np.float64(0.5), set_only=set_only)

    def strip(v):
        if isinstance(v, dict):
            return {k: strip(e) for k, e in v.items()}
        if isinstance(v, (list, tuple)):
            return [strip(e) for e in v]
        return None
    return strip(f)


def n_prepared(spec: ChainSpec, sensor: SensorSpec, set_only=False) -> int:
    """Size of one kernel's prepared coefficient vector."""
    return len(prepared_leaves(fold_shape(spec, sensor, set_only)))


def prepared_view(spec: ChainSpec, sensor: SensorSpec, flat, set_only=False) -> dict:
    """A flat prepared vector (values or symbols) in fold_sensor_coeffs' structure."""
    it = iter(flat)

    def fill(v):
        if isinstance(v, dict):
            return {k: fill(e) for k, e in v.items()}
        if isinstance(v, list):
            return [fill(e) for e in v]
        return next(it)
    return fill(fold_shape(spec, sensor, set_only))


def prepare_sensor(spec: ChainSpec, sensor: SensorSpec, coeffs_sensor, coeffs_unit,
                   set_only=False) -> np.ndarray:
    """The prepared vector of one kernel from the table's coefficients, in the unit's float
    type, one scalar IEEE operation at a time in fold_sensor_coeffs' order: what
    `<unit>_table_prepare` computes (C loops in templates/magcal.c.j2, a second writing of
    this order that host_tests/test_prepare.py holds to the same bits)."""
    ft = np_dtype(spec.unit)
    cs_ = np.asarray(coeffs_sensor, dtype=ft)
    cu = np.asarray(coeffs_unit, dtype=ft)
    c = CoeffView([cs_[k] for k in range(cs_.size)], spec.sensor_blocks(sensor))
    u = CoeffView([cu[k] for k in range(cu.size)], spec.unit_blocks())
    with np.errstate(all="ignore"):   # a poisoned (NaN) or zero-lsb table folds to NaN/inf
        f = fold_sensor_coeffs(spec, sensor, c, u, ft(0.5), set_only=set_only)
    return np.array([ft(x) for x in prepared_leaves(f)], dtype=ft)


def folded_sensor_kernel(spec: ChainSpec, sensor: SensorSpec, raw, temp_C, coil_A, f: dict,
                         half, set_only=False, channels=(), rate_dps=()):
    """sensor_kernel's outputs from the folded coefficients f (fold_sensor_coeffs): the
    operations a call cannot avoid. Same arguments as sensor_kernel otherwise."""
    out = {}
    idx, _ = sensor.axis_map()
    o = spec.opts(sensor)
    if set_only or sensor.set_reset:
        s, r = raw[0:3], raw[3:6]
        v = [s[idx[k]] - r[idx[k]] for k in range(3)]
        if not set_only:
            oc = [(s[i] + r[i]) * half for i in range(3)]
            out["chip_offset_nT"] = ([oc[i] * f["offset_scale"] for i in range(3)]
                                     if is_physical(sensor) else
                                     [(oc[i] - f["zero_count"]) * f["offset_scale"]
                                      for i in range(3)])
            out["offset_counts"] = oc
    elif is_physical(sensor):
        v = [raw[idx[k]] for k in range(3)]
    else:
        v = [raw[idx[k]] - f["zero_count"] for k in range(3)]
    n = spec.degree(sensor) + 1
    if sensor.temperature:
        dT = temp_C - f["t_ref_C"]
        b = [_horner([f["b_poly"][k][i] for k in range(n)], dT) for i in range(3)]
        M = [[_horner([f["M_poly"][k][i][j] for k in range(n)], dT) for j in range(3)]
             for i in range(3)]
    else:
        b, M = f["b_poly"][0], f["M_poly"][0]
    x = [v[i] - b[i] for i in range(3)]
    if spec.coils:
        coil = _couple(f["K"], coil_A)
        x = [x[i] - coil[i] for i in range(3)]
    if o.channels:
        ch = _couple(f["C"], list(channels[:len(o.channels)]))
        x = [x[i] - ch[i] for i in range(3)]
    if o.lagged_channels:
        chl = _couple(f["C_lag"], list(channels[len(o.channels):]))
        x = [x[i] - chl[i] for i in range(3)]
    if o.channel_scale:
        for j in range(len(o.channels)):
            x = [x[i] - f["g"][i][j] * channels[j] * x[i] for i in range(3)]
    if o.nonlinear:
        x = [x[i] - f["cubic"][i] * x[i] * x[i] * x[i] for i in range(3)]
    B = [_dot3(M[i], x) for i in range(3)]
    if o.sr_compensation:
        w = list(rate_dps)
        if "H" in f:
            H = f["H"]
            w = [H[0][i] * rate_dps[0] + H[1][i] * rate_dps[1] + H[2][i] * rate_dps[2]
                 for i in range(3)]
        wB = [w[1] * B[2] - w[2] * B[1], w[2] * B[0] - w[0] * B[2], w[0] * B[1] - w[1] * B[0]]
        B = [B[i] + f["sr_comp"] * wB[i] for i in range(3)]
    if "H" in f:
        B = [_dot3(f["H"][i], B) for i in range(3)]
    out["field_body_nT"] = B
    norm2 = B[0] * B[0] + B[1] * B[1] + B[2] * B[2]
    out["band_margin_nT2"] = [norm2 - f["field_min2"], f["field_max2"] - norm2]
    return out


def agreement_kernel(fields, agree):
    """Cross-sensor agreement margins, pairs (i, j) with i < j in unit order:
    (agree_i + agree_j)^2 - |B_i - B_j|^2, >= 0 when the two agree."""
    n = len(fields)
    margins = []
    for i in range(n):
        for j in range(i + 1, n):
            d = [fields[i][k] - fields[j][k] for k in range(3)]
            tol = agree[i] + agree[j]
            margins.append(tol * tol - (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]))
    return margins


def select_logic(n_sensors, order, valid, agrees):
    """Disagreement flags and the selected sensor, from validity and pairwise agreement.

    valid[i]: is_valid(status) before this step; agrees(i, j): margin >= 0. A valid sensor that
    has at least two valid others and agrees with fewer than half of them disagrees. The
    selected sensor is the first in `order` that is valid and does not disagree.
    Returns (disagree list, selected index or -1, reason, rank in order or -1).
    """
    n_cmp = [0] * n_sensors
    n_agree = [0] * n_sensors
    for i in range(n_sensors):
        if not valid[i]:
            continue
        for j in range(n_sensors):
            if j != i and valid[j]:
                n_cmp[i] += 1
                if agrees(min(i, j), max(i, j)):
                    n_agree[i] += 1
    disagree = [valid[i] and n_cmp[i] >= 2 and 2 * n_agree[i] < n_cmp[i]
                for i in range(n_sensors)]
    for rank, i in enumerate(order):
        if valid[i] and not disagree[i]:
            if n_cmp[i] == 0:
                reason = SELECT_SINGLE
            elif n_agree[i] > 0:
                reason = SELECT_CONFIRMED
            else:
                reason = SELECT_UNCONFIRMED
            return disagree, i, reason, rank
    return disagree, -1, SELECT_NONE, -1


# ---- the Python reference: the wrapper logic and the kernel in float32 ----------------


def np_dtype(unit: Unit):
    return np.float32 if unit.float_type == "float32" else np.float64


@dataclass
class SensorState:
    """What `<unit>_<sensor>_state_t` holds between calls (None: not yet set)."""

    offset_counts: object = None     # (3,) stored (SET + RESET) / 2, counts
    temp_el_C: object = None         # element temperature of the thermal-lag filter
    channel_el: object = None        # (n,) lagged channels' filter states


NULL_STATE = False   # reference_sensor(state=NULL_STATE): the C call with state == NULL


def reference_sensor(spec: ChainSpec, sensor: SensorSpec, coeffs_sensor, coeffs_unit,
                     raw_counts, temp_C, coil_A=None, set_only=False, offset_counts=None,
                     channels=None, rate_dps=None, dt_s=None, state=None):
    """Python reference of `<unit>_<sensor>_correct` (and `_correct_set` when set_only) over
    a sequence of samples, as successive calls on one sensor state (empty at the start).

    Each chain scalar is a numpy array over samples of the unit's float type, and every
    operation is an elementwise IEEE operation in the order of the C: the coefficients
    prepared once (`prepare_sensor`, the C's `<unit>_table_prepare`), then
    `folded_sensor_kernel` on them; no BLAS, no reductions. Only the thermal-lag
    filter, a recursion, runs sample by sample.
    raw_counts: int (N, 6|3), for set_only (N, 3) SET counts; a physical-input sensor's
    readings in its input unit (converted to the float type first, as its C API takes
    them); temp_C: (N,) (converted to the float type first, as the C API takes it;
    ignored for a sensor with no temperature); coil_A (N, ncoil), channels {column name:
    (N,)}, rate_dps (N, 3), dt_s (N,): None means zeros (as a null aux);
    offset_counts: set_only, (N, 3) stored offset per sample, NaN rows meaning none.
    Returns {output: (N, k) array, 'status': (N,) uint16}; pair mode also 'offset_counts',
    the state's stored offset after each call (NaN until the first unsaturated pair).
    state: the SensorState the calls start from and update in place (None: a fresh one),
    or NULL_STATE for calls with state == NULL (no filter,
    nothing stored, SET-only readings have no offset). set_only without offset_counts
    uses the state's stored offset.
    Wrapper steps, in the C's order: saturation; non-finite inputs (-> zeros, state kept);
    thermal lag; missing offset (set_only -> zeros); clamp; kernel; band check; offset store.
    """
    ft = np_dtype(spec.unit)
    o = spec.opts(sensor)
    physical = is_physical(sensor)
    # the C API takes counts as int32 and physical readings as the float type
    raw_counts = np.asarray(raw_counts, dtype=np.float64).astype(ft) if physical \
        else np.asarray(raw_counts)
    n = raw_counts.shape[0]
    if sensor.temperature:
        temp = np.asarray(temp_C, dtype=np.float64).astype(ft)
    else:   # no temperature: the raw struct's temp_C is ignored
        temp = np.zeros(n, dtype=ft)
    coeffs_sensor = np.asarray(coeffs_sensor, dtype=ft)
    c = CoeffView([coeffs_sensor[k] for k in range(coeffs_sensor.size)],
                  spec.sensor_blocks(sensor))
    status = np.zeros(n, dtype=np.uint16)

    def aux(values, width):
        if values is None:
            return np.zeros((n, width), dtype=ft)
        return np.asarray(values, dtype=np.float64).astype(ft).reshape(n, width)

    # saturation at the part's rails; physical inputs: |value| beyond the full scale
    if physical:
        lim = ft(saturation_limit(sensor))
        sat = np.any((raw_counts > lim) | (raw_counts < -lim), axis=1)
    else:
        sat = np.any((raw_counts <= sensor.count_min) | (raw_counts >= sensor.count_max),
                     axis=1)
    status[sat] |= STATUS_SATURATED
    # non-finite inputs (only those this sensor reads)
    inputs = {}
    if spec.coils:
        inputs["coil_A"] = aux(coil_A, len(spec.coils))
    kch = o.kernel_channels
    if kch:
        inputs["channels"] = aux(None if channels is None else
                                 np.stack([np.asarray(channels[name], dtype=np.float64)
                                           for name in kch], axis=1), len(kch))
    if o.sr_compensation:
        inputs["rate_dps"] = aux(rate_dps, 3)
    if o.thermal_lag or o.lagged_channels:
        inputs["dt_s"] = aux(dt_s, 1)
    nonfinite = ~np.isfinite(temp)
    if physical:
        nonfinite |= ~np.all(np.isfinite(raw_counts), axis=1)
    for v in inputs.values():
        nonfinite |= ~np.all(np.isfinite(v), axis=1)
    status[nonfinite] |= STATUS_NONFINITE
    zeroed = nonfinite.copy()
    cols = {k: [np.where(nonfinite, ft(0), v[:, j]) for j in range(v.shape[1])]
            for k, v in inputs.items()}
    # thermal lag: the element temperature, a recursion over the calls
    t = np.where(nonfinite, ft(0), temp)
    null_state = state is NULL_STATE
    if state is None:
        state = SensorState()
    if o.thermal_lag and not null_state:
        tau = c.scalar("lag_tau_s")
        el = state.temp_el_C
        t_el = t.copy()
        dts = cols["dt_s"][0]
        dts = np.where(dts >= 0, dts, ft(0)).astype(ft)   # a step back in time holds the filter
        for k in np.nonzero(~nonfinite)[0]:
            with np.errstate(over="ignore", invalid="ignore"):
                new = None if el is None else lag_kernel(t[k], el, dts[k], tau)
            # a non-finite result (NaN/inf state, overflow) restarts the filter at t[k]
            el = new if new is not None and np.isfinite(new) else t[k]
            t_el[k] = el
        t = t_el
        state.temp_el_C = el
    raw = [np.where(nonfinite, ft(0), raw_counts[:, i]).astype(ft) if physical else
           raw_counts[:, i].astype(ft) for i in range(raw_counts.shape[1])]
    if set_only:
        if offset_counts is not None:
            off = np.asarray(offset_counts, dtype=ft)
        elif null_state or state.offset_counts is None:
            off = np.full((n, 3), np.nan, dtype=ft)
        else:
            off = np.broadcast_to(np.asarray(state.offset_counts, dtype=ft), (n, 3))
        no_offset = ~np.all(np.isfinite(off), axis=1) & ~zeroed
        status[no_offset] |= STATUS_NO_OFFSET
        zeroed |= no_offset
        raw += [np.where(zeroed, ft(0), off[:, i]) for i in range(3)]
    if o.lagged_channels and not null_state:
        # the lagged channels' filters: advanced by the calls that reach the kernel (the
        # C's run_kernel), each a recursion like the thermal lag's
        nch = len(o.channels)
        taus = c.get("lag_channel_tau_s")
        dts = np.where(cols["dt_s"][0] >= 0, cols["dt_s"][0], ft(0)).astype(ft)
        chs = cols["channels"]
        els = list(state.channel_el) if state.channel_el is not None else None
        for j in range(len(o.lagged_channels)):
            chs[nch + j] = chs[nch + j].copy()
        for k in np.nonzero(~zeroed)[0]:
            if els is not None:
                with np.errstate(over="ignore", invalid="ignore"):
                    for j in range(len(o.lagged_channels)):
                        new = lag_kernel(chs[nch + j][k], els[j], dts[k], taus[j])
                        if np.isfinite(new):
                            chs[nch + j][k] = new
            els = [chs[nch + j][k] for j in range(len(o.lagged_channels))]
        if els is not None:
            state.channel_el = els
    # clamp to the calibrated range (C: if (t < t_min) ... else if (t > t_max) ...);
    # a sensor with no temperature has no range and nothing to clamp
    t = np.where(zeroed, ft(0), t)
    if sensor.temperature:
        t_min, t_max = c.scalar("t_min_C"), c.scalar("t_max_C")
        margin = c.scalar("temp_margin_C")
        below, above = t < t_min, t > t_max
        # C: the distance outside, one float subtraction, against the margin
        with np.errstate(invalid="ignore", over="ignore"):
            far = (below & ((t_min - t).astype(ft) > margin)) | \
                (above & ((t - t_max).astype(ft) > margin))
        t = np.where(below, t_min, np.where(above, t_max, t)).astype(ft)
        status[(below | above) & ~zeroed] |= STATUS_TEMP_EXTRAPOLATED
        status[far & ~zeroed] |= STATUS_TEMP_CLAMPED

    # the kernel: the folded chain on the prepared coefficients (what the C kernels read)
    prep = prepare_sensor(spec, sensor, coeffs_sensor, coeffs_unit, set_only=set_only)
    f = prepared_view(spec, sensor, [prep[k] for k in range(prep.size)], set_only=set_only)
    with np.errstate(all="ignore"):
        out = folded_sensor_kernel(spec, sensor, raw, t, cols.get("coil_A", []), f, ft(0.5),
                                   set_only=set_only, channels=cols.get("channels", ()),
                                   rate_dps=cols.get("rate_dps", ()))
    result = {}
    for name, vals in out.items():
        arr = np.stack([np.broadcast_to(np.asarray(v, dtype=ft), (n,)) for v in vals], axis=1)
        result[name] = np.where(zeroed[:, None], ft(0), arr).astype(ft)
    if "offset_counts" in result:   # the state's offset: refreshed by unsaturated pairs
        stored = ~sat & ~zeroed & (not null_state)
        last = np.maximum.accumulate(np.where(stored, np.arange(n), -1))
        before = np.full(3, np.nan, ft) if null_state or state.offset_counts is None else \
            np.asarray(state.offset_counts, ft)
        result["offset_counts"] = np.where(
            (last >= 0)[:, None], result["offset_counts"][np.maximum(last, 0)],
            before[None, :]).astype(ft)
        if stored.any():
            state.offset_counts = result["offset_counts"][-1].copy()
    margin = result.pop("band_margin_nT2")
    plausible = (margin[:, 0] >= 0) & (margin[:, 1] >= 0)
    status[~plausible & ~zeroed] |= STATUS_IMPLAUSIBLE
    result["status"] = status
    return result


def reference_select(spec: ChainSpec, coeffs_by_sensor: dict, fields, statuses):
    """Python reference of `<unit>_select`, over samples.

    fields: (N, S, 3) calibrated fields in unit sensor order, float type; statuses: (N, S)
    uint16 from the sensor calls. Returns dict: status (N, S) with DISAGREE added,
    field_body_nT (N, 3), sensor (N,) int (-1 none), rank (N,), reason (N,).
    """
    ft = np_dtype(spec.unit)
    fields = np.asarray(fields, dtype=ft)
    statuses = np.array(statuses, dtype=np.uint16)
    n, S = statuses.shape
    agree = [ft(np.asarray(coeffs_by_sensor[s.name], dtype=ft)[
        spec.offsets(spec.sensor_blocks(s))["agree_nT"]]) for s in spec.unit.sensors]
    with np.errstate(all="ignore"):
        margins = agreement_kernel([[fields[:, i, k] for k in range(3)] for i in range(S)],
                                   agree)
    pair_index = {}
    k = 0
    for i in range(S):
        for j in range(i + 1, S):
            pair_index[(i, j)] = k
            k += 1
    margins = np.stack(margins, axis=1) if margins else np.zeros((n, 0), ft)
    order = spec.fallback_order()
    out_status = statuses.copy()
    sel_field = np.zeros((n, 3), dtype=ft)
    sensor = np.full(n, -1, dtype=np.int64)
    rank = np.full(n, -1, dtype=np.int64)
    reason = np.full(n, SELECT_NONE, dtype=np.int64)
    for r in range(n):   # the selection logic is branchy; it is cheap per sample
        valid = [is_valid(statuses[r, i]) for i in range(S)]
        disagree, chosen, why, rk = select_logic(
            S, order, valid, lambda i, j: margins[r, pair_index[(i, j)]] >= 0)
        for i in range(S):
            if disagree[i]:
                out_status[r, i] |= STATUS_DISAGREE
        if chosen >= 0:
            sel_field[r] = fields[r, chosen]
        sensor[r], rank[r], reason[r] = chosen, rk, why
    return {"status": out_status, "field_body_nT": sel_field, "sensor": sensor,
            "rank": rank, "reason": reason}
