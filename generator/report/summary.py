"""The report's first section: per sensor what an attitude engineer asks first, and the
verdict against the unit's [requirements] (ICD section 4).

Per sensor, over the samples the fit used (generator.campaign.check.gather_samples, the
report's CampaignAnalysis):

* |B| error before and after: RMS of |B~| - |B_ref| (raw, after SET/RESET and the axis
  mapping) and of |M(T)(B~ - b(T))| - |B_ref|;
* angle error before and after: RMS of the angle between the raw / calibrated vector and
  the reference vector, on the samples with reference vectors, for a sensor whose M maps
  to the reference's frame (a magnitude-only fit knows M only up to a rotation: no angle);
* valid fraction: of all rows of the files, those the flight chain keeps valid by their
  inputs: reading present and not saturated, temperature within the calibrated range
  widened by the chain's margin temp_margin_C (docs/chain.md);
* the calibrated temperature range; what was fitted and what held at the prior (the
  reference fit's per-coefficient "data"/"prior" tags, fit stats "observability");
* the reading noise per axis the fit used and where it came from (the unit file, the part
  catalogue's typical figure, or estimated from the data: fit stats noise_goodness);
* warnings (the sanity checks before a calibration is written, the noise-only goodness
  test and the mounting-rotation check, fit.goodness and fit.sanity);
* the predicted calibration error at the unit's field (fit stats "predicted_error": from
  the coefficients' 1-sigma, raised to the fit's residual beyond the reading noise where
  that is larger, and then said so).

Verdict (ICD section 4): field_error_nT is the |B| RMS after calibration, angle_deg the
angle RMS against the reference, per sensor. A sensor meets the requirements when every
requirement that can be assessed holds; one that cannot be assessed (no reference vectors
for the angle) is said so, never counted as met. With no [requirements] the report says so
and gives no verdict.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from generator.report.document import Section, Table, significant


def requirements(cs) -> tuple:
    """({key: value} of [requirements], where they came from). The unit of a fit carries
    them (Unit.extra); a coefficients.json does not, so the unit file the fit names is
    read again."""
    req = ((cs.unit.extra or {}).get("requirements") or {})
    if req:
        return dict(req), "the unit file"
    path = cs.fit_info.get("unit_file")
    if path and Path(path).is_file():
        from generator.errors import InputError
        from generator.io.unitfile import load_unit
        try:
            req = (load_unit(path).extra or {}).get("requirements") or {}
        except InputError as e:
            return {}, f"unit file not readable ({e.message})"
        return dict(req), str(path)
    return {}, "no unit file"


def _angle_deg(a, b) -> np.ndarray:
    cos = np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _rms(x):
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x ** 2))) if x.size else None


def sensor_figures(cs, analysis, name) -> dict:
    """The summary's numbers of one sensor (module docstring)."""
    S = analysis.samples[name]
    v = cs.sensors[name]
    out = {"n": S.n}
    if S.n:
        cal = cs.calibration(name)
        B = cal.apply64(S.x, S.T)
        out["norm_before_nT"] = _rms(np.linalg.norm(S.x, axis=1) - S.norm)
        out["norm_after_nT"] = _rms(np.linalg.norm(B, axis=1) - S.norm)
        # per file: an RMS over every sample can hide one campaign the calibration worsens
        per_file = []
        for f in np.unique(S.file):
            k = S.file == f
            per_file.append({
                "file": str(analysis.tels[int(f)].path) if int(f) < len(analysis.tels)
                else str(int(f)),
                "n": int(k.sum()),
                "norm_before_nT": _rms(np.linalg.norm(S.x[k], axis=1) - S.norm[k]),
                "norm_after_nT": _rms(np.linalg.norm(B[k], axis=1) - S.norm[k])})
        out["per_file"] = per_file
        vec = S.is_vec
        if vec.any() and analysis.body_frame(name):
            out["angle_before_deg"] = _rms(_angle_deg(S.x[vec], S.ref[vec]))
            out["angle_after_deg"] = _rms(_angle_deg(B[vec], S.ref[vec]))
            out["n_angle"] = int(vec.sum())
    # valid fraction over every row of every file
    lo = hi = None
    if "t_min_C" in v:
        margin = float(v.get("temp_margin_C", 0.0))
        lo, hi = float(v["t_min_C"]) - margin, float(v["t_max_C"]) + margin
    total = valid = 0
    for pre in analysis.pres:
        sd = pre.get(name)
        if sd is None:
            continue
        ok = np.asarray(sd.usable, bool) & np.isfinite(sd.field_frame_nT).all(axis=1)
        if lo is not None:
            with np.errstate(invalid="ignore"):
                ok &= (sd.temp_C >= lo) & (sd.temp_C <= hi)
        total += len(ok)
        valid += int(ok.sum())
    out["valid_fraction"] = valid / total if total else None
    out["rows"] = total
    return out


