"""The verbs' work, callable from Python: fit, apply, generate (the CLI is a thin shell)."""

from __future__ import annotations

import csv

import numpy as np

from generator.flight.chain import STATUS_BITS, ChainSpec, SensorOptions, is_physical, is_valid
from generator.flight.coeffs import CoefficientSet
from generator.errors import InputError
from generator.progress import Progress
from generator.io.telemetry import Telemetry
from generator.io.outputs import atomic_file
from generator.io.telemetry_csv import read_telemetry
from generator.io.unit import Unit
from generator.io.unitfile import load_unit


# ---- raw inputs of the chain from telemetry --------------------------------------------


def chain_inputs(tel: Telemetry, spec: ChainSpec, sensor_name: str,
                 coils_off: bool = False, aux_off: bool = False) -> dict:
    """Raw counts, temperature and currents of one sensor as the flight API takes them.

    A column the chain needs (coil current, channel, body rate) that the file lacks is
    InputError: never assumed 0. coils_off=True: the caller knows the data were recorded
    with the magnetorquers off, so absent coil columns are 0 A (cells still count);
    aux_off=True: likewise for the chain's telemetry channels and body rates (a heater
    never on, a unit that stood still).

    Returns raw_counts (N, 6|3) int64 (a physical-input sensor: its readings, float64 in
    its input unit; HostUnit rounds them once to the flight float type, as the reference
    does), temp_C (N,) (zeros for a sensor with no temperature, which the chain ignores),
    coil_A (N, ncoil) or None, and present (N,) bool: False where a needed cell is
    missing (those rows are not run through the chain: a missing value is not a number
    the flight code would see).
    """
    s = spec.unit.sensor(sensor_name)
    if s.set_reset:
        cols = [f"{s.name}_set_{a}" for a in "xyz"] + [f"{s.name}_reset_{a}" for a in "xyz"]
    else:
        cols = [f"{s.name}_{a}" for a in "xyz"]
    counts = np.stack([tel.columns[c] for c in cols], axis=1)
    temp = tel.columns[f"{s.name}_temp_C"] if s.temperature else np.zeros(tel.n)
    present = np.all(np.isfinite(counts), axis=1) & np.isfinite(temp)
    if is_physical(s):
        raw = np.where(np.isfinite(counts), counts, 0.0)
    else:
        raw = np.where(np.isfinite(counts), counts, s.zero_count).astype(np.int64)
    def optional(names, what, zero_if_absent=False):
        """Columns as (N, k); rows with a missing cell are not present. A column the chain
        needs that the file lacks is bad input: a current or channel is never assumed 0."""
        nonlocal present
        if not names:
            return None
        if zero_if_absent and not any(c in tel.columns for c in names):
            return np.zeros((tel.n, len(names)))   # the caller states they were 0
        for c in names:
            if c not in tel.columns:
                raise InputError(tel.path, f"missing from the header: the chain of sensor "
                                           f"'{s.name}' needs this {what} (it is never "
                                           "assumed to be 0)", column=c)
        cols = np.stack([tel.columns[c] for c in names], axis=1)
        present &= np.all(np.isfinite(cols), axis=1)
        return np.where(np.isfinite(cols), cols, 0.0)

    o = spec.opts(s)
    coil = optional(list(spec.coils), "magnetorquer current", zero_if_absent=coils_off)
    ch = optional(list(o.channels), "telemetry channel", zero_if_absent=aux_off)
    channels = {c: ch[:, k] for k, c in enumerate(o.channels)} if ch is not None else None
    rate = optional(["rate_x_dps", "rate_y_dps", "rate_z_dps"] if o.sr_compensation else [],
                    "body rate", zero_if_absent=aux_off)
    dt = None
    if o.thermal_lag:
        t = tel.time_s
        dt = np.diff(t, prepend=t[0])
    return {"raw_counts": raw, "temp_C": np.where(np.isfinite(temp), temp, 0.0),
            "coil_A": coil, "channels": channels, "rate_dps": rate, "dt_s": dt,
            "present": present}


# ---- fit ----------------------------------------------------------------------------------


def _has_ref_vectors(tel: Telemetry) -> bool:
    return tel.has("ref_x_nT", "ref_y_nT", "ref_z_nT")


