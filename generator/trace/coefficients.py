"""The coefficient sets around a trace: the baseline (the core fit as `magcal fit` makes
it, or the identity where no file carries a reference), the effects a supplied set
already carries, the float64 model of a set's chain, and the extended coefficient set
the traced models are written into (the chain's layout, effects in their flight forms).
"""

from __future__ import annotations

import json

import numpy as np

from generator.errors import InputError
from generator.fit.calibration import SensorCalibration
from generator.flight.chain import MAX_POLY_DEGREE, ChainSpec, SensorOptions
from generator.flight.coeffs import CoefficientSet, json_default
from generator.trace import effects as fx
from generator.trace.model import BaseFit, SensorModel, base_from_coefficients
from generator.trace.samples import SensorSamples, gather_samples


def baseline_coefficients(unit, tels, progress=None) -> tuple:
    """The core fit as `magcal fit` makes it (fit_unit; K where coil currents step; H
    from a deployed file), or the identity where no file carries any field reference
    (data calibrated upstream: only deviations from a constant can be traced).
    Returns (CoefficientSet, {sensor: degree}, notes)."""
    from generator.fit.thermal import fit_unit
    say = progress or (lambda m: None)
    notes = []
    try:
        cals = fit_unit(unit, tels, progress=None)
        degrees = {n: int(c.stats.get("degree", 3)) for n, c in cals.items()}
        core = "generator.fit.thermal.fit_unit"
    except InputError as err:
        has_ref = any(t.has("ref_x_nT", "ref_y_nT", "ref_z_nT") or t.has("ref_norm_nT")
                      for t in tels) or unit.lab_field_nT is not None
        if has_ref:
            raise
        notes.append("no file carries a field reference (reference vectors, ref_norm_nT or "
                     "the unit's lab_field_nT): the baseline is the identity calibration "
                     "(B = B~, the data as calibrated upstream) and only deviations from a "
                     f"constant per static position are traced ({err.message})")
        lo = min(float(np.nanmin(t.columns[s.temp_column])) for t in tels for s in unit.sensors
                 if s.temp_column in t.columns)
        hi = max(float(np.nanmax(t.columns[s.temp_column])) for t in tels for s in unit.sensors
                 if s.temp_column in t.columns)
        cals = {s.name: SensorCalibration.constant(s.name, np.zeros(3), np.eye(3), 25.0,
                                                   lo, hi, method="identity (no reference)")
                for s in unit.sensors}
        degrees = {s.name: 0 for s in unit.sensors}
        core = "identity"
    K, coils, H = None, (), None
    # K from files whose coil currents step while the unit stands in static positions
    # (a moving unit's field would leak into K); elsewhere the currents stay candidates
    def steps_in_positions(t):
        pos = t.get("position")
        if pos is None:
            return False
        static = np.nan_to_num(np.asarray(pos, float)) > 0
        return any(c.startswith("coil_") and c.endswith("_A")
                   and np.nanmax(np.abs(np.where(static, t.columns[c], 0.0))) > 0
                   for c in t.columns)
    coil_tels = [t for t in tels if steps_in_positions(t)]
    if coil_tels:
        from generator.fit.coils import fit_coils
        try:
            cf = fit_coils(unit, coil_tels)
            K, coils = cf.K(), tuple(cf.coils)
            notes.append(f"coil coupling K fitted from {', '.join(str(t.path) for t in coil_tels)}")
        except InputError as err:
            notes.append(f"no coil coupling in the baseline ({err.message}); coil currents "
                         "are candidate channels")
    if any(s.frame == "boom" for s in unit.sensors) and unit.boom_reference and core != "identity":
        deployed = [t for t in tels if not t.has("ref_x_nT", "ref_y_nT", "ref_z_nT")]
        if deployed:
            from generator.fit.alignment import align_boom
            try:
                H = align_boom(unit, deployed[0], cals, coil_K_nT_per_A=K).H
            except InputError as err:
                notes.append(f"boom alignment not fitted ({err.message}); H = identity")
    # the fit's SET/RESET decision is the chain's, as in pipeline.fit: M was fitted to the
    # compensated output where the decision is on
    sr_opts, sr_values = sr_chain_options(cals)
    for n in sr_opts:
        notes.append(f"{n}: SET/RESET gyro compensation in the baseline chain (c = "
                     f"{sr_values[n]['sr_comp_s_per_deg']:.4g} s/deg, the fit's decision)")
    cs = CoefficientSet.from_calibrations(unit, cals, H_boom_to_body=H, K_nT_per_A=K,
                                          coils=coils, fit_info={"core": core},
                                          sensor_options=sr_opts, option_values=sr_values)
    say(f"baseline: {core}" + (f", coils {', '.join(coils)}" if coils else ""))
    return cs, degrees, notes


