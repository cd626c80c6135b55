"""Sections of the fit report that redraw seed 000's figures from the campaign's data.

Each section: a figure (generator/report/figures_seed.py), the table(s) with its numbers,
and a caption that says what to look for. Built from the report's CampaignAnalysis (the
samples as the fit used them, with their time, position, file and constant-temperature
segments); a figure whose data the campaign lacks is left out, never drawn empty.

* profile_section: fig. 21 and 23, the chamber profile split into segments and the
  sensor temperatures (the static-position file);
* positions_section: fig. 26, raw and calibrated field in positions 1-3 against time;
* axis_rms_section: per-axis vector RMS before and after, per sensor;
* examples_sections: fig. 14 (rotation: raw and calibrated) and fig. 16 (twelve
  positions: raw and calibrated);
* projections_section: fig. 8-9, per-axis normalised projections before and after H.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from generator.report.document import Section, Table

FIG26_POSITIONS = (1, 2, 3)     # seed 000 fig. 26 shows positions 1-3


def _static_file(analysis):
    """Index of the first file with static positions, or None."""
    for k, t in enumerate(analysis.tels):
        pos = t.get("position")
        if pos is not None and np.any(np.nan_to_num(np.asarray(pos, float)) > 0):
            return k
    return None


def _rotation_file(analysis):
    """Index of the first moving file without reference vectors (a rotation), or None."""
    for k, t in enumerate(analysis.tels):
        pos = t.get("position")
        static = pos is not None and np.any(np.nan_to_num(np.asarray(pos, float)) > 0)
        if not static and not t.has("ref_x_nT", "ref_y_nT", "ref_z_nT"):
            return k
    return None


def _runs(values):
    """[(value, first index, last index)] of the runs of equal values."""
    v = np.asarray(values)
    if not v.size:
        return []
    cut = np.nonzero(v[1:] != v[:-1])[0] + 1
    starts = np.concatenate([[0], cut])
    stops = np.concatenate([cut, [len(v)]]) - 1
    return [(v[a], int(a), int(b)) for a, b in zip(starts, stops)]


def _vector_sensors(cs, analysis):
    """Sensors with reference-vector samples and M in the reference's frame."""
    return [s.name for s in cs.unit.sensors
            if analysis.samples[s.name].is_vec.any() and analysis.body_frame(s.name)]


