"""The verbs' work, callable from Python: fit, apply, generate (the CLI is a thin shell)."""

from __future__ import annotations

import dataclasses

import numpy as np

from generator.flight.chain import STATUS_BITS, ChainSpec, SensorOptions, is_physical, is_valid
from generator.flight.coeffs import CoefficientSet
from generator.errors import InputError
from generator.progress import Progress
from generator.io.telemetry import Telemetry
from generator.io.outputs import atomic_file
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
    kch = list(o.kernel_channels)          # the channels, then the lagged ones
    ch = optional(kch, "telemetry channel", zero_if_absent=aux_off)
    channels = {c: ch[:, k] for k, c in enumerate(kch)} if ch is not None else None
    rate = optional(["rate_x_dps", "rate_y_dps", "rate_z_dps"] if o.sr_compensation else [],
                    "body rate", zero_if_absent=aux_off)
    dt = None
    if o.thermal_lag or o.lagged_channels:      # the filters advance by the time step
        t = tel.time_s
        dt = np.diff(t, prepend=t[0])
    return {"raw_counts": raw, "temp_C": np.where(np.isfinite(temp), temp, 0.0),
            "coil_A": coil, "channels": channels, "rate_dps": rate, "dt_s": dt,
            "present": present}


# ---- fit ----------------------------------------------------------------------------------


def _has_ref_vectors(tel: Telemetry) -> bool:
    return tel.has("ref_x_nT", "ref_y_nT", "ref_z_nT")