def fit(unit_path, data_paths, progress=None, method="auto", prior=None,
        accept_misfit=False) -> CoefficientSet:
    """Fit a unit from all the given files jointly.

    * b(T), M(T) per sensor: fit.thermal.fit_unit over every file (reference vectors where
      a file carries them, else magnitudes; coil-driven samples left out); what the data
      do not determine is held at the prior: `prior` (path of a coefficients.json, a ground
      calibration with its 1-sigma) or else the part's nominal;
    * coil coupling K: from files whose magnetorquer currents step (fit_coils);
    * boom alignment H: from a file recorded with the boom deployed, i.e. one without
      reference vectors (the jig campaigns carry them with the boom stowed), by Wahba
      between the reference body sensor and the boom MMC5883 (fit_alignment); checked to
      be a rotation.
    Every calibration passes fit.sanity before anything is written (InputError if not);
    a reference-vector fit far beyond the noise floor (fit.goodness: most often a
    reference in another frame) is InputError unless accept_misfit.
    fit_info["set_reset_compensation"]: per sensor whether the chain compensates the
    SET/RESET rotation error with the gyro, and why; where enabled, the chain has the
    sr_compensation option (SensorOptions) with c = sr_comp_s_per_deg of the decision; the
    decision is taken before the fit and M is fitted to the compensated chain output
    (fit.setreset_fit), so a steady turn's rotation error is removed once.
    `prior` must be a calibration of these sensors (fit.prior_unit: same part, frame, axes,
    input; another unit id only when every sensor is so): else InputError naming the key.
    uncertainty_1sigma also carries sr_comp_s_per_deg and, per boom sensor, H_boom_to_body.
    """
    from generator.fit.alignment import align_boom
    from generator.fit.coils import coil_columns, fit_coils, has_coil_steps
    from generator.fit.sanity import check_rotation
    from generator.fit.scale_check import check_reading_scale
    from generator.io.names import column_fault
    from generator.fit.thermal import fit_unit

    def _load_prior(path, unit) -> dict:
        """{sensor: reference.Prior} from a coefficients.json (values and uncertainty_1sigma;
        a coefficient without a 1-sigma keeps the part's)."""
        from generator.fit.prior_unit import check_prior_unit
        from generator.fit.reference import Prior, nominal_prior

        try:
            cs = CoefficientSet.load(path)
        except InputError:
            raise
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise InputError(path, f"--prior: not a readable coefficients.json ({e})") from None
        for note in check_prior_unit(cs.unit, unit, path):
            progress(note)
        out = {}
        for s in unit.sensors:
            if s.name not in cs.sensors:
                continue
            v = cs.sensors[s.name]
            b, M = np.asarray(v["b_poly_nT"], float), np.asarray(v["M_poly"], float)
            if abs(float(v["t_ref_C"]) - 25.0) > 1e-9:
                raise InputError(path, f"--prior: sensor '{s.name}' has t_ref_C "
                                       f"{float(v['t_ref_C'])}, the fit uses 25")
            u = cs.uncertainty.get(s.name, {})
            nom = nominal_prior(b.shape[0] - 1)
            bs = np.asarray(u.get("b_poly_nT", nom.b_sigma_nT), float)
            Ms = np.asarray(u.get("M_poly", nom.M_sigma), float)
            out[s.name] = Prior(b, M, bs, Ms, f"{path} (sensor {s.name})")
        return out

    progress = progress or Progress(quiet=True)
    unit = load_unit(unit_path)
    progress(f"unit {unit.id}: {len(unit.sensors)} sensors")
    priors = _load_prior(prior, unit) if prior else None
    tels = []
    for p in data_paths:
        tel = read_telemetry(p, unit)
        progress(f"read {p}: {tel.n} samples, {len(tel.columns)} columns")
        tels.append(tel)
    for t in tels:          # coil names reach the flight C: C identifiers only, checked first
        for c in coil_columns(t):
            fault = column_fault(c)
            if fault:
                raise InputError(t.path, f"header: coil column {fault}")
    check_reading_scale(unit, tels)   # a wrong lsb_nT or input is not a calibration
    cals = fit_unit(unit, tels, progress=progress, method=method, prior=priors,
                    accept_misfit=accept_misfit)
    info = {"sources": [str(p) for p in data_paths], "unit_file": str(unit_path),
            "method": method, "notes": [],
            "prior": str(prior) if prior else "part nominal (M = I, b = 0, "
                                                "generator.fit.reference.PART_PRIOR_SIGMA)",
            "set_reset_compensation": {n: c.stats.get("set_reset_compensation")
                                       for n, c in cals.items()}}
    sr_opts, sr_values = {}, {}
    for n, c in cals.items():
        sr = c.stats.get("set_reset_compensation") or {}
        if sr.get("enabled"):
            sr_opts[n] = SensorOptions(sr_compensation=True)
            sr_values[n] = {"sr_comp_s_per_deg": sr["sr_comp_s_per_deg"]}
            progress(f"{n}: SET/RESET gyro compensation in the chain: {sr['why']}")

    K, coils = None, ()
    coil_tels = [t for t in tels if has_coil_steps(t)]
    if coil_tels:
        cf = fit_coils(unit, coil_tels)
        K, coils = cf.K(), tuple(cf.coils)
        info["coils"] = cf.to_dict()
        progress(f"coil coupling K from {', '.join(t.path for t in coil_tels)}")

    H = None
    if any(s.frame == "boom" for s in unit.sensors):
        deployed = [t for t in tels if not _has_ref_vectors(t)]
        if deployed and unit.boom_reference:
            al = align_boom(unit, deployed[0], cals, coil_K_nT_per_A=K)
            H = al.H
            info["alignment"] = {"source": deployed[0].path, **al.result.to_dict(),
                                 "notes": list(al.notes),
                                 "sanity": check_rotation(H, source=deployed[0].path)}
            progress(f"boom alignment H from {deployed[0].path}: {al.result.angle_deg:.3f} "
                     f"+- {al.result.sigma_angle_deg:.3f} deg")
        elif not unit.boom_reference:
            info["notes"].append("the unit file names no [boom] reference sensor: nothing "
                                 "to align the boom sensors to, H is the identity")
        else:
            info["notes"].append("no campaign with the boom deployed (one without reference "
                                 "vectors): H is the identity")
        if H is None:
            progress(info["notes"][-1])
    cs = CoefficientSet.from_calibrations(unit, cals, H_boom_to_body=H, K_nT_per_A=K,
                                          coils=coils, fit_info=info,
                                          sensor_options=sr_opts, option_values=sr_values)
    # 1-sigma of the blocks fitted here, not by the sensor fits: c of the SET/RESET
    # compensation (setreset.compensation_decision) and H (per boom sensor: its chain
    # uses H; from the alignment's rotation covariance)
    for n, c in cals.items():
        sr = c.stats.get("set_reset_compensation") or {}
        if n in sr_values and sr.get("sr_comp_sigma_s_per_deg") is not None:
            cs.uncertainty.setdefault(n, {})["sr_comp_s_per_deg"] = np.array(
                float(sr["sr_comp_sigma_s_per_deg"]))
    if H is not None:
        sH = rotation_sigma(H, al.result.cov_rad2)
        for s in unit.sensors:
            if s.frame == "boom":
                cs.uncertainty.setdefault(s.name, {})["H_boom_to_body"] = sH
    return cs


