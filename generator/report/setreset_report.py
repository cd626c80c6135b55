"""The SET/RESET section of the fit report: offset error while turning (seed 000 fig.
12-13, absolute and relative to the field), the seed's plane rotation against the general
case, the gyro compensation's gain and the fit's decision per sensor.

setreset_section(...) is the hook with plain arrays (re-exported by report.py);
setreset_sections(cs, out_dir) the report's section from a fit.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from generator.report.document import Section, Table

SEED_BOUND_PCT = 0.001     # seed 000: offset error below 0.001 % of the field


def setreset_section(out_dir, rate_dps, theta_deg, error_nT, t_TM_ms, *, field_nT=None,
                     title="SET/RESET offset error while turning",
                     stem="setreset_error_maps") -> Section:
    """SET/RESET offset error maps (seed 000 fig. 12-13): error_nT (K, R, Th) for K
    measurement times t_TM_ms, rates rate_dps (R) and field-to-axis angles theta_deg (Th)
    (e.g. generator.fit.setreset.offset_error_maps()["error_abs_nT"][..., 0])."""
    from generator.report import figures

    E = np.abs(np.asarray(error_nT, float))
    rate = np.asarray(rate_dps, float)
    theta = np.asarray(theta_deg, float)
    tTM = np.atleast_1d(np.asarray(t_TM_ms, float))
    png = figures.error_maps(Path(out_dir) / f"{stem}.png", title, rate, theta,
                             [E[k] for k in range(len(tTM))],
                             [f"t_TM = {t:g} ms" for t in tTM],
                             unit="|offset error|, nT")
    tables = []
    for k, t in enumerate(tTM):
        rows = [[f"{r:g}"] + [float(E[k, i, j]) for j in range(len(theta))]
                for i, r in enumerate(rate)]
        tables.append(Table(["rate deg/s \\ theta deg"] + [f"{x:g}" for x in theta], rows,
                            f"|offset error| nT, t_TM = {t:g} ms"))
    worst = [[f"{t:g}", float(E[k].max()),
              (100.0 * float(E[k].max()) / field_nT) if field_nT else None]
             for k, t in enumerate(tTM)]
    tables.append(Table(["t_TM ms", "largest error nT", "% of |B|"], worst,
                        "Largest error on the grid"))
    figs = [(png.name, "Offset error maps (absolute): rate against angle between field and "
                       "axis. Look for where the error grows: with the rate, and away from "
                       "the field along the axis (0 deg).", list(range(len(tTM))))]
    if field_nT:    # seed 000 fig. 13: the same error relative to the field
        rel = 100.0 * E / float(field_nT)
        png_rel = figures.error_maps(Path(out_dir) / f"{stem}_relative.png",
                                     title + " (relative to |B|)", rate, theta,
                                     [rel[k] for k in range(len(tTM))],
                                     [f"t_TM = {t:g} ms" for t in tTM],
                                     unit="|offset error|, % of |B|",
                                     contour=(SEED_BOUND_PCT, f"{SEED_BOUND_PCT:g} %"))
        first = len(tables)
        for k, t in enumerate(tTM):
            rows = [[f"{r:g}"] + [float(rel[k, i, j]) for j in range(len(theta))]
                    for i, r in enumerate(rate)]
            tables.append(Table(["rate deg/s \\ theta deg"] + [f"{x:g}" for x in theta], rows,
                                f"|offset error| % of |B| = {field_nT:.0f} nT, t_TM = {t:g} ms"))
        figs.append((png_rel.name, "Offset error maps relative to the field (seed 000 fig. 13). "
                                   "White line: the seed's bound, 0.001 %; look for the "
                                   "rates the unit turns at against it.",
                     list(range(first, len(tables)))))
    return Section(title, [
        "The RESET reading is taken t_delay after the SET one; a body turning meanwhile "
        "leaves (B - B')/2 in the offset (seed 000 eq. 4, generalised to any geometry)."],
        tables, figs)


def setreset_sections(cs, out_dir) -> list:
    from generator.fit import setreset

    field = float(cs.unit.lab_field_nT or setreset.DEFAULT_FIELD_NT)
    maps = setreset.offset_error_maps(field_nT=field)
    sec = setreset_section(out_dir, maps["rate_dps"], maps["theta_deg"],
                           maps["error_abs_nT"][..., 0], maps["t_TM_ms"], field_nT=field)
    rows = [[r["t_TM_ms"], r["t_delay_ms"], r["rate_dps"], r["seed_plane_nT"],
             r["seed_plane_pct"], r["worst_nT"], r["worst_pct"], r["worst_over_seed"],
             "yes" if r["seed_bound_holds_general"] else "no"]
            for r in maps["worst_case"]]
    sec.tables.append(Table(["t_TM ms", "t_delay ms", "rate deg/s", "seed case (field on the "
                             "axis) nT", "%", "any geometry, worst nT", "%", "x seed case",
                             "< 0.001 %"], rows,
                            "The seed's plane rotation against the general case"))
    gain = setreset.compensation_gain(field_nT=field, n_trials=1000)
    grow = []
    for i, r in enumerate(gain["rate_dps"]):
        for k, tTM in enumerate(gain["t_TM_ms"]):
            grow.append([float(r), float(tTM)] + [100.0 * float(gain["removed"][i, k, j])
                                                  for j in range(len(gain["gyro_noise_dps"]))])
    sec.tables.append(Table(["rate deg/s", "t_TM ms"] + [f"removed % (gyro noise {g:g} deg/s)"
                                                        for g in gain["gyro_noise_dps"]], grow,
                            "Gyro compensation: share of the offset error it removes"))
    sec.paragraphs.append(
        f"Field {field:.0f} nT. The seed treats the field along the axis, where the error is "
        "second order in the angle turned (B (1 - cos phi) / 2); for any other direction the "
        "projection changes to first order (B sin theta phi), hence the general worst case. "
        "The chain can compensate it with the gyro rate (SensorOptions.sr_compensation).")
    sr = cs.fit_info.get("set_reset_compensation") or {}
    rows = [[s.name, "yes" if cs.spec.opts(s).sr_compensation else "no",
             float(cs.sensors[s.name]["sr_comp_s_per_deg"])
             if cs.spec.opts(s).sr_compensation else "-",
             (sr.get(s.name) or {}).get("why", "not decided by the fit")]
            for s in cs.unit.sensors if s.set_reset]
    sec.tables.append(Table(["sensor", "gyro compensation in the chain", "c s rad/deg", "why"],
                            rows, "SET/RESET gyro compensation per sensor (decided by the fit: "
                            "the error over the recorded rates against a fraction of the "
                            "noise, generator.fit.setreset.compensation_decision)"))
    return [sec]