def fit(unit_path, data_paths, progress=None, method="auto", prior=None,
        accept_misfit=False, max_samples=None, max_rows=None) -> CoefficientSet:
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
    max_samples: the most usable samples a sensor's fit takes (None: the default cap
    fit.samples.MAX_FIT_SAMPLES; 0: all): above it a systematic random subsample, said in
    the sensor's notes and per-file "fit_samples" (fit.thermal.fit_sensor).
    max_rows: the most rows the fit reads (None: fit.read_cap.read_cap_rows; 0: every
    row): above it blocks of consecutive rows drawn at random, the residual over every
    row checked after the fit (fit.read_cap).
    """
    from generator.fit.alignment import align_boom
    from generator.fit.coils import coil_columns, fit_coils, has_coil_steps
    from generator.fit.sanity import check_rotation
    from generator.fit.scale_check import check_reading_scale
    from generator.io.full_scale import check_full_scale
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
            # a sensor without temperature (temperature = false) has a constant model and
            # no t_ref_C in its block: nothing to check
            if "t_ref_C" in v and abs(float(v["t_ref_C"]) - 25.0) > 1e-9:
                raise InputError(path, f"--prior: sensor '{s.name}' has t_ref_C "
                                       f"{float(v['t_ref_C'])}, the fit uses 25")
            u = cs.uncertainty.get(s.name, {})
            nom = nominal_prior(b.shape[0] - 1)
            bs = np.asarray(u.get("b_poly_nT", nom.b_sigma_nT), float)
            Ms = np.asarray(u.get("M_poly", nom.M_sigma), float)
            rng = ((float(v["t_min_C"]), float(v["t_max_C"]))
                   if "t_min_C" in v and "t_max_C" in v else None)
            out[s.name] = Prior(b, M, bs, Ms, f"{path} (sensor {s.name})", rng)
        return out

    from generator.fit.samples import MAX_FIT_SAMPLES, check_max_samples
    max_samples = check_max_samples(MAX_FIT_SAMPLES if max_samples is None else max_samples,
                                    "--max-samples")
    progress = progress or Progress(quiet=True)
    from generator.io.recordings import refuse_repeated_recordings
    refuse_repeated_recordings(data_paths)   # each recording counts once
    unit = load_unit(unit_path)
    progress(f"unit {unit.id}: {len(unit.sensors)} sensors")
    priors = _load_prior(prior, unit) if prior else None
    from generator.fit.read_cap import check_every_row, read_for_fit
    # above the read cap, blocks of rows drawn at random (fit.read_cap); else every row
    tels, read_cap = read_for_fit(unit, data_paths, max_samples, progress, max_rows)
    for t in tels:          # coil names reach the flight C: C identifiers only, checked first
        for c in coil_columns(t):
            fault = column_fault(c)
            if fault:
                raise InputError(t.path, f"header: coil column {fault}")
    from generator.io.recordings import repeated_rows_warnings
    from generator.io.telemetry_csv import text_column_notes
    # overlapping recordings: said, not dropped; above the read cap over every row, in the
    # every-row pass (fit.read_cap.check_every_row), not over the blocks read
    repeated = repeated_rows_warnings(tels) if read_cap is None else []
    text_notes = [n for t in tels for n in text_column_notes(t)]   # text columns left out
    for w in repeated + text_notes:
        progress(w)
    check_full_scale(unit, tels)      # every sample beyond full scale: a wrong input unit
    check_reading_scale(unit, tels)   # a wrong lsb_nT or input is not a calibration
    # the settling analysis reads only the files: it runs beside the sensors' fits (in
    # the forked child that finishes its sensors first), its warnings added below; its
    # module imported here, once, not in that child
    import generator.campaign.check  # noqa: F401
    cals, settling = fit_unit(unit, tels, progress=progress, method=method, prior=priors,
                              accept_misfit=accept_misfit, max_samples=max_samples,
                              beside=lambda: _settling_analysis(data_paths, tels, unit))
    info = {"sources": [str(p) for p in data_paths], "unit_file": str(unit_path),
            "method": method, "notes": list(repeated) + text_notes,
            "prior": str(prior) if prior else "part nominal (M = I, b = 0, "
                                                "generator.fit.reference.PART_PRIOR_SIGMA)",
            "set_reset_compensation": {n: c.stats.get("set_reset_compensation")
                                       for n, c in cals.items()}}
    _orbit_notes(unit, tels, cals, info, progress)
    _settling_warnings(settling, cals, info, progress)
    check_every_row(unit, data_paths, cals, read_cap, info, progress)   # above the read cap
    from generator.trace.coefficients import sr_chain_options
    sr_opts, sr_values = sr_chain_options(cals)
    for n in sr_opts:
        progress(f"{n}: SET/RESET gyro compensation in the chain: "
                 f"{cals[n].stats['set_reset_compensation']['why']}")
    if prior:     # the chain on board is fixed: its optional stages stay (values too)
        kept, kept_values = _prior_stages(prior, unit, info, progress)
        for n, o in kept.items():
            if n in sr_opts and not o.sr_compensation:   # the data's own decision stays
                o = dataclasses.replace(o, sr_compensation=True)
                kept_values[n] = {**kept_values[n], **sr_values[n]}
            sr_opts[n], sr_values[n] = o, kept_values[n]

    K, coils = None, ()
    coil_tels = [t for t in tels if has_coil_steps(t)]
    if coil_tels:
        cf = fit_coils(unit, coil_tels)
        K, coils = cf.K(), tuple(cf.coils)
        info["coils"] = cf.to_dict()
        progress(f"coil coupling K from {', '.join(t.path for t in coil_tels)}")

    if K is None and prior:                 # in flight: the ground's coil coupling stays
        K, coils = _prior_coils(prior, unit, info, progress)

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


def _prior_coils(prior, unit, info, progress):
    """(K, coils) of the prior coefficient set when the data step no coil (orbit
    telemetry): the coupling is kept, not dropped (None, () if the prior has none)."""
    cs = CoefficientSet.load(prior)
    if not cs.spec.coils:
        return None, ()
    K = {s.name: np.asarray(cs.sensors[s.name]["K_nT_per_A"], float) for s in unit.sensors
         if s.name in cs.sensors and "K_nT_per_A" in cs.sensors[s.name]}
    if len(K) != len(unit.sensors):
        return None, ()
    info["coils"] = {"source": f"{prior} (the prior: no file steps the magnetorquers)"}
    progress(f"coil coupling K kept from the prior {prior}")
    return K, tuple(cs.spec.coils)


def _prior_stages(prior, unit, info, progress):
    """(sensor_options, option_values) of the prior coefficient set: the flight code on
    board was built for that chain, and a table must match its layout, so a
    recalibration against a prior keeps the prior's optional stages (SET/RESET
    compensation, traced channels, lag, nonlinearity) with their values; only b(T) and
    M(T) (and what the data determine of the rest, elsewhere) are new."""
    cs = CoefficientSet.load(prior)
    opts, values = {}, {}
    for s in unit.sensors:
        if s.name not in cs.sensors:
            continue
        o = cs.spec.opts(s)
        if o == SensorOptions():
            continue
        base = {b.name for b in ChainSpec(unit, poly_degree=cs.spec.poly_degree,
                                          coils=cs.spec.coils).sensor_blocks(s)}
        opts[s.name] = o
        values[s.name] = {b.name: np.asarray(cs.sensors[s.name][b.name], float)
                          for b in cs.spec.sensor_blocks(s) if b.name not in base}
        progress(f"{s.name}: the chain's optional stages kept from the prior ({prior})")
    if opts:
        info["notes"].append(f"optional chain stages kept from the prior {prior} (the "
                             "flight code on board has them): "
                             + ", ".join(sorted(opts)))
    return opts, values


def _orbit_notes(unit, tels, cals, info, progress) -> None:
    """Provenance of a reference computed from the field model (ICD section 4) and, per
    sensor, the floor a calibration against it cannot beat: sqrt(noise^2 + model^2)
    (the sensor's per-axis noise as the fit sees it, the model's |B| error)."""
    from generator.fit.samples import field_noise_nT
    from generator.io.orbit import describe

    for t in tels:          # kp_index beside the file's own ref_norm_nT (io.orbit)
        if "kp_left_out" in t.meta:
            k = t.meta["kp_left_out"]
            info["notes"].append(f"{t.path}: {k['samples']} samples with Kp >= "
                                 f"{k['threshold']:g} left out (kp_index)")
            progress(info["notes"][-1])
    refs = {t.path: t.meta["field_reference"] for t in tels if "field_reference" in t.meta}
    if not refs:
        return
    info["field_reference"] = refs
    info["notes"].extend(f"{p}: {describe(v)}" for p, v in refs.items())
    model = max(v["model_floor_nT"] for v in refs.values())
    duration_s = sum(float(t.time_s[-1] - t.time_s[0]) for t in tels
                     if "field_reference" in t.meta and t.n)
    for s in unit.sensors:
        noise = field_noise_nT(s)
        if noise is None or s.name not in cals:
            continue
        floor = float(np.hypot(noise, model))
        reached = (cals[s.name].stats.get("fit") or {}).get("rms_norm_nT")
        info["notes"].append(
            f"{s.name}: against the field model the |B| residual cannot go below "
            f"~{floor:.0f} nT rms = sqrt(noise {noise:.0f}^2 + model {model:.0f}^2) "
            "(docs/orbit.md)" + (f"; the fit reached {reached:.0f} nT on its own samples"
                                 if reached is not None else ""))
        cals[s.name].stats["field_model_floor_nT"] = floor
        fit = cals[s.name].stats.get("fit") or {}
        if reached is not None and fit.get("n"):
            _floor_warning(s.name, float(reached), int(fit["n"]), noise, model, floor,
                           duration_s, cals[s.name], info, progress)


def _settling_analysis(data_paths, tels, unit) -> dict:
    """campaign.check.settling_warnings on the static-position files (magcal check's own
    analysis, default program): {sensor: warning} for a sensor that reaches a level without
    ever settling there ({} without static-position files). It reads only the files, not
    the fit: fit_unit runs it beside the sensors' fits."""
    from generator.campaign.check import settling_warnings

    static = [(p, t) for p, t in zip(data_paths, tels) if t.get("position") is not None
              and bool(np.any(np.nan_to_num(np.asarray(t.get("position"), float)) > 0))]
    if not static:
        return {}
    return settling_warnings(unit, [p for p, _ in static], tels=[t for _, t in static])


