"""The fit methods side by side on the same data: do known field vectors close the gap?

Seed 000 (section 4 of docs/methods.md) calibrated an MMC5883 (No.2) from magnitudes only,
by an ellipsoid fit, two ways; |B| after calibration, mean and standard deviation in nT
(the seed's table says "СКО", the standard deviation of the magnitude; methods.md
translates it "RMS"):

    raw 63845.06 / 25809.33,  rotation 51539.62 / 571.19,  twelve positions 52292.39 / 1985.77

Twelve static positions left about 3.5 times the scatter of a rotation through all
orientations.  Here the methods of generator.fit.thermal.fit_unit are fitted to the same files and
compared on them:

* "ellipsoid": seed 000 from the magnitudes only, per temperature level (M symmetric,
  known up to a rotation) -- the seed's "twelve positions" route;
* "analytic": seed 001 with the known field vectors, h = Q P R B + b per level;
* "auto": the pipeline's reference-vector fit (joint or segments by held-out error).

Per sensor and method, on every file (fitted or not): mean and standard deviation of |B|
(the seed's two figures) and the RMS of |B| - |B_ref| (B_ref the reference vector's
magnitude, else ref_norm_nT, else the unit's lab_field_nT); on the files with reference
vectors the RMS vector error against the reference vectors (per axis), the same
after the one rotation that best aligns the calibrated field with the reference (what a
magnitude-only fit cannot know), and -- with the truth (truth.json) -- the errors of b(T)
and of M(T) against the true W(T)^-1, b(T) at the samples' reported temperatures (M also
through its symmetric polar factor, which is what a magnitude-only fit determines).

`evaluate` files (e.g. the hand rotation, all orientations, boom deployed) are not fitted:
every calibration is also scored on them by |B| only (a boom sensor sees H^T B there, and
|H^T B| = |B|).  A file among them without reference vectors also gives the seed's
"rotation" row: an ellipsoid fitted to that file.

Public API: compare_methods(unit, telemetries, truth=None, *, evaluate=()) -> dict;
sections(result) -> [generator.report.document.Section]; SEED_000_MMC5883_NO2.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from generator.errors import InputError
from generator.fit.reference import T_REF_C
from generator.fit.thermal import FIT_METHODS, fit_unit
from generator.report.document import Section, Table, pm

#: Seed 000, section 4: |B| after calibration of MMC5883 No.2, mean and standard deviation
#: ("СКО") in nT.
SEED_000_MMC5883_NO2 = {
    "raw": {"mean_norm_nT": 63845.06, "sd_norm_nT": 25809.33},
    "rotation": {"mean_norm_nT": 51539.62, "sd_norm_nT": 571.19},
    "twelve positions": {"mean_norm_nT": 52292.39, "sd_norm_nT": 1985.77},
}
SEED_PART = "MMC5883MA"
TITLE = "Fit methods compared: do known vectors close the gap?"   # the first section's

#: Methods compared, in table order, with the seed row each corresponds to.
COMPARED = ("ellipsoid", "analytic", "auto")
_SEED_ROW = {"raw": "raw", "ellipsoid": "twelve positions", "rotation": "rotation"}
_LABEL = {
    "raw": "raw (uncalibrated)",
    "truth": "true parameters (floor)",
    "ellipsoid": "ellipsoid, magnitudes only",
    "analytic": "analytic known-vector, seed 001 + R",
    "auto": "auto",
}


# ---------------------------------------------------------------------------------------
# data
# ---------------------------------------------------------------------------------------
def _eval_data(tel, unit):
    """Per sensor: field, temperature, reference vectors (or None) and magnitudes of the
    samples every calibration can be scored on (usable, no coil current, a reference)."""
    from generator.io.telemetry_csv import preprocess

    data = preprocess(tel, unit)
    n = tel.n
    ref = None
    if tel.has("ref_x_nT", "ref_y_nT", "ref_z_nT"):
        ref = np.stack([tel.columns[f"ref_{c}_nT"] for c in "xyz"], axis=1).astype(float)
    norm = tel.get("ref_norm_nT")
    norm = (np.asarray(norm, float) if norm is not None else
            np.full(n, float(unit.lab_field_nT)) if unit.lab_field_nT is not None else
            np.full(n, np.nan))
    if ref is not None:
        norm = np.where(np.isfinite(ref).all(axis=1), np.linalg.norm(ref, axis=1), norm)
    coil = np.zeros(n, bool)
    for c in ("coil_x_A", "coil_y_A", "coil_z_A"):
        if c in tel.columns:
            coil |= np.nan_to_num(tel.columns[c], nan=0.0) != 0
    out = {}
    for s in unit.sensors:
        if s.name not in data:
            continue
        d = data[s.name]
        # a sensor without temperature (ICD section 4) is scored at the constant model's
        # stand-in temperature (SensorData.temp_or), as it was fitted, not dropped at NaN
        T = np.asarray(d.temp_or(T_REF_C), float)
        use = (d.usable & np.isfinite(T) & np.isfinite(d.field_frame_nT).all(axis=1)
               & ~coil & np.isfinite(norm) & (norm > 0))
        vec = None
        if ref is not None:   # a file with vector columns is scored on its vector rows
            use &= np.isfinite(ref).all(axis=1)
            vec = ref[use]
        out[s.name] = {"x": d.field_frame_nT[use], "T": T[use], "ref": vec,
                       "norm": norm[use], "n": int(use.sum())}
    return out


# ---------------------------------------------------------------------------------------
# metrics
# ---------------------------------------------------------------------------------------
def _rms(a):
    a = np.asarray(a, float)
    return float(np.sqrt(np.mean(a ** 2))) if a.size else None


def best_rotation(B_from, B_to):
    """Rotation U minimising sum |U B_from - B_to|^2 (Kabsch, det +1)."""
    H = np.asarray(B_from, float).T @ np.asarray(B_to, float)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def _angle_deg(U):
    return float(np.degrees(np.arccos(np.clip((np.trace(U) - 1.0) / 2.0, -1.0, 1.0))))


def _field_metrics(B, d):
    """|B| mean and RMS error; vector RMS (per axis) raw and after the best rotation."""
    nB = np.linalg.norm(B, axis=1)
    m = {"n": int(len(B)), "mean_norm_nT": float(np.mean(nB)), "sd_norm_nT": float(np.std(nB)),
         "rms_norm_nT": _rms(nB - d["norm"]), "rms_vector_nT": None,
         "rms_vector_best_rotation_nT": None, "best_rotation_deg": None}
    if d["ref"] is not None and len(B):
        m["rms_vector_nT"] = _rms(B - d["ref"])
        U = best_rotation(B, d["ref"])
        m["rms_vector_best_rotation_nT"] = _rms(B @ U.T - d["ref"])
        m["best_rotation_deg"] = _angle_deg(U)
    return m


def _polar_sym(M):
    """Symmetric positive factor sqrt(M^T M) of each M (..., 3, 3)."""
    MtM = np.einsum("...ki,...kj->...ij", M, M)
    w, V = np.linalg.eigh(MtM)
    return np.einsum("...ik,...k,...jk->...ij", V, np.sqrt(np.maximum(w, 0.0)), V)


def _truth_metrics(cal, truth, name, T):
    """b(T) and M(T) against the truth at the reported temperatures T (RMS over samples).

    Offsets: |b - b_true| in nT; matrices: Frobenius norm of M - W_true^-1 in ppm, and the
    same for their symmetric polar factors (what a magnitude-only fit determines)."""
    from generator.io.truth import true_W, true_b

    Tu, counts = np.unique(np.asarray(T, float), return_counts=True)
    w = counts / counts.sum()
    M_true = np.linalg.inv(true_W(truth, name, Tu))
    b_true = true_b(truth, name, Tu)
    M_fit = cal.M_at(Tu)
    b_fit = cal.b_at(Tu)
    wrms = lambda e: float(np.sqrt(np.sum(w * e ** 2)))  # noqa: E731
    db = np.linalg.norm(b_fit - b_true, axis=1)
    dM = np.linalg.norm(M_fit - M_true, axis=(1, 2))
    dS = np.linalg.norm(_polar_sym(M_fit) - _polar_sym(M_true), axis=(1, 2))
    return {"offset_error_rms_nT": wrms(db), "matrix_error_rms_ppm": 1e6 * wrms(dM),
            "matrix_sym_error_rms_ppm": 1e6 * wrms(dS)}


# ---------------------------------------------------------------------------------------
# comparison
# ---------------------------------------------------------------------------------------
def _joined(parts):
    """One sensor's scoring data over several files, concatenated (None if empty)."""
    parts = [p for p in parts if p is not None and p["n"]]
    if not parts:
        return None
    refs = [p["ref"] for p in parts]
    return {"x": np.concatenate([p["x"] for p in parts]),
            "T": np.concatenate([p["T"] for p in parts]),
            "norm": np.concatenate([p["norm"] for p in parts]),
            "ref": np.concatenate(refs) if all(r is not None for r in refs) else None,
            "n": sum(p["n"] for p in parts)}


