"""The report of `magcal fit`: summary, coefficients, the seed's figures from the data.

The document model (Report, Section, Table) is generator/report/document.py. Building
blocks for the verbs:

* fit_sections(cs): summary and coefficients (tables only; no data needed);
* CampaignAnalysis(cs, data_paths): the numbers the figures need, computed once from the
  telemetry with the fit's own public functions (segments, levels, per-level fits,
  coefficient covariance from generator.campaign.check.poly_covariance);
* temperature_section(...), rms_section(...): seed 000 fig. 24-25 and 27-29;
* hooks taking plain arrays, for numbers other modules produce: alignment_section
  (fig. 10), setreset_section (fig. 12-13), coil_distance_section (fig. 5-6),
  residual_causes_section (residuals against their traced causes);
* write_fit_report(cs, out_dir, data_paths): the whole `magcal fit` report.

Size: the fit report, section by section (summary, coefficients, temperature, RMS, H,
coils, SET/RESET, inputs); the document model is report/document.py and the figures
report/figures.py.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np


from generator.report.document import Report, Section, Table, pm, resolved, significant
from generator.report.setreset_report import setreset_section  # noqa: F401 (a hook, re-exported)


# =======================================================================================
# Fit summary (tables only)
# =======================================================================================
COEF_NAMES = ("b_x", "b_y", "b_z", "m_xx", "m_xy", "m_xz", "m_yx", "m_yy", "m_yz",
              "m_zx", "m_zy", "m_zz")
COEF_UNITS = ("nT", "nT", "nT") + ("",) * 9


def fit_sections(cs) -> list:
    """Per-sensor summary of a fit: method, range, residuals, coefficients at t_ref."""
    rows = []
    info = cs.fit_info.get("sensors", {})
    for s in cs.unit.sensors:
        v = cs.sensors[s.name]
        st = info.get(s.name, {}).get("stats", {}) or {}
        fitst = st.get("fit", {}) or {}
        held = st.get("holdout", {}) or {}
        chosen = st.get("chosen")
        held_rms = None
        if chosen in held and isinstance(held[chosen], dict):
            held_rms = held[chosen].get("rms_vector_nT") or held[chosen].get("rms_norm_nT")
        rows.append([
            s.name, s.part, s.frame, info.get(s.name, {}).get("method", ""),
            f"{float(v['t_min_C']):.1f} .. {float(v['t_max_C']):.1f}" if s.temperature
            else "none: no temperature (constant model)",
            st.get("samples_used", st.get("n_samples", "")),
            _first(fitst, "rms_vector_nT") if fitst else _first(st, "rms_vector_nT"),
            _first(fitst, "rms_norm_nT") if fitst else _first(st, "rms_norm_nT"),
            held_rms,
        ])
    summary = Section("Fit summary", [
        "Calibration B = M(T)(B~ - b(T)) per sensor, polynomial (up to cubic) in temperature "
        "(seed 000, eq. 5-7). Temperatures outside the calibrated range are clamped and "
        "flagged by the flight code. Residual RMS: vector residual per axis where reference "
        "vectors exist, and of |B|; held-out: of the method chosen."]
        + ([f"No temperature (temperature = false): "
            f"{', '.join(s.name for s in cs.unit.sensors if not s.temperature)}. Their b and "
            "M are constant: no temperature model, no clamp, no temperature flag."]
           if not all(s.temperature for s in cs.unit.sensors) else []),
        [Table(["sensor", "part", "frame", "method", "calibrated range degC", "samples",
                "vector residual RMS nT/axis", "|B| residual RMS nT", "held-out RMS nT"],
               rows, "Fit per sensor")])
    coef = Section("Coefficients at the reference temperature", [
        "1-sigma from the fit's covariance (coefficients.json, uncertainty_1sigma)."])
    for s in cs.unit.sensors:
        v = cs.sensors[s.name]
        u = cs.uncertainty.get(s.name, {})
        b0 = np.asarray(v["b_poly_nT"])[0]
        M0 = np.asarray(v["M_poly"])[0]
        bs = np.asarray(u["b_poly_nT"])[0] if "b_poly_nT" in u else np.full(3, np.nan)
        Ms = np.asarray(u["M_poly"])[0] if "M_poly" in u else np.full((3, 3), np.nan)
        rows = [[ax, pm(b0[i], bs[i])] + [pm(M0[i, j], Ms[i, j]) for j in range(3)]
                for i, ax in enumerate("xyz")]
        coef.tables.append(Table(["axis", "b nT", "M x", "M y", "M z"], rows,
                                 f"{s.name} at {float(v['t_ref_C']):.1f} degC (1-sigma)"
                                 if s.temperature else
                                 f"{s.name}, constant: no temperature (1-sigma)"))
    return [summary, coef]


def _first(d, *keys):
    for k in keys:
        if k in d and d[k] is not None:
            return d[k]
    return ""


def method_section(cs) -> Section | None:
    """The held-out comparison of the temperature models (generator.fit.thermal stats)."""
    rows = []
    for s in cs.unit.sensors:
        st = cs.fit_info.get("sensors", {}).get(s.name, {}).get("stats", {}) or {}
        h = st.get("holdout")
        if not h:
            if st.get("why"):
                rows.append([s.name, "-", None, None, st.get("chosen", ""), st.get("why")])
            continue

        def score(m):
            e = h.get(m)
            if not isinstance(e, dict):
                return None
            return e.get("rms_vector_nT") or e.get("rms_norm_nT")
        scores = {m: score(m) for m in ("joint", "segments")}
        cells, why = _held_out_choice(scores, st.get("chosen", ""), st.get("why", ""))
        rows.append([s.name, h.get("scheme", "")] + cells + [st.get("chosen", ""), why])
    if not rows:
        return None
    return Section("Temperature model: held-out choice", [
        "Two ways to fit the temperature dependence (seed 000 sec. 5): 'segments' calibrates "
        "each constant-temperature level and fits a polynomial through the levels; 'joint' "
        "fits the polynomial model to all samples, ramps included. The one with the smaller "
        "error on held-out data is kept."],
        [Table(["sensor", "held-out scheme", "joint RMS nT", "segments RMS nT", "chosen",
                "why"], rows, "Held-out comparison")])


CHOICE_DECIMALS_MAX = 3      # 0.001 nT: below it two held-out RMS are the same number


def _held_out_choice(scores, chosen, why) -> tuple:
    """(the held-out RMS cells, the why) printed alike: with the decimals that tell the
    scores apart (at least 1, at most CHOICE_DECIMALS_MAX), so the table shows the
    difference the choice was made on; scores equal at that precision are said to tie."""
    got = {m: v for m, v in scores.items() if v is not None}
    if len(got) < 2 or not str(why).startswith("smaller held-out error"):
        return [scores[m] for m in scores], why
    vals = list(got.values())
    d = next((d for d in range(1, CHOICE_DECIMALS_MAX + 1)
              if len({f"{v:.{d}f}" for v in vals}) == len(vals)), CHOICE_DECIMALS_MAX)
    cells = ["-" if v is None else f"{v:.{d}f}" for v in scores.values()]
    listed = ", ".join(f"{m} {v:.{d}f} nT" for m, v in got.items())
    if len({f"{v:.{d}f}" for v in vals}) < len(vals):
        why = (f"a tie within rounding ({listed}: equal to {10.0 ** -d:g} nT); {chosen} "
               "kept")
    else:
        why = f"smaller held-out error: {listed}"
    return cells, why


def polynomial_table(cs, name) -> Table:
    """All polynomial coefficients of one sensor with their 1-sigma."""
    v = cs.sensors[name]
    u = cs.uncertainty.get(name, {})
    b = np.asarray(v["b_poly_nT"], float)
    M = np.asarray(v["M_poly"], float)
    K = b.shape[0]
    bs = np.asarray(u.get("b_poly_nT", np.full_like(b, np.nan)), float)
    Ms = np.asarray(u.get("M_poly", np.full_like(M, np.nan)), float)
    rows = []
    for c, nm in enumerate(COEF_NAMES):
        if c < 3:
            vals = [pm(b[k, c], bs[k, c]) for k in range(K)]
        else:
            i, j = divmod(c - 3, 3)
            vals = [pm(M[k, i, j], Ms[k, i, j]) for k in range(K)]
        rows.append([nm] + vals)
    header = ["coefficient"] + ["A0"] + [f"A{k} per degC" + (f"^{k}" if k > 1 else "")
                                         for k in range(1, K)]
    if "t_ref_C" not in v:   # a sensor with no temperature
        return Table(header, rows, f"{name}: constant coefficients (no temperature), with "
                                   "1-sigma (b in nT, m dimensionless)")
    return Table(header, rows, f"{name}: polynomial coefficients A_k of dT^k, dT = T - "
                               f"{float(v['t_ref_C']):g} degC, with 1-sigma (b in nT/degC^k, "
                               "m in 1/degC^k)")


# =======================================================================================
# Numbers from the campaign (computed once)
# =======================================================================================
MAX_COV_ROWS = 8000     # samples entering the band's covariance (every k-th; see check)


class CampaignAnalysis:
    """The telemetry as the fit used it, and what the report's figures need.

    Per sensor: the samples (generator.campaign.check.gather_samples), temperature levels and
    per-level constant calibrations (reference-vector fit where vectors exist, else the
    ellipsoid fit: the seed's per-segment b_i, m_ij), the covariance of the fitted
    polynomial (its 1-sigma band), and the |B| RMS before / after per level and position.
    """

    def __init__(self, cs, data_paths, progress=None):
        from generator.campaign.check import gather_samples
        from generator.io.telemetry_csv import preprocess, read_telemetry

        say = progress or (lambda m: None)
        self.cs = cs
        self.unit = cs.unit
        self.paths = [str(p) for p in data_paths]
        self.tels = [read_telemetry(p, cs.unit) for p in data_paths]
        self.pres = [preprocess(t, cs.unit) for t in self.tels]
        self.samples = gather_samples(cs.unit, self.tels, self.pres)
        say(f"report: read {len(self.tels)} file(s) again for the figures")
        self.levels = {}
        self.level_fits = {}
        self.dropped = {}
        for s in cs.unit.sensors:
            self._levels(s.name)

    def coil_study(self):
        """The coil study of the input files that are one (fit_coil_study), fitted once
        for every section that shows it; None when no file is a coil study."""
        if not hasattr(self, "_coil_study"):
            from generator.fit.coils import fit_coil_study, is_coil_study
            tels = [t for t in self.tels if is_coil_study(t)]
            self._coil_study = fit_coil_study(self.cs.unit, tels) if tels else None
        return self._coil_study

    def coil_interference(self, current_A=0.1):
        """(coil campaign Telemetry, CoilFit, interference_table rows at current_A with the
        coil study's laws) of the first file whose magnetorquer currents step, fitted once
        for the summary and the interference section; None without such a file."""
        key = ("_coil_interference", float(current_A))
        if key not in self.__dict__:
            from generator.fit.coils import fit_coils, has_coil_steps, interference_table
            tel = next((t for t in self.tels if has_coil_steps(t)), None)
            out = None
            if tel is not None:
                cf = fit_coils(self.cs.unit, [tel])
                out = (tel, cf, interference_table(self.cs.unit, cf, current_A=current_A,
                                                   study=self.coil_study()))
            self.__dict__[key] = out
        return self.__dict__[key]

    # ---- levels and per-level fits ------------------------------------------------------
    def _levels(self, name):
        from generator.campaign.check import level_tolerance_C
        from generator.errors import InputError
        from generator.fit.ellipsoid import ellipsoid_fit
        from generator.fit.thermal import group_levels, reference_fit

        S = self.samples[name]
        segs = [g for g in S.segments if len(g.index)]
        levels = group_levels(segs, level_tolerance_C(S.T)) if segs else []
        self.levels[name] = levels
        fits, dropped = [], []
        for lev in levels:
            idx = np.concatenate([g.index for g in lev])
            temp = float(np.mean(S.T[idx]))
            iv = idx[S.is_vec[idx]]
            try:
                if len(iv):
                    b, M, inf = reference_fit(S.x[iv], S.ref[iv], None)
                    fits.append({"temp_C": temp, "n": int(len(iv)), "b": b[0], "M": M[0],
                                 "b_sig": inf["b_poly_sigma_nT"][0],
                                 "M_sig": inf["M_poly_sigma"][0], "kind": "reference vectors",
                                 "positions": sorted({int(g.position) for g in lev})})
                else:
                    b, M, inf = ellipsoid_fit(S.x[idx], S.norm[idx])
                    fits.append({"temp_C": temp, "n": int(len(idx)), "b": b, "M": M,
                                 "b_sig": inf["b_sigma_nT"], "M_sig": inf["M_sigma"],
                                 "kind": "ellipsoid",
                                 "positions": sorted({int(g.position) for g in lev})})
            except InputError as e:
                dropped.append(f"level {temp:.1f} degC: {e.message}")
        self.level_fits[name] = fits
        self.dropped[name] = dropped

    # ---- fitted polynomial and its band ------------------------------------------------
    def degree(self, name) -> int:
        st = self.cs.fit_info.get("sensors", {}).get(name, {}).get("stats", {}) or {}
        if "degree" in st:
            return int(st["degree"])
        b = np.asarray(self.cs.sensors[name]["b_poly_nT"])
        M = np.asarray(self.cs.sensors[name]["M_poly"])
        nz = [k for k in range(len(b)) if np.any(b[k] != 0) or np.any(M[k] != 0)]
        return max(nz) if nz else 0

    def body_frame(self, name) -> bool:
        info = self.cs.fit_info.get("sensors", {}).get(name, {})
        if "body_frame" in info:
            return bool(info["body_frame"])
        return bool(self.samples[name].is_vec.any())

    def covariance(self, name):
        """PolyCovariance of the fitted coefficients (residual scatter), or None."""
        from generator.campaign.check import poly_covariance
        S = self.samples[name]
        if S.n == 0:
            return None
        v = self.cs.sensors[name]
        deg = self.degree(name)
        # a sensor with no temperature: constant, every sample at dT = 0
        t_ref, t_lo, t_hi = (float(v["t_ref_C"]), float(v["t_min_C"]), float(v["t_max_C"])) \
            if "t_ref_C" in v else (0.0, 0.0, 0.0)
        return poly_covariance(S.x, S.T, S.ref, S.norm, degree=deg,
                               t_range_C=(t_lo, t_hi),
                               b_poly=np.asarray(v["b_poly_nT"])[:deg + 1],
                               M_poly=np.asarray(v["M_poly"])[:deg + 1],
                               body_frame=self.body_frame(name),
                               t_ref_C=t_ref, max_rows=MAX_COV_ROWS)

    # ---- |B| RMS before / after ---------------------------------------------------------
    def rms_groups(self, name):
        """{"temperature": [(label, n, before, after)], "position": [...]}: RMS of
        |B~| - |B| (raw) and |M(T)(B~ - b(T))| - |B| (calibrated), nT."""
        S = self.samples[name]
        if S.n == 0:
            return {"temperature": [], "position": []}
        cal = self.cs.calibration(name)
        before = np.linalg.norm(S.x, axis=1) - S.norm
        after = np.linalg.norm(cal.apply64(S.x, S.T), axis=1) - S.norm

        def rms(m):
            return (int(m.sum()), float(np.sqrt(np.mean(before[m] ** 2))),
                    float(np.sqrt(np.mean(after[m] ** 2))))
        if self.cs.unit.sensor(name).temperature:
            temp = self._temperature_groups(name, S, rms)
        else:    # no temperature (ICD section 4): S.T is the constant model's stand-in,
            # not a reading; a temperature bin of it would be invented: all samples only
            temp = [("all (no temperature)", *rms(np.ones(S.n, bool)))]
        pos = []
        for q in np.unique(S.position):
            m = S.position == q
            pos.append((f"{q}" if q > 0 else "moving", *rms(m)))
        return {"temperature": temp, "position": pos if len(pos) > 1 or
                (len(pos) == 1 and pos[0][0] != "moving") else []}

    def _temperature_groups(self, name, S, rms):
        """Constant-temperature levels (with 'ramps' between them), else 10 degC bins,
        then all samples."""
        temp = []
        in_level = np.zeros(S.n, bool)
        # one level alone is no temperature axis: then 10 degC bins, as with none
        for lev in (self.levels[name] if len(self.levels[name]) >= 2 else []):
            idx = np.concatenate([g.index for g in lev])
            m = np.zeros(S.n, bool)
            m[idx] = True
            in_level |= m
            temp.append((f"{np.mean(S.T[idx]):.1f} degC", *rms(m)))
        if not temp:      # no constant-temperature levels: 10 degC bins
            edges = np.arange(np.floor(S.T.min() / 10) * 10, S.T.max() + 10, 10)
            for a, b in zip(edges[:-1], edges[1:]):
                m = (S.T >= a) & (S.T < b)
                if m.any():
                    temp.append((f"{a:g}..{b:g} degC", *rms(m)))
        elif (~in_level).any():
            temp.append(("ramps", *rms(~in_level)))
        temp.append(("all", *rms(np.ones(S.n, bool))))
        return temp


# =======================================================================================
# Sections with figures (fit report)
# =======================================================================================
def temperature_section(cs, analysis: CampaignAnalysis, name, out_dir) -> Section:
    """Temperature dependence of every offset and matrix coefficient of one sensor
    (seed 000 fig. 24-25); see temperature_sections."""
    return temperature_sections(cs, analysis, out_dir, [name])[0]


def temperature_sections(cs, analysis: CampaignAnalysis, out_dir, names=None) -> list:
    """One section per sensor (seed 000 fig. 24-25): per-level estimates with 1-sigma error
    bars, the fitted polynomial with its 1-sigma band from the coefficient covariance, and
    the tables of both; the figures are drawn together (generator.report.figures.coefficient_grids)."""
    from generator.report import figures

    names = names or [s.name for s in cs.unit.sensors]
    jobs, sections = [], []
    for name in names:
        v = cs.sensors[name]
        cal = cs.calibration(name)
        if "t_min_C" not in v:   # no temperature: nothing to draw against it
            sections.append(Section(f"Temperature dependence: {name}", [
                f"{name} reports no temperature (temperature = false): its b and M are "
                "constant, neither clamped nor flagged for temperature."],
                [polynomial_table(cs, name)]))
            continue
        t_lo, t_hi = float(v["t_min_C"]), float(v["t_max_C"])
        fits = analysis.level_fits[name]
        LT = np.array([f["temp_C"] for f in fits])
        Lval = np.array([np.concatenate([f["b"], np.ravel(f["M"])]) for f in fits]
                        ).reshape(-1, 12)
        Lsig = np.array([np.concatenate([f["b_sig"], np.ravel(f["M_sig"])]) for f in fits]
                        ).reshape(-1, 12)
        grid = np.linspace(t_lo, t_hi, 61) if t_hi > t_lo else np.array([t_lo])

        def curve(T, cal=cal):
            T = np.atleast_1d(np.asarray(T, float))
            return np.hstack([cal.b_at(T), cal.M_at(T).reshape(len(T), 9)])
        pc = analysis.covariance(name)
        band = pc.sigma_at(grid) if pc is not None else np.full((len(grid), 12), np.nan)
        png = Path(out_dir) / f"temperature_{name}.png"
        jobs.append(dict(path=png, title=f"{name}: calibration coefficients against temperature "
                                         f"(calibrated range {t_lo:.1f}..{t_hi:.1f} °C)",
                         names=COEF_NAMES, units=COEF_UNITS, level_T=LT, level_val=Lval,
                         level_sig=Lsig, curve_T=grid, curve_val=curve(grid), curve_band=band,
                         t_range=(t_lo, t_hi)))
        kinds = sorted({f["kind"] for f in fits})
        sec = Section(f"Temperature dependence: {name}", [
            f"Points: b and M of each constant-temperature level calibrated on its own ("
            f"{' and '.join(kinds) + ' fit' if kinds else 'no level could be calibrated'}; "
            f"the seed's per-segment b_i, m_ij) with 1-sigma. Line: the fitted polynomial "
            f"(degree {analysis.degree(name)}; {cal_method(cs, name)}); band: its 1-sigma from "
            "the covariance of the polynomial coefficients (the fit's design over all samples, "
            "scaled by the residual scatter). b in nT in frame axes; m dimensionless."])
        rows = []
        for f in fits:
            vals = np.concatenate([f["b"], np.ravel(f["M"])])
            sigs = np.concatenate([f["b_sig"], np.ravel(f["M_sig"])])
            rows.append([f"{f['temp_C']:.2f}", f["n"], len(f["positions"])]
                        + [pm(a, b) for a, b in zip(vals, sigs)])
        hdr = ["level degC", "samples", "positions"] + [f"{n} {u}".strip() for n, u in
                                                        zip(COEF_NAMES, COEF_UNITS)]
        if rows:     # no level: no points, and no empty table
            sec.tables.append(Table(hdr, rows, f"{name}: per-level estimates (points, "
                                               "1-sigma)"))
        Tc = np.unique(np.clip(np.concatenate([[t_lo], LT, [t_hi]]), t_lo, t_hi))
        cv = curve(Tc)
        cb = pc.sigma_at(Tc) if pc is not None else np.full((len(Tc), 12), np.nan)
        rows = [[f"{T:.2f}"] + [pm(cv[k, c], cb[k, c]) for c in range(12)]
                for k, T in enumerate(Tc)]
        sec.tables.append(Table(["T degC"] + hdr[3:], rows,
                                f"{name}: fitted polynomial ± 1-sigma band (line and band) at "
                                "the levels and the ends of the calibrated range"))
        sec.figures.append((png.name, f"{name}: temperature dependence of b and M. Look for "
                                      "the points (levels) on the line within their error "
                                      "bars; a point off the line is a level the polynomial "
                                      "does not follow.", list(range(len(sec.tables)))))
        sec.tables.append(polynomial_table(cs, name))
        if len(fits) < 2:
            sec.paragraphs.append(
                f"{len(fits)} constant-temperature level(s) found (the segment finder needs "
                "10 min of steady temperature): the points cannot show the temperature "
                "dependence; the line is the fit of all samples.")
        if analysis.dropped[name]:
            sec.paragraphs.append("Levels without an estimate: "
                                  + "; ".join(analysis.dropped[name]))
        sections.append(sec)
    figures.coefficient_grids(jobs)
    return sections


def cal_method(cs, name) -> str:
    return cs.fit_info.get("sensors", {}).get(name, {}).get("method", "") or "fit"


def rms_section(cs, analysis: CampaignAnalysis, out_dir) -> Section:
    """|B| RMS before and after calibration per temperature level and per position
    (seed 000 fig. 27-29), one row of bar charts per sensor, and the table."""
    from generator.report import figures

    rows_fig, rows_tab = [], []
    for s in cs.unit.sensors:
        g = analysis.rms_groups(s.name)
        panels = []
        t_group = ("temperature", "per temperature", "level, °C") if s.temperature else \
            ("temperature", "all samples (no temperature)", "")
        for kind, title, xl in (t_group, ("position", "per position", "position")):
            if not g[kind]:
                continue
            panels.append({"title": title, "xlabel": xl,
                           "labels": [x[0].replace(" degC", "") for x in g[kind]],
                           "before": [x[2] for x in g[kind]], "after": [x[3] for x in g[kind]]})
            for label, n, b, a in g[kind]:
                rows_tab.append([s.name, kind, label, n, b, a,
                                 (b / a) if a > 0 else None])
        if panels:
            rows_fig.append((s.name, panels))
    sec = Section("|B| RMS before and after calibration", [
        "RMS of |B~| - |B| (raw readings after SET/RESET and axis mapping: 'before') and of "
        "|M(T)(B~ - b(T))| - |B| ('after'), |B| the reference magnitude, per constant-"
        "temperature level ('ramps': samples between levels) and per static position "
        "(seed 000 fig. 27-29). Samples with magnetorquer current are left out (as in the "
        "fit)."],
        [Table(["sensor", "group", "label", "samples", "before nT", "after nT",
                "improvement x"], rows_tab, "|B| RMS per sensor, level and position")])
    if rows_fig:
        png = figures.rms_bars(Path(out_dir) / "rms_before_after.png",
                               "|B| RMS error before and after calibration (log scale)",
                               rows_fig)
        sec.figures.append((png.name, "|B| RMS before (grey) and after (blue) calibration, "
                                      "per temperature and per position. Look for the blue "
                                      "bars at the sensor's noise in every group; a group "
                                      "where they stay up lies outside the calibrated range "
                                      "or holds an effect the model lacks."))
    return sec


# =======================================================================================
# Hooks: other modules' numbers -> figure + table
# =======================================================================================
def _slug(s) -> str:
    return re.sub(r"[^a-z0-9]+", "_", str(s).lower()).strip("_") or "x"


def alignment_section(out_dir, angle_before_deg, angle_after_deg, *, pair="mmc1/mmc2",
                      time_s=None, H=None, sigma_angle_deg=None, seed_after_deg=0.07,
                      title=None, stem=None, H_sigma=None) -> Section:
    """Angle between the two magnetometers' vectors before (H = I) and after the alignment
    H (seed 000 fig. 10). Per-sample angles in, figure + table of their statistics out.
    H is printed to the digits its 1-sigma supports (h_matrix_table): H_sigma, its
    entries' 1-sigma (the coefficient set's uncertainty_1sigma, pipeline.rotation_sigma),
    else sigma_angle_deg."""
    from generator.report import figures

    b = np.asarray(angle_before_deg, float)
    a = np.asarray(angle_after_deg, float)

    def stats(x):
        return [float(np.mean(x)), float(np.sqrt(np.mean(x ** 2))),
                float(np.percentile(x, 95)), float(np.max(x))] if x.size else [None] * 4
    rows = [["before (H = I)", len(b)] + stats(b), ["after H", len(a)] + stats(a)]
    png = figures.angle_before_after(
        Path(out_dir) / f"{stem or 'alignment_' + _slug(pair)}.png",
        f"{pair}: angle between the vectors before and after H", b, a,
        x=time_s, xlabel="time, s" if time_s is not None else "sample")
    paras = [f"Angle between the calibrated vectors of {pair.replace('/', ' and ')} "
             f"(boom sensor rotated by H), per sample; seed 000: <= {seed_after_deg:g} deg "
             "after the agreement algorithm."]
    tables = [Table(["", "samples", "mean deg", "RMS deg", "95 % deg", "max deg"], rows,
                    f"{pair}: angle statistics")]
    if H is not None:
        tables.append(h_matrix_table(H, H_sigma, sigma_angle_deg))
    return Section(title or f"Agreement of the two magnetometers ({pair})", paras, tables,
                   [(png.name, f"{pair}: angle between the vectors before and after H. Look "
                               "for the angle after H down at the noise's level, with no trend "
                               "in time; before H it is the misalignment itself.", [0])])


def h_matrix_table(H, H_sigma=None, sigma_angle_deg=None) -> Table:
    """H (boom -> body) to the digits its 1-sigma supports: every entry rounded where the
    largest entry's 1-sigma has its second significant digit (pm, the report's value-with-
    sigma rule; one decimal place for the whole matrix, since the diagonal's own first-order
    1-sigma vanishes: its error is second order in the rotation). The entries' 1-sigma
    H_sigma (3x3, first order in the rotation error: pipeline.rotation_sigma, stored in the
    coefficient set's uncertainty_1sigma), else the rotation's 1-sigma (an off-diagonal
    entry moves by up to the rotation angle in rad); with neither, 6 decimals and the
    caption says so."""
    Hm = np.asarray(H, float)
    sig = None
    if H_sigma is not None:
        sig = float(np.max(np.asarray(H_sigma, float)))
    elif sigma_angle_deg is not None:
        sig = float(np.radians(sigma_angle_deg))
    if sig is not None and np.isfinite(sig) and sig > 0:
        cells = [[ax] + [pm(Hm[i, j], sig).split(" ± ")[0] for j in range(3)]
                 for i, ax in enumerate("xyz")]
        caption = (f"H (boom -> body), to its 1-sigma (largest per entry "
                   f"{significant(sig, 2)})")
    else:
        cells = [[ax] + [f"{Hm[i, j]:.6f}" for j in range(3)] for i, ax in enumerate("xyz")]
        caption = "H (boom -> body), no 1-sigma: 6 decimals"
    if sigma_angle_deg is not None:
        caption += f", rotation 1-sigma {sigma_angle_deg:.2g} deg"
    return Table(["row", "x", "y", "z"], cells, caption)


def coil_distance_section(out_dir, distance_cm, series_nT, *, current_A=None,
                          title="Magnetorquer interference against distance",
                          stem="coil_distance") -> Section:
    """Coil interference by distance (seed 000 fig. 5-6): series_nT {label: (D,) nT at
    distance_cm (NaN where not measured)}."""
    from generator.report import figures

    d = np.asarray(distance_cm, float)
    png = figures.coil_distance(Path(out_dir) / f"{stem}.png", title, d, series_nT,
                                current_A=current_A)
    rows = [[label] + [float(x) for x in np.asarray(v, float)] for label, v in series_nT.items()]
    return Section(title, [
        "Field of a magnetorquer coil at the magnetometer; a dipole falls off as 1/r^3."
        + (f" Coil current {current_A:g} A." if current_A else "")],
        [Table(["series"] + [f"{x:g} cm nT" for x in d], rows, "Interference |dB| in nT")],
        [(png.name, "Coil interference against distance (log-log)")])


def residual_causes_section(out_dir, effects, *, title="Residuals and their traced causes",
                            stem="residual_causes") -> Section:
    """Residuals against the quantity that explains them (trace). effects: list of dicts
    {"sensor", "effect", "explained_by" (str), "x" (N,), "residual_before_nT" (N,),
    "residual_after_nT" (N,) or None, "rms_before_nT", "rms_after_nT", "evidence"}."""
    from generator.report import figures

    rows, panels = [], []
    for e in effects:
        before = np.asarray(e["residual_before_nT"], float)
        after = None if e.get("residual_after_nT") is None else \
            np.asarray(e["residual_after_nT"], float)
        rb = e.get("rms_before_nT", float(np.sqrt(np.mean(before ** 2))) if before.size else None)
        ra = e.get("rms_after_nT", float(np.sqrt(np.mean(after ** 2)))
                   if after is not None and after.size else None)
        rows.append([e.get("sensor", ""), e.get("effect", ""), e.get("explained_by", ""),
                     len(before), rb, ra, e.get("evidence", "")])
        panels.append({"title": f"{e.get('sensor', '')}: {e.get('effect', '')}",
                       "xlabel": e.get("explained_by", ""), "x": e["x"], "before": before,
                       "after": after})
    sec = Section(title, ["Each panel: the residual against the quantity that explains it, "
                          "before and after the model gained the effect."],
                  [Table(["sensor", "effect", "explained by", "samples", "RMS before nT",
                          "RMS after nT", "evidence"], rows, "Effects found")])
    if panels:
        png = figures.residual_causes(Path(out_dir) / f"{stem}.png", title, panels)
        sec.figures.append((png.name, "Residuals against their traced causes"))
    else:
        sec.paragraphs.append("No effect found: nothing significant is left in the residual.")
    return sec


# =======================================================================================
# The fit report
# =======================================================================================
def inputs_section(cs, analysis: CampaignAnalysis | None, data_paths) -> Section:
    if analysis is None:
        return Section("Inputs", [f"Telemetry: {', '.join(str(p) for p in data_paths)}."])
    rows = []
    for t in analysis.tels:
        dt = np.diff(t.time_s)
        pos = t.get("position")
        rows.append([str(t.path), t.n, float(t.time_s[-1] - t.time_s[0]) / 3600.0 if t.n else 0.0,
                     float(np.median(dt[dt > 0])) if np.any(dt > 0) else None,
                     "static positions" if pos is not None and np.any(np.nan_to_num(pos) > 0)
                     else "moving",
                     "vectors" if t.has("ref_x_nT", "ref_y_nT", "ref_z_nT") else
                     "ref_norm_nT" if t.has("ref_norm_nT") else "lab_field_nT"])
    exc = [[s.name, S.n] + [S.excluded.get(k, 0) for k in ("missing", "saturated", "coil current",
                                                          "no reference")]
           for s in cs.unit.sensors for S in [analysis.samples[s.name]]]
    return Section("Inputs", [f"Unit {cs.unit.id} ({cs.fit_info.get('unit_file', '')})."], [
        Table(["file", "samples", "duration h", "sample period s", "kind", "reference"], rows,
              "Telemetry files"),
        Table(["sensor", "used", "missing", "saturated", "coil current", "no reference"], exc,
              "Samples per sensor: used and left out")])


def extras_sections(cs, analysis: CampaignAnalysis | None, out_dir) -> list:
    """Coil coupling and boom alignment, where the fit found them."""
    out = []
    info = cs.fit_info
    coils = info.get("coils")
    if coils and cs.spec.coils:
        rows = []
        for s in cs.unit.sensors:
            K = np.asarray(cs.sensors[s.name].get("K_nT_per_A", np.zeros((3, 0))), float)
            sig = (coils.get("sensors", {}).get(s.name) or {}).get("K_sigma_nT_per_A")
            sig = np.asarray(sig, float) if sig is not None else None
            # without the fit's 1-sigma (K from a prior): printed to a tenth of the
            # sensor's resolution per ampere -- its LSB (counts) or, for physical input,
            # its noise: below that a coupling moves the reading by less than a tenth of
            # it at 1 A (more than any coil draws), so it is 0 (the fit's numerical
            # zeros, -4.5e-15, are not printed as values)
            res = float(s.lsb_nT) if s.counts and s.lsb_nT and np.isfinite(s.lsb_nT) \
                and s.lsb_nT > 0 else float(s.noise_nT or 1.0)
            for i, ax in enumerate("xyz"):
                rows.append([s.name, ax] + [
                    pm(K[i, j], sig[i, j]) if sig is not None and sig.shape == K.shape
                    else resolved(K[i, j], 0.1 * res) for j in range(K.shape[1])])
        out.append(Section("Magnetorquer coupling K", [
            f"dB = K i, nT per A, one column per coil ({', '.join(cs.spec.coils)}), fitted "
            "from the coil-step campaign (seed 000 sec. 1), with its 1-sigma."],
            [Table(["sensor", "axis"] + [f"{c} nT/A" for c in cs.spec.coils], rows, "K")]))
    al = info.get("alignment")
    if al and analysis is not None:
        try:
            out.extend(_alignment_from_fit(cs, analysis, al, out_dir))
        except Exception as e:    # the report must not lose the fit over a figure
            out.append(Section("Agreement of the two magnetometers",
                               [f"Angle figure not drawn: {type(e).__name__}: {e}"]))
    return out


def seed000_sections(cs, analysis: CampaignAnalysis | None, out_dir) -> list:
    """The measurement-chain results of seed 000 beside the seed's own figures: agreement
    of the two magnetometers (H), magnetorquer interference by distance and the |B|
    error with and without the coil term, SET/RESET offset error while turning."""
    out = []
    al = cs.fit_info.get("alignment")
    if al:
        seed = al.get("seed", {})
        rows = []
        for when in ("before", "after"):
            f = al[when]
            rows.append([when + (" (H = I)" if when == "before" else " H"), f["n"]]
                        + [float(x) for x in f["proj_diff_mean_pct"]]
                        + [float(max(f["proj_diff_max_pct"])), float(f["angle_mean_deg"]),
                           float(f["angle_max_deg"])])
        rows.append(["seed 000, after", "-", "-", "-", "-",
                     float(seed.get("proj_diff_max_pct", 0.5)), "-",
                     float(seed.get("angle_max_deg", 0.07))])
        out.append(Section("Agreement of the two magnetometers: figures of merit", [
            f"H (boom -> body) from {al.get('source')}: "
            f"{pm(al['angle_deg'], al['sigma_angle_deg'])} deg (1-sigma). Difference of the normalised "
            "projections per axis and angle between the reference and the boom vectors, before "
            "and after H (seed 000 eq. 2-3). Noise alone gives a mean angle of "
            f"{al.get('noise_floor_angle_mean_deg', float('nan')):.4f} deg."]
            + [n if n.startswith("H:") else f"H: {n}" for n in al.get("notes", [])
               if isinstance(n, str)],
            [Table(["", "samples", "proj. diff x mean %", "y mean %", "z mean %",
                    "proj. diff max %", "angle mean deg", "angle max deg"], rows,
                   "Before and after H, beside the seed's figures")]))
    if cs.spec.coils and analysis is not None:
        try:
            out.extend(_coil_sections(cs, analysis, out_dir))
        except Exception as e:     # the report must not lose the fit over a figure
            out.append(Section("Magnetorquer interference", [f"Not computed: {e}"]))
    if analysis is not None:              # the coil study from data (report/coil_study.py)
        from generator.report.coil_study import coil_study_sections
        out.extend(coil_study_sections(cs, analysis, out_dir))
    if any(s.set_reset for s in cs.unit.sensors):
        from generator.report.setreset_report import setreset_sections
        out.extend(setreset_sections(cs, out_dir))
    return out


def _pm_or_why(value, sigma) -> str:
    return pm(value, sigma) if sigma else significant(value) + " (no 1-sigma)"


def _coil_sections(cs, analysis, out_dir) -> list:
    from generator.fit.coils import PANEL_STATE, SEED_POINTS_CM, correction_table

    got = analysis.coil_interference(0.1)
    if got is None:
        return []
    tel, cf, rows = got
    study = analysis.coil_study()
    pts = [float(r) for r in SEED_POINTS_CM]
    if study is not None:
        how = ("each row takes the distance law the coil study measured for its sensor and "
               "coil, or that coil's law on another sensor carried to this one (said so in "
               "the row); r is where that law gives the row's measured interference. A "
               "law gives the same interference at 5, 15 and 30 cm for every row that uses "
               "it, so those values are printed once, in the law's own row. A coil the "
               "study did not measure has no distance ('not measured')")
    else:
        how = ("scaled as 1/r^3 from the sensor's assumed distance to the coil (boom sensors "
               "30 cm, the boom's length; body sensors an assumed 10 cm): no coil study was "
               "given, so nothing about distance is measured")
    from generator.report.coil_study import exponent_text, law_value_text, undetermined_text
    table, laws = [], []
    for r in rows:
        law, r0 = r["law"], r["distance_cm"]
        if law is not None and all(w is not law for w in laws):
            laws.append(law)

        def carried(p):     # a value carried by a law: undetermined at relative sigma >= 1
            v, sig = r["at_cm"][p], r["at_cm_sigma"].get(p)
            if law is not None and sig is not None and sig >= v:
                return undetermined_text(law)
            return _pm_or_why(v, sig)
        at = (["-"] * len(pts) if r0 is None else ["law row"] * len(pts)
              if law is not None else [carried(p) for p in pts])
        r_sig = r.get("distance_sigma_cm")
        r_loose = (law is not None and r["distance_source"] not in ("assumed", "given")
                   and (law.undetermined() or (r_sig is not None and r_sig >= r0)))
        flags = list(r["flags"]) + (["assumed distance, dipole fall-off (the 1-sigma is "
                                     "K's alone)"]
                                    if r["distance_source"] == "assumed" else [])
        x, xs = r["interference_nT"], r["interference_sigma_nT"]
        pct = r["pct_of_lab_field"]
        table.append([r["sensor"], r["coil"],
                      pm(r["K_col_nT_per_A"], r["K_col_sigma_nT_per_A"]), pm(x, xs),
                      "-" if pct is None else pm(pct, pct * xs / x) if x > 0 else pct,
                      r["distance_source"],
                      "-" if r0 is None else undetermined_text(law) if r_loose else
                      pm(r0, r["distance_sigma_cm"]) if r.get("distance_sigma_cm") else
                      f"{r0:.3g} ({r['distance_source']})"
                      if r["distance_source"] in ("assumed", "given") else
                      f"{r0:.3g} (no 1-sigma)"]
                     + at + ["; ".join(flags) or "-"])
    for w in laws:
        table.append(["law", f"{w.sensor} {w.coil}, {PANEL_STATE[w.panel]}", "-", "-", "-",
                      "n = " + exponent_text(w), f"measured {w.r_min_cm:g}..{w.r_max_cm:g}"]
                     + [law_value_text(w, p, 0.1) for p in pts]
                     + ["; ".join(w.flags(*pts)) or "-"])
    seed_np, seed_p = rows[0]["seed_no_panel_at_cm"], rows[0]["seed_panel_at_cm"]
    # the seed's 30 cm figures as it quotes them (no 1-sigma given); at 5 and 15 cm each
    # panel state is scaled by its own law of the first row's sensor and coil (the other
    # state's where the study did not measure it, said so): its exponent's 1-sigma alone
    # (the seed's figure has none), 'undetermined' where that spans more than a factor e;
    # without a study by an assumed 1/r^3 that carries none: 3 digits
    for label, seed, key, panel in (("no panel", seed_np, "seed_no_panel_law", 0),
                                    ("with panel", seed_p, "seed_panel_law", 1)):
        law_s = rows[0][key] if rows[0]["distance_cm"] is not None else None

        def scaled(p):
            if p == 30.0:
                return f"{seed[30.0]:g}"
            if law_s is None or not law_s.exponent_sigma:
                return significant(seed[p])
            ln_sig = abs(np.log(30.0 / p)) * law_s.exponent_sigma
            return (undetermined_text(law_s) if ln_sig >= 1.0 or law_s.undetermined()
                    else pm(seed[p], seed[p] * ln_sig))
        if law_s is None:
            how_s = ("measured at 30 cm only (no 1-sigma given); 5 and 15 cm scaled as "
                     "1/r^3, an assumption with no 1-sigma: 3 significant digits")
        else:
            how_s = ("measured at 30 cm only (no 1-sigma given); 5 and 15 cm scaled by the "
                     f"law of {law_s.sensor} {law_s.coil}, {PANEL_STATE[law_s.panel]} "
                     "(1-sigma: its exponent's)")
            if law_s.panel != panel:
                how_s += (f": the {PANEL_STATE[law_s.panel]} law, the study has no "
                          f"{PANEL_STATE[panel]} law of this sensor and coil")
        table.append(["seed 000", label, "-", f"{seed[30.0]:g}",
                      significant(100 * seed[30.0] / 51540.0, 2), how_s,
                      "30"] + [scaled(p) for p in pts] + ["-"])
    sec = Section("Magnetorquer interference at 0.1 A", [
        f"|K column| x 0.1 A per sensor and coil from {tel.path} (1-sigma after ±); {how}. "
        "The seed's points are 5, 15 and 30 cm; it measured 167.87 nT without and 307.57 nT "
        "with the solar panel at 30 cm and 0.1 A.",
        "Flags: a law whose points scatter beyond their errors (chi2 above its 99 % "
        "quantile at the law's degrees of freedom), a law used outside the distances "
        "it was measured at (extrapolated), and an exponent or value the law's points do "
        "not determine (its 1-sigma at least its magnitude, or spanning more than a factor "
        "e: printed 'undetermined')."],
        [Table(["sensor", "coil", "|K col| nT/A", "at 0.1 A nT", "% of lab field",
                "distance law", "r cm"] + [f"at {p:g} cm nT" for p in pts] + ["flags"],
               table, "Interference by sensor and coil")])
    dist = None
    if laws:     # the study's own figure shows its laws against the seed, measured points
        sec.paragraphs.append("Against distance: the coil study's figure (section 'Coil "
                              "study') shows the measured points, the laws and the seed's "
                              "figures; the laws' values at the seed's points are their rows "
                              "here.")
    else:
        shown = [r for r in rows if r["frame"] == "boom"] or rows   # no boom: the body's
        series = {f"{r['sensor']} {r['coil']} (assumed {r['distance_cm']:g} cm)":
                  [r["at_cm"][p] for p in pts] for r in shown if r["distance_cm"] is not None}
        series["seed 000, no panel"] = [seed_np[p] for p in pts]
        series["seed 000, with panel"] = [seed_p[p] for p in pts]
        dist = coil_distance_section(out_dir, pts, series, current_A=0.1)
    cals = {s.name: cs.calibration(s.name) for s in cs.unit.sensors}
    corr = correction_table(cs.unit, tel, cals, cf)
    crow = [[n, r["rms_norm_nT"]["without"], r["rms_norm_nT"]["with"],
             (r.get("rms_norm_on_nT") or {}).get("without"),
             (r.get("rms_norm_on_nT") or {}).get("with")] for n, r in corr.items()]
    sec.tables.append(Table(["sensor", "|B| RMS without K nT", "with K nT",
                             "current on: without nT", "with nT"], crow,
                            "The coil term in the chain: |B| error before and after"))
    return [sec] if dist is None else [sec, dist]


def _alignment_from_fit(cs, analysis, al, out_dir) -> Section:
    from generator.fit.alignment import angle_between_deg, calibrated_fields

    src = al.get("source")
    k = next(i for i, p in enumerate(analysis.paths) if p == src)
    tel = analysis.tels[k]
    cals = {s.name: cs.calibration(s.name) for s in cs.unit.sensors}
    K = None
    if cs.spec.coils:
        K = {s.name: np.asarray(cs.sensors[s.name]["K_nT_per_A"]) for s in cs.unit.sensors}
    fields, mask = calibrated_fields(cs.unit, tel, cals, K, analysis.pres[k])
    ref = cs.unit.boom_reference
    boom = next((s.name for s in cs.unit.sensors if s.frame == "boom"
                 and s.part == cs.unit.sensor(ref).part), None) or \
        next(s.name for s in cs.unit.sensors if s.frame == "boom")
    H = np.asarray(cs.unit_values["H_boom_to_body"], float)
    B1, B2 = fields[ref][mask], fields[boom][mask]
    res = al.get("result", al)
    from generator.report.seed_sections import projections_section
    return [alignment_section(out_dir, angle_between_deg(B1, B2),
                              angle_between_deg(B1, B2 @ H.T), pair=f"{ref}/{boom}",
                              time_s=tel.time_s[mask], H=H,
                              sigma_angle_deg=res.get("sigma_angle_deg"),
                              H_sigma=cs.uncertainty.get(boom, {}).get("H_boom_to_body")),
            projections_section(out_dir, tel.time_s[mask], B1, B2, H, pair=f"{ref}/{boom}")]


def fit_report(cs, out_dir, data_paths=(), progress=None, compare=True) -> Report:
    """The report of a fit, figures written into out_dir. compare: add the method
    comparison when the campaign has a rotation and twelve positions."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if not data_paths:
        return _fit_report(cs, out_dir, data_paths, progress, compare)
    # figures to draw: their drawer (matplotlib imported, a first draw) starts now, on
    # the other core, while this process computes what they show (generator.report.drawer)
    from generator.report.drawer import early_drawer
    with early_drawer():
        return _fit_report(cs, out_dir, data_paths, progress, compare)


def _fit_report(cs, out_dir, data_paths, progress, compare) -> Report:
    say = progress or (lambda m: None)
    analysis = CampaignAnalysis(cs, data_paths, progress) if data_paths else None
    rep = Report(f"magcal fit: unit {cs.unit.id}")
    from generator.report.summary import summary_section
    rep.add(summary_section(cs, analysis))     # first: the verdict
    inputs = rep.add(inputs_section(cs, analysis, data_paths))
    rep.extend(fit_sections(cs))
    m = method_section(cs)
    if m:
        rep.add(m)
    if analysis is not None:
        from generator.report.figures import parallel

        say("report: drawing the figures")
        with parallel():
            from generator.report import seed_sections as seed
            rep.add(rms_section(cs, analysis, out_dir))
            for sec in (seed.axis_rms_section(cs, analysis, out_dir),
                        seed.profile_section(cs, analysis, out_dir)):
                if sec is not None:
                    rep.add(sec)
            rep.extend(temperature_sections(cs, analysis, out_dir))
            sec = seed.positions_section(cs, analysis, out_dir)
            if sec is not None:
                rep.add(sec)
            rep.extend(seed.examples_sections(cs, analysis, out_dir))
            rep.extend(extras_sections(cs, analysis, out_dir))
            rep.extend(seed000_sections(cs, analysis, out_dir))
        say("report: figures drawn")
    else:
        for s in cs.unit.sensors:
            rep.add(Section(f"Coefficients: {s.name}", [], [polynomial_table(cs, s.name)]))
        rep.extend(extras_sections(cs, analysis, out_dir))
        rep.extend(seed000_sections(cs, analysis, out_dir))
    if compare:
        from generator.report.seed_sections import comparison_sections
        rep.extend(comparison_sections(cs, analysis, progress))
    gone = left_out(cs, analysis, [s.title for s in rep.sections], compare)
    if gone:
        inputs.paragraphs.append("Left out for this unit and these files: "
                                 + "; ".join(gone) + ".")
    notes = [n for n in cs.fit_info.get("notes", [])]
    for s in cs.unit.sensors:
        st = cs.fit_info.get("sensors", {}).get(s.name, {}).get("stats", {}) or {}
        notes += [f"{s.name}: {n}" for n in st.get("notes", [])]
    if notes:
        rep.add(Section("Notes", notes))
    return rep


def left_out(cs, analysis, titles, compare=True) -> list:
    """Why a seed 000 section of the fit report is not in it, one clause per section left
    out (the report never shows an empty section instead)."""
    if analysis is None:
        return []
    from generator.fit.coils import has_coil_steps, is_coil_study

    def missing(prefix):
        return not any(t.startswith(prefix) for t in titles)
    from generator.report.seed_sections import FIG26_POSITIONS, _rotation_file, _static_file
    static = _static_file(analysis) is not None
    out = []
    if missing("Per-axis RMS"):
        out.append("the per-axis RMS before and after (seed 000's per-axis bars): no sensor "
                   "has samples with reference vectors in its calibration's frame")
    if missing("Chamber profile"):
        out.append("the chamber profile (seed 000 fig. 21, 23): " + (
            "no sensor reports a temperature (temperature = false)"
            if not any(s.temperature for s in cs.unit.sensors)
            else "no file with static positions"))
    if missing("Calibrated measurements in the positions"):
        out.append("the calibrated measurements in the positions (seed 000 fig. 26): " + (
            "no file with static positions" if not static else
            f"no sensor has reference vectors in positions "
            f"{', '.join(str(p) for p in FIG26_POSITIONS)} in its calibration's frame"))
    if missing("Example calibration: rotation"):
        out.append("Example calibration: rotation (seed 000 fig. 14): " + (
            "no rotation among the files (a moving file without reference vectors)"
            if _rotation_file(analysis) is None else "no sensor has samples in the rotation"))
    if missing("Example calibration: twelve positions"):
        out.append("Example calibration: twelve positions (seed 000 fig. 16): " + (
            "no file with static positions" if not static
            else "no sensor has samples in the file with static positions"))
    if missing("Agreement of the two magnetometers"):
        out.append("the agreement of the two magnetometers, H (seed 000 fig. 8-10): " + (
            "the unit has no boom sensor" if not any(s.frame == "boom" for s in cs.unit.sensors)
            else "H was not fitted (no rotation with the boom deployed among the files)"))
    if missing("Magnetorquer"):
        out.append("magnetorquer coupling and interference (seed 000 fig. 5-6): " + (
            "no coil campaign (static positions, stepped magnetorquer currents) among the "
            "files" if not any(has_coil_steps(t) for t in analysis.tels)
            else "the unit's chain has no coil term"))
    if missing("Coil study") and not any(is_coil_study(t) for t in analysis.tels):
        out.append("the coil study: no coil-study file (a coil_distance_cm column, "
                   "docs/coil_study.md)")
    if missing("SET/RESET") and not any(s.set_reset for s in cs.unit.sensors):
        out.append("SET/RESET offset error (seed 000 fig. 12-13): no SET/RESET part")
    if compare and missing("Fit methods compared"):
        out.append("the fit methods compared: they need a file with reference vectors in "
                   "static positions and a rotation without them")
    return out


def write_fit_report(cs, out_dir, data_paths=(), progress=None, extra_sections=()) -> Path:
    """report.html and report.md (with the PNG figures) in out_dir; returns the HTML path.
    extra_sections: further Sections (e.g. the method comparison), placed before the notes."""
    from generator.report.compare import TITLE
    rep = fit_report(cs, out_dir, data_paths, progress,     # --compare-methods gave it
                     compare=not any(s.title == TITLE for s in extra_sections))
    if extra_sections:
        notes = [s for s in rep.sections if s.title == "Notes"]
        rep.sections = [s for s in rep.sections if s.title != "Notes"]
        rep.extend(extra_sections)
        rep.sections += notes
    return rep.write(out_dir)


def fit_summary(cs, coefficients_path, report_path) -> dict:
    """JSON summary of a fit (magcal fit --json)."""
    sensors = {}
    for s in cs.unit.sensors:
        v = cs.sensors[s.name]
        info = cs.fit_info.get("sensors", {}).get(s.name, {})
        st = info.get("stats", {}) or {}
        fitst = st.get("fit", {}) or {}
        sensors[s.name] = {
            "method": info.get("method"), "chosen": st.get("chosen"),
            "degree": st.get("degree"),
            "calibrated_range_C": [float(v["t_min_C"]), float(v["t_max_C"])]
            if "t_min_C" in v else None,   # None: no temperature, constant model
            "samples_used": st.get("samples_used"),
            "rms_vector_nT": fitst.get("rms_vector_nT"),
            "rms_norm_nT": fitst.get("rms_norm_nT"),
            "temp_margin_C": float(v["temp_margin_C"]) if "temp_margin_C" in v else None,
            "set_reset_compensation": {
                "in_chain": bool(cs.spec.opts(s).sr_compensation),
                "why": (st.get("set_reset_compensation") or {}).get("why")},
        }
    return {"unit": cs.unit.id, "coefficients": str(coefficients_path),
            "report": str(report_path), "sensors": sensors,
            "coil_coupling": bool(cs.spec.coils),
            "alignment": "alignment" in cs.fit_info}