def _settling_warnings(settling, cals, info, progress) -> None:
    """The warnings of _settling_analysis: each in the output, the report's summary and the
    fit's notes. Kept apart from the sanity warnings (stats["campaign_warnings"]): it is
    about the campaign, not the calibration's plausibility, and the calibration is still
    written."""
    for name, w in settling.items():
        if name not in cals:
            continue
        cals[name].stats.setdefault("campaign_warnings", []).append(w)
        info["notes"].append(f"WARNING: {name}: {w}")
        progress(f"WARNING: {name}: {w}")


def _floor_warning(name, reached, n, noise, model, floor, duration_s, cal, info,
                   progress) -> None:
    """fit.floor_check on one sensor: a residual well beyond the floor is a warning in the
    output, the report's summary (sanity warnings) and the coefficients.json notes."""
    from generator.fit.floor_check import floor_check, floor_warning

    chk = floor_check(reached, n, noise, model, duration_s)
    cal.stats["field_model_floor_check"] = chk
    if not chk["flagged"]:
        return
    w = floor_warning(name, reached, floor, chk)
    cal.stats.setdefault("sanity", {}).setdefault("warnings", []).append(w)
    cal.stats.setdefault("notes", []).append(w)
    info["notes"].append("WARNING: " + w)
    progress(f"WARNING: {w}")


