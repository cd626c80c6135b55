"""A unit's coefficient set: `coefficients.json`, in the layout of the chain definition.

The file carries the unit description and the chain structure, so `magcal generate`,
`magcal apply` and `magcal table` need nothing else. Values are stored in float64 (JSON
numbers round-trip exactly); the flight code rounds them to its float type once.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from generator import __version__
from generator.fit.calibration import SensorCalibration
from generator.flight.chain import ChainSpec, SensorOptions, is_physical
from generator.errors import InputError
from generator.io.json_input import load_json
from generator.io.unit import Unit

FORMAT = "magcal-coefficients"
FORMAT_VERSION = 1

# Plausible |B| for the flight check: LEO spans about 18,000-55,000 nT, the lab ~50,000.
FIELD_BAND_nT = (15000.0, 70000.0)
AGREE_SIGMAS = 5.0
# The largest temp_margin_C written: the span of plausible temperatures (tables.py "temp",
# -100..150 degC), beyond which a margin means nothing.
TEMP_MARGIN_MAX_C = 250.0
# fit_info["boom_alignment"] when no H was fitted (no body-frame reference for the boom)
NO_BOOM_ALIGNMENT = ("identity, not fitted (no body-frame reference or no boom campaign): "
                     "the boom sensors' field is reported in the boom frame")


def temp_margin_C(unit, cal) -> float:
    """How far outside its calibrated range a sensor's temperature may go with the sample
    still valid (chain block temp_margin_C): the distance d at which the extrapolated
    error, the calibration's own predicted error (stats["predicted_error"]
    ["field_error_nT"], from the coefficients' 1-sigma) plus d times the error's growth
    outside the range (stats["extrapolation"]["growth_nT_per_C"],
    fit.thermal.extrapolation_growth), reaches the unit's requirement ([requirements]
    field_error_nT, ICD section 4). No requirement or no growth estimate: 0 (every
    sample outside the range is invalid). A temperature-independent (constant,
    one-temperature) model follows the same rule: its growth is the error its unfitted
    temperature terms add, from the part's prior 1-sigma of the slope
    (fit.thermal.extrapolation_growth; uncertainty_1sigma, fit.thermal.
    unfitted_degree_sigma), so it stays valid only as far as that drift keeps the error
    within the requirement (beyond its measured range the samples are flagged
    TEMP_EXTRAPOLATED, beyond the margin TEMP_CLAMPED and invalid). Without a requirement
    a constant model has nothing to be held to and stays valid everywhere (the maximum
    margin), flagged TEMP_EXTRAPOLATED outside its measured range: a one-temperature
    ground calibration must not make every orbit sample invalid (issue 16)."""
    st = cal.stats or {}
    req = ((unit.extra or {}).get("requirements") or {}).get("field_error_nT")
    if not req and st.get("valid_outside_range"):
        return TEMP_MARGIN_MAX_C
    g = (st.get("extrapolation") or {}).get("growth_nT_per_C")
    if not req or not g or not np.isfinite(g) or g <= 0:
        return 0.0
    own = float((st.get("predicted_error") or {}).get("field_error_nT") or 0.0)
    return float(min(max(float(req) - own, 0.0) / float(g), TEMP_MARGIN_MAX_C))


def default_agree_nT(sensor, cal) -> float:
    """Tolerance of one sensor in the cross-sensor check (nT): AGREE_SIGMAS x the larger of
    the sensor's noise (the unit file's noise_nT, else the part's typical noise from the
    catalogue) and its fit residual per axis; with neither, a few counts (counts input)."""
    from generator.io import parts as catalogue

    part = catalogue.find(sensor.part)
    per_axis = float(sensor.noise_nT or (part.noise_nT if part and part.noise_nT else 0.0))
    stats = cal.stats or {}
    fit = stats.get("fit") or {}
    resid = fit.get("rms_vector_nT", stats.get("rms_vector_nT"))
    if resid is not None and np.isfinite(resid):
        per_axis = max(per_axis, float(resid) / np.sqrt(3.0))
    else:          # magnitudes only: the |B| residual is one axis's worth of error
        resid = fit.get("rms_norm_nT")
        if resid is not None and np.isfinite(resid):
            per_axis = max(per_axis, float(resid))
    if per_axis <= 0:
        if sensor.input == "counts":
            per_axis = 50.0 * sensor.lsb_nT / 25.0   # no noise figure: a few counts
        else:
            # real-number readings and nothing known of their noise: a thousandth of the
            # full scale, the resolution of a 10..12-bit converter (coarser than any part
            # in the catalogue, so the check does not reject good sensors)
            per_axis = 1e-3 * float(sensor.full_scale_nT)
    return AGREE_SIGMAS * np.sqrt(3.0) * per_axis


@dataclass
class CoefficientSet:
    spec: ChainSpec
    sensors: dict                      # name -> {block name: ndarray float64}
    unit_values: dict = field(default_factory=dict)   # block name -> ndarray
    uncertainty: dict = field(default_factory=dict)   # name -> {block: 1-sigma ndarray}
    fit_info: dict = field(default_factory=dict)      # JSON-able: methods, stats, sources

    def __post_init__(self):
        # Coil and channel names come from telemetry headers and reach the generated C as
        # macros and comments: only C identifiers pass, whatever built the set.
        from generator.io.names import column_fault, macro_collision

        cols = (*self.spec.coils, *self.spec.aux_channels)
        for col in cols:
            fault = column_fault(col)
            if fault:
                raise InputError(self.unit.path, f"telemetry column {fault}: it cannot name a "
                                                 "coil or channel of the flight C")
        clash = macro_collision(cols)
        if clash:
            raise InputError(self.unit.path, f"telemetry columns '{clash[0]}' and "
                                             f"'{clash[1]}' give the same C macro")

    @property
    def unit(self) -> Unit:
        return self.spec.unit

    # ---- flat vectors in layout order --------------------------------------------------
    def flat_sensor(self, name) -> np.ndarray:
        s = self.unit.sensor(name)
        parts = [np.asarray(self.sensors[name][b.name], dtype=np.float64).reshape(-1)
                 for b in self.spec.sensor_blocks(s)]
        return np.concatenate(parts)

    def flat_unit(self) -> np.ndarray:
        parts = [np.asarray(self.unit_values[b.name], dtype=np.float64).reshape(-1)
                 for b in self.spec.unit_blocks()]
        return np.concatenate(parts) if parts else np.zeros(0)

    # ---- construction ------------------------------------------------------------------
    @staticmethod
    def from_calibrations(unit: Unit, cals: dict, H_boom_to_body=None, K_nT_per_A=None,
                          coils=(), fit_info=None, agree_nT=None,
                          field_band_nT=FIELD_BAND_nT, sensor_options=None,
                          option_values=None) -> "CoefficientSet":
        """From fitted SensorCalibration objects (and optional H and coil couplings).

        sensor_options: {sensor: chain.SensorOptions} (optional stages, e.g. the SET/RESET
        gyro compensation); option_values: {sensor: {block name: value}}, the values of
        the blocks those options add (e.g. sr_comp_s_per_deg). A block left without a
        value is a ValueError.

        agree_nT: {sensor: tolerance} for the cross-sensor check; by default
        AGREE_SIGMAS x sqrt(3) x the sensor's per-axis scatter (its noise_nT, or the fit's
        per-axis residual when larger)."""
        # the degree of b(T), M(T): of the sensors that have a temperature (a sensor with
        # none is constant whatever degree its calibration carries)
        with_t = [cals[s.name] for s in unit.sensors if s.temperature]
        degree = with_t[0].b_poly_nT.shape[0] - 1 if with_t else 0
        opts = tuple((s.name, sensor_options[s.name]) for s in unit.sensors
                     if (sensor_options or {}).get(s.name) not in (None, SensorOptions()))
        spec = ChainSpec(unit, poly_degree=degree, coils=tuple(coils), sensor_options=opts)
        sensors, unc = {}, {}
        for s in unit.sensors:
            cal: SensorCalibration = cals[s.name]
            # blocks the sensor's chain has (chain.ChainSpec.sensor_blocks): a physical
            # input has no lsb/zero, a sensor with no temperature a constant b, M (the
            # calibration's value at its t_ref, the k = 0 term) and no temperature range
            nk = spec.degree(s) + 1
            v = {}
            if not is_physical(s):
                v["lsb_nT"] = np.array(s.lsb_nT)
                v["zero_count"] = np.array(float(s.zero_count))
            if s.temperature:
                v["t_ref_C"] = np.array(cal.t_ref_C)
                v["t_min_C"] = np.array(cal.t_min_C)
                v["t_max_C"] = np.array(cal.t_max_C)
                v["temp_margin_C"] = np.array(temp_margin_C(unit, cal))
            v["b_poly_nT"] = np.asarray(cal.b_poly_nT, float)[:nk]
            v["M_poly"] = np.asarray(cal.M_poly, float)[:nk]
            if coils:
                v["K_nT_per_A"] = np.asarray(K_nT_per_A[s.name], float) if K_nT_per_A \
                    else np.zeros((3, len(coils)))
            v["agree_nT"] = np.array(float(agree_nT[s.name]) if agree_nT else
                                     default_agree_nT(s, cal))
            for k, a in (option_values or {}).get(s.name, {}).items():
                v[k] = np.asarray(a, float)
            missing = [b.name for b in spec.sensor_blocks(s) if b.name not in v]
            if missing:
                raise ValueError(f"sensor '{s.name}': no value for {', '.join(missing)} "
                                 "(option_values)")
            sensors[s.name] = v
            u = {}
            if cal.b_poly_sigma_nT is not None:
                u["b_poly_nT"] = np.asarray(cal.b_poly_sigma_nT, float)[:nk]
            if cal.M_poly_sigma is not None:
                u["M_poly"] = np.asarray(cal.M_poly_sigma, float)[:nk]
            unc[s.name] = u
        unit_values = {"field_min_nT": np.array(float(field_band_nT[0])),
                       "field_max_nT": np.array(float(field_band_nT[1]))}
        info = dict(fit_info or {})
        if spec.has_boom:
            unit_values["H_boom_to_body"] = np.eye(3) if H_boom_to_body is None \
                else np.asarray(H_boom_to_body, float)
            if H_boom_to_body is None:   # the generated header and the report say so
                info.setdefault("boom_alignment", NO_BOOM_ALIGNMENT)
        info.setdefault("sensors", {})
        for name, cal in cals.items():
            info["sensors"].setdefault(name, {}).update(
                {"method": cal.method, "body_frame": cal.body_frame, "stats": cal.stats})
        return CoefficientSet(spec, sensors, unit_values, unc, info)

    def with_boom_stowed(self) -> "CoefficientSet":
        """The same coefficients with H = identity: for data taken in the jig."""
        unit_values = dict(self.unit_values)
        if "H_boom_to_body" in unit_values:
            unit_values["H_boom_to_body"] = np.eye(3)
        return CoefficientSet(self.spec, self.sensors, unit_values, self.uncertainty,
                              self.fit_info)

    def calibration(self, name) -> SensorCalibration:
        """The sensor's calibration; a sensor with no temperature: constant b, M with
        t_ref 0 and an unbounded range (the model holds at any temperature)."""
        v = self.sensors[name]
        if "t_ref_C" not in v:
            return SensorCalibration(name, np.array(v["b_poly_nT"]), np.array(v["M_poly"]),
                                     0.0, -np.inf, np.inf)
        return SensorCalibration(
            name, np.array(v["b_poly_nT"]), np.array(v["M_poly"]), float(v["t_ref_C"]),
            float(v["t_min_C"]), float(v["t_max_C"]))

    # ---- JSON --------------------------------------------------------------------------
    def to_json_dict(self) -> dict:
        return {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "generator": f"magcal {__version__}",
            "unit": self.unit.to_dict(),
            "chain": self.spec.to_dict(),
            "layout_hash": f"0x{self.spec.layout_hash():08x}",
            "sensors": {n: {k: _tolist(a) for k, a in v.items()} for n, v in self.sensors.items()},
            "unit_coefficients": {k: _tolist(a) for k, a in self.unit_values.items()},
            "uncertainty_1sigma": {n: {k: _tolist(a) for k, a in v.items()}
                                   for n, v in self.uncertainty.items()},
            "fit": self.fit_info,
        }

    def check_plausible(self, source) -> "CoefficientSet":
        """The same checks as a loaded coefficients.json (validate_document and the value
        ranges) on a set computed here, e.g. fitted from data: InputError naming `source`
        (the data) when the result is no plausible calibration. Returns self."""
        d = json.loads(json.dumps(self.to_json_dict(), default=json_default))
        try:
            CoefficientSet.from_json_dict(d, None)
        except InputError as e:
            raise InputError(source, f"the data give no plausible calibration: "
                                     f"{e.message}") from None
        return self

    def save(self, path) -> None:
        Path(path).write_text(json.dumps(self.to_json_dict(), indent=1, sort_keys=False,
                                         default=json_default) + "\n")

    @staticmethod
    def load(path) -> "CoefficientSet":
        path = Path(path)
        d = load_json(path, "coefficient file")
        return CoefficientSet.from_json_dict(d, path)

    @staticmethod
    def from_json_dict(d: dict, path=None) -> "CoefficientSet":
        """A coefficient set from a parsed coefficients.json: untrusted input, checked
        against the schema (validate_document) before any use."""
        unit, spec = validate_document(d, path)
        sensors = {}
        for s in unit.sensors:
            sv = d["sensors"][s.name]
            sensors[s.name] = {b.name: _block_array(sv, b, f"sensors.{s.name}", path, unit)
                               for b in spec.sensor_blocks(s)}
        unit_values = {b.name: _block_array(d.get("unit_coefficients", {}), b,
                                            "unit_coefficients", path, unit)
                       for b in spec.unit_blocks()}
        for s in unit.sensors:
            _check_sensor_values(sensors[s.name], f"sensors.{s.name}", path)
        _check_unit_values(unit_values, path)
        unc = _uncertainty(d.get("uncertainty_1sigma", {}), unit, path)
        cs = CoefficientSet(spec, sensors, unit_values, unc, d.get("fit", {}))
        want = d.get("layout_hash")
        if want is not None and want != f"0x{spec.layout_hash():08x}":
            raise InputError(path, f"layout_hash {_short(want)} does not match the chain "
                                   f"structure in the file (0x{spec.layout_hash():08x}): "
                                   "written for another chain version, or edited by hand")
        return cs


# ---- schema of coefficients.json (untrusted input) ---------------------------------------

# Plausible magnitudes of the coefficients, by block; anything beyond is not a calibration
# of a magnetometer but a corrupted or hostile file. Reasoning per bound:
#  * fields and offsets: the parts in use saturate below 5e6 nT (AK8963 +-4912 uT), so an
#    offset, coupling or tolerance beyond 1e8 nT (0.1 T) is not a sensor property;
#  * M(T): a gain beyond a factor 1e3 from 1 is a wrong lsb_nT, not a calibration;
#  * temperatures: above absolute zero and below 300 degC (no part survives solder reflow
#    temperatures of about 250 degC for long);
#  * every value must also be finite in float32 (the flight type), which 1e8 ensures.
FIELD_LIMIT_nT = 1e8
GAIN_LIMIT = 1e3
TEMP_RANGE_C = (-273.15, 300.0)
GENERIC_LIMIT = 1e8
# H must be a rotation: |H H^T - I| below 1e-4 (0.006 deg, far below the ~0.05 deg
# accuracy of a boom alignment; a JSON float64 Wahba solution is exact to ~1e-15).
ORTHO_TOL = 1e-4
INPUT_KINDS = ("counts", "nT", "uT", "mG", "G")
OPTION_KEYS = ("channels", "thermal_lag", "nonlinear", "sr_compensation", "channel_scale",
               "lagged_channels")
_BLOCK_LIMITS = {"lsb_nT": FIELD_LIMIT_nT, "zero_count": 2.0 ** 31, "b_poly_nT": FIELD_LIMIT_nT,
                 "M_poly": GAIN_LIMIT, "K_nT_per_A": FIELD_LIMIT_nT, "agree_nT": FIELD_LIMIT_nT,
                 "C_nT_per_unit": FIELD_LIMIT_nT, "field_min_nT": FIELD_LIMIT_nT,
                 "field_max_nT": FIELD_LIMIT_nT, "H_boom_to_body": 1.0 + ORTHO_TOL,
                 "t_ref_C": 300.0, "t_min_C": 300.0, "t_max_C": 300.0}


def validate_document(d, path=None):
    """(Unit, ChainSpec) of a parsed coefficients.json, or InputError naming the key.

    Checked: format and version; the unit section with the same rules as a unit file
    (names, parts, frames, axes, numbers); the chain section (degree, coil and channel
    names as C identifiers, options known and typed, for known sensors only); `sensors`
    a table of exactly the unit's sensors, each holding exactly its chain's blocks."""
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise InputError(path, f"not a {FORMAT} file (missing 'format': '{FORMAT}')")
    if d.get("format_version") != FORMAT_VERSION:
        raise InputError(path, f"format_version {_short(d.get('format_version'))} is not "
                               f"supported (this is {FORMAT_VERSION})")
    unit = _validate_unit(d.get("unit"), path)
    spec = _validate_chain(d.get("chain", {}), unit, path)
    sensors = d.get("sensors")
    if not isinstance(sensors, dict):
        raise InputError(path, "sensors: must be an object {sensor name: coefficients}, "
                               f"not {type(sensors).__name__}")
    for name in sensors:
        if name not in unit.sensor_names:
            raise InputError(path, f"sensors.{_short(name)}: not a sensor of the unit "
                                   f"({', '.join(unit.sensor_names)})")
    for s in unit.sensors:
        sv = sensors.get(s.name)
        if sv is None:
            raise InputError(path, f"sensors.{s.name}: missing")
        if not isinstance(sv, dict):
            raise InputError(path, f"sensors.{s.name}: must be an object of coefficient "
                                   f"blocks, not {type(sv).__name__}")
        known = [b.name for b in spec.sensor_blocks(s)]
        for k in sv:
            if k not in known:
                raise InputError(path, f"sensors.{s.name}.{_short(k)}: not a coefficient of "
                                       f"this chain ({', '.join(known)})")
    uc = d.get("unit_coefficients", {})
    if not isinstance(uc, dict):
        raise InputError(path, "unit_coefficients: must be an object")
    known = [b.name for b in spec.unit_blocks()]
    for k in uc:
        if k not in known:
            raise InputError(path, f"unit_coefficients.{_short(k)}: not a unit coefficient of "
                                   f"this chain ({', '.join(known)})")
    if not isinstance(d.get("fit", {}), dict):
        raise InputError(path, "fit: must be an object")
    return unit, spec


def _validate_unit(u, path) -> Unit:
    from generator.io.unitfile import unit_from_doc

    if not isinstance(u, dict):
        raise InputError(path, "unit: missing, or not an object")
    sensors = u.get("sensors")
    if not isinstance(sensors, list) or not all(isinstance(x, dict) for x in sensors):
        raise InputError(path, "unit.sensors: must be a list of sensor objects")
    doc = {"unit": {k: u[k] for k in ("id", "lab_field_nT", "float")
                    if u.get(k) is not None},
           "sensor": [{k: v for k, v in x.items() if v is not None} for x in sensors]}
    if u.get("boom_reference") is not None:
        doc["boom"] = {"reference": u["boom_reference"]}
    try:
        unit_from_doc(path, doc)
    except InputError as e:
        raise InputError(path, f"unit: {e.message}") from None
    for i, x in enumerate(sensors, start=1):
        where = f"unit.sensors #{i}"
        if x.get("input", "counts") not in INPUT_KINDS:
            raise InputError(path, f"{where}: input: {_short(x.get('input'))} is not one of "
                                   f"{', '.join(INPUT_KINDS)}")
        if not isinstance(x.get("temperature", True), bool):
            raise InputError(path, f"{where}: temperature: not true or false")
        r = x.get("range_nT")
        if r is not None and not (_is_number(r) and 0 < r <= FIELD_LIMIT_nT):
            raise InputError(path, f"{where}: range_nT: {_short(r)} is not a positive "
                                   f"number up to {FIELD_LIMIT_nT:g}")
    try:
        return Unit.from_dict(u)
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(path, f"unit: {_short(str(e))}") from None


def _validate_chain(c, unit: Unit, path) -> ChainSpec:
    from generator.flight.chain import MAX_POLY_DEGREE, SensorOptions
    from generator.io.names import column_fault, macro_collision

    if not isinstance(c, dict):
        raise InputError(path, "chain: must be an object")
    deg = c.get("poly_degree", 3)
    if isinstance(deg, bool) or not isinstance(deg, int) or not 0 <= deg <= MAX_POLY_DEGREE:
        raise InputError(path, f"chain.poly_degree: {_short(deg)} is not an integer "
                               f"0..{MAX_POLY_DEGREE}")
    coils = _column_list(c.get("coils", []), "chain.coils", path)
    so = c.get("sensor_options", {})
    if not isinstance(so, dict):
        raise InputError(path, "chain.sensor_options: must be an object {sensor: options}")
    opts = []
    for name, o in so.items():
        where = f"chain.sensor_options.{_short(name)}"
        if name not in unit.sensor_names:
            raise InputError(path, f"{where}: not a sensor of the unit")
        if not isinstance(o, dict):
            raise InputError(path, f"{where}: must be an object")
        for k, v in o.items():
            if k not in OPTION_KEYS:
                raise InputError(path, f"{where}.{_short(k)}: unknown option "
                                       f"({', '.join(OPTION_KEYS)})")
            if k not in ("channels", "lagged_channels") and not isinstance(v, bool):
                raise InputError(path, f"{where}.{k}: not true or false")
        chans = _column_list(o.get("channels", []), f"{where}.channels", path)
        if o.get("sr_compensation") and not unit.sensor(name).set_reset:
            raise InputError(path, f"{where}.sr_compensation: the sensor has no SET/RESET")
        if o.get("channel_scale") and not chans:
            raise InputError(path, f"{where}.channel_scale: needs channels")
        lagged = _column_list(o.get("lagged_channels", []), f"{where}.lagged_channels", path)
        for lst, key in ((chans, "channels"), (lagged, "lagged_channels")):
            if len(set(lst)) != len(lst):
                raise InputError(path, f"{where}.{key}: a channel is named twice")
        opts.append((name, SensorOptions(chans, o.get("thermal_lag", False),
                                         o.get("nonlinear", False),
                                         o.get("sr_compensation", False),
                                         o.get("channel_scale", False), lagged)))
    spec = ChainSpec(unit, poly_degree=deg, coils=coils, sensor_options=tuple(opts))
    clash = macro_collision([*spec.coils, *spec.aux_channels])
    if clash:
        raise InputError(path, f"chain: columns '{clash[0]}' and '{clash[1]}' give the same "
                               "C macro")
    for col in (*spec.coils, *spec.aux_channels):
        fault = column_fault(col)
        if fault:
            raise InputError(path, f"chain: column {fault}")
    return spec


def _column_list(v, where, path) -> tuple:
    from generator.io.names import column_fault

    if not isinstance(v, list):
        raise InputError(path, f"{where}: must be a list of column names")
    for c in v:
        fault = column_fault(c)
        if fault:
            raise InputError(path, f"{where}: {fault}")
    if len(set(v)) != len(v):
        raise InputError(path, f"{where}: a column is named twice")
    return tuple(v)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)


def _short(v, limit: int = 40) -> str:
    r = repr(v)
    return r if len(r) <= limit else r[:limit] + "..."


def _check_sensor_values(v: dict, where, path) -> None:
    """Plausibility of one sensor's blocks (the chain decides which it has: a sensor with
    no temperature has no t_*_C, a physical-input sensor no lsb_nT)."""
    if "t_min_C" in v:
        t_min, t_max, t_ref = float(v["t_min_C"]), float(v["t_max_C"]), float(v["t_ref_C"])
        for k, t in (("t_min_C", t_min), ("t_max_C", t_max), ("t_ref_C", t_ref)):
            if not TEMP_RANGE_C[0] <= t <= TEMP_RANGE_C[1]:
                raise InputError(path, f"{where}.{k}: {t:g} degC is outside the physical "
                                       f"range {TEMP_RANGE_C[0]:g}..{TEMP_RANGE_C[1]:g} degC")
        if not t_min <= t_max:
            raise InputError(path, f"{where}.t_min_C: {t_min:g} is above t_max_C {t_max:g}")
    if "lsb_nT" in v and not float(v["lsb_nT"]) > 0:
        raise InputError(path, f"{where}.lsb_nT: must be positive")
    if not float(v["agree_nT"]) > 0:
        raise InputError(path, f"{where}.agree_nT: must be positive")
    M0 = np.asarray(v["M_poly"])[0]
    sv = np.linalg.svd(M0, compute_uv=False)
    if not np.linalg.det(M0) > 0 or sv[-1] < 1.0 / GAIN_LIMIT or sv[0] > GAIN_LIMIT:
        raise InputError(path, f"{where}.M_poly: M(t_ref) must have det > 0 and gains within "
                               f"{1 / GAIN_LIMIT:g}..{GAIN_LIMIT:g} (det {np.linalg.det(M0):.3g}, "
                               f"singular values {sv[-1]:.3g}..{sv[0]:.3g})")


def _check_unit_values(v: dict, path) -> None:
    lo, hi = float(v["field_min_nT"]), float(v["field_max_nT"])
    if not 0 <= lo < hi:
        raise InputError(path, f"unit_coefficients.field_min_nT: need 0 <= field_min_nT "
                               f"< field_max_nT ({lo:g}, {hi:g})")
    if "H_boom_to_body" in v:
        H = np.asarray(v["H_boom_to_body"])
        err = float(np.max(np.abs(H @ H.T - np.eye(3))))
        if err > ORTHO_TOL or not np.linalg.det(H) > 0:
            raise InputError(path, f"unit_coefficients.H_boom_to_body: not a rotation "
                                   f"(|H H^T - I| = {err:.3g}, tolerance {ORTHO_TOL:g}; "
                                   f"det {np.linalg.det(H):.6g})")


def _uncertainty(u, unit: Unit, path) -> dict:
    if not isinstance(u, dict):
        raise InputError(path, "uncertainty_1sigma: must be an object")
    out = {}
    for n, v in u.items():
        if n not in unit.sensor_names or not isinstance(v, dict):
            raise InputError(path, f"uncertainty_1sigma.{_short(n)}: not an object of a "
                                   "sensor of the unit")
        out[n] = {}
        for k, a in v.items():
            try:
                arr = np.asarray(a, dtype=np.float64)
            except (TypeError, ValueError):
                arr = None
            if arr is None or not np.all(np.isfinite(arr)) or np.any(arr < 0):
                raise InputError(path, f"uncertainty_1sigma.{n}.{_short(k)}: not finite "
                                       "non-negative numbers")
            out[n][k] = arr
    return out


def _block_array(section, block, where, path, unit=None):
    if block.name not in section:
        raise InputError(path, f"{where}.{block.name}: missing")
    raw = section[block.name]
    if _has_bool(raw):
        raise InputError(path, f"{where}.{block.name}: true/false where numbers go")
    if _has_str(raw):
        raise InputError(path, f"{where}.{block.name}: text where numbers go (write the "
                               "number itself, not in quotes)")
    try:
        a = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise InputError(path, f"{where}.{block.name}: not numbers") from None
    if a.shape != tuple(block.shape):
        raise InputError(path, f"{where}.{block.name}: shape {a.shape}, expected {block.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(path, f"{where}.{block.name}: non-finite value")
    limit = _BLOCK_LIMITS.get(block.name, GENERIC_LIMIT)
    if a.size and np.max(np.abs(a)) > limit:
        i = tuple(int(k) for k in np.unravel_index(int(np.argmax(np.abs(a))), a.shape)) \
            if a.ndim else ()
        raise InputError(path, f"{where}.{block.name}{list(i) if i else ''}: "
                               f"{a[i] if i else float(a):g} is beyond the plausible "
                               f"magnitude {limit:g} {block.unit}")
    return a


def _has_bool(v) -> bool:
    if isinstance(v, bool):
        return True
    return isinstance(v, list) and any(_has_bool(x) for x in v)


def _has_str(v) -> bool:
    if isinstance(v, str):
        return True
    return isinstance(v, list) and any(_has_str(x) for x in v)


def _tolist(a):
    a = np.asarray(a)
    return a.item() if a.ndim == 0 else a.tolist()


def json_default(o):
    """json.dumps default= for numpy arrays and scalars (every JSON the tool writes)."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    raise TypeError(f"not JSON-serialisable: {type(o)}")