def compare_methods(unit, telemetries, truth=None, *, evaluate=(), methods=COMPARED,
                    progress=None) -> dict:
    """Fit `telemetries` with each method and score every calibration on the same data.

    unit: generator.io.unit.Unit; telemetries: Telemetry list (fitted and scored); truth:
    truth.json path or loaded dict (adds the true-parameter row and the b(T), M(T)
    errors); evaluate: further Telemetry, scored but not fitted; one without reference
    vectors also gives the seed's "rotation" row, an ellipsoid fitted to that file.

    Returns a JSON-able dict {"files", "evaluate_files", "truth", "seed", "methods",
    "sensors": {name: {"part", "frame", "rows", "analytic_levels"}}}. Each row: "key"
    ("raw", "truth", a method, or "rotation:<file>"), "label", "method" (the
    SensorCalibration's description), "method_used", "fitted_on" (paths), "fit_s",
    "own" (metrics on the files it was fitted on; raw and truth: the fitted files),
    "files" ({path: metrics} for every file), "vector" (metrics on the files with
    reference vectors), "truth" (b and M errors, or None), "seed" (the seed's figures
    for the corresponding row on an MMC5883, or None). Metrics: n, mean_norm_nT,
    sd_norm_nT, rms_norm_nT, rms_vector_nT, rms_vector_best_rotation_nT,
    best_rotation_deg.
    """
    from generator.io.truth import load_truth, true_calibrated_frame

    say = progress or (lambda msg: None)
    if not telemetries:
        raise InputError(unit.path, "compare: no telemetry files given")
    truth_d = load_truth(truth) if isinstance(truth, (str, Path)) else truth
    fit_paths = [t.path for t in telemetries]
    all_tels = list(telemetries) + [t for t in evaluate if t.path not in fit_paths]
    scoring = {t.path: _eval_data(t, unit) for t in all_tels}

    cals, fit_s, fitted_on = {}, {}, {}
    for m in methods:
        t0 = time.perf_counter()
        cals[m] = fit_unit(unit, telemetries, progress=progress, method=m)
        fit_s[m] = time.perf_counter() - t0
        fitted_on[m] = fit_paths
        say(f"compare: {m} fitted in {fit_s[m]:.2f} s")
    for tel in evaluate:
        if tel.path in fit_paths or tel.has("ref_x_nT", "ref_y_nT", "ref_z_nT"):
            continue
        key = f"rotation:{Path(tel.path).name}"
        t0 = time.perf_counter()
        cals[key] = fit_unit(unit, [tel], progress=progress, method="ellipsoid")
        fit_s[key] = time.perf_counter() - t0
        fitted_on[key] = [tel.path]

    sensors = {}
    for s in unit.sensors:
        per_file = {p: d[s.name] for p, d in scoring.items() if s.name in d and d[s.name]["n"]}
        if not any(p in per_file for p in fit_paths):
            continue
        vec_data = _joined([d for d in per_file.values() if d["ref"] is not None])

        def calibrate(key, d):
            if key == "raw":
                return d["x"]
            if key == "truth":
                return true_calibrated_frame(truth_d, s.name, d["x"], d["T"])
            return cals[key][s.name].apply64(d["x"], d["T"])

        keys = ["raw"] + (["truth"] if truth_d is not None else []) + list(cals)
        rows = []
        for key in keys:
            cal = cals[key][s.name] if key in cals else None
            own = _joined([per_file.get(p) for p in fitted_on.get(key, fit_paths)])
            vec = _field_metrics(calibrate(key, vec_data), vec_data) if vec_data else None
            label = _LABEL.get(key, f"ellipsoid on {key.split(':', 1)[-1]} (rotation)")
            if key == "auto" and cal is not None:
                label = f"auto: {cal.method}"
            elif cal is not None and key in FIT_METHODS and cal.stats.get("method") != key:
                label += f" (not available: fitted by {cal.stats.get('method')})"
            row = {"key": key, "label": label,
                   "method": cal.method if cal is not None else "",
                   "method_used": cal.stats.get("method") if cal is not None else "",
                   "fitted_on": fitted_on.get(key, []), "fit_s": fit_s.get(key),
                   "own": _field_metrics(calibrate(key, own), own) if own else None,
                   "files": {p: _field_metrics(calibrate(key, d), d)
                             for p, d in per_file.items()},
                   "vector": vec,
                   "truth": (_truth_metrics(cal, truth_d, s.name, own["T"])
                             if cal is not None and truth_d is not None and own else None)}
            seed_key = _SEED_ROW.get(key.split(":")[0])
            row["seed"] = (dict(SEED_000_MMC5883_NO2[seed_key], row=seed_key)
                           if seed_key and s.part == SEED_PART else None)
            rows.append(row)
        levels = []
        if "analytic" in cals and cals["analytic"][s.name].stats.get("method") == "analytic":
            for lev in cals["analytic"][s.name].stats["segments"]["level_fits"]:
                levels.append({k: lev[k] for k in (
                    "temp_C", "samples", "residual_rms_seed001_nT", "residual_rms_nT",
                    "R_angle_deg", "R_rotvec_deg", "R_rotvec_sigma_deg", "k", "k_sigma",
                    "e_deg", "e_sigma_deg", "b_nT", "b_sigma_nT")})
        sensors[s.name] = {"part": s.part, "frame": s.frame, "temperature": s.temperature,
                           "rows": rows,
                           "analytic_levels": levels}
    return {"files": fit_paths, "evaluate_files": [t.path for t in evaluate],
            "truth": (str(truth) if isinstance(truth, (str, Path)) else
                      "given" if truth is not None else None),
            "seed": {"source": "seed 000, section 4: MMC5883 No.2, |B| mean and standard "
                               "deviation (nT)", **SEED_000_MMC5883_NO2},
            "methods": list(cals), "sensors": sensors}