# ---- apply --------------------------------------------------------------------------------


# seconds of wall time between two progress lines of a long apply (not one per chunk)
PROGRESS_EVERY_S = 5.0
# output names written as Parquet (any other name: CSV, as ever)
PARQUET_SUFFIXES = (".parquet", ".pq")


def apply(cs: CoefficientSet, data_path, out_path, host=None, progress=None,
          coils_off=False, at_rest=False, collect=True, chunk_bytes=None,
          progress_every_s=None, clock=None) -> dict:
    """Correct a telemetry file through the compiled flight C; write the ICD output: a CSV,
    or a Parquet file of the same columns when out_path ends in .parquet or .pq.
    coils_off: the data were recorded with the magnetorquers off; at_rest: standing still,
    absent rate and channel columns are 0 (see chain_inputs, aux_off).

    The file streams through in chunks (io.telemetry_csv.iter_telemetry, about
    chunk_bytes of text each): each chunk is validated, corrected by the flight C on whole
    arrays (each sensor's chain state carried from chunk to chunk, so the calls are the
    same sequence as one batch over the file) and written (Parquet: in row groups of
    _ParquetOutput.ROW_GROUP_ROWS);
    the output file appears only when the whole input was good (atomic_file). Memory is
    bounded by the chunk size when collect=False. A progress line every progress_every_s
    (default PROGRESS_EVERY_S) seconds of clock() (time.monotonic) tells the rows done.

    Returns per-sensor outputs (field_body_nT, status, valid, present) for callers and
    tests, with "selected" and "fallback_order"; collect=False (the command line): only
    {"n": samples, "n_valid": {sensor: count}}.
    """
    from generator.flight.host import HostUnit
    from generator.io.telemetry_csv import CHUNK_BYTES, TEXT_COLUMNS_KEY, iter_telemetry

    progress = progress or Progress(quiet=True)
    host = host or HostUnit(cs)
    names = [s.name for s in cs.unit.sensors]
    states = {n: host.new_state(n) for n in names}
    n_valid = dict.fromkeys(names, 0)
    pieces, n, prev_t = [], 0, None
    text_columns = {}
    ticker = _RowsProgress(progress, data_path, PROGRESS_EVERY_S if progress_every_s is None
                           else progress_every_s, clock)
    out_class = _ParquetOutput if is_parquet_name(out_path) else _CsvOutput
    with atomic_file(out_path, "wb") as f:
        out = out_class(f, cs.unit, cs.spec.fallback_order())
        try:
            for tel in iter_telemetry(data_path, cs.unit,
                                      chunk_bytes=chunk_bytes or CHUNK_BYTES):
                res = _apply_chunk(cs, host, tel, states, prev_t, coils_off, at_rest)
                out.write(tel.path, tel.time_s, res)
                for name in names:
                    n_valid[name] += int(res[name]["valid"].sum())
                n += tel.n
                text_columns.update(tel.meta.get(TEXT_COLUMNS_KEY) or {})
                if tel.n:
                    prev_t = float(tel.time_s[-1])
                if collect:
                    pieces.append(res)
                ticker(n)
            out.close()
        except BaseException:
            out.abort()
            raise
    if text_columns:        # columns the chain does not read, not numbers: left out
        progress(f"{data_path}: " + "; ".join(text_columns.values()))
    for name in names:
        progress(f"{name}: {n_valid[name]} of {n} samples valid")
    progress(f"wrote {out_path}: {out.FORMAT}, {n:,} rows")
    if not collect:
        return {"n": n, "n_valid": n_valid}
    results = {name: {k: np.concatenate([p[name][k] for p in pieces])
                      for k in pieces[0][name]} for name in names}
    results["selected"] = {k: np.concatenate([p["selected"][k] for p in pieces])
                           for k in pieces[0]["selected"]}
    results["fallback_order"] = cs.spec.fallback_order()
    return results


