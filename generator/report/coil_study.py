"""The coil study in the report (seed 000 fig. 5-6, from data): coil interference at known
distances, without and with the solar panel, the distance law fitted to it, beside the
seed's 30 cm / 0.1 A figures. The data format is docs/coil_study.md; the fits are
generator/fit/coils.py (fit_coil_study).

    coil_study_sections(cs, analysis, out_dir)   # [] when no input file is a coil study
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from generator.fit.coils import (SEED_30CM_NO_PANEL_NT, SEED_30CM_PANEL_NT, SEED_CURRENT_A,
                                 fit_coil_study, is_coil_study)
from generator.report.document import Section, Table, pm, significant

PANEL = {0: "without panel", 1: "with panel"}


def coil_study_sections(cs, analysis, out_dir, current_A=SEED_CURRENT_A) -> list:
    """The coil-study section of the fit report, from the input files that are coil
    studies (a coil_distance_cm column); [] when there are none."""
    study = analysis.coil_study() if hasattr(analysis, "coil_study") else _fit(cs, analysis)
    if study is None or not study.points:
        return []
    png = coil_study_figure(Path(out_dir) / "coil_study.png", study, current_A)
    point_rows = []
    for p in study.points:
        law = study.law(p.sensor, p.coil, p.panel)
        point_rows.append([p.sensor, p.coil, PANEL[p.panel], f"{p.distance_cm:g}",
                           pm(p.K_norm_nT_per_A, p.K_norm_sigma_nT_per_A),
                           pm(p.K_norm_nT_per_A * current_A, p.K_norm_sigma_nT_per_A * current_A),
                           "-" if law is None else law_value_text(law, p.distance_cm, current_A),
                           p.n_samples])
    law_rows = []
    for w, c in zip(study.laws, study.seed_comparison(current_A)):
        lim = w.chi2_limit_per_dof()
        law_rows.append([w.sensor, w.coil, PANEL[w.panel], w.n_points,
                         f"{w.r_min_cm:g}..{w.r_max_cm:g}",
                         exponent_text(w), law_value_text(w, 30.0, current_A),
                         f"{c['seed_nT']:.2f}",
                         undetermined_text(w) if w.undetermined_at(30.0) else _ratio(c),
                         f"- ({w.n_points} points: no degree of freedom)"
                         if w.chi2_per_dof is None else
                         f"{w.chi2_per_dof:.2f} (99 %: {lim:.2f})",
                         "; ".join(w.flags(30.0)) or "-"])
    paragraphs = [
        f"Coil interference measured at known distances (coil_distance_cm) without and with "
        f"the solar panel (panel), from {', '.join(str(s) for s in study.sources)}. Per "
        "distance and panel state, K (nT/A, the sensor's frame axes) is fitted like a coil "
        "campaign: the readings against the current plus a constant per static position. "
        f"Through the points of each sensor and panel state the law |K| = K30 (30 cm / r)^n "
        "is fitted in log-log, weighted by the points' 1-sigma, its uncertainty scaled up "
        "by sqrt(chi2/dof) where the points scatter more than their errors. With two "
        "distances the law goes through both points: its 1-sigma is theirs propagated "
        "plainly, and no degree of freedom is left to test whether they scatter more than "
        "their errors (flag 'unchecked'). A dipole gives "
        f"n = 3. The seed measured {SEED_30CM_NO_PANEL_NT} nT without and "
        f"{SEED_30CM_PANEL_NT} nT with the panel at 30 cm and {SEED_CURRENT_A:g} A.",
        "What to look for: points on their line (chi2/dof near 1), n within its "
        "uncertainty of 3, and the panel's factor at 30 cm against the seed's "
        f"{SEED_30CM_PANEL_NT / SEED_30CM_NO_PANEL_NT:.2f}.",
        "Flags: chi2/dof above its 99 % quantile at the law's degrees of freedom (points "
        "that scatter only by their 1-sigma exceed it once in a hundred laws: beyond it "
        "the errors or the power law are off), a law through two points that no misfit "
        "test checks (unchecked), a law evaluated outside the distances "
        "it was measured at (the 30 cm comparison with the seed is then extrapolated), and "
        "an exponent or value the points do not determine (undetermined: its 1-sigma at "
        "least its magnitude, or a value's 1-sigma spanning more than a factor e; printed "
        "'undetermined' instead of numbers)."]
    ratios = _panel_ratios(study)
    if ratios:
        paragraphs.append("Panel factor at 30 cm (with / without): " + "; ".join(
            f"{s} {c}: {why or (pm(r, sig) if sig else significant(r, 2) + ' (no 1-sigma)')}"
            for (s, c), (r, sig, why) in ratios.items()) + ".")
    paragraphs += [f"Note: {n}" for n in study.notes]
    return [Section(f"Coil study: interference against distance at {current_A:g} A", paragraphs,
                    [Table(["sensor", "coil", "panel", "points", "measured cm", "exponent n",
                            f"at 30 cm, {current_A:g} A nT", "seed 000 nT", "ratio to seed",
                            "chi2/dof", "flags"], law_rows,
                           "Distance law per sensor and panel state"),
                     Table(["sensor", "coil", "panel", "distance cm", "|K| nT/A",
                            f"at {current_A:g} A nT", "law nT", "samples"], point_rows,
                           "K per distance and panel state (the points)")],
                    [(png.name, "Coil interference against distance, log-log: points with "
                      "1-sigma, the fitted laws, the seed's 30 cm figures", [0, 1])])]


def undetermined_text(law) -> str:
    """What the report prints instead of a law's number the points do not determine
    (DistanceLaw.undetermined, undetermined_at: relative 1-sigma at least 1)."""
    return f"undetermined (distances {law.span_text()} too close)"


def exponent_text(law) -> str:
    """The law's n to its 1-sigma, and '(2 points, unchecked)' where no misfit test backs
    the 1-sigma (plain propagation of the two points' errors); 'undetermined (...)' where
    the 1-sigma is at least n's magnitude."""
    if law.undetermined():
        return undetermined_text(law)
    n = (pm(law.exponent, law.exponent_sigma) if law.exponent_sigma
         else f"{law.exponent:.2f} (no 1-sigma)")
    return n + (f" ({law.n_points} points, unchecked)" if law.unchecked() else "")


def law_value_text(law, r_cm, current_A) -> str:
    """The law's interference at r_cm and current_A, to its 1-sigma; 'undetermined (...)'
    where that 1-sigma spans more than a factor e."""
    if law.undetermined_at(r_cm):
        return undetermined_text(law)
    sig = law.sigma_at(r_cm, current_A)
    v = float(law.at(r_cm, current_A))
    return pm(v, sig) if sig else significant(v) + " (no 1-sigma)"


def _fit(cs, analysis):
    tels = [t for t in getattr(analysis, "tels", []) if is_coil_study(t)]
    return fit_coil_study(cs.unit, tels) if tels else None


def _ratio(c) -> str:
    """The ratio to the seed's figure, to the precision of its 1-sigma where known."""
    if c["sigma_nT"]:
        return pm(c["ratio_to_seed"], c["sigma_nT"] / c["seed_nT"])
    return significant(c["ratio_to_seed"], 2) + " (no 1-sigma)"


def _panel_ratios(study) -> dict:
    out = {}
    for w in study.laws:
        if w.panel != 1:
            continue
        base = study.law(w.sensor, w.coil, 0)
        if base is not None and base.K_30cm_nT_per_A > 0:
            r = w.K_30cm_nT_per_A / base.K_30cm_nT_per_A
            sig = None   # first order, the two laws independent (separate points)
            if w.K_30cm_sigma_nT_per_A is not None and base.K_30cm_sigma_nT_per_A is not None:
                sig = r * np.hypot(w.K_30cm_sigma_nT_per_A / w.K_30cm_nT_per_A,
                                   base.K_30cm_sigma_nT_per_A / base.K_30cm_nT_per_A)
            loose = next((x for x in (w, base) if x.undetermined_at(30.0)), None)
            out[(w.sensor, w.coil)] = (r, sig, loose and undetermined_text(loose))
    return out


def coil_study_figure(path, study, current_A=SEED_CURRENT_A) -> Path:
    """Interference at current_A against distance, log-log: points with 1-sigma bars, the
    fitted law of each sensor, coil and panel state, the seed's 30 cm figures."""
    from generator.report.figures import _figure, _save

    fig = _figure(6.5, 4.2)
    ax = fig.subplots()
    keys = sorted({(p.sensor, p.coil, p.panel) for p in study.points})
    r_all = np.array([p.distance_cm for p in study.points])
    grid = np.geomspace(r_all.min() * 0.9, max(r_all.max(), 30.0) * 1.1, 50)
    for k, key in enumerate(keys):
        pts = [p for p in study.points if (p.sensor, p.coil, p.panel) == key]
        r = np.array([p.distance_cm for p in pts])
        y = np.array([p.K_norm_nT_per_A for p in pts]) * current_A
        e = np.array([p.K_norm_sigma_nT_per_A for p in pts]) * current_A
        color = f"C{k % 10}"
        label = f"{key[0]} {key[1]}, {PANEL[key[2]]}"
        ax.errorbar(r, y, yerr=e, fmt="o" if key[2] == 0 else "s", ms=4, color=color,
                    capsize=2, lw=1, label=label)
        law = study.law(*key)
        if law is not None:
            ax.loglog(grid, law.at(grid, current_A), "-" if key[2] == 0 else "--", lw=0.8,
                      color=color, label=f"law, {PANEL[key[2]]}: n = " + exponent_text(law))
    seed = current_A / SEED_CURRENT_A
    ax.loglog([30.0], [SEED_30CM_NO_PANEL_NT * seed], "*", ms=10, color="k",
              label="seed 000, 30 cm, no panel")
    ax.loglog([30.0], [SEED_30CM_PANEL_NT * seed], "*", ms=10, color="0.5",
              label="seed 000, 30 cm, panel")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("distance coil - magnetometer, cm", fontsize=8)
    ax.set_ylabel(f"interference |dB| at {current_A:g} A, nT", fontsize=8)
    ax.grid(alpha=0.3, lw=0.5, which="both")
    ax.legend(fontsize=6)
    ax.tick_params(labelsize=7)
    ax.set_title("Coil study: interference against distance", fontsize=10)
    fig.subplots_adjust(left=0.13, right=0.98, top=0.9, bottom=0.13)
    distance_ticks(ax, r_all, extra_cm=(30.0,), fontsize=7)
    return _save(fig, path)


def distance_ticks(ax, distances_cm, extra_cm=(), fontsize=7) -> list:
    """x ticks of a log distance axis at the measured distances and extra_cm (the seed's
    30 cm) whose labels do not overlap: the smallest and the largest measured distance and
    extra_cm first, then the rest from small to large, each kept only where its label
    clears those kept (label width
    from the font size: a digit or point is at most 0.65 em wide in the default font, plus
    half an em between labels). Call after the axes' limits and position are final.
    Returns the ticks kept."""
    from matplotlib.ticker import NullFormatter

    lo, hi = np.log10(ax.get_xlim())
    fig = ax.get_figure()
    width_pt = fig.get_size_inches()[0] * 72.0 * ax.get_position().width
    def inside(v):
        v = np.unique(np.asarray(v, float))
        return v[(v > 0) & (np.log10(np.maximum(v, 1e-300)) >= lo)
                 & (np.log10(np.maximum(v, 1e-300)) <= hi)]
    r, extra = inside(distances_cm), inside(extra_cm)
    if not r.size and not extra.size:
        return []
    order = ([r.min(), r.max()] if r.size else []) + list(extra) + list(r)
    kept = []

    def place(x):
        label = f"{x:g}"
        centre = (np.log10(x) - lo) / (hi - lo) * width_pt
        return centre, 0.65 * fontsize * len(label) / 2.0

    for x in order:
        if any(x == k for k in kept):
            continue
        c, half = place(x)
        if all(abs(c - ck) >= half + hk + 0.5 * fontsize for ck, hk in map(place, kept)):
            kept.append(x)
    kept.sort()
    ax.set_xticks(kept)
    ax.set_xticklabels([f"{x:g}" for x in kept])
    ax.xaxis.set_minor_formatter(NullFormatter())
    return kept