# ---------------------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------------------
def _f(v, fmt=".2f"):
    return "-" if v is None else format(v, fmt)


def _pms(values, sigmas, sign=False):
    """Per-axis values with their 1-sigma, each to its sigma's precision (pm)."""
    return "; ".join(pm(v, e, sign=sign) for v, e in zip(values, sigmas))


def _name(path):
    return Path(path).name


def sections(result) -> list:
    """Report sections of a compare_methods result (generator.report.report Section/Table)."""
    files = list(result["files"]) + [p for p in result["evaluate_files"]
                                     if p not in result["files"]]
    has_truth = result["truth"] is not None
    seed = SEED_000_MMC5883_NO2
    intro = Section(TITLE, [
        "Seed 000 calibrated an MMC5883 (No.2) from field magnitudes only by an ellipsoid "
        "fit; |B| had a standard deviation of "
        f"{seed['twelve positions']['sd_norm_nT']:.2f} nT after twelve static positions "
        f"against {seed['rotation']['sd_norm_nT']:.2f} nT after a rotation through all "
        "orientations (mean "
        f"{seed['twelve positions']['mean_norm_nT']:.2f} vs "
        f"{seed['rotation']['mean_norm_nT']:.2f} nT). Here each method is fitted to "
        f"{', '.join(_name(p) for p in result['files'])}"
        + (f"; {', '.join(_name(p) for p in result['evaluate_files'])} is scored without "
           "being fitted (the rotation row is an ellipsoid fitted to it)"
           if result["evaluate_files"] else "") + ".",
        "|B| mean and SD: on the files the row was fitted to (the seed's two figures; the "
        "seed's are beside the MMC5883 rows, a different unit and data set). |B| RMS: of "
        "|B_cal| - |B_ref| per file. Vector RMS: per axis against the reference vectors; "
        "'after rotation' removes the one rotation that best aligns the calibrated field "
        "with them (a magnitude-only fit knows M only up to a rotation)."
        + (" b and M errors: against the true b(T), W(T)^-1 at the reported temperatures "
           "of the fitted samples (RMS over samples); sym(M) compares the symmetric polar "
           "factors sqrt(M^T M)." if has_truth else "")])
    header = ["sensor", "method", "fitted on", "|B| mean nT", "|B| SD nT", "seed |B| mean nT",
              "seed |B| SD nT"]
    header += [f"|B| RMS {_name(p)} nT" for p in files]
    header += ["vector RMS nT", "after rotation nT", "rotation deg"]
    if has_truth:
        header += ["b error nT", "M error ppm", "sym(M) error ppm"]
    rows, conclusions = [], []
    for name, srow in result["sensors"].items():
        for r in srow["rows"]:
            o, sd, v = r["own"] or {}, r["seed"], r["vector"] or {}
            row = [name, r["label"], ", ".join(_name(p) for p in r["fitted_on"]) or "-",
                   _f(o.get("mean_norm_nT")), _f(o.get("sd_norm_nT")),
                   _f(sd["mean_norm_nT"]) if sd else "-", _f(sd["sd_norm_nT"]) if sd else "-"]
            row += [_f(r["files"].get(p, {}).get("rms_norm_nT")) for p in files]
            row += [_f(v.get("rms_vector_nT")), _f(v.get("rms_vector_best_rotation_nT")),
                    _f(v.get("best_rotation_deg"), ".3f")]
            if has_truth:
                t = r["truth"] or {}
                row += [_f(t.get("offset_error_rms_nT")),
                        _f(t.get("matrix_error_rms_ppm"), ".0f"),
                        _f(t.get("matrix_sym_error_rms_ppm"), ".0f")]
            rows.append(row)
        conclusions.append(_gap_sentence(name, srow, files, result["files"]))
    intro.paragraphs.extend(c for c in conclusions if c)
    intro.tables.append(Table(header, rows, "Calibrated field by fit method"))

    lev = Section("Known vectors: the rotation R that seed 001 lacks", [
        "Per constant-temperature level: seed 001's model h = Q P B + b and its extension "
        "h = Q P R B + b, R a small rotation between the sensor's own base frame (axis 1, "
        "plane of axes 1-2) and the frame of the reference vectors. Residuals are in "
        "reading space (RMS over axes); 1-sigma after ±."])
    for name, srow in result["sensors"].items():
        if not srow["analytic_levels"]:
            continue
        rows = []
        for L in srow["analytic_levels"]:
            rows.append([f"{L['temp_C']:.1f}" if srow.get("temperature", True)
                         else "all (no temperature)", L["samples"],
                         _f(L["residual_rms_seed001_nT"]), _f(L["residual_rms_nT"]),
                         _f(L["R_angle_deg"], ".3f"),
                         _pms(L["R_rotvec_deg"], L["R_rotvec_sigma_deg"], sign=True),
                         _pms(L["k"], L["k_sigma"]),
                         _pms(L["e_deg"], L["e_sigma_deg"], sign=True),
                         _pms(L["b_nT"], L["b_sigma_nT"])])
        lev.tables.append(Table(["level degC", "samples", "residual seed 001 nT",
                                 "residual with R nT", "R angle deg", "R rotation vector deg",
                                 "k", "e deg", "b nT"], rows, f"{name} ({srow['part']})"))
    if not lev.tables:      # no constant-temperature level: nothing to show, say so
        intro.paragraphs.append("Seed 001's per-level model (with the rotation R) needs "
                                "constant-temperature levels; none was found in these files.")
        return [intro]
    return [intro, lev]