def is_parquet_name(path) -> bool:
    """Is `path` an output to write as Parquet (its name ends in .parquet or .pq)?"""
    return str(path).lower().endswith(PARQUET_SUFFIXES)


class _RowsProgress:
    """'apply: 1,200,000 of ~3,000,000 rows (40 %)' at most once every every_s seconds of
    clock(). The total is io.telemetry_csv._rows_at_most (an upper bound: '~'), counted
    only when the first line is due (a short run never reads the file twice) and never
    when progress is quiet."""

    def __init__(self, progress, data_path, every_s, clock=None):
        from generator.progress import Every

        self.progress, self.data_path = progress, data_path
        self.due = Every(every_s, clock) if clock is not None else Every(every_s)
        self.quiet = bool(getattr(progress, "quiet", False))
        self.total = False                    # not counted yet (None: cannot be told)

    def __call__(self, rows: int) -> None:
        if self.quiet or not self.due():
            return
        if self.total is False:
            from generator.io.telemetry_csv import _rows_at_most

            self.total = _rows_at_most(self.data_path)
        if self.total:
            total = max(self.total, rows)
            self.progress(f"apply: {rows:,} of ~{total:,} rows "
                          f"({100.0 * rows / total:.0f} %)")
        else:
            self.progress(f"apply: {rows:,} rows")


def _apply_chunk(cs, host, tel: Telemetry, states: dict, prev_t, coils_off, at_rest) -> dict:
    """One chunk through the flight C: every sensor's chain on its carried state, then the
    cross-check and selection for the attitude system."""
    results = {}
    for s in cs.unit.sensors:
        inp = chain_inputs(tel, cs.spec, s.name, coils_off=coils_off, aux_off=at_rest)
        if inp["dt_s"] is not None and prev_t is not None and tel.n:
            inp["dt_s"][0] = tel.time_s[0] - prev_t      # the step from the last chunk
        out = host.correct(s.name, inp["raw_counts"], inp["temp_C"], inp["coil_A"],
                           channels=inp["channels"], rate_dps=inp["rate_dps"],
                           dt_s=inp["dt_s"], state=states[s.name])
        results[s.name] = {"field_body_nT": out["field_body_nT"], "status": out["status"],
                           "present": inp["present"]}
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
    results["selected"] = sel
    return results


# status given to the selection for a sensor whose sample is missing from the file
STATUS_ABSENT = 0x8000


def _apply_header(unit: Unit) -> list:
    header = ["time_s"]
    for s in unit.sensors:
        header += [f"{s.name}_x_nT", f"{s.name}_y_nT", f"{s.name}_z_nT", f"{s.name}_valid",
                   f"{s.name}_status"]
    return header + ["sel_x_nT", "sel_y_nT", "sel_z_nT", "sel_sensor", "sel_reason"]