def rotation_sigma(H, cov_rad2) -> np.ndarray:
    """1-sigma of each element of H = exp([d]x) H_true for a small rotation error d
    (body axes) of covariance cov_rad2: dH = [d]x H, first order."""
    H = np.asarray(H, float)
    J = []
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1.0
        Kx = np.array([[0, -e[2], e[1]], [e[2], 0, -e[0]], [-e[1], e[0], 0]])
        J.append(Kx @ H)
    J = np.stack(J)                                    # (3, 3, 3): d H / d d_k
    var = np.einsum("kij,kl,lij->ij", J, np.asarray(cov_rad2, float), J)
    return np.sqrt(np.maximum(var, 0.0))


# ---- apply --------------------------------------------------------------------------------


def apply(cs: CoefficientSet, data_path, out_path, host=None, progress=None,
          coils_off=False, at_rest=False) -> dict:
    """Correct a telemetry file through the compiled flight C; write the ICD output CSV.
    coils_off: the data were recorded with the magnetorquers off; at_rest: standing still,
    absent rate and channel columns are 0 (see chain_inputs, aux_off).

    Returns per-sensor outputs (field_body_nT, status, valid) for callers and tests.
    """
    from generator.flight.host import HostUnit

    progress = progress or Progress(quiet=True)
    tel = read_telemetry(data_path, cs.unit)
    host = host or HostUnit(cs)
    results = {}
    for s in cs.unit.sensors:
        inp = chain_inputs(tel, cs.spec, s.name, coils_off=coils_off, aux_off=at_rest)
        out = host.correct(s.name, inp["raw_counts"], inp["temp_C"], inp["coil_A"],
                           channels=inp["channels"], rate_dps=inp["rate_dps"],
                           dt_s=inp["dt_s"])
        results[s.name] = {"field_body_nT": out["field_body_nT"], "status": out["status"],
                           "present": inp["present"]}
    # cross-check and selection for the attitude system, through the flight C
    fields = np.stack([results[s.name]["field_body_nT"] for s in cs.unit.sensors], axis=1)
    statuses = np.stack([np.where(results[s.name]["present"], results[s.name]["status"],
                                  STATUS_ABSENT) for s in cs.unit.sensors], axis=1)
    sel = host.select(fields, statuses)
    for k, s in enumerate(cs.unit.sensors):
        r = results[s.name]
        # a sample missing from the file carries the ABSENT bit; valid: no status bit but
        # the informational TEMP_EXTRAPOLATED (chain.is_valid)
        r["status"] = np.where(r["present"], sel["status"][:, k],
                               np.asarray(r["status"], dtype=np.uint16) | STATUS_ABSENT)
        r["valid"] = is_valid(r["status"]) & r["present"]
        progress(f"{s.name}: {int(r['valid'].sum())} of {tel.n} samples valid")
    results["selected"] = sel
    results["fallback_order"] = cs.spec.fallback_order()
    write_apply_csv(out_path, tel, cs.unit, results)
    return results