def fitted_vs_prior(cs, name) -> str:
    """What the data determined and what was held at the prior (fit stats)."""
    st = cs.fit_info.get("sensors", {}).get(name, {}).get("stats", {}) or {}
    ob = st.get("observability") or {}
    params = ob.get("parameters") or []
    if params:
        held = [p["name"] for p in params if p.get("source") == "prior"]
        if not held:
            return f"all {len(params)} coefficients from the data"
        return (f"{len(params) - len(held)} of {len(params)} from the data; held at the prior"
                f" ({ob.get('prior_source', 'prior')}): {', '.join(held)}")
    note = ob.get("note") or "not recorded by the fit"
    return note.split(";")[0]


def predicted_line(cs) -> str | None:
    """One paragraph: per sensor the predicted field and angle error (fit stats
    predicted_error), labelled where it was raised to the fit's own residual."""
    parts = []
    for s in cs.unit.sensors:
        st = cs.fit_info.get("sensors", {}).get(s.name, {}).get("stats", {}) or {}
        pe = st.get("predicted_error") or {}
        if pe.get("field_error_nT") is None:
            continue
        txt = f"{s.name} {pe['field_error_nT']:.1f} nT / {pe['angle_error_deg']:.3f} deg"
        if pe.get("raised_to_achieved"):
            txt += (f" (raised to the fit's own residual beyond the reading noise; from the "
                    f"coefficients' 1-sigma alone {pe['field_error_from_sigma_nT']:.1f} nT / "
                    f"{pe['angle_error_from_sigma_deg']:.3f} deg)")
        parts.append(txt)
    if not parts:
        return None
    return ("Predicted calibration error at the unit's field (field / angle, from the "
            "coefficients' 1-sigma, never below the fit's own residual beyond the reading "
            "noise): " + "; ".join(parts) + ".")


def noise_used(spec, stats) -> str:
    """The reading noise per field axis the fit used and where it came from: the noise
    test's figure (fit stats noise_goodness: noise_nT, noise_from; 3 significant digits),
    its source named for a reader: the unit file's noise_nT or the part catalogue's
    typical figure ('stated' before the catalogue was recorded as a source of its own:
    the unit file where it states one, else the catalogue), with what turns a reading's
    figure into a field axis' (the count quantisation, the SET/RESET pair's average); or
    estimated from the data. Any other noise_from is printed as the fit wrote it. '-'
    when the fit ran no noise test and the unit states none."""
    g = (stats or {}).get("noise_goodness") or {}
    noise, src = g.get("noise_nT"), str(g.get("noise_from") or "")
    if noise is None or not np.isfinite(float(noise)) or float(noise) <= 0:
        return "-" if not spec.noise_nT else f"{spec.noise_nT:g} (unit file; no noise test ran)"
    noise = float(noise)
    if src == "stated":
        src = "unit file" if spec.noise_nT else "part catalogue"
    if src == "unit file" or src.startswith("part catalogue"):
        how = [w for w, on in (("with the LSB's quantisation", getattr(spec, "counts", False)),
                               ("averaged over the SET/RESET pair",
                                getattr(spec, "set_reset", False))) if on]
        base = [f"{spec.noise_nT:g} per reading"] if src == "unit file" else []
        detail = ", ".join(base + how)
        src = src.replace(" (", ", ").replace(")", "")     # 'part catalogue, typical
        return f"{significant(noise)} ({src}{': ' + detail if detail else ''})"
    if "difference" in src and not src.startswith("estimated"):
        src = "estimated from " + src
    return f"{significant(noise)} ({src})" if src else significant(noise)


def verdict(fig, req) -> tuple:
    """(verdict text, [reasons]) of one sensor against the requirements."""
    if not req:
        return "no requirements given", []
    fails, unknown = [], []
    lim = req.get("field_error_nT")
    if lim is not None:
        a = fig.get("norm_after_nT")
        if a is None:
            unknown.append("|B| (no samples)")
        elif a > lim:
            fails.append(f"|B| RMS {a:.1f} nT > {lim:g} nT")
        # every file must meet it, not only the RMS over all of them
        for pf in fig.get("per_file") or []:
            if a is not None and a <= lim and pf["norm_after_nT"] > lim:
                fails.append(f"|B| RMS {pf['norm_after_nT']:.1f} nT > {lim:g} nT on "
                             f"{Path(pf['file']).name}")
    lim = req.get("angle_deg")
    if lim is not None:
        a = fig.get("angle_after_deg")
        if a is None:
            unknown.append("angle (no reference vectors in the sensor's frame)")
        elif a > lim:
            fails.append(f"angle RMS {a:.3f} deg > {lim:g} deg")
    if fails:
        return "FAILS", fails + [f"not assessed: {u}" for u in unknown]
    if unknown:
        return "NOT ASSESSED", [f"not assessed: {u}" for u in unknown]
    return "MEETS", []