def _apply_comments(source, unit: Unit, fallback_order) -> list:
    """The output's notes, each 'key: text': the CSV's comment lines (after '# '), the
    Parquet file's key-value metadata."""
    names = [s.name for s in unit.sensors]
    return [f"magcal apply: calibrated field in the body frame, from {source}",
            "<s>_status: bits " + " ".join(f"{k}={v}" for k, v in STATUS_BITS.items())
            + f" ABSENT={STATUS_ABSENT}; valid = no bit but TEMP_EXTRAPOLATED",
            "sel_*: the vector for attitude control (fallback order "
            + " > ".join(names[i] for i in fallback_order) + ")"]


def _apply_preamble(source, unit: Unit, fallback_order) -> str:
    """The comment lines and the header line of the output CSV."""
    return ("".join(f"# {c}\n" for c in _apply_comments(source, unit, fallback_order))
            + ",".join(_apply_header(unit)) + "\n")


def _apply_columns(time_s, unit: Unit, results: dict) -> list:
    """The output's columns in header order, each ("float", float64 values, present or
    None) -- missing where not present or not finite --, ("int", values, numpy integer
    type of the Parquet column) or ("str", pyarrow string array, None)."""
    from generator.flight.chain import SELECT_REASONS
    from generator.io.arrow_np import int64_array, string_array

    cols = [("float", time_s, None)]
    for s in unit.sensors:
        r = results[s.name]
        for k in range(3):
            cols.append(("float", r["field_body_nT"][:, k], r["present"]))
        cols += [("int", r["valid"], np.int8), ("int", r["status"], np.uint16)]
    sel = results["selected"]
    k_sel = np.asarray(sel["sensor"], dtype=np.int64)
    chosen = k_sel >= 0
    for k in range(3):
        cols.append(("float", sel["field_body_nT"][:, k], chosen))
    names = string_array([s.name for s in unit.sensors])
    cols.append(("str", names.take(int64_array(np.where(chosen, k_sel, 0), valid=chosen)),
                 None))
    by_value = {v: k for k, v in SELECT_REASONS.items()}
    reason = np.asarray(sel["reason"], dtype=np.int64)
    unknown = sorted(set(np.unique(reason).tolist()) - set(by_value))
    if unknown:
        raise RuntimeError(f"select returned reason {unknown[0]}, not in SELECT_REASONS")
    lut = string_array([by_value.get(i) for i in range(max(by_value) + 1)])
    cols.append(("str", lut.take(int64_array(reason)), None))
    return cols


def _apply_rows(time_s, unit: Unit, results: dict) -> memoryview:
    """The data rows of the output CSV, formatted column by column (io.outputs: every
    float as repr(float(v)), missing values as empty cells)."""
    from generator.io.outputs import csv_lines, float_cells, int_cells

    cells = {"float": lambda v, present: float_cells(v, present),
             "int": lambda v, _: int_cells(v), "str": lambda v, _: v}
    return csv_lines([cells[kind](v, extra) for kind, v, extra in
                      _apply_columns(time_s, unit, results)])


def _apply_batch(columns, schema):
    """One chunk's _apply_columns as a pyarrow RecordBatch of the Parquet output's schema:
    the values the CSV's cells read back as (a float64: the float32 result widened
    exactly, as repr writes it; null where the CSV cell is empty), integers as integers."""
    import pyarrow as pa

    from generator.io.arrow_np import float64_array

    arrays = []
    for kind, v, extra in columns:
        if kind == "float":
            with np.errstate(invalid="ignore"):         # a signalling NaN stays a NaN
                x = np.asarray(v, dtype=np.float64)
            ok = np.isfinite(x)
            if extra is not None:
                ok &= np.asarray(extra, dtype=bool)
            arrays.append(float64_array(x, ok))
        elif kind == "int":
            arrays.append(pa.array(np.asarray(v).astype(extra)))
        else:
            arrays.append(v)
    return pa.RecordBatch.from_arrays(arrays, schema=schema)


