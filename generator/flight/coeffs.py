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
    sample outside the range is invalid)."""
    st = cal.stats or {}
    req = ((unit.extra or {}).get("requirements") or {}).get("field_error_nT")
    g = (st.get("extrapolation") or {}).get("growth_nT_per_C")
    if not req or not g or not np.isfinite(g) or g <= 0:
        return 0.0
    own = float((st.get("predicted_error") or {}).get("field_error_nT") or 0.0)
    return float(min(max(float(req) - own, 0.0) / float(g), TEMP_MARGIN_MAX_C))


def default_agree_nT(sensor, cal) -> float:
    """Tolerance of one sensor in the cross-sensor check (nT)."""
    per_axis = float(sensor.noise_nT or 0.0)
    resid = (cal.stats or {}).get("rms_vector_nT")
    if resid is not None and np.isfinite(resid):
        per_axis = max(per_axis, float(resid) / np.sqrt(3.0))
    if per_axis <= 0:
        per_axis = 50.0 * sensor.lsb_nT / 25.0   # no noise figure: a few counts
    return AGREE_SIGMAS * np.sqrt(3.0) * per_axis


@dataclass
class CoefficientSet:
    spec: ChainSpec
    sensors: dict                      # name -> {block name: ndarray float64}
    unit_values: dict = field(default_factory=dict)   # block name -> ndarray
    uncertainty: dict = field(default_factory=dict)   # name -> {block: 1-sigma ndarray}
    fit_info: dict = field(default_factory=dict)      # JSON-able: methods, stats, sources

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

    def save(self, path) -> None:
        Path(path).write_text(json.dumps(self.to_json_dict(), indent=1, sort_keys=False,
                                         default=json_default) + "\n")

    @staticmethod
    def load(path) -> "CoefficientSet":
        path = Path(path)
        try:
            d = json.loads(path.read_text())
        except FileNotFoundError:
            raise InputError(path, "file not found") from None
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise InputError(path, f"not a JSON coefficient file: {e}") from None
        return CoefficientSet.from_json_dict(d, path)

    @staticmethod
    def from_json_dict(d: dict, path=None) -> "CoefficientSet":
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise InputError(path, f"not a {FORMAT} file (missing 'format': '{FORMAT}')")
        if d.get("format_version") != FORMAT_VERSION:
            raise InputError(path, f"format_version {d.get('format_version')!r} is not "
                                   f"supported (this is {FORMAT_VERSION})")
        try:
            unit = Unit.from_dict(d["unit"])
            spec = ChainSpec.from_dict(unit, d.get("chain", {}))
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(path, f"bad 'unit' or 'chain' section: {e!r}") from None
        sensors = {}
        for s in unit.sensors:
            sv = d.get("sensors", {}).get(s.name)
            if sv is None:
                raise InputError(path, f"sensors.{s.name}: missing")
            vals = {}
            for b in spec.sensor_blocks(s):
                vals[b.name] = _block_array(sv, b, f"sensors.{s.name}", path)
            sensors[s.name] = vals
        unit_values = {b.name: _block_array(d.get("unit_coefficients", {}), b,
                                            "unit_coefficients", path)
                       for b in spec.unit_blocks()}
        unc = {n: {k: np.asarray(a, float) for k, a in v.items()}
               for n, v in d.get("uncertainty_1sigma", {}).items()}
        cs = CoefficientSet(spec, sensors, unit_values, unc, d.get("fit", {}))
        want = d.get("layout_hash")
        if want is not None and want != f"0x{spec.layout_hash():08x}":
            raise InputError(path, f"layout_hash {want} does not match the chain structure "
                                   f"in the file (0x{spec.layout_hash():08x}): written for another chain version, or edited by hand")
        return cs


def _block_array(section, block, where, path):
    if block.name not in section:
        raise InputError(path, f"{where}.{block.name}: missing")
    try:
        a = np.asarray(section[block.name], dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, f"{where}.{block.name}: not numbers") from None
    if a.shape != tuple(block.shape):
        raise InputError(path, f"{where}.{block.name}: shape {a.shape}, expected {block.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(path, f"{where}.{block.name}: non-finite value")
    return a


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