# status given to the selection for a sensor whose sample is missing from the file
STATUS_ABSENT = 0x8000


def write_apply_csv(out_path, tel: Telemetry, unit: Unit, results: dict):
    """ICD columns (time_s, <s>_x/y/z_nT, <s>_valid) plus, compatibly, <s>_status and the
    selected vector for the attitude system (sel_x/y/z_nT, sel_sensor, sel_reason)."""
    from generator.flight.chain import SELECT_REASONS

    header = ["time_s"]
    for s in unit.sensors:
        header += [f"{s.name}_x_nT", f"{s.name}_y_nT", f"{s.name}_z_nT", f"{s.name}_valid",
                   f"{s.name}_status"]
    header += ["sel_x_nT", "sel_y_nT", "sel_z_nT", "sel_sensor", "sel_reason"]
    reasons = {v: k for k, v in SELECT_REASONS.items()}
    names = [s.name for s in unit.sensors]
    sel = results["selected"]
    with atomic_file(out_path, "w", newline="") as f:
        f.write(f"# magcal apply: calibrated field in the body frame, from {tel.path}\n")
        f.write("# <s>_status: bits " + " ".join(f"{k}={v}" for k, v in STATUS_BITS.items())
                + f" ABSENT={STATUS_ABSENT}; valid = no bit but TEMP_EXTRAPOLATED\n")
        f.write("# sel_*: the vector for attitude control (fallback order "
                + " > ".join(names[i] for i in results["fallback_order"]) + ")\n")
        w = csv.writer(f, lineterminator="\n")
        w.writerow(header)
        t = tel.time_s
        cols = []
        for s in unit.sensors:
            r = results[s.name]
            cols.append((r["field_body_nT"], r["valid"], r["status"], r["present"]))
        for i in range(tel.n):
            row = [_fmt(t[i])]
            for field, valid, status, present in cols:
                if present[i]:
                    row += [_fmt(field[i, 0]), _fmt(field[i, 1]), _fmt(field[i, 2])]
                else:
                    row += ["", "", ""]
                row += ["1" if valid[i] else "0", str(int(status[i]))]
            k = int(sel["sensor"][i])
            if k >= 0:
                row += [_fmt(sel["field_body_nT"][i, 0]), _fmt(sel["field_body_nT"][i, 1]),
                        _fmt(sel["field_body_nT"][i, 2]), names[k]]
            else:
                row += ["", "", "", ""]
            row.append(reasons[int(sel["reason"][i])])
            w.writerow(row)


def _fmt(v) -> str:
    # shortest repr that round-trips the value (float32 outputs stay exact)
    return str(v.item() if hasattr(v, "item") else v) if np.isfinite(v) else ""


__all__ = ["Progress", "chain_inputs", "fit", "apply", "write_apply_csv", "InputError"]