def _apply_schema(columns, source, unit: Unit, fallback_order):
    """The Parquet output's schema: the CSV's column names, a type per column kind of
    _apply_columns; the CSV's comment lines as key-value metadata ('key: text')."""
    import pyarrow as pa

    types = {"float": pa.float64(), "str": pa.string()}
    fields = [pa.field(name, pa.from_numpy_dtype(np.dtype(extra)) if kind == "int"
                       else types[kind])
              for name, (kind, _, extra) in zip(_apply_header(unit), columns)]
    meta = dict(c.split(": ", 1) for c in _apply_comments(source, unit, fallback_order))
    return pa.schema(fields, metadata=meta)


class _CsvOutput:
    """The apply output as CSV text into an open binary file: the preamble before the
    first chunk's rows."""

    FORMAT = "CSV"

    def __init__(self, f, unit: Unit, fallback_order):
        self.f, self.unit, self.fallback_order = f, unit, fallback_order
        self.started = False

    def write(self, source, time_s, results) -> None:
        if not self.started:
            self.started = True
            self.f.write(_apply_preamble(source, self.unit, self.fallback_order).encode())
        self.f.write(_apply_rows(time_s, self.unit, results))

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass


class _ParquetOutput:
    """The apply output as Parquet into an open binary file (pyarrow ParquetWriter), in
    row groups of ROW_GROUP_ROWS rows (the last one shorter): the chunks' columns wait
    until a row group is full, so memory holds at most a row group and a chunk, whatever
    the file's length. (A row group per chunk would be small -- ~13,000 rows of the
    default chunk -- and the footer the writer keeps, a few KiB per row group, would grow
    with the file: 31 MiB more from 2x10^5 to 10^6 rows in 256 KiB chunks.)"""

    FORMAT = "Parquet"
    # 2^16 rows: ~16 MiB of the fm1 unit's 31 columns as float64; a footer entry per 2^16
    # rows, as common writers make them (bench/bench_io.write_long_parquet)
    ROW_GROUP_ROWS = 1 << 16

    def __init__(self, f, unit: Unit, fallback_order):
        self.f, self.unit, self.fallback_order = f, unit, fallback_order
        self.writer = self.schema = None
        self.pending, self.rows = [], 0

    def write(self, source, time_s, results) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        columns = _apply_columns(time_s, self.unit, results)
        if self.writer is None:          # the first chunk (there is one, maybe empty)
            self.schema = _apply_schema(columns, source, self.unit, self.fallback_order)
            self.writer = pq.ParquetWriter(self.f, self.schema)
        if not len(time_s):
            return
        self.pending.append(_apply_batch(columns, self.schema))
        self.rows += len(time_s)
        while self.rows >= self.ROW_GROUP_ROWS:
            table = pa.Table.from_batches(self.pending, schema=self.schema)
            self.writer.write_table(table.slice(0, self.ROW_GROUP_ROWS),
                                    row_group_size=self.ROW_GROUP_ROWS)
            rest = table.slice(self.ROW_GROUP_ROWS)
            self.pending, self.rows = rest.to_batches(), rest.num_rows

    def close(self) -> None:
        """Write the last row group and the footer (the file is complete once atomic_file
        has renamed it)."""
        import pyarrow as pa

        if self.writer is None:
            return
        if self.rows:
            self.writer.write_table(pa.Table.from_batches(self.pending, schema=self.schema),
                                    row_group_size=self.rows)
            self.pending, self.rows = [], 0
        self.writer.close()

    def abort(self) -> None:
        """An error: the file is removed (atomic_file); the writer is closed so that it
        does not write its footer later, into a closed file, when it is collected."""
        if self.writer is not None and self.writer.is_open:
            import contextlib

            with contextlib.suppress(Exception):
                self.writer.close()


def write_apply_csv(out_path, tel: Telemetry, unit: Unit, results: dict):
    """ICD columns (time_s, <s>_x/y/z_nT, <s>_valid) plus, compatibly, <s>_status and the
    selected vector for the attitude system (sel_x/y/z_nT, sel_sensor, sel_reason)."""
    with atomic_file(out_path, "wb") as f:
        f.write(_apply_preamble(tel.path, unit, results["fallback_order"]).encode())
        f.write(_apply_rows(tel.time_s, unit, results))


__all__ = ["Progress", "chain_inputs", "fit", "apply", "write_apply_csv", "InputError"]