# ---- fig. 21 and 23 -------------------------------------------------------------------
def profile_section(cs, analysis, out_dir):
    from generator.report import figures_seed

    k = _static_file(analysis)
    if k is None:
        return None
    tel = analysis.tels[k]
    series, segs, seg_rows, sum_rows = [], [], [], []
    for s in cs.unit.sensors:
        if not s.temperature:
            continue
        S = analysis.samples[s.name]
        m = S.file == k
        if not m.any():
            continue
        series.append((s.name, S.time_s[m] / 3600.0, S.T[m]))
        mine = [g for g in S.segments if getattr(g, "file", None) == k and len(g.index)]
        for g in mine:
            segs.append((s.name, g.t_start_s / 3600.0, g.t_stop_s / 3600.0, g.temp_C))
            seg_rows.append([s.name, int(g.position), f"{g.t_start_s / 3600.0:.2f}",
                             f"{g.t_stop_s / 3600.0:.2f}", f"{g.duration_s / 60.0:.1f}",
                             f"{g.temp_C:.2f}",
                             len(g.index)])
        sum_rows.append([s.name, f"{float(S.T[m].min()):.1f}", f"{float(S.T[m].max()):.1f}",
                         len(mine), len(analysis.levels[s.name]),
                         ", ".join(f"{np.mean(S.T[np.concatenate([g.index for g in lev])]):.1f}"
                                   for lev in analysis.levels[s.name]) or "none"])
    if not series:
        return None
    pos = tel.get("position")
    positions = [(int(p), float(tel.time_s[a]) / 3600.0, float(tel.time_s[b]) / 3600.0)
                 for p, a, b in _runs(np.nan_to_num(np.asarray(pos, float)).astype(int))
                 if p > 0]
    png = figures_seed.temperature_profile(
        Path(out_dir) / "chamber_profile.png",
        f"{Path(tel.path).name}: sensor temperatures and constant-temperature segments",
        series, segs, positions)
    tables = [Table(["sensor", "min degC", "max degC", "segments", "levels",
                     "level temperatures degC"], sum_rows,
                    "Temperature range, segments and levels per sensor")]
    if seg_rows:       # none found: said in the text, not shown as an empty table
        tables.append(Table(["sensor", "position", "start h", "end h", "minutes",
                             "mean degC", "samples"], seg_rows,
                            "Constant-temperature segments found (the fit's segment finder)"))
    paras = ["The recorded chamber profile split into constant-temperature segments, and "
             "the sensor temperatures (seed 000 fig. 21 and 23). A segment is a stretch of "
             "one position where the sensor's temperature stays within the finder's "
             "tolerance for at least 10 min; segments at about the same temperature form a "
             "level, and the per-level method calibrates each level on its own."]
    if not seg_rows:
        paras.append("No segment was found: the temperature never settled within a hold "
                     "(holds shorter than a few board time constants), so the per-level "
                     "method has no level to calibrate.")
    return Section("Chamber profile: segments and sensor temperatures", paras, tables,
                   [(png.name, "Sensor temperature against time; thick bars: the constant-"
                               "temperature segments found, shaded bands and numbers: the "
                               "positions. Look for a bar at every chamber level in every "
                               "position, and for sensors on one board moving together.",
                     list(range(len(tables))))])


# ---- fig. 26 --------------------------------------------------------------------------
def positions_section(cs, analysis, out_dir):
    from generator.report import figures_seed

    k = _static_file(analysis)
    if k is None:
        return None
    rows_fig, rows_tab = [], []
    for name in _vector_sensors(cs, analysis):
        S = analysis.samples[name]
        m = (S.file == k) & np.isin(S.position, FIG26_POSITIONS) & S.is_vec
        if not m.any():
            continue
        cal = cs.calibration(name).apply64(S.x[m], S.T[m])
        t = S.time_s[m] / 3600.0
        bounds = [(int(p), float(t[a]), float(t[b])) for p, a, b in _runs(S.position[m])]
        rows_fig.append((name, t, S.x[m], cal, S.ref[m], bounds))
        for p in FIG26_POSITIONS:
            q = S.position[m] == p
            if not q.any():
                continue
            d0 = S.x[m][q] - S.ref[m][q]
            d1 = cal[q] - S.ref[m][q]
            rows_tab.append([name, p, int(q.sum())]
                            + [float(np.sqrt(np.mean(d0[:, c] ** 2))) for c in range(3)]
                            + [float(np.sqrt(np.mean(d1[:, c] ** 2))) for c in range(3)])
    if not rows_fig:
        return None
    png = figures_seed.positions_timeline(
        Path(out_dir) / "positions_1_3.png",
        "Raw and calibrated field in positions "
        f"{', '.join(str(p) for p in FIG26_POSITIONS)} through the temperature cycle", rows_fig)
    return Section("Calibrated measurements in the positions", [
        "Each sensor's field components in positions 1-3 against time while the chamber "
        "steps through its levels (seed 000 fig. 26), as the difference to the reference "
        "vector: raw readings (after SET/RESET and the axis mapping) and calibrated."],
        [Table(["sensor", "position", "samples", "raw x RMS nT", "raw y", "raw z",
                "calibrated x RMS nT", "calibrated y", "calibrated z"], rows_tab,
               "RMS of (field - reference) per axis in each position")],
        [(png.name, "Raw (grey) and calibrated (blue) components minus the reference "
                    "vector. Look for the calibrated points on zero at every temperature, "
                    "within the noise; raw ones sit off by the offset and scale error and "
                    "drift as the chamber steps."
                    + figures_seed.thinning_note([len(r[1]) for r in rows_fig]))])