def sr_chain_options(cals) -> tuple:
    """({sensor: SensorOptions(sr_compensation=True)}, {sensor: {"sr_comp_s_per_deg": c}})
    for the sensors whose fit decided on the SET/RESET gyro compensation
    (stats["set_reset_compensation"], fit.setreset.compensation_decision)."""
    opts, values = {}, {}
    for n, c in cals.items():
        sr = c.stats.get("set_reset_compensation") or {}
        if sr.get("enabled"):
            opts[n] = SensorOptions(sr_compensation=True)
            values[n] = {"sr_comp_s_per_deg": sr["sr_comp_s_per_deg"]}
    return opts, values


def initial_effects(cs: CoefficientSet, name: str, S: SensorSamples, model_info=None):
    """Effects a supplied coefficient set already carries (its chain options)."""
    o = cs.spec.opts(name)
    out = []
    for cls in fx.CATALOGUE:
        out.extend(cls.from_flight(cs.sensors[name], o, S, model_info))
    return out


def model_from_coefficients(cs: CoefficientSet, name: str, S: SensorSamples) -> SensorModel:
    """The float64 model of a coefficient set's chain for one sensor (all blocks as
    given, nothing free): B_cal = model.field(S)."""
    base = base_from_coefficients(cs, name, degree=cs.spec.poly_degree)
    return _fixed_model(base, initial_effects(cs, name, S))


def _fixed_model(base: BaseFit, effects) -> SensorModel:
    m = SensorModel(base, free_b=[], free_M=None, free_K=False, groups=[], Bp0=np.zeros((0, 3)))
    for e, p in effects:
        m = m.with_effect(e, p)
    return m


def calibrated_field64(cs: CoefficientSet, tel, sensor: str):
    """float64 B_cal of one sensor of a telemetry file through the extended chain model
    (boom sensors rotated by H), for every usable sample; returns (row index, (n, 3))."""
    unit = cs.unit
    ch_names = list(dict.fromkeys(c for s in unit.sensors
                                  for c in cs.spec.opts(s).kernel_channels))
    norm_tel = _with_any_reference(tel)
    S = gather_samples(unit, [norm_tel], [0], coils=cs.spec.coils,
                       H=cs.unit_values.get("H_boom_to_body"), channels=ch_names)[sensor]
    m = model_from_coefficients(cs, sensor, S)
    B = m.field(S)
    if unit.sensor(sensor).frame == "boom" and "H_boom_to_body" in cs.unit_values:
        B = B @ np.asarray(cs.unit_values["H_boom_to_body"], float).T
    return S.order.copy(), B


def _with_any_reference(tel):
    """The same telemetry with a dummy magnitude reference where it has none (so that
    every usable sample is gathered)."""
    from generator.io.telemetry import Telemetry
    cols = dict(tel.columns)
    if "ref_norm_nT" not in cols and not tel.has("ref_x_nT", "ref_y_nT", "ref_z_nT"):
        cols["ref_norm_nT"] = np.full(tel.n, 1.0)
    return Telemetry(tel.path, cols, tel.line_numbers, dict(tel.meta))