def _gap_sentence(name, srow, files, fitted):
    """One generated sentence per sensor: ellipsoid against analytic, from the numbers."""
    rows = {r["key"]: r for r in srow["rows"]}
    ell, ana, tru = rows.get("ellipsoid"), rows.get("analytic"), rows.get("truth")
    if not ell or not ana or ana["method_used"] != "analytic":
        return ""
    parts = []
    for p in files:
        e, a = ell["files"].get(p), ana["files"].get(p)
        if e and a:
            floor = (tru or {}).get("files", {}).get(p, {}).get("rms_norm_nT")
            parts.append(f"|B| RMS on {_name(p)}{'' if p in fitted else ' (not fitted)'} "
                         f"{e['rms_norm_nT']:.2f} nT ellipsoid vs {a['rms_norm_nT']:.2f} nT "
                         "analytic" + (f" (true parameters {floor:.2f} nT)"
                                       if floor is not None else ""))
    ev, av = ell["vector"], ana["vector"]
    if ev and av:
        parts.append(f"vector RMS {ev['rms_vector_nT']:.1f} nT ellipsoid "
                     f"({ev['rms_vector_best_rotation_nT']:.1f} nT after a "
                     f"{ev['best_rotation_deg']:.3f} deg rotation) vs "
                     f"{av['rms_vector_nT']:.1f} nT analytic")
    if ell.get("truth") and ana.get("truth"):
        et, at = ell["truth"], ana["truth"]
        parts.append(f"b error {et['offset_error_rms_nT']:.2f} vs {at['offset_error_rms_nT']:.2f}"
                     f" nT, sym(M) error {et['matrix_sym_error_rms_ppm']:.0f} vs "
                     f"{at['matrix_sym_error_rms_ppm']:.0f} ppm")
    return f"{name}: " + "; ".join(parts) + "." if parts else ""