# ---- per-axis RMS ---------------------------------------------------------------------
def axis_rms_section(cs, analysis, out_dir):
    from generator.report import figures_seed

    names, before, after, rows = [], [], [], []
    for name in _vector_sensors(cs, analysis):
        S = analysis.samples[name]
        v = S.is_vec
        cal = cs.calibration(name).apply64(S.x[v], S.T[v])
        b = np.sqrt(np.mean((S.x[v] - S.ref[v]) ** 2, axis=0))
        a = np.sqrt(np.mean((cal - S.ref[v]) ** 2, axis=0))
        names.append(name)
        before.append(b)
        after.append(a)
        rows.append([name, int(v.sum())] + [float(x) for x in b] + [float(x) for x in a])
    if not names:
        return None
    png = figures_seed.axis_rms_bars(Path(out_dir) / "axis_rms.png",
                                     "Vector residual RMS per axis before and after "
                                     "calibration (log scale)", names, before, after)
    return Section("Per-axis RMS before and after calibration", [
        "RMS of (field - reference vector) per frame axis over every sample with a "
        "reference vector, raw and calibrated (the per-axis companion of the |B| bars)."],
        [Table(["sensor", "samples", "before x nT", "before y nT", "before z nT",
                "after x nT", "after y nT", "after z nT"], rows, "Per-axis RMS")],
        [(png.name, "Per-axis RMS before (grey, outlined in the axis colour) and after "
                    "(filled). Look for after near the sensor's noise on all three axes; one "
                    "axis well above the others points at a term the model lacks.")])


# ---- fig. 14 and 16 -------------------------------------------------------------------
def _norm_stats(B):
    n = np.linalg.norm(B, axis=1)
    return float(np.mean(n)), float(np.std(n))


def examples_sections(cs, analysis, out_dir) -> list:
    from generator.report import figures_seed

    out = []
    for kind, k in (("rotation", _rotation_file(analysis)),
                    ("twelve positions", _static_file(analysis))):
        if k is None:
            continue
        rows_fig, rows_tab, pos_rows = [], [], []
        for s in cs.unit.sensors:
            S = analysis.samples[s.name]
            m = S.file == k
            if not m.any():
                continue
            cal = cs.calibration(s.name).apply64(S.x[m], S.T[m])
            radius = float(np.median(S.norm[m]))
            rows_fig.append((s.name, S.x[m], cal, radius))
            (mr, sr), (mc, sc) = _norm_stats(S.x[m]), _norm_stats(cal)
            rows_tab.append([s.name, int(m.sum()), radius, mr, sr, mc, sc])
            if kind == "twelve positions":
                for p in np.unique(S.position[m]):
                    q = S.position[m] == p
                    pos_rows.append([s.name, int(p), int(q.sum()),
                                     *(_norm_stats(S.x[m][q])), *(_norm_stats(cal[q]))])
        if not rows_fig:
            continue
        stem = "example_rotation" if kind == "rotation" else "example_twelve_positions"
        png = figures_seed.sphere_projections(
            Path(out_dir) / f"{stem}.png",
            f"{Path(analysis.tels[k].path).name}: raw and calibrated readings ({kind})",
            rows_fig)
        tables = [Table(["sensor", "samples", "reference |B| nT", "raw |B| mean nT",
                         "raw |B| SD nT", "calibrated |B| mean nT", "calibrated |B| SD nT"],
                        rows_tab, f"|B| mean and standard deviation ({kind}; seed 000's "
                                  "two figures)")]
        if pos_rows:
            tables.append(Table(["sensor", "position", "samples", "raw |B| mean nT",
                                 "raw SD nT", "calibrated |B| mean nT", "calibrated SD nT"],
                                pos_rows, "Per position"))
        fig_no = "14" if kind == "rotation" else "16"
        out.append(Section(f"Example calibration: {kind}", [
            f"Raw and calibrated readings in the three coordinate planes (seed 000 fig. "
            f"{fig_no}): a calibrated sensor lies on the sphere of the reference magnitude."
            + (" The rotation turns the unit through all orientations, so the points cover "
               "the sphere." if kind == "rotation" else
               " The twelve positions give twelve clusters (spread along the sphere by the "
               "temperature steps while raw).")],
            tables,
            [(png.name, "Raw (grey) and calibrated (blue) readings near each coordinate "
                        "plane (within 0.35 |B| of it), green: the circle of the reference "
                        "magnitude. Look for the calibrated points on the circle and "
                        "centred; raw points form a shifted, stretched ellipse."
                        + figures_seed.thinning_note([len(r[1]) for r in rows_fig],
                                                     "samples, of those near each plane"),
              list(range(len(tables))))]))
    return out