def to_coefficient_set(base: CoefficientSet, traces: dict, info=None) -> CoefficientSet:
    """The baseline coefficient set with every traced sensor's final model written in
    the chain's layout: refitted b_poly_nT, M_poly (poly_degree raised where an effect
    needs it, unit-wide), K, and the flight forms of the effects (ChainSpec options
    channels / thermal_lag / nonlinear / sr_compensation and their blocks; a bias step
    becomes the offset after it; a time offset has no flight form). Sensors without a
    traced effect keep the baseline's values."""
    unit = base.unit
    values, options = {}, {}
    degree = base.spec.poly_degree
    for s in unit.sensors:
        v = {k: np.array(a, float) for k, a in base.sensors[s.name].items()}
        o = base.spec.opts(s.name).to_dict()
        tr = traces.get(s.name)
        if tr is not None and tr.steps:
            m = tr.final_model
            mv = m.values()
            o = {"channels": [], "thermal_lag": False, "nonlinear": False,
                 "sr_compensation": False}
            for k in ("C_nT_per_unit", "lag_tau_s", "cubic_per_nT2", "sr_comp_s_per_deg",
                      "g_per_unit", "C_lag_nT_per_unit", "lag_channel_tau_s"):
                v.pop(k, None)
            D = m.base.degree
            v["b_poly_nT"] = mv["b_poly_nT"].copy()
            v["M_poly"] = mv["M_poly"].copy()
            if mv["K_nT_per_A"] is not None:
                v["K_nT_per_A"] = mv["K_nT_per_A"]
            later = []
            for i, e in enumerate(m.effects):
                if e.in_chain:
                    e.to_flight(m.effect_params(i), v, o, m)
                else:
                    later.append(i)
            g = v.pop("_g_by_channel", None)
            if g:                  # channel scales, aligned with the sensor's channels
                v["g_per_unit"] = np.stack([g.get(ch, np.zeros(3)) for ch in o["channels"]],
                                           axis=1)
            f = v.pop("_axis_factor", None)
            if f is not None:      # a per-axis factor on x before the cubic and M (see
                #                    ChannelScale.to_flight): y = f x, y - n y^3 = f (x - n f^2 x^3)
                v["M_poly"] = np.asarray(v["M_poly"], float) * f[None, None, :]
                if "cubic_per_nT2" in v:
                    v["cubic_per_nT2"] = np.asarray(v["cubic_per_nT2"], float) * f * f
            if m.free_M is None:   # no absolute reference: keep the baseline's mean output
                _recentre(v, o, tr, m)
            for i in later:        # a step's new offset (the others have no flight form)
                m.effects[i].to_flight(m.effect_params(i), v, o, m)
            degree = max(degree, v["b_poly_nT"].shape[0] - 1, D)
        values[s.name] = v
        options[s.name] = o
    degree = min(degree, MAX_POLY_DEGREE)
    sensor_options = tuple((s.name, SensorOptions.from_dict(options[s.name]))
                           for s in unit.sensors
                           if SensorOptions.from_dict(options[s.name]) != SensorOptions())
    spec = ChainSpec(unit, poly_degree=degree, coils=base.spec.coils,
                     sensor_options=sensor_options)
    sensors = {}
    for s in unit.sensors:
        v = values[s.name]
        for key, shape in (("b_poly_nT", (3,)), ("M_poly", (3, 3))):
            a = v[key]
            if a.shape[0] < degree + 1:
                v[key] = np.concatenate([a, np.zeros((degree + 1 - a.shape[0],) + shape)])
            # a sensor without temperature: constant b, M (its model sits at dT = 0)
            v[key] = v[key][:spec.degree(s) + 1]
        sensors[s.name] = {b.name: np.asarray(v[b.name], float).reshape(b.shape)
                           for b in spec.sensor_blocks(s)}
    fit_info = dict(base.fit_info)
    if info:
        fit_info["trace"] = info
    unc = {n: ({} if (traces.get(n) and traces[n].steps) else u)
           for n, u in base.uncertainty.items()}
    cs = CoefficientSet(spec, sensors, dict(base.unit_values), unc, fit_info)
    try:       # the set the trace writes passes the checks of any coefficient file
        CoefficientSet.from_json_dict(json.loads(json.dumps(cs.to_json_dict(),
                                                            default=_json_default)))
    except InputError as e:    # not the user's input: an inconsistency of the trace
        raise RuntimeError(f"the traced coefficients fail their own check: {e}") from e
    return cs


def _recentre(v, o, tr, m: SensorModel):
    """Position-only data fix b(T) up to a constant: shift b0 so that the extended flight
    chain (what the blocks in v carry) has the baseline's mean output over the data."""
    S = tr.S_fit
    b = np.asarray(v["b_poly_nT"], float)
    t_ref, t_lo, t_hi = (float(v["t_ref_C"]), float(v["t_min_C"]), float(v["t_max_C"])) \
        if "t_ref_C" in v else (0.0, 0.0, 0.0)   # no temperature: constant, dT = 0
    base = BaseFit(tr.name, b.shape[0] - 1, t_ref, t_lo,
                   t_hi, b, np.asarray(v["M_poly"], float),
                   np.asarray(v["K_nT_per_A"], float) if "K_nT_per_A" in v else None, m.base.H)
    opts = SensorOptions.from_dict(o)
    inits = [ep for cls in fx.CATALOGUE for ep in cls.from_flight(v, opts, S, None)]
    B_new = _fixed_model(base, inits).field(S)
    B_old = tr.base_model.field(S)
    Mbar = np.asarray(v["M_poly"])[0]
    v["b_poly_nT"][0] = v["b_poly_nT"][0] + np.linalg.solve(Mbar, (B_new - B_old).mean(axis=0))


_json_default = json_default          # (kept name: tests use it)