def summary_section(cs, analysis) -> Section:
    """The first section: per sensor the figures of the module docstring and the verdict."""
    req, src = requirements(cs)
    rows, warn_rows = [], []
    for s in cs.unit.sensors:
        v = cs.sensors[s.name]
        st = cs.fit_info.get("sensors", {}).get(s.name, {}).get("stats", {}) or {}
        if analysis is not None:
            f = sensor_figures(cs, analysis, s.name)
        else:    # no telemetry given to the report: the fit's own residual only
            fit = st.get("fit") or {}
            f = {"norm_after_nT": fit.get("rms_norm_nT")}
        vt, why = verdict(f, req)
        ang = (lambda k: f.get(k))
        rows.append([
            s.name, s.part, noise_used(s, st), f.get("norm_before_nT"), f.get("norm_after_nT"),
            ang("angle_before_deg"), ang("angle_after_deg"),
            f"{100 * f['valid_fraction']:.1f}%" if f.get("valid_fraction") is not None
            else None,
            f"{float(v['t_min_C']):.1f} .. {float(v['t_max_C']):.1f}" if "t_min_C" in v
            else "no temperature",
            fitted_vs_prior(cs, s.name),
            vt + (": " + "; ".join(why) if why else "")])
        for w in (st.get("sanity") or {}).get("warnings", []):
            warn_rows.append([s.name, w])
        for w in st.get("campaign_warnings") or []:       # pipeline._settling_warnings
            warn_rows.append([s.name, f"campaign: {w}"])
        for pf in f.get("per_file") or []:
            if pf["n"] and pf["norm_after_nT"] > pf["norm_before_nT"]:
                warn_rows.append([s.name, (
                    f"the calibration makes |B| worse on {Path(pf['file']).name}: "
                    f"{pf['norm_before_nT']:.1f} nT RMS before, {pf['norm_after_nT']:.1f} "
                    "after (a campaign unlike the others: its reference, frame or "
                    "conditions?)")])
    warn_rows += coil_study_warnings(analysis)
    if req:
        head = ("Requirements from " + src + ": "
                + ", ".join(f"{k} = {v:g}" for k, v in req.items())
                + " (ICD section 4: |B| RMS after calibration and angle RMS against the "
                  "reference, per sensor).")
        met = [r[0] for r in rows if r[-1].startswith("MEETS")]
        failed = [r[0] for r in rows if r[-1].startswith("FAILS")]
        overall = ("Verdict: every sensor meets the requirements." if len(met) == len(rows)
                   else "Verdict: " + (f"{', '.join(failed)} fail(s); " if failed else "")
                   + f"{len(met)} of {len(rows)} sensors meet the requirements.")
    else:
        head = ("No [requirements] in the unit file (" + src + "): the numbers below are not "
                "judged. Add field_error_nT and angle_deg (ICD section 4) for a verdict.")
        overall = "Verdict: none (no requirements given)."
    paras = [overall, head,
             "Before: raw readings (after SET/RESET and the axis mapping); after: the "
             "calibration. |B| and angle over the samples the fit used (reference vectors "
             "for the angle, on sensors whose M maps to the reference's frame). Valid: rows "
             "of all files the flight chain keeps valid by their inputs (present, not "
             "saturated, temperature within the calibrated range plus the chain's margin)."]
    pred = predicted_line(cs)
    if pred:
        paras.append(pred)
    tables = [Table(["sensor", "part", "noise the fit used nT/axis", "|B| RMS before nT",
                     "|B| RMS after nT",
                     "angle RMS before deg", "angle RMS after deg", "valid",
                     "calibrated degC", "fitted / held at the prior", "verdict"], rows,
                    "Per sensor: errors before and after, validity, range, verdict")]
    if warn_rows:
        tables.append(Table(["sensor", "warning"], warn_rows,
                            "Warnings of the fit and of the coil study"))
    else:
        paras.append("Warnings: none (the fit's sanity checks passed for every sensor).")
    return Section("Summary and verdict", paras, tables)


def coil_study_warnings(analysis) -> list:
    """[sensor, warning] rows for the distance laws of a coil study (DistanceLaw.flags):
    points that scatter beyond their errors, and a law the report evaluates outside its
    measured distances -- at 30 cm (the seed's comparison, always), at the seed's 5 and
    15 cm and at each sensor's distance r (the interference table, when a coil campaign
    is given too)."""
    study = analysis.coil_study() if analysis is not None else None
    if study is None:
        return []
    from generator.fit.coils import PANEL_STATE, SEED_POINTS_CM
    inter = None
    if hasattr(analysis, "coil_interference"):
        from generator.errors import InputError
        try:
            inter = analysis.coil_interference(0.1)
        except InputError:     # the interference section says why; the laws still warn
            inter = None
    at = SEED_POINTS_CM if inter is not None else (30.0,)
    out = [[w.sensor, f"coil study, law of {w.coil} {PANEL_STATE[w.panel]}: {f}"]
           for w in study.laws for f in w.flags(*at)]
    for r in (inter[2] if inter is not None else []):
        f = r["law"].extrapolated(r["distance_cm"]) if r["law"] is not None else None
        if f:
            w = r["law"]
            out.append([r["sensor"], f"{r['coil']}: interference at 0.1 A from the law of "
                                     f"{w.sensor} {w.coil} {PANEL_STATE[w.panel]}, {f}"])
    return out