# ---- fig. 8-9 -------------------------------------------------------------------------
def projections_section(out_dir, time_s, B_ref, B_boom, H, *, pair) -> Section:
    """Per-axis normalised projections B/|B| of the reference and the boom sensor, before
    (H = I) and after H (seed 000 fig. 8-9, eq. 2)."""
    from generator.report import figures_seed

    u1 = B_ref / np.linalg.norm(B_ref, axis=1)[:, None]
    u2 = B_boom / np.linalg.norm(B_boom, axis=1)[:, None]
    u2h = (B_boom @ np.asarray(H, float).T)
    u2h /= np.linalg.norm(u2h, axis=1)[:, None]
    rows = []
    for label, u in (("before (H = I)", u2), ("after H", u2h)):
        d = 100.0 * np.abs(u1 - u)
        rows.append([label, len(u)] + [float(x) for x in d.mean(axis=0)]
                    + [float(x) for x in d.max(axis=0)])
    names = pair.split("/")
    t = np.asarray(time_s, float)
    hours = t.size and float(t.max() - t.min()) > 7200.0
    png = figures_seed.projections_before_after(
        Path(out_dir) / "projections_before_after.png",
        f"{pair}: normalised projections before and after H", t / 3600.0 if hours else t,
        u1, u2, u2h, names, time_label="time, h" if hours else "time, s")
    return Section("Agreement of the two magnetometers: projections per axis", [
        f"Normalised projections B/|B| of {names[0]} and of {names[1]} (rotated by H) per "
        "axis against time (seed 000 fig. 8-9, eq. 2); the seed reaches at most 0.5 % "
        "difference after the agreement algorithm."],
        [Table(["", "samples", "mean |diff| x %", "y %", "z %", "max |diff| x %", "y %",
                "z %"], rows, "Difference of the normalised projections, per axis")],
        [(png.name, f"Rows 1-2: {names[0]} (black) and {names[1]} (coloured), before and "
                    "after H; row 3: their difference in %. Look for the difference after H "
                    "scattered about zero within the noise; before H a fixed misalignment "
                    "shows as a difference that follows the attitude."
                    + figures_seed.thinning_note([len(t)]))])


# ---- rotation against twelve positions ----------------------------------------------
def comparison_sections(cs, analysis, progress=None) -> list:
    """The rotation against the twelve positions (generator.report.compare), when the
    campaign has both: a static-position file with reference vectors and a rotation
    without them; else []."""
    from generator.report import compare

    if analysis is None or _rotation_file(analysis) is None or _static_file(analysis) is None:
        return []
    tels = analysis.tels
    vec = [t for t in tels if t.has("ref_x_nT", "ref_y_nT", "ref_z_nT")]
    (progress or (lambda m: None))("report: comparing the fit methods (rotation against "
                                   "twelve positions)")
    return compare.sections(compare.compare_methods(
        cs.unit, vec, evaluate=[t for t in tels if t not in vec], progress=progress))
